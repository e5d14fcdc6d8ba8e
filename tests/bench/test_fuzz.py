"""A bounded fuzz (seconds) of issue 20's classes: only typed errors or no-confident-wrong-K results; the full
graph within the parity bound of the runtime, and mutated .ort files typed or equal to the original (issue 48)."""

import subprocess
import sys

import numpy as np
import pytest
from helpers import example_camera

from dimenet.runtime.bench.fuzz import FuzzReport, fuzz_files, fuzz_full_graph, fuzz_ort_file, fuzz_rectifier
from dimenet.runtime.bench.fuzz_stream import fuzz_streams
from dimenet.runtime.rectify.model import MODEL_NAMES, bundled_model_bytes
from dimenet.runtime.rectify.rectifier import Rectifier


@pytest.mark.parametrize("model", MODEL_NAMES)
@pytest.mark.parametrize("mode", ["dimenet", "map"])
def test_hostile_frames_end_typed_or_without_a_confident_wrong_k(frames, mode, model):
    camera = example_camera()
    rect = Rectifier.load(model, K_c=camera.K, image_size=camera.image_size, mode=mode)
    report = FuzzReport()
    fuzz_rectifier(rect, frames, 84, np.random.default_rng(3), report)
    assert report.bad == 0, report.table()
    assert report.counts["rectify"]["typed"] > 20 and report.counts["rectify"]["ok"] > 5  # both kinds happen


@pytest.mark.parametrize("model", MODEL_NAMES)
def test_hostile_streams_end_typed_or_without_a_confident_wrong_k(frames, model):
    """Streams (issue 51): hostile times, per-frame K_c, samples, options and frames; a typed error leaves the stream
    usable (``fuzz_stream``)."""
    camera = example_camera()
    rect = Rectifier.load(model, K_c=camera.K, image_size=camera.image_size)
    report = FuzzReport()
    fuzz_streams(rect, frames, 60, np.random.default_rng(6), report)
    assert report.bad == 0, report.table()
    counts = report.counts["stream"]
    assert counts["typed"] > 30 and counts["ok"] > 100, report.table()  # both kinds happen


def test_mutated_files_end_in_typed_errors(tmp_path):
    report = FuzzReport()
    fuzz_files(tmp_path, 40, np.random.default_rng(4), report)
    assert report.bad == 0, report.table()
    assert report.counts["crafted model"]["typed"] == 40, report.table()  # issue 33: every crafted model refused
    assert all(c["typed"] > 10 for c in report.counts.values()), report.table()


@pytest.fixture(scope="module")
def scenes():
    """Simulated galaxy-s8 frames of every scene: rig, natural and one-plane (planar) frames."""
    from dimenet.runtime.sim.simulator import simulate

    return simulate("galaxy-s8", seed=7, natural_frames=3, planar_frames=3)


@pytest.mark.parametrize("model", MODEL_NAMES)
def test_the_full_graph_equals_the_runtime_on_the_fuzz_s_frames_within_the_parity_bound(scenes, model):
    """The full graph against ``Rectifier.network`` on frames of every scene, in other units, subsets and
    hostile variants, half of them with masked NaN, inf and camera-centre points among theirs, and on no
    point (N = 0, all masked): issue 48 #2 and #3 (models_spec/model-v1.md, "The full graph's contract")."""
    pytest.importorskip("onnx")
    report = FuzzReport()
    fuzz_full_graph(bundled_model_bytes(model), model, scenes, 150, np.random.default_rng(5), report)
    assert report.bad == 0, report.table()
    counts = report.counts["full graph"]
    assert counts["ok"] > 50 and counts["typed"] > 20, report.table()  # compared, and refused by the runtime


@pytest.mark.parametrize("model", MODEL_NAMES)
def test_mutated_ort_files_end_in_typed_errors_or_the_original_s_delta_k(model):
    pytest.importorskip("onnx")
    pytest.importorskip("torch")  # the ORT-format conversion sits beside the torch export
    report = FuzzReport()
    fuzz_ort_file(bundled_model_bytes(model), model, 40, np.random.default_rng(6), report)
    assert report.bad == 0, report.table()
    assert report.counts[".ort file"]["typed"] > 30, report.table()


def test_bench_fuzz_without_onnx_or_torch_runs_and_says_which_areas_it_skips():
    """The base install has neither: `dimenet bench --fuzz` still fuzzes the rectifier and the readers, and
    one line per area it skips names the install that brings it."""
    code = (
        "import sys; sys.modules['onnx'] = sys.modules['torch'] = None\n"  # import raises ImportError
        "from dimenet.runtime.cli.main import main\n"
        "sys.exit(main(sys.argv[1:]))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code, "bench", "--fuzz", "4", "--seed", "2"], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert any(line.startswith("rectify ") for line in lines) and not any(
        line.startswith("full graph ") for line in lines
    )
    skipped = [line for line in lines if "skipped" in line]
    assert len(skipped) == 2, done.stdout
    assert skipped[0].startswith("full graph: skipped, it needs onnx (the export extra): ") and "[export]" in skipped[0]
    assert skipped[1].startswith(".ort file: skipped, it needs torch and onnx (the train extra): ")
