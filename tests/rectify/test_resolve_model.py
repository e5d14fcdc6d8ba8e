"""One reading of a model argument (``resolve_model``) and the one features -> Delta K interface (``DeltaKModel``)."""

from pathlib import Path

import numpy as np
import pytest

from dimenet.runtime.errors import ModelError
from dimenet.runtime.evaluation.predictor import Predictor, load_predictor
from dimenet.runtime.rectify.model import (
    BUNDLED_MODELS,
    DEFAULT_NAME,
    DeltaKModel,
    ModelRef,
    bundled_model_bytes,
    load_model,
    resolve_model,
)


@pytest.mark.parametrize("name", BUNDLED_MODELS)
def test_every_bundled_name_resolves_to_its_file(name):
    ref = resolve_model(name)
    assert ref == ModelRef(bundled=name)
    assert not ref.run_dir
    assert ref.model_bytes() == bundled_model_bytes(name)
    assert BUNDLED_MODELS[name] in ref.source


def test_no_model_is_the_default():
    assert resolve_model(None) == resolve_model(DEFAULT_NAME) == ModelRef(bundled=DEFAULT_NAME)


def test_a_path_is_a_file_or_a_run_dir(tmp_path, monkeypatch):
    file = tmp_path / "model.onnx"
    file.write_bytes(b"not read until loaded")
    assert resolve_model(file) == resolve_model(str(file)) == ModelRef(path=file)
    assert resolve_model(file).model_bytes() == b"not read until loaded"
    assert resolve_model(file).source == str(file)
    assert not resolve_model(file).run_dir
    assert resolve_model(tmp_path).run_dir
    (tmp_path / "default").mkdir()  # a folder named as a bundled model: "./default" is the folder
    monkeypatch.chdir(tmp_path)
    assert resolve_model("./default") == ModelRef(path=Path("default"))
    assert resolve_model("default") == ModelRef(bundled="default")


def test_an_unknown_name_is_a_model_error_naming_the_bundled_models():
    with pytest.raises(ModelError, match="any_scene: no such model file or RUN_DIR") as caught:
        resolve_model("any_scene")
    for name in BUNDLED_MODELS:
        assert name in str(caught.value)


def test_onnx_model_and_predictor_meet_the_one_interface():
    model = load_model()
    predictor = load_predictor(DEFAULT_NAME)
    assert isinstance(model, DeltaKModel) and isinstance(predictor, DeltaKModel)
    assert isinstance(Predictor.of_model(model), DeltaKModel)
    features = np.zeros((1, model.spec.features.size), np.float32)
    for each in (model, predictor):
        assert each.frame_delta_k(features).dtype == np.float64
        np.testing.assert_array_equal(each.frame_delta_k(features), each.delta_k(features)[0])
    assert not isinstance(Path("."), DeltaKModel)
