// The golden vectors (models_spec/golden/golden.json) through the full graph with ONNX Runtime for
// Node.js: the second-language check that the graph alone gives what the Python runtime gives.
//   node run.mjs FULL.onnx GOLDEN.json
// Exit 0: every value of every frame within TOLERANCE_PX; 1: one is not; 2: the golden file or the graph
// cannot be checked (one line naming the frame and field: the file's schema is checked, against the
// graph's outputs, before anything is compared, so a pass never checks nothing).
import { readFileSync } from 'node:fs';

const TOLERANCE_PX = 3.0517578125e-5;
const FORMAT = 'dimenet-golden/1';

class Unusable extends Error {}

const shown = (v) => {
  if (v === undefined) return 'nothing';
  const text = JSON.stringify(v);
  return text.length > 40 ? `${text.slice(0, 37)}...` : text;
};

const isObject = (v) => typeof v === 'object' && v !== null && !Array.isArray(v);

// An array of `shape[0]` entries (any count where it is null), each an array of shape.slice(1) or, last, a
// finite number; Unusable naming `where` otherwise.
function numbers(value, shape, where) {
  const [count, ...rest] = shape;
  const what = count === null ? 'an array' : `an array of ${count}`;
  if (!Array.isArray(value)) throw new Unusable(`${where} must be ${what}, got ${shown(value)}`);
  if (count !== null && value.length !== count) {
    throw new Unusable(`${where} has ${value.length} entries, expected ${count}`);
  }
  value.forEach((v, i) => {
    if (rest.length) numbers(v, rest, `${where}[${i}]`);
    else if (typeof v !== 'number' || !Number.isFinite(v)) {
      throw new Unusable(`${where}[${i}] must be a finite number, got ${shown(v)}`);
    }
  });
  return value;
}

function object(value, where) {
  if (!isObject(value)) throw new Unusable(`${where} must be an object, got ${shown(value)}`);
  return value;
}

// The graph's outputs a golden frame holds, by name: their sizes (golden.md).
const EXPECTED = { delta_k: [4], K: [3, 3], sigma: [4] };

// The graph's inputs, all of which a golden frame gives (the pose as expected.rvec, expected.tvec).
const INPUTS = ['points_2d', 'points_3d', 'mask', 'K_c', 'image_size', 'rvec', 'tvec'];

const label = (frame, index) =>
  `frame ${index}${isObject(frame) && typeof frame.name === 'string' ? ` (${frame.name})` : ''}`;

// Unusable unless the frame holds the graph's inputs and, for each output the graph has, its expected values.
function checkFrame(frame, index, outputs) {
  const where = label(frame, index);
  object(frame, where);
  const x = object(frame.inputs, `${where}: inputs`);
  const want = object(frame.expected, `${where}: expected`);
  const n = numbers(x.points_2d, [null, 2], `${where}: inputs.points_2d`).length;
  numbers(x.points_3d, [n, 3], `${where}: inputs.points_3d (one per 2D point)`);
  if (!Array.isArray(x.mask) || x.mask.length !== n) {
    const got = Array.isArray(x.mask) ? `${x.mask.length} entries` : shown(x.mask);
    throw new Unusable(`${where}: inputs.mask must be an array of ${n} booleans (one per 2D point), got ${got}`);
  }
  x.mask.forEach((m, i) => {
    if (typeof m !== 'boolean') throw new Unusable(`${where}: inputs.mask[${i}] must be a boolean, got ${shown(m)}`);
  });
  numbers(x.K_c, [3, 3], `${where}: inputs.K_c`);
  numbers(x.image_size, [2], `${where}: inputs.image_size`);
  numbers(want.rvec, [3], `${where}: expected.rvec`);
  numbers(want.tvec, [3], `${where}: expected.tvec`);
  for (const [name, shape] of Object.entries(EXPECTED)) {
    const field = `${where}: expected.${name}`;
    if (outputs.includes(name)) numbers(want[name], shape, field);
    else if (want[name] !== null && want[name] !== undefined) {
      throw new Unusable(`${field} is given, but the graph has no ${name} output`);
    }
  }
}

// Unusable unless the graph takes a full graph's inputs and gives at least delta_k and K.
function checkGraph(session) {
  const inputs = session.inputNames;
  const outputs = session.outputNames;
  if (INPUTS.some((name) => !inputs.includes(name)) || inputs.length !== INPUTS.length) {
    throw new Unusable(`it takes ${inputs.join(', ')}: a full graph takes ${INPUTS.join(', ')}`);
  }
  for (const name of ['delta_k', 'K']) {
    if (!outputs.includes(name)) throw new Unusable(`it has no ${name} output (outputs: ${outputs.join(', ')})`);
  }
}

function checkGolden(golden, outputs) {
  object(golden, 'the file');
  if (golden.format !== FORMAT) throw new Unusable(`format must be ${FORMAT}, got ${shown(golden.format)}`);
  if (!Array.isArray(golden.frames) || golden.frames.length === 0) {
    throw new Unusable(`frames must be a non-empty array, got ${shown(golden.frames)}`);
  }
  golden.frames.forEach((frame, i) => checkFrame(frame, i, outputs));
}

// Runs check(), prefixing the message of an Unusable it throws with `path`.
function about(path, check) {
  try {
    return check();
  } catch (err) {
    if (err instanceof Unusable) err.message = `${path}: ${err.message}`;
    throw err;
  }
}

async function main(argv) {
  const [modelPath, goldenPath] = argv;
  if (!modelPath || !goldenPath || argv.length !== 2) throw new Unusable('usage: node run.mjs FULL.onnx GOLDEN.json');
  let golden;
  try {
    golden = JSON.parse(readFileSync(goldenPath, 'utf8'));
  } catch (err) {
    throw new Unusable(`${goldenPath}: not a readable JSON file (${err.message})`);
  }
  let ort;
  try {
    ort = await import('onnxruntime-node');
  } catch (err) {
    throw new Unusable(`onnxruntime-node is not installed (npm ci in export/node_runner): ${err.message}`);
  }
  let session;
  try {
    session = await ort.InferenceSession.create(modelPath);
  } catch (err) {
    throw new Unusable(`${modelPath}: not a loadable ONNX model (${err.message})`);
  }
  about(modelPath, () => checkGraph(session));
  const outputs = session.outputNames;
  about(goldenPath, () => checkGolden(golden, outputs));
  const double = (rows, dims) => new ort.Tensor('float64', Float64Array.from(rows.flat(2)), dims);
  let worst = 0;
  let failed = 0;
  let compared = 0;
  for (const [index, frame] of golden.frames.entries()) {
    const x = frame.inputs;
    const want = frame.expected;
    const n = x.points_2d.length;
    let out;
    try {
      out = await session.run({
        points_2d: double(x.points_2d, [n, 2]),
        points_3d: double(x.points_3d, [n, 3]),
        mask: new ort.Tensor('bool', Uint8Array.from(x.mask, (m) => (m ? 1 : 0)), [n]),
        K_c: double(x.K_c, [3, 3]),
        image_size: double(x.image_size, [2]),
        rvec: double(want.rvec, [3]),
        tvec: double(want.tvec, [3]),
      });
    } catch (err) {
      throw new Unusable(`${goldenPath}: ${label(frame, index)}: the graph does not run (${err.message})`);
    }
    for (const name of Object.keys(EXPECTED).filter((k) => outputs.includes(k))) {
      const got = out[name].data;
      const expected = want[name].flat();
      let diff = got.length === expected.length ? 0 : NaN;
      expected.forEach((v, i) => {
        diff = Math.max(diff, Math.abs(got[i] - v)); // NaN (a NaN output, another size) stays NaN
      });
      compared += expected.length;
      worst = Math.max(worst, diff);
      if (!(diff <= TOLERANCE_PX)) {
        failed += 1;
        const why = got.length === expected.length ? `differs by ${diff.toExponential(2)} px` : `has ${got.length} values`;
        console.error(`${label(frame, index)}: ${name} ${why} (expected ${expected.length})`);
      }
    }
  }
  console.log(
    `${golden.frames.length} golden frames (${compared} values) through ${modelPath} with onnxruntime-node ` +
      `${ort.env.versions.common}: largest difference ${worst.toExponential(2)} px (tolerance ${TOLERANCE_PX} px), ` +
      `${failed} failed`,
  );
  return failed ? 1 : 0;
}

try {
  process.exitCode = await main(process.argv.slice(2));
} catch (err) {
  const message = err instanceof Unusable ? err.message : `${err.name}: ${err.message}`;
  console.error(`run.mjs: ${message.replace(/\s+/g, ' ').trim()}`);
  process.exitCode = 2;
}
