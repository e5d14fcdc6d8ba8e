"""Golden vectors (`dimenet export SOURCE --golden DIR`): a fixed set of frames across cameras,
scenes and fallbacks with what the Python runtime gives for them, so the full graph, a runner in
another language and later releases are held to the same numbers (models_spec/golden.md).

The frames are simulated, deterministically (seeds below): the paper's galaxy-s8 and iphone-12-pro
(rig, rig at 64 points, natural, planar, the galaxy-s8 at half resolution) and cameras of a held-out
random-scene family, where the bundled model's K falls back on some; one frame is spoiled on purpose
(25 px of noise on its 2D points: the range rule). K_c is the mean true K of each camera's train
frames, rounded to 0.01 px.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dimenet.runtime.evaluation.conditions import drop_inference_points
from dimenet.runtime.formats.atomic import atomic_write
from dimenet.runtime.geometry import k_matrix, k_params, solve_pnp_start
from dimenet.runtime.rectify.model import load_model
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.user_camera import checked_camera
from dimenet.runtime.sim.family import family_member, family_profiles
from dimenet.runtime.sim.simulator import simulate

FORMAT = "dimenet-golden/1"
# The parity bound the runtime, the full graph and a port are held to (models_spec/model-v1.md, "The full graph's
# contract"): two float32 steps of the network's Delta K (a float32: a step is at most 2^-23 of it) at a |Delta K|
# of PARITY_DELTA_PX, PARITY_PX = 2^-15 px, and above that of |Delta K| (``parity_px``). The golden frames' |Delta K|
# are below PARITY_DELTA_PX; export/node_runner/run.mjs's TOLERANCE_PX is PARITY_PX.
PARITY_STEPS = 2 * 2.0**-23
PARITY_DELTA_PX = 128.0
PARITY_PX = PARITY_STEPS * PARITY_DELTA_PX
GOLDEN_FILE = "golden.json"
FAMILY_SEED, FAMILY_CAMERAS = 303, 4  # a family no model trains on (train: 0; held-out families 101, 202)
# The family's frames, per camera: test frames; camera 2's 83 the bundled model's K_c keeps by the structure rule,
# camera 3's 87 where its K fits worse than K_c.
FAMILY_FRAMES = ((80, 81, 82), (80, 81, 82), (80, 81, 83), (87,))


@dataclass(frozen=True)
class GoldenFrame:
    """One frame's inputs: name, what it shows, points_2d (N, 2) px, points_3d (N, 3), K_c (3, 3) px,
    image_size (width, height) px."""

    name: str
    note: str
    points_2d: np.ndarray
    points_3d: np.ndarray
    K_c: np.ndarray
    image_size: tuple


def _k_c(ds) -> np.ndarray:
    return k_matrix(np.round(k_params(ds.K_true[ds.frames_in("train")]).mean(0), 2))


def _frame(ds, b: int, name: str, note: str, K_c=None) -> GoldenFrame:
    m = ds.valid[b] & ds.infer_mask[b]
    return GoldenFrame(
        name, note, ds.points_2d[b][m], ds.points_3d[b][m], _k_c(ds) if K_c is None else K_c, tuple(ds.image_size)
    )


def golden_frames() -> list[GoldenFrame]:
    """The golden set's frames (about 20), in a fixed order."""
    frames = []
    s8 = simulate("galaxy-s8", seed=0, natural_frames=4, planar_frames=4)
    test = np.flatnonzero(s8.frames_in("test"))
    kinds = {kind: [b for b in test if s8.scene[b] == kind] for kind in ("rig", "natural", "planar")}
    for k, b in enumerate(kinds["rig"][:3]):
        frames.append(_frame(s8, b, f"galaxy-s8-rig-{k}", "galaxy-s8 4032x3024, the paper's rig"))
    few = drop_inference_points(
        s8.select(np.isin(np.arange(s8.n_frames), kinds["rig"][3:4])), 64, np.random.default_rng(0)
    )
    frames.append(_frame(few, 0, "galaxy-s8-rig-64", "galaxy-s8, the rig at 64 points", _k_c(s8)))
    for kind in ("natural", "planar"):
        for k, b in enumerate(kinds[kind][:2]):
            frames.append(_frame(s8, b, f"galaxy-s8-{kind}-{k}", f"galaxy-s8, {kind} points"))
    half = _frame(s8, kinds["rig"][4], "galaxy-s8-half", "galaxy-s8 at half resolution (2016x1512)")
    K_half = half.K_c.copy()
    K_half[:2] *= 0.5
    K_half[:2, 2] -= 0.25
    frames.append(
        GoldenFrame(half.name, half.note, (half.points_2d + 0.5) / 2 - 0.5, half.points_3d, K_half, (2016, 1512))
    )
    iphone = simulate("iphone-12-pro", seed=0)
    for k, b in enumerate(np.flatnonzero(iphone.frames_in("test"))[:2]):
        frames.append(_frame(iphone, b, f"iphone-12-pro-rig-{k}", "iphone-12-pro 4032x3024, the paper's rig"))
    for i, profile in enumerate(family_profiles(FAMILY_CAMERAS, FAMILY_SEED)):
        ds = family_member(profile, i, FAMILY_SEED, FAMILY_CAMERAS, scenes="random")
        size = "x".join(str(int(v)) for v in ds.image_size)
        for k, b in enumerate(FAMILY_FRAMES[i]):
            frames.append(_frame(ds, b, f"family-{FAMILY_SEED}-{i}-{k}", f"held-out camera {size}, a random rig"))
    spoiled = frames[0]
    noise = np.random.default_rng(1).normal(scale=25.0, size=spoiled.points_2d.shape)
    noisy = np.clip(spoiled.points_2d + noise, 0.0, np.array(spoiled.image_size) - 1.0)
    frames.append(
        GoldenFrame(
            "noisy",
            "galaxy-s8 rig, 25 px of noise on the 2D points: the range rule",
            noisy,
            spoiled.points_3d,
            spoiled.K_c,
            spoiled.image_size,
        )
    )
    return frames


def parity_px(delta_k) -> float:
    """The parity bound (px) of a frame whose Delta K (px) is ``delta_k``: PARITY_PX, or where its largest
    |Delta K| is above PARITY_DELTA_PX two float32 steps of it."""
    return PARITY_STEPS * max(PARITY_DELTA_PX, float(np.abs(delta_k).max()))


def expected(rect: Rectifier, frame: GoldenFrame) -> dict:
    """What the Python runtime gives for one frame: the C0 pose (SQPnP under K_c), the network's
    Delta K, K and sigma (``Rectifier.network``), and ``rectify``'s K, fallback, its code and errors."""
    rvec, tvec = solve_pnp_start(frame.points_2d, frame.points_3d, frame.K_c)
    net = rect.network(frame.points_2d, frame.points_3d, rvec, tvec)
    result = rect.rectify(frame.points_2d, frame.points_3d)
    return {
        "rvec": rvec.tolist(),
        "tvec": tvec.tolist(),
        "delta_k": net.delta_k.tolist(),
        "K": net.K.tolist(),
        "sigma": None if net.sigma is None else net.sigma.tolist(),
        "rectified_K": result.K.tolist(),
        "fallback": result.fallback,
        "fallback_code": result.fallback_code,
        "e_px": result.reprojection_error_px,
        "e_c_px": result.reprojection_error_kc_px,
    }


def golden(model_path=None) -> dict:
    """The golden set of a generic model (a bundled model's name or a .onnx; None: the bundled
    default) as a JSON-ready dict."""
    model = load_model(model_path)
    records = []
    for frame in golden_frames():
        rect = Rectifier(model, "dimenet", _camera(frame))
        records.append(
            {
                "name": frame.name,
                "note": frame.note,
                "inputs": {
                    "points_2d": frame.points_2d.tolist(),
                    "points_3d": frame.points_3d.tolist(),
                    "mask": [True] * len(frame.points_2d),
                    "K_c": frame.K_c.tolist(),
                    "image_size": [float(v) for v in frame.image_size],
                },
                "expected": expected(rect, frame),
            }
        )
    return {"format": FORMAT, "model": {"source": model.source, "sha256": model.sha256}, "frames": records}


def _camera(frame: GoldenFrame):
    return checked_camera(frame.K_c, frame.image_size, frame.name)


def write_golden(out_dir, model_path=None) -> Path:
    """Write ``out_dir/golden.json`` (atomically). Returns its path."""
    out = Path(out_dir) / GOLDEN_FILE
    out.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(golden(model_path), indent=None, separators=(",", ":"))
    return atomic_write(out, lambda f: f.write(text.encode("utf-8")))
