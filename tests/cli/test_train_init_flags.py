"""`dimenet train --init MODEL` keeps the init's grid, features, data step, moments and head (issue 48, side
note): each of those flags given another value is named on a warning line instead of being silently
ignored, the run's config records what is trained, and without --init the flags and defaults hold."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

pytest.importorskip("torch")

from dimenet.runtime.cli.main import main  # noqa: E402
from dimenet.runtime.formats.dataset import write_dataset  # noqa: E402
from dimenet.runtime.rectify.model import load_model  # noqa: E402


@pytest.fixture
def trained(s8_dataset, tmp_path, monkeypatch):
    """Runs `dimenet train` on the galaxy-s8 dataset with the training itself replaced by a stub;
    returns (exit code, the TrainConfig it got, stderr's lines)."""
    import dimenet.training.trainer as trainer

    data = write_dataset(s8_dataset, tmp_path / "s8.npz")
    got = {}

    def stub(datasets, config, run_dir, **kwargs):
        got["config"] = config
        return SimpleNamespace(history=[], best_epoch=0, best_val_e=0.0, seconds=0.0, run_dir=run_dir)

    monkeypatch.setattr(trainer, "train", stub)

    def run(capsys, *flags):
        code = main(["train", str(data), "--out", str(tmp_path / "run"), *flags])
        return code, got.get("config"), capsys.readouterr().err.splitlines()

    return run


def test_flags_an_init_fixes_are_named_when_it_overrides_them(trained, capsys):
    code, config, err = trained(capsys, "--init", "paper-rig", "--data-step", "--moments", "--grid", "16x12")
    assert code == 0
    assert err == [
        "dimenet train: warning: --grid 16x12 is ignored: --init paper-rig keeps its own grid, 8x6",
        "dimenet train: warning: --data-step is ignored: --init paper-rig keeps its own feature, without the data step",
        "dimenet train: warning: --moments is ignored: --init paper-rig keeps its own feature, without the moments",
    ]
    f = config.features
    assert (str(f.grid), f.data_step, f.moments, config.head) == ("8x6", False, False, "mlp")
    assert f == load_model("paper-rig").spec.features  # the init's whole feature, recorded


def test_flags_that_agree_with_the_init_or_are_left_out_give_no_warning(trained, capsys):
    code, config, err = trained(capsys, "--init", "any-scene", "--data-step", "--head", "gated_step")
    assert code == 0 and err == []
    assert (config.features.data_step, config.features.moments, config.head) == (True, True, "gated_step")
    code, config, err = trained(capsys, "--init", "any-scene", "--features", "B", "--head", "mlp")
    assert err == [
        "dimenet train: warning: --features B is ignored: --init any-scene keeps its own feature variant, A",
        "dimenet train: warning: --head mlp is ignored: --init any-scene keeps its own head, gated_step",
    ]


def test_without_init_the_flags_and_defaults_hold(trained, capsys):
    code, config, err = trained(capsys)
    assert code == 0 and err == []
    f = config.features
    assert (str(f.grid), f.variant, f.data_step, f.moments, config.head) == (
        "8x6",
        "A",
        False,
        False,
        "mlp",
    )
    code, config, err = trained(capsys, "--grid", "4x3", "--features", "B", "--data-step", "--head", "gated_step")
    assert code == 0 and err == []
    f = config.features
    assert (str(f.grid), f.variant, f.data_step, config.head) == ("4x3", "B", True, "gated_step")
