// The golden vectors (models_spec/golden/golden.json) through the full graph with ONNX Runtime for
// Node.js: the second-language check that the graph alone gives what the Python runtime gives.
//   node run.mjs FULL.onnx GOLDEN.json   (exit 0: every frame within TOLERANCE_PX; 1: one is not)
import { readFileSync } from 'node:fs';
import * as ort from 'onnxruntime-node';

const TOLERANCE_PX = 1e-6;
const [modelPath, goldenPath] = process.argv.slice(2);
if (!modelPath || !goldenPath) {
  console.error('usage: node run.mjs FULL.onnx GOLDEN.json');
  process.exit(2);
}
const golden = JSON.parse(readFileSync(goldenPath, 'utf8'));
if (golden.format !== 'dimenet-golden/1') {
  console.error(`${goldenPath}: not a dimenet-golden/1 file`);
  process.exit(2);
}
const session = await ort.InferenceSession.create(modelPath);
const double = (rows, dims) => new ort.Tensor('float64', Float64Array.from(rows.flat(2)), dims);

let worst = 0;
let failed = 0;
for (const frame of golden.frames) {
  const x = frame.inputs;
  const want = frame.expected;
  const n = x.points_2d.length;
  const out = await session.run({
    points_2d: double(x.points_2d, [n, 2]),
    points_3d: double(x.points_3d, [n, 3]),
    mask: new ort.Tensor('bool', Uint8Array.from(x.mask, (m) => (m ? 1 : 0)), [n]),
    K_c: double(x.K_c, [3, 3]),
    image_size: double(x.image_size, [2]),
    rvec: double(want.rvec, [3]),
    tvec: double(want.tvec, [3]),
  });
  const pairs = [
    ['delta_k', out.delta_k.data, want.delta_k],
    ['K', out.K.data, want.K.flat()],
  ];
  if (want.sigma !== null) pairs.push(['sigma', out.sigma.data, want.sigma]);
  for (const [name, got, expected] of pairs) {
    const diff = Math.max(...expected.map((v, i) => Math.abs(got[i] - v)));
    worst = Math.max(worst, diff);
    if (!(diff <= TOLERANCE_PX)) {
      failed += 1;
      console.error(`${frame.name}: ${name} differs by ${diff.toExponential(2)} px`);
    }
  }
}
console.log(
  `${golden.frames.length} golden frames through ${modelPath} with onnxruntime-node ${ort.env.versions.common}: ` +
    `largest difference ${worst.toExponential(2)} px (tolerance ${TOLERANCE_PX} px), ${failed} failed`,
);
process.exit(failed ? 1 : 0);
