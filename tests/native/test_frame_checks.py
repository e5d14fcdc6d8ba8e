"""The input rules' fast tests in the compiled core (``native.core.frame_checks``, ``validated_frame``'s with
a camera without a lens) against the numpy rules: the same verdict (all_inside, clearly_spread) and the 3D
points' covariance invariants to the bit on the bench's 2000 frames and both models' golden frames, and the same
accepted frames, invariants and InputError messages on hostile ones, alone and in a batch."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import random_frames

from dimenet.runtime import native
from dimenet.runtime.bench.latency import bench_frames
from dimenet.runtime.errors import InputError
from dimenet.runtime.geometry import MAX_COORDINATE, covariance_invariants
from dimenet.runtime.rectify.checks import (
    SPREAD_ABSOLUTE,
    SPREAD_RATIO,
    ImageBounds,
    all_inside,
    validated_batch,
    validated_frame,
    well_spread,
)

pytestmark = pytest.mark.skipif(not native.compiled_available(), reason="the compiled core is not built")

GOLDEN_DIR = Path(__file__).resolve().parents[2] / "models_spec" / "golden"
IMAGE = ImageBounds((4032, 3024))


def numpy_verdict(p2, p3) -> int:
    if not all_inside(IMAGE, p2, p3):
        return 1
    spread = well_spread(p3, covariance_invariants(p3)) and well_spread(p2, covariance_invariants(p2))
    return 0 if spread else 2


def core_checks(p2, p3) -> tuple[int, tuple]:
    core = native._compiled()[0]
    return core.frame_checks(p2, p2, p3, IMAGE.width, IMAGE.height, MAX_COORDINATE, SPREAD_RATIO, SPREAD_ABSOLUTE)


def core_verdict(p2, p3) -> int:
    return core_checks(p2, p3)[0]


def test_the_core_gives_the_references_invariants_to_the_bit():
    # bench frames, then scenes from 1e-6 to 1e10 mm, far off their origin, planar and repeated points
    p2, p3 = bench_frames(300, 320, (4032, 3024))
    rng = np.random.default_rng(11)
    scenes = list(p3)
    for scale in 10.0 ** np.arange(-6, 11):
        X = rng.normal(0.0, scale, (int(rng.integers(6, 2000)), 3)) + rng.normal(0.0, 30 * scale, 3)
        scenes += [X, X * [1.0, 1.0, 0.0], np.repeat(X[:3], 4, 0)]
    for X in scenes:
        X = np.ascontiguousarray(X[np.all(np.abs(X) < MAX_COORDINATE, 1)])
        x = np.full((len(X), 2), 100.0)
        verdict, invariants = core_checks(x, X)
        assert verdict != 1
        assert invariants == covariance_invariants(X)  # floats compared exactly


def test_outside_points_give_no_invariants():
    x, X = hostile_frames()["outside"]
    verdict, invariants = core_checks(x, X)
    assert verdict == 1 and np.isnan(invariants).all()


def test_the_same_verdict_on_the_bench_and_golden_frames():
    p2, p3 = bench_frames(2000, 320, (4032, 3024))
    frames = list(zip(p2, p3))
    for path in (GOLDEN_DIR / "golden.json", GOLDEN_DIR / "paper-rig" / "golden.json"):
        for f in json.loads(path.read_text())["frames"]:
            x = f["inputs"]
            if tuple(int(v) for v in x["image_size"]) == (4032, 3024):
                frames.append((np.array(x["points_2d"], dtype=np.float64), np.array(x["points_3d"], dtype=np.float64)))
    verdicts = [(numpy_verdict(x, X), core_verdict(x, X)) for x, X in frames]
    assert all(a == b for a, b in verdicts)
    assert len(verdicts) > 2000 and {a for a, _ in verdicts} <= {0, 1, 2}


def hostile_frames():
    x, X, _, _, _ = random_frames(np.random.default_rng(4), frames=1, points=30)
    x, X = np.ascontiguousarray(x[0]), np.ascontiguousarray(X[0])
    line = X.copy()
    line[:, 1:] = 0.0
    edits = {
        "ordinary": (x, X),
        "a NaN pixel": (np.where(np.arange(30)[:, None] == 3, np.nan, x), X),
        "an inf coordinate": (x, np.where(np.arange(30)[:, None] == 5, np.inf, X)),
        "beyond the range": (x, np.where(np.arange(30)[:, None] == 6, MAX_COORDINATE, X)),
        "on the edge": (np.where(np.arange(30)[:, None] == 2, -0.5, x), X),
        "outside": (np.where(np.arange(30)[:, None] == 2, -0.51, x), X),
        "collinear 3D points": (x, line),
        "coincident pixels": (np.repeat(x[:1], 30, 0), X),
        "repeated correspondences": (np.repeat(x[:3], 10, 0), np.repeat(X[:3], 10, 0)),
    }
    return edits


@pytest.mark.parametrize("case", sorted(hostile_frames()))
def test_validated_frame_accepts_and_refuses_alike(case):
    x, X = hostile_frames()[case]
    out = {}
    for exact_map, name in ((False, "python"), (True, "c")):
        with native.using(name):
            try:
                out[name] = validated_frame(IMAGE, lambda p, valid=True: p, x, X, exact_map=exact_map)
            except InputError as exc:
                out[name] = str(exc)
    if isinstance(out["python"], str):
        assert out["python"] == out["c"], case
    else:
        assert all(np.array_equal(a, b) for a, b in zip(out["python"][:3], out["c"][:3])), case
        assert out["python"][3] == out["c"][3], case  # the 3D invariants, to the bit


@pytest.mark.parametrize("case", sorted(hostile_frames()))
def test_validated_batch_accepts_and_refuses_alike(case):
    # the hostile frame third in a batch of ordinary ones; and after a frame that is not spread, so the
    # first frame outside is named before it, as the numpy rules name them
    frames = hostile_frames()
    for before in ("ordinary", "collinear 3D points"):
        batch = [frames["ordinary"], frames[before], frames[case], frames["ordinary"]]
        x, X = (np.stack([f[i] for f in batch]) for i in (0, 1))
        valid = np.ones(x.shape[:2], bool)
        out = {}
        for exact_map, name in ((False, "python"), (True, "c")):
            with native.using(name):
                try:
                    fr = validated_batch(IMAGE, lambda p, valid=True: p, x, X, valid, None, exact_map=exact_map)
                    pairs = [a for pair in fr.frames for a in pair]
                    out[name] = (fr.points_2d, fr.points_3d, fr.points_2d_image, *pairs)
                except InputError as exc:
                    out[name] = str(exc)
        if isinstance(out["python"], str):
            assert out["python"] == out["c"], (case, before)
        else:
            assert all(np.array_equal(a, b) for a, b in zip(out["python"], out["c"])), (case, before)
