"""A fuzz of the rectifier and the file readers with hostile input (issue 20's classes, and
issue 33's crafted model files).

Every case must end in a ``DimenetError`` (``typed``) or in a result that is no confident wrong
K (``ok``): K_c's own solution with a reason, or a finite K inside the spec's bounds with every
point in front of the camera at its pose. Anything else is a ``crash`` (another exception) or
``silent-wrong``. Where onnx is installed, the full graph too (issue 48: within the parity bound of the
runtime, masked garbage changing nothing, a frame without a point giving K_c), and with torch the .ort
loader on mutated files; streams in ``bench.fuzz_stream``. The suite runs a few hundred cases
(tests/bench/test_fuzz.py), on both bundled models; ``dimenet bench --fuzz N`` runs as many as asked.
"""

from __future__ import annotations

import json
import re
import traceback
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Callable

import cv2
import numpy as np

from dimenet.runtime.assets import asset
from dimenet.runtime.errors import DimenetError
from dimenet.runtime.formats.camera_file import read_camera
from dimenet.runtime.formats.cameras import json_file, ros
from dimenet.runtime.formats.dataset import read_dataset
from dimenet.runtime.formats.motion import read_motion, write_gyro, write_lens_shift
from dimenet.runtime.formats.points import read_points, write_points
from dimenet.runtime.formats.rig import load_rig
from dimenet.runtime.geometry import MIN_POINTS, k_matrix, k_params, solve_pnp_start
from dimenet.runtime.plugins import entry_points
from dimenet.runtime.rectify.model import bundled_model_bytes, onnx_model_from_bytes
from dimenet.runtime.rectify.onnx_graph import MAX_MODEL_BYTES
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.user_camera import checked_camera

OUTCOMES = ("typed", "ok", "crash", "silent-wrong")


@dataclass
class FuzzReport:
    """Per area (``rectify``, ``rectify_batch``, ``dataset file``, ...), the count of each outcome, and
    the first few crashes and silent-wrong cases (case name and what happened)."""

    counts: dict = field(default_factory=dict)
    failures: list = field(default_factory=list)

    def add(self, area: str, case: str, outcome: str, detail: str = "") -> None:
        self.counts.setdefault(area, Counter())[outcome] += 1
        if outcome in ("crash", "silent-wrong") and len(self.failures) < 20:
            self.failures.append(f"{area} / {case}: {outcome}: {detail}")

    @property
    def bad(self) -> int:
        return sum(c["crash"] + c["silent-wrong"] for c in self.counts.values())

    def table(self) -> str:
        rows = [f"{'area':<16} {'tried':>6} " + " ".join(f"{o:>12}" for o in OUTCOMES)]
        for area, c in self.counts.items():
            rows.append(f"{area:<16} {sum(c.values()):>6} " + " ".join(f"{c[o]:>12}" for o in OUTCOMES))
        return "\n".join(rows + self.failures)


def frame_variants(rng: np.random.Generator, x: np.ndarray, X: np.ndarray, K: np.ndarray) -> Iterator:
    """(name, points_2d, points_3d) hostile variants of one frame's valid points x (N, 2) px, X
    (N, 3) mm seen under K."""
    n = len(x)
    pick = rng.integers(n)
    _, rvec, tvec = cv2.solvePnP(X, x, K, None, flags=cv2.SOLVEPNP_SQPNP)
    R, t = cv2.Rodrigues(rvec)[0], tvec.ravel()

    def edited(a, value, column=None):
        a = a.copy()
        a[pick, rng.integers(a.shape[1]) if column is None else column] = value
        return a

    behind = X @ R.T + t
    behind[rng.random(n) < rng.uniform(0.05, 0.9)] *= -1.0
    yield "nan 2D", edited(x, np.nan), X
    yield "inf 3D", x, edited(X, np.inf)
    yield "huge 3D", x, edited(X, 10.0 ** rng.uniform(10, 300) * rng.choice([-1, 1]))
    yield "huge 2D", edited(x, 10.0 ** rng.uniform(4, 300)), X
    yield "outside the image", edited(x, rng.uniform(4032, 9000), 0), X
    yield "points behind the camera", x, (behind - t) @ R
    yield "shuffled", x[rng.permutation(n)], X
    yield "y-flipped", np.c_[x[:, 0], 3023.0 - x[:, 1]], X
    yield "noise", np.clip(x + rng.normal(0, rng.uniform(5, 200), x.shape), 0, [4031, 3023]), X
    yield "one point repeated", np.repeat(x[:1], n, 0), np.repeat(X[:1], n, 0)
    yield "three points repeated", np.resize(x[:3], (n, 2)), np.resize(X[:3], (n, 3))
    yield "collinear", x, np.outer(np.linspace(0, 1, n), X[1] - X[0]) + X[0]
    k = int(rng.integers(0, 9))
    yield f"{k} points", x[:k], X[:k]
    yield "3D scaled", x, X * 10.0 ** rng.uniform(-6, 6)
    yield "2D shifted", x + rng.uniform(-3000, 3000, 2), X
    yield "mismatched counts", x, X[:-1]
    yield "swapped", X, x
    yield "strings", x.astype(str), X
    yield "objects", np.array([[1, None]] * n, dtype=object), X
    yield "ragged", [[1.0, 2.0], [3.0]] * n, X
    yield "3D as (N, 3, 1)", x, X[..., None]


def judge_frame(rect: Rectifier, X: np.ndarray, res, K_c=None) -> tuple[str, str]:
    """A result is ok when it is K_c's solution with a reason, or a finite, in-bounds K whose pose
    has every point in front of the camera; ``K_c`` (3, 3) px the frame's own (None: the Rectifier's)."""
    depth = np.asarray(X, dtype=np.float64) @ cv2.Rodrigues(res.rvec)[0][2] + res.tvec[2]
    if not depth.min() > 0:
        return "silent-wrong", f"a point behind the camera at the returned pose (fallback {res.fallback!r})"
    if res.fallback is not None and res.fallback.refusal:
        population = rect.frame_population_K_cov(K_c)
        kept_cov = res.K_cov is None if population is None else np.array_equal(res.K_cov, population)
        same = np.array_equal(res.K, rect.K_c if K_c is None else K_c) and kept_cov
        return ("ok", "") if same else ("silent-wrong", f"fallback {res.fallback!r} without K_c's solution")
    k = np.array([res.K[0, 0], res.K[1, 1], res.K[0, 2], res.K[1, 2]])
    if not (np.isfinite(res.reprojection_error_px) and rect.k_within_bounds(k, K_c=K_c)):
        return "silent-wrong", f"K {k.tolist()} or e {res.reprojection_error_px} with no fallback"
    return "ok", ""


def outcome_of(call: Callable, judge: Callable) -> tuple[str, str]:
    try:
        result = call()
    except DimenetError:
        return "typed", ""
    except Exception as exc:  # the fuzz's finding: anything but a typed error
        return "crash", f"{type(exc).__name__}: {exc} | {traceback.format_exc(limit=-1).strip()[-160:]}"
    return judge(result)


def random_rig_frames(frames, rng: np.random.Generator) -> Iterator[tuple]:
    """Endlessly, a rig frame of ``frames`` (a dataset) drawn at random: its valid points x (N, 2) px, X (N, 3) mm
    and K_true (3, 3) px."""
    rig = np.flatnonzero(frames.scene == "rig")
    while True:
        b = int(rng.choice(rig))
        m = frames.valid[b]
        yield frames.points_2d[b][m], frames.points_3d[b][m], frames.K_true[b]


def fuzz_rectifier(rect: Rectifier, frames, n_cases: int, rng: np.random.Generator, report: FuzzReport) -> None:
    """``n_cases`` hostile frames made from ``frames`` (a dataset's rig frames), through
    ``rect.rectify`` and, two at a time with a clean frame, ``rect.rectify_batch``."""
    done = 0
    for x, X, K in random_rig_frames(frames, rng):
        if done >= n_cases:
            break
        for name, p2, p3 in frame_variants(rng, x, X, K):
            if done >= n_cases:
                break
            done += 1
            outcome, detail = outcome_of(
                lambda p2=p2, p3=p3: rect.rectify(p2, p3), lambda r, p3=p3: judge_frame(rect, p3, r)
            )
            report.add("rectify", name, outcome, detail)
            try:
                a2, a3 = np.asarray(p2, dtype=np.float64), np.asarray(p3, dtype=np.float64)
            except (TypeError, ValueError):
                continue
            if a2.ndim != 2 or a2.shape != (len(x), 2) or a3.shape != (len(x), 3):
                continue
            p2b, p3b = np.stack([x, a2]), np.stack([X, a3])

            def batch_call(p2b=p2b, p3b=p3b):
                return rect.rectify_batch(p2b, p3b, np.ones(p2b.shape[:2], bool))

            def batch_judge(r, p3b=p3b):
                one = SimpleNamespace(
                    rvec=r.rvec[1],
                    tvec=r.tvec[1],
                    fallback=r.fallback[1],
                    K=r.K[1],
                    reprojection_error_px=r.reprojection_error_px[1],
                    K_cov=None if r.K_cov is None or np.all(np.isnan(r.K_cov[1])) else r.K_cov[1],
                )
                return judge_frame(rect, p3b[1], one)

            outcome, detail = outcome_of(batch_call, batch_judge)
            report.add("rectify_batch", name, outcome, detail)


def _masked_garbage(rng: np.random.Generator, x: np.ndarray, X: np.ndarray, rvec, tvec, k: int) -> tuple:
    """The frame's points with ``k`` masked points put among them, holding NaN, inf or a huge value, or in
    3D the camera centre at the pose: (points_2d, points_3d, mask)."""
    centre = -cv2.Rodrigues(rvec)[0].T @ tvec
    junk_2d = rng.choice([np.nan, np.inf, -np.inf, 1e300], (k, 2))
    junk_3d = np.where(rng.random((k, 1)) < 0.5, centre, rng.choice([np.nan, np.inf, -np.inf, 1e300], (k, 3)))
    order = rng.permutation(len(x) + k)
    return np.r_[x, junk_2d][order], np.r_[X, junk_3d][order], np.r_[np.ones(len(x), bool), np.zeros(k, bool)][order]


def _graph_frames(rng: np.random.Generator, x: np.ndarray, X: np.ndarray, K: np.ndarray) -> Iterator:
    """(name, points_2d, points_3d) for the full graph from one frame's inference points: as they are,
    a random subset, in another unit, and ``frame_variants``'s hostile frames that are (N, 2) and (N, 3)
    numbers (the others are the rectifier's input rules, which come before the graph)."""
    n = len(x)
    subset = np.sort(rng.choice(n, int(rng.integers(min(MIN_POINTS, n), n + 1)), replace=False))
    unit = float(rng.uniform(-6, 8))
    yield "as simulated", x, X
    yield "a subset", x[subset], X[subset]
    yield f"3D unit 1e{unit:.1f}", x, X * 10.0**unit
    for name, p2, p3 in frame_variants(rng, x, X, K):
        try:
            p2, p3 = np.asarray(p2, np.float64), np.asarray(p3, np.float64)
        except (TypeError, ValueError):
            continue
        if p2.shape == (len(p2), 2) and p3.shape == (len(p2), 3):
            yield name, p2, p3


class _Graph:
    """A generic model's full graph under ONNX Runtime beside the model's ``Rectifier`` for one camera."""

    def __init__(self, session, rect: Rectifier) -> None:
        self.session, self.rect = session, rect
        self.names = [o.name for o in session.get_outputs()]

    def run(self, points_2d, points_3d, mask, rvec, tvec) -> dict:
        feeds = {"points_2d": points_2d, "points_3d": points_3d, "mask": mask, "K_c": self.rect.K_c}
        feeds |= {"image_size": np.array(self.rect.image_size, np.float64), "rvec": rvec, "tvec": tvec}
        return dict(zip(self.names, self.session.run(None, feeds)))

    def against_runtime(self, rng: np.random.Generator, p2, p3, garbage: bool) -> tuple:
        """(the runtime's ``network`` result, the graph's outputs) at the C0 pose, the graph's points with
        as many masked garbage points as real ones when ``garbage``."""
        with np.errstate(over="ignore"):  # SQPnP's unit of a 1e300 coordinate (the network refuses the frame)
            rvec, tvec = solve_pnp_start(p2, p3, self.rect.K_c)
        net = self.rect.network(p2, p3, rvec, tvec)
        k = len(p2) if garbage else 0
        return net, self.run(*_masked_garbage(rng, p2, p3, rvec, tvec, k), rvec, tvec)

    def without_points(self, rng: np.random.Generator, n: int) -> dict:
        """The graph's outputs for n points all masked, holding garbage, at a random pose."""
        rvec, tvec = rng.normal(size=3), rng.normal(size=3)
        return self.run(*_masked_garbage(rng, np.zeros((0, 2)), np.zeros((0, 3)), rvec, tvec, n), rvec, tvec)


def fuzz_full_graph(
    blob: bytes, source: str, frames, n_cases: int, rng: np.random.Generator, report: FuzzReport
) -> None:
    """``n_cases`` frames made from ``frames`` (a dataset: each frame's inference points, every scene)
    through the full graph of the generic model ``blob`` (``export.full_graph``; needs onnx) at the C0
    pose SQPnP gives under K_c, one in two with masked garbage among the points (``_masked_garbage``),
    against ``Rectifier.network`` on the same points: ok when ΔK, K and sigma are finite and within the
    parity bound (``export.golden.parity_px``), typed where the runtime refuses the frame. With each
    frame, the graph on no point (N = 0, and its points all masked over garbage): ok when ΔK = 0, K = K_c
    and sigma is the population's (``Rectifier.population_K_cov``), as for a frame that keeps K_c."""
    import onnxruntime as ort

    tools = entry_points("dimenet.export_tools")  # the export package's, reached as it registers them
    full_graph, parity_px = tools["full_graph"].load(), tools["parity_px"].load()

    session = ort.InferenceSession(full_graph(blob, source), providers=["CPUExecutionProvider"])
    model = onnx_model_from_bytes(blob, source)
    kinds = {str(kind): np.flatnonzero(frames.scene == kind) for kind in np.unique(frames.scene)}
    done = 0
    while done < n_cases:
        kind = str(rng.choice(sorted(kinds)))
        b = int(rng.choice(kinds[kind]))
        m = frames.valid[b] & frames.infer_mask[b]
        x, X, K = frames.points_2d[b][m], frames.points_3d[b][m], frames.K_true[b]
        K_c = k_matrix(np.round(k_params(K) + rng.normal(0.0, [30.0, 30.0, 15.0, 15.0]), 2))
        graph = _Graph(session, Rectifier(model, "dimenet", checked_camera(K_c, frames.image_size, "fuzz camera")))
        for name, p2, p3 in _graph_frames(rng, x, X, K):
            if done >= n_cases:
                break
            done += 1
            garbage = bool(rng.random() < 0.5)
            outcome, detail = outcome_of(
                lambda graph=graph, p2=p2, p3=p3, garbage=garbage: graph.against_runtime(rng, p2, p3, garbage),
                lambda result: _judge_graph(result[1], vars(result[0]), parity_px(result[0].delta_k)),
            )
            report.add("full graph", f"{kind}: {name}{', masked garbage' if garbage else ''}", outcome, detail)
        population = graph.rect.population_K_cov
        kept = {
            "delta_k": np.zeros(4),
            "K": K_c,
            "sigma": None if population is None else np.sqrt(population.diagonal()),
        }
        for name, n in (("N = 0", 0), ("every point masked", len(x))):
            report.add("full graph", name, *_judge_graph(graph.without_points(rng, n), kept, parity_px(0.0)))


def _judge_graph(out: dict, want: dict, bound: float) -> tuple[str, str]:
    """ok when the graph's outputs (``out``) ΔK, K and sigma are finite and within ``bound`` px of
    ``want``'s (a sigma of None: nothing to compare)."""
    worst = 0.0
    for key in ("delta_k", "K", "sigma"):
        value, got = want[key], out.get(key)
        if value is None:
            continue
        if not np.isfinite(got).all():
            return "silent-wrong", f"{key} {got.tolist()}, not finite"
        worst = max(worst, float(np.abs(got - value).max()))
    if worst <= bound:
        return "ok", ""
    return "silent-wrong", f"{worst:.3g} px from the runtime's (bound {bound:g} px)"


# Texts a number's field may hold that Python's int() or float() reads otherwise than a data file means, or not at all.
HOSTILE_NUMBERS = (
    "1" * 400,  # past float64
    "1" * 5000,  # past int()'s 4300 digits
    str(2**63),  # past the 64-bit clock
    "\u00b2",  # str.isdigit() but not int()
    "\u0661\u0662",  # Arabic-Indic digits: int() reads 12
    "\uff11",  # a full-width one
    "1_000",
    "0x10",
    "1e400",
    "nan",
    "-0",
    " ",
)


def _mutations(rng: np.random.Generator, blob: bytes) -> Iterator[tuple[str, bytes]]:
    """Byte-level mutations of a file: bit flips, truncation, a zeroed or random run, appended junk, and one number
    (a run of digits with its sign, point and exponent, or a random byte) replaced by one of HOSTILE_NUMBERS."""
    n = len(blob)
    numbers = [m.span() for m in re.finditer(rb"[-+]?[0-9][0-9.eE+-]*", blob)] or [(i, i) for i in range(n)]
    while True:
        kind = int(rng.integers(6))
        if kind == 5:
            start, end = numbers[int(rng.integers(len(numbers)))]
            number = HOSTILE_NUMBERS[int(rng.integers(len(HOSTILE_NUMBERS)))].encode("utf-8")
            yield "a hostile number", blob[:start] + number + blob[end:]
            continue
        b = bytearray(blob)
        if kind == 0:
            for i in rng.integers(0, n, int(rng.integers(1, 8))):
                b[i] ^= 1 << int(rng.integers(8))
            yield "bit flips", bytes(b)
        elif kind == 1:
            yield "truncated", bytes(b[: int(rng.integers(0, n))])
        elif kind == 2:
            i, k = int(rng.integers(n)), int(rng.integers(1, 256))
            b[i : i + k] = bytes(min(k, n - i))
            yield "zeroed run", bytes(b)
        elif kind == 3:
            i, k = int(rng.integers(n)), int(rng.integers(1, 256))
            b[i : i + k] = rng.integers(0, 256, min(k, n - i), dtype=np.uint8).tobytes()
            yield "random run", bytes(b)
        else:
            yield "appended junk", bytes(b) + rng.integers(0, 256, int(rng.integers(1, 4096)), dtype=np.uint8).tobytes()


def _pb_varint(value: int) -> bytes:
    out = bytearray()
    while value > 0x7F:
        out.append(value & 0x7F | 0x80)
        value >>= 7
    return bytes(out + bytes([value]))


def _pb(number: int, value) -> bytes:
    """One protobuf field: an int as a varint, str or bytes length-delimited."""
    if isinstance(value, int):
        return _pb_varint(number << 3) + _pb_varint(value)
    data = value.encode() if isinstance(value, str) else value
    return _pb_varint(number << 3 | 2) + _pb_varint(len(data)) + data


def _tensor(name: str, dims: tuple, *fields: bytes, data_type: int = 1) -> bytes:
    """An ONNX TensorProto: name, dims, data type (1 float32) and further fields."""
    return b"".join([_pb(8, name), *(_pb(1, d) for d in dims), _pb(2, data_type), *fields])


def _external(location: str) -> bytes:
    return _pb(13, _pb(1, "location") + _pb(2, location)) + _pb(14, 1)  # external_data, data_location EXTERNAL


def _crafted_models(blob: bytes) -> Iterator[tuple[str, bytes]]:
    """Issue 33's model files, made from the bundled model's bytes without the onnx package: its
    spec's weights_sha256 set to null (same length), then a field appended that protobuf merges
    into the model or its graph (an unused initializer or node, a sparse tensor, a function), or
    the file padded past MAX_MODEL_BYTES. Each must be a ModelError before any run."""
    entry = blob.index(b'"weights_sha256": "') + len(b'"weights_sha256": ')
    blob = blob[:entry] + b"null" + b" " * 62 + blob[entry + 66 :]
    graph = {
        "unused (100000, 100000) float32 with 16 bytes": _pb(5, _tensor("unused", (100000, 100000), _pb(9, bytes(16)))),
        "external data at /etc/passwd": _pb(5, _tensor("passwd", (4,), _external("/etc/passwd"))),
        "external data beside the cwd": _pb(5, _tensor("beside", (4,), _external("weights.bin"))),
        "segment": _pb(5, _tensor("part", (4,), _pb(3, _pb(1, 0) + _pb(2, 2)), _pb(9, bytes(16)))),
        "float64 initializer": _pb(5, _tensor("doubles", (2,), _pb(9, bytes(16)), data_type=11)),
        "Loop with a subgraph": _pb(
            1, _pb(1, "M") + _pb(2, "out") + _pb(3, "forever") + _pb(4, "Loop") + _pb(5, _pb(1, "body") + _pb(6, b""))
        ),
        "operator Tanh": _pb(1, _pb(1, "features") + _pb(2, "t") + _pb(4, "Tanh")),
        "operator of another domain": _pb(1, _pb(1, "features") + _pb(2, "t") + _pb(4, "Erf") + _pb(7, "com.x")),
        "sparse initializer": _pb(15, _pb(1, _tensor("v", (1,), _pb(9, bytes(4)))) + _pb(3, 4)),
    }
    cases = [(name, blob + _pb(7, field)) for name, field in graph.items()]
    cases += [("model-local function", blob + _pb(25, _pb(1, "Twice") + _pb(10, "custom")))]
    cases += [("past the size cap", blob + _pb(6, bytes(MAX_MODEL_BYTES)))]  # doc_string
    while True:
        yield from cases


def _refused(model) -> tuple[str, str]:
    return "silent-wrong", f"loaded ({model.source}): a crafted model must be refused"


def _text_sources(folder: Path) -> dict:
    """The recording's text files (a points CSV of format 2, the gyroscope's and the lens shift's samples), each as
    (bytes, name, reader) for ``fuzz_files``; the points reader read to its end."""
    frame = [
        (f"f{i}", 1000 * i, 10.0 * j, 5.0 * j, float(j), float(j * j), 500.0, 3000.0, 3000.0, 2000.0, 1500.0)
        for i in range(2)
        for j in range(7)
    ]
    times = np.arange(1, 6) * 1_000_000
    files = {
        "points file": ("points.csv", lambda p: write_points(p, frame, frame_k_c=True), lambda p: list(read_points(p))),
        "gyroscope file": ("gyro.csv", lambda p: write_gyro(p, np.c_[times, np.full((5, 3), 0.01)]), read_motion),
        "lens-shift file": ("ois.csv", lambda p: write_lens_shift(p, np.c_[times, np.full((5, 2), 1.5)]), read_motion),
    }
    sources = {}
    for area, (name, write, reader) in files.items():
        path = write(folder / name)
        sources[area] = (path.read_bytes(), name, reader)
    return sources


def fuzz_files(folder: str | Path, n_cases: int, rng: np.random.Generator, report: FuzzReport) -> None:
    """``n_cases`` mutated files of each kind, read by their reader: a dataset (the example frames),
    the bundled model, the paper rig, the example camera as ROS YAML, a points CSV of format 2, a gyroscope's and a
    lens shift's samples. A reader that returns counts
    as ok: a mutation may miss what the reader reads (e.g. zip padding). Then ``n_cases`` crafted
    model files (``_crafted_models``), which must each be refused."""
    folder = Path(folder)
    model = bundled_model_bytes()
    camera = json_file.read(json.loads(asset("example_camera.json").read_text(encoding="utf-8")), "camera")
    sources = {
        "dataset file": (asset("example_frames.npz").read_bytes(), "data.npz", read_dataset),
        "model file": (model, "model.onnx", None),
        "rig file": (asset("paper_rig.json").read_bytes(), "rig.json", load_rig),
        "camera file": (ros.write(camera, "camera.yaml").encode("utf-8"), "camera.yaml", read_camera),
        **_text_sources(folder),
    }
    for area, (blob, name, reader) in sources.items():
        mutations = _mutations(rng, blob)
        for _ in range(n_cases):
            case, data = next(mutations)
            path = folder / name
            path.write_bytes(data)
            if reader is None:
                call = lambda data=data, name=name: onnx_model_from_bytes(data, name)  # noqa: E731
            else:
                call = lambda reader=reader, path=path: reader(path)  # noqa: E731
            outcome, detail = outcome_of(call, lambda result: ("ok", ""))
            report.add(area, case, outcome, detail)
    crafted = _crafted_models(model)
    for _ in range(n_cases):
        case, data = next(crafted)
        outcome, detail = outcome_of(lambda data=data: onnx_model_from_bytes(data, "crafted.onnx"), _refused)
        report.add("crafted model", case, outcome, detail)


def fuzz_ort_file(blob: bytes, source: str, n_cases: int, rng: np.random.Generator, report: FuzzReport) -> None:
    """``n_cases`` byte mutations (``_mutations``) of the model's ORT-format file (`dimenet export --format
    ort`, ``export.onnx_export.ort_format_bytes``: needs torch and onnx) through the runtime's loader: each
    must end in a typed error or load as a model whose Delta K on probe features is the original's, bit
    for bit; a model that loads and gives another is silent-wrong."""
    ort_format_bytes = entry_points("dimenet.export_tools")["ort_format_bytes"].load()

    original = ort_format_bytes(blob, source)
    model = onnx_model_from_bytes(original, "model.ort")
    probe = rng.normal(size=(8, model.spec.features.size)).astype(np.float32)
    want = model.delta_k(probe)

    def same_delta_k(got: np.ndarray) -> tuple[str, str]:
        if np.array_equal(got, want):
            return "ok", ""
        return "silent-wrong", f"loaded; Delta K up to {np.nanmax(np.abs(got - want)):.3g} px off the original's"

    mutations = _mutations(rng, original)
    for _ in range(n_cases):
        case, data = next(mutations)
        outcome, detail = outcome_of(
            lambda data=data: onnx_model_from_bytes(data, "mutated.ort").delta_k(probe), same_delta_k
        )
        report.add(".ort file", case, outcome, detail)
