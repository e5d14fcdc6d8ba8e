"""The runtime against the committed golden vectors of each bundled model (models_spec/golden/golden.json,
written by `dimenet export default --golden models_spec/golden`, and models_spec/golden/paper-rig/golden.json
by `dimenet export paper-rig --golden models_spec/golden/paper-rig`): the network's Delta K, K and sigma at
the stored C0 pose, and rectify's K, fallback and errors, each within the parity bound (PARITY_PX,
models_spec/model-v1.md, "The full graph's contract"). A change of a bundled model, the feature, a rule or
the simulator that moves any of them fails here until the golden set is written again."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dimenet.export.golden import PARITY_PX as TOLERANCE_PX
from dimenet.runtime.rectify.model import bundled_source, load_model
from dimenet.runtime.rectify.rectifier import Rectifier

GOLDEN_DIR = Path(__file__).resolve().parents[2] / "models_spec" / "golden"
GOLDEN = {"default": GOLDEN_DIR / "golden.json", "paper-rig": GOLDEN_DIR / "paper-rig" / "golden.json"}


@pytest.fixture(scope="module")
def golden() -> dict:
    return json.loads(GOLDEN["default"].read_text())


@pytest.fixture(scope="module", params=sorted(GOLDEN))
def named_golden(request) -> tuple:
    return request.param, json.loads(GOLDEN[request.param].read_text())


def test_the_golden_set_spans_cameras_scenes_and_fallbacks(golden):
    frames = golden["frames"]
    assert golden["format"] == "dimenet-golden/1" and 18 <= len(frames) <= 30
    sizes = {tuple(f["inputs"]["image_size"]) for f in frames}
    # Each rule falls back on one of the frames under one of the bundled models (the same frames).
    reasons = [f["expected"]["fallback"] for path in GOLDEN.values() for f in json.loads(path.read_text())["frames"]]
    assert len(sizes) >= 4 and sum(r is None for r in reasons) >= 15
    assert {"structure", "worse than K_c", "mean error of"} <= {
        key for key in ("structure", "worse than K_c", "mean error of") for r in reasons if r and key in r
    }
    codes = [f["expected"]["fallback_code"] for path in GOLDEN.values() for f in json.loads(path.read_text())["frames"]]
    assert [c is None for c in codes] == [r is None for r in reasons]
    assert {"structure", "worse_than_k_c", "out_of_range"} <= set(codes)
    assert (
        min(len(f["inputs"]["points_2d"]) for f in frames)
        <= 66
        < 320
        <= max(len(f["inputs"]["points_2d"]) for f in frames)
    )


def test_each_bundled_model_s_set_has_the_same_frames_and_names_its_model(golden, named_golden):
    name, other = named_golden
    assert [f["inputs"] for f in other["frames"]] == [f["inputs"] for f in golden["frames"]]
    assert other["model"]["source"] == bundled_source(name)
    assert other["model"]["sha256"] == load_model(name).sha256


def test_the_runtime_gives_the_golden_numbers(named_golden):
    name, golden = named_golden
    for frame in golden["frames"]:
        x, want = frame["inputs"], frame["expected"]
        rect = Rectifier.load(name, K_c=np.array(x["K_c"]), image_size=tuple(int(v) for v in x["image_size"]))
        p2, p3 = np.array(x["points_2d"]), np.array(x["points_3d"])
        net = rect.network(p2, p3, np.array(want["rvec"]), np.array(want["tvec"]))
        for got, key in ((net.delta_k, "delta_k"), (net.K, "K"), (net.sigma, "sigma")):
            np.testing.assert_allclose(
                got, np.array(want[key]), rtol=0, atol=TOLERANCE_PX, err_msg=f"{frame['name']} {key}"
            )
        result = rect.rectify(p2, p3)
        assert result.fallback == want["fallback"], frame["name"]
        assert result.fallback_code == want["fallback_code"], frame["name"]
        np.testing.assert_allclose(result.K, np.array(want["rectified_K"]), rtol=0, atol=TOLERANCE_PX)
        assert abs(result.reprojection_error_px - want["e_px"]) <= TOLERANCE_PX
        assert abs(result.reprojection_error_kc_px - want["e_c_px"]) <= TOLERANCE_PX
