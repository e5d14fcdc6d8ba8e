"""training/config.py: `dimenet train` and `dimenet reproduce` take their defaults from the
dataclasses, without importing torch (runs on the base install too)."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys

from dimenet.runtime.cli.main import build_parser
from dimenet.training.config import ReproduceConfig, TrainConfig


def test_train_and_reproduce_defaults_are_the_configs_own():
    parser = build_parser()
    train = parser.parse_args(["train", "data.npz", "--out", "run"])
    d = TrainConfig()
    assert (train.grid, train.features, train.epochs, train.seed, train.focal_weight) == (
        str(d.features.grid),
        d.features.variant,
        d.epochs,
        d.seed,
        d.focal_weight,
    )
    reproduce = parser.parse_args(["reproduce", "--out", "out"])
    not_flags = ("out_dir", "held_out_cameras")
    defaults = {f.name: f.default for f in dataclasses.fields(ReproduceConfig) if f.name not in not_flags}
    assert {k: getattr(reproduce, k) for k in defaults} == defaults  # held_out_cameras: --quick's


def test_train_help_states_the_defaults_and_imports_no_torch():
    code = (
        "import sys\n"
        "import dimenet.training.commands, dimenet.training.config\n"
        "from dimenet.runtime.cli.main import main\n"
        "for cmd in ('train', 'reproduce'):\n"
        "    try:\n"
        "        main([cmd, '--help'])\n"
        "    except SystemExit as exc:\n"
        "        assert exc.code == 0, exc.code\n"
        "assert 'torch' not in sys.modules\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env={**os.environ, "COLUMNS": "200"}
    )
    assert done.returncode == 0, done.stderr
    d = TrainConfig()
    for text in (
        f"(default {d.features.grid})",
        f"(default {d.features.variant})",
        f"(default {d.epochs};",
        f"(default {d.seed})",
    ):
        assert text in done.stdout
    assert f"(default {d.focal_weight}; 0: the paper's loss alone)" in done.stdout


def test_the_config_holds_a_feature_spec_and_round_trips_through_json():
    from dimenet.runtime.rectify.features import FeatureSpec
    from dimenet.runtime.rectify.grid import Grid

    config = TrainConfig(
        features=FeatureSpec(Grid(4, 3), "C", data_step=True, moments=True), head="gated_step", hidden=(64, 32)
    )
    text = json.dumps(config.to_dict())
    assert TrainConfig.from_dict(json.loads(text)) == config
    assert json.loads(text)["features"] == config.features.to_dict()  # the spec's own form, not copied fields
    assert not {"grid", "variant", "data_step", "moments"} & {f.name for f in dataclasses.fields(TrainConfig)}
