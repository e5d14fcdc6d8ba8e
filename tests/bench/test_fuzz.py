"""A bounded fuzz (seconds) of issue 20's classes: only typed errors or no-confident-wrong-K results."""

import numpy as np
import pytest
from helpers import example_camera

from dimenet.runtime.bench.fuzz import FuzzReport, fuzz_files, fuzz_rectifier
from dimenet.runtime.rectify.model import BUNDLED_MODELS
from dimenet.runtime.rectify.rectifier import Rectifier


@pytest.mark.parametrize("model", sorted(BUNDLED_MODELS))
@pytest.mark.parametrize("mode", ["dimenet", "map"])
def test_hostile_frames_end_typed_or_without_a_confident_wrong_k(frames, mode, model):
    camera = example_camera()
    rect = Rectifier.load(model, K_c=camera.K, image_size=camera.image_size, mode=mode)
    report = FuzzReport()
    fuzz_rectifier(rect, frames, 84, np.random.default_rng(3), report)
    assert report.bad == 0, report.table()
    assert report.counts["rectify"]["typed"] > 20 and report.counts["rectify"]["ok"] > 5  # both kinds happen


def test_mutated_files_end_in_typed_errors(tmp_path):
    report = FuzzReport()
    fuzz_files(tmp_path, 40, np.random.default_rng(4), report)
    assert report.bad == 0, report.table()
    assert report.counts["crafted model"]["typed"] == 40, report.table()  # issue 33: every crafted model refused
    assert all(c["typed"] > 10 for c in report.counts.values()), report.table()
