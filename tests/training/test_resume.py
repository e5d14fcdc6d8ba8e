"""`dimenet train --resume RUN_DIR`: a training stopped after epoch k (killed, or interrupted) continues at k + 1
from its checkpoint and ends with the same weights, history and spec, bit for bit, as one never stopped."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time

import pytest

torch = pytest.importorskip("torch")  # the base-only install has no torch: skip, not fail

from dimenet.runtime.cli.main import main
from dimenet.runtime.formats.dataset import write_dataset
from dimenet.runtime.sim.profiles import PROFILES
from dimenet.runtime.sim.simulator import simulate
from dimenet.training import trainer
from dimenet.training.config import TrainConfig
from dimenet.training.run_dir import CHECKPOINT, HISTORY, SPEC, WEIGHTS, read_checkpoint

TINY = dataclasses.replace(PROFILES["galaxy-s8"], name="tiny-s8", n_train=30, n_test=8)
EPOCHS = 4


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    path = tmp_path_factory.mktemp("tiny") / "tiny.npz"
    write_dataset(simulate(TINY, seed=3), path)
    return path


@pytest.fixture(scope="module")
def uninterrupted(tiny, tmp_path_factory):
    run = tmp_path_factory.mktemp("whole") / "run"
    assert main(["train", str(tiny), "--out", str(run), "--epochs", str(EPOCHS), "--seed", "2"]) == 0
    return run


def _same_run(a, b) -> None:
    """The same weights and history, byte for byte, and the same spec but for the command line."""
    for name in (WEIGHTS, HISTORY):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    specs = [json.loads((run / SPEC).read_text()) for run in (a, b)]
    for spec in specs:
        spec["provenance"].pop("command")
    assert specs[0] == specs[1]


def _stop_after(monkeypatch, epoch: int) -> None:
    """Interrupt the training once the checkpoint of ``epoch`` is written (as Ctrl-C would there)."""
    write = trainer.write_checkpoint

    def write_then_stop(run_dir, tensors, state):
        write(run_dir, tensors, state)
        if state["epoch"] == epoch:
            raise KeyboardInterrupt

    monkeypatch.setattr(trainer, "write_checkpoint", write_then_stop)


def test_an_interrupted_training_resumes_at_its_epoch_with_the_same_weights(tiny, uninterrupted, tmp_path, capsys):
    run = tmp_path / "run"
    with pytest.MonkeyPatch.context() as patch:
        _stop_after(patch, 2)
        assert main(["train", str(tiny), "--out", str(run), "--epochs", str(EPOCHS), "--seed", "2"]) == 130
    assert not (run / WEIGHTS).exists() and read_checkpoint(run)[1]["epoch"] == 2
    refused = main(["train", str(tiny), "--out", str(run)])  # a new training would overwrite what was done
    assert refused == 2 and "--resume" in capsys.readouterr().err
    epochs = []
    with pytest.MonkeyPatch.context() as patch:
        write = trainer.write_checkpoint
        patch.setattr(trainer, "write_checkpoint", lambda d, t, s: (epochs.append(s["epoch"]), write(d, t, s)))
        assert main(["train", "--resume", str(run)]) == 0
    assert epochs == [3, 4]  # on from epoch 3, not from the start
    _same_run(run, uninterrupted)
    assert not (run / CHECKPOINT).exists()  # the run is written: nothing left to resume
    assert main(["train", "--resume", str(run)]) == 0 and "nothing to resume" in capsys.readouterr().out


def test_a_killed_training_resumes_with_the_same_weights(tiny, uninterrupted, tmp_path):
    """SIGKILL at any moment: the checkpoint is the last epoch's whole (written atomically)."""
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "dimenet", "train", str(tiny), "--out", str(run), "--epochs", str(EPOCHS)]
    proc = subprocess.Popen([*cmd, "--seed", "2"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while not (run / CHECKPOINT).exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    assert proc.returncode == -signal.SIGKILL, "the training ended before it could be killed"
    stopped_at = read_checkpoint(run)[1]["epoch"]
    assert 1 <= stopped_at < EPOCHS and not (run / WEIGHTS).exists()
    assert main(["train", "--resume", str(run)]) == 0
    _same_run(run, uninterrupted)


def test_resume_refuses_other_settings_and_a_checkpoint_of_another_training(tiny, tmp_path, monkeypatch, capsys):
    run = tmp_path / "run"
    _stop_after(monkeypatch, 1)
    assert main(["train", str(tiny), "--out", str(run), "--epochs", "3"]) == 130
    capsys.readouterr()
    assert main(["train", "--resume", str(run), "--epochs", "5"]) == 2
    assert "--epochs given, but a resumed training keeps" in capsys.readouterr().err
    from dimenet.runtime.errors import InputError
    from dimenet.training.trainer import read_training_data, train

    datasets, sha256 = read_training_data(tiny)
    with pytest.raises(InputError, match="the checkpoint of another training \\(config differ"):
        train(datasets, TrainConfig(epochs=3, seed=9), run, dataset_sha256=sha256, resume=True)
    assert main(["train", "--resume", str(tmp_path / "nothing")]) == 2
    assert "no checkpoint, so no training to resume" in capsys.readouterr().err
