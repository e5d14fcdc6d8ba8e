"""`dimenet bench --ingest` (``bench.ingest``) on small rendered photos: scored against their truth, and the
same photos as a folder of real photos with their rig (no truth: timed and counted)."""

from __future__ import annotations

import dataclasses
import json
import shutil

import pytest

from dimenet.runtime.bench.ingest import RIG_FILE, format_ingest_report, rendered_with, run_ingest_bench
from dimenet.runtime.errors import DatasetError, IngestError
from dimenet.runtime.formats.render_truth import read_truth
from dimenet.runtime.formats.rig import paper_rig, rig_to_dict
from dimenet.runtime.sim.profiles import get_profile
from dimenet.runtime.sim.render import TRUTH_FILE, scaled_profile, write_render


def test_rendered_photos_are_scored_against_their_truth_and_real_ones_counted(tmp_path):
    rendered = tmp_path / "rendered"
    write_render(rendered, paper_rig(), scaled_profile(get_profile("galaxy-s8"), 3.0), 2, seed=0)
    figures = run_ingest_bench(rendered, n=2, seed=0, profile="galaxy-s8", workers=1)
    assert figures["photos"] == 2 and figures["boards_shown"] > 0
    assert figures["detection_rate"] == figures["boards_found"] / figures["boards_shown"] > 0.5
    assert figures["identity_errors"] == 0 and figures["corner_rms_px"] < 0.5 and figures["k_error_px"] < 5.0
    assert f"{figures['photos']} photos, {figures['frames']} frames" in format_ingest_report(figures)

    real = tmp_path / "real"
    real.mkdir()
    for photo in sorted(rendered.glob("photo-*")):
        shutil.copy(photo, real)
    (real / RIG_FILE).write_text(json.dumps(rig_to_dict(paper_rig())))
    assert not (real / TRUTH_FILE).exists()
    counted = run_ingest_bench(real, n=2, seed=0, profile="galaxy-s8", workers=1)
    assert counted["photos"] == 2 and counted["boards_in_rig"] == len(paper_rig().boards)
    assert sum(len(b) for b in counted["boards"].values()) == figures["boards_found"] + figures["extra_boards"]
    assert "2 real photos" in format_ingest_report(counted)


def test_a_folder_rendered_with_other_options_is_refused_not_reused(tmp_path):
    """`bench --ingest DIR --seed 1` on photos rendered with seed 0 once scored those silently."""
    write_render(tmp_path, paper_rig(), scaled_profile(get_profile("galaxy-s8"), 6.0), 1, seed=0)
    truth = read_truth(tmp_path / TRUTH_FILE)
    assert rendered_with(truth, tmp_path / TRUTH_FILE) == {"n": 1, "seed": 0, "profile": "galaxy-s8"}
    with pytest.raises(DatasetError, match="its meta does not say how the photos were rendered"):
        rendered_with(dataclasses.replace(truth, meta={}), tmp_path / TRUTH_FILE)
    for asked, message in (
        ({"seed": 1}, "--seed 0, not --seed 1"),
        ({"n": 30, "seed": 0}, "--n 1, not --n 30"),
        ({"profile": "iphone-12-pro"}, "--profile galaxy-s8, not --profile iphone-12-pro"),
    ):
        with pytest.raises(IngestError, match=rf"holds photos rendered with {message}: give a new folder"):
            run_ingest_bench(tmp_path, n=30, seed=1, profile="galaxy-s8", workers=1, asked=asked)
