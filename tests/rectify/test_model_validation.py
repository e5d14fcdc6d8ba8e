"""Issue 20, "Model specs are trusted": every malformed spec, a graph whose real output differs
from the declared one, and a model file whose bytes differ from the sha256 in its spec are a
ModelError naming the file (never a traceback, never a model that loads and then fails or falls
back on every frame). Spec 1.0-1.3 files still load, without the integrity check.

The spec cases edit the spec of the device model bundled before the generic default
(tests/data); the file cases need ``onnx`` to build or edit a graph (skipped without it), except
the byte-flip cases, which need the runtime only.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import math

import numpy as np
import onnxruntime as ort
import pytest
from helpers import DEVICE_MODEL

from dimenet.runtime.assets import asset
from dimenet.runtime.errors import ModelError
from dimenet.runtime.formats.dataset import read_dataset
from dimenet.runtime.rectify.model import DEFAULT_MODEL, load_onnx_model, onnx_model_from_bytes
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.spec import (
    METADATA_KEY,
    VERSION,
    WEIGHTS_SHA256_KEY,
    WEIGHTS_SHA256_PLACEHOLDER,
    ModelSpec,
)
from dimenet.runtime.rectify.uncertainty import D_FLOOR_PX, MAX_PMD_PX, MAX_POINTS, SIGMA_MAX_PX, SIGMA_MIN_PX, T_FLOOR

SOURCE = "suspect.onnx"


@pytest.fixture(scope="module")
def bundled() -> bytes:
    """The device model the project bundled before the generic default (spec 1.4, stamped)."""
    return DEVICE_MODEL.read_bytes()


@pytest.fixture(scope="module")
def base(bundled) -> dict:
    """The device model's spec as a dict (read through ONNX Runtime: no onnx needed)."""
    session = ort.InferenceSession(bundled, providers=["CPUExecutionProvider"])
    return json.loads(session.get_modelmeta().custom_metadata_map[METADATA_KEY])


def _edited(d: dict, path: str, value) -> dict:
    """A deep copy of d with the item at path ('a.b.0') set to value (or deleted for _DELETE)."""
    d = copy.deepcopy(d)
    *parents, last = path.split(".")
    node = d
    for key in parents:
        node = node[int(key)] if isinstance(node, list) else node[key]
    last = int(last) if isinstance(node, list) else last
    if value is _DELETE:
        del node[last]
    else:
        node[last] = value
    return d


_DELETE = object()
NAN, INF = float("nan"), float("inf")

MALFORMED = [
    # K_c: a 4-vector of finite numbers with fx, fy > 0
    ("K_c", [3000.0, 3000.0, 2016.0], r"K_c must be 4 numbers"),
    ("K_c", [[3000.0, 0, 2016.0], [0, 3000.0, 1512.0], [0, 0, 1]], r"K_c must be 4 numbers"),
    ("K_c.0", INF, r"K_c must hold finite numbers"),
    ("K_c.1", NAN, r"K_c must hold finite numbers"),
    ("K_c.3", -INF, r"K_c must hold finite numbers"),
    ("K_c.0", 0.0, r"K_c must have fx, fy > 0"),
    ("K_c.1", -3059.6, r"K_c must have fx, fy > 0"),
    ("K_c.2", "2023.8", r"K_c must hold finite numbers"),
    ("K_c.2", True, r"K_c must hold finite numbers"),
    ("K_c", "3059.6", r"K_c must be 4 numbers"),
    ("K_c", _DELETE, r"no 'K_c'"),
    # image_size: two integers in [1, 100000]
    ("image_size", [4032], r"image_size must be 2 integers"),
    ("image_size", [4032, 3024, 3], r"image_size must be 2 integers"),
    ("image_size", [0, 0], r"image_size must be 1 to 100000"),
    ("image_size", [4032, -1], r"image_size must be 1 to 100000"),
    ("image_size", [4032.5, 3024], r"image_size must be an integer"),
    ("image_size", [NAN, 3024], r"image_size must be an integer"),
    ("image_size", [10**6, 3024], r"image_size must be 1 to 100000"),
    ("image_size", [10**400, 3024], r"image_size must be an integer"),
    ("image_size", ["4032", 3024], r"image_size must be an integer"),
    ("image_size", "4032x3024", r"image_size must be 2 integers"),
    ("image_size", {"width": 4032}, r"image_size must be 2 integers"),
    # K_bounds: (4, 2), finite, low < high, containing K_c
    ("K_bounds", [[3000.0, 3100.0]] * 3, r"K_bounds must be 4 x 2 numbers"),
    ("K_bounds", [[3000.0, 3050.0, 3100.0]] * 4, r"K_bounds must be 4 x 2 numbers"),
    ("K_bounds", [3000.0, 3100.0] * 4, r"K_bounds must be 4 x 2 numbers"),
    ("K_bounds.0", [3085.3, 3032.7], r"K_bounds of fx must have low < high"),
    ("K_bounds.2", [2000.0, 2000.0], r"K_bounds of cx must have low < high"),
    ("K_bounds.1", [NAN, 3085.6], r"K_bounds must hold finite numbers"),
    ("K_bounds.3", [1261.9, INF], r"K_bounds must hold finite numbers"),
    ("K_bounds.0", [3060.0, 3085.3], r"K_bounds of fx \[3060.0, 3085.3\] must contain K_c's fx 3059.6"),
    ("K_bounds.3", [1000.0, 1200.0], r"K_bounds of cy .* must contain K_c's cy"),
    # hidden: a list of positive ints
    ("hidden", [], r"hidden must be a list of layer widths"),
    ("hidden", 256, r"hidden must be a list of layer widths"),
    ("hidden", [256, 0], r"hidden must be >= 1"),
    ("hidden", [256, -128], r"hidden must be >= 1"),
    ("hidden", [256.5, 128], r"hidden must be an integer"),
    ("hidden", ["256", 128], r"hidden must be an integer"),
    ("hidden", [True, 128], r"hidden must be an integer"),
    # features (FeatureSpec and Grid raise InputError: a ModelError here)
    ("features", "8x6 A", r"features must be an object"),
    ("features.grid", "8y6", r"features.grid must look like '8x6'"),
    ("features.grid", 86, r"features.grid must be a string"),
    ("features.grid", "0x6", r"grid must have at least 1x1 cells"),
    ("features.grid", "5000x6", r"features.grid 5000x6 has more cells than the 4032x3024 image"),
    ("features.variant", "Z", r"feature variant must be one of A, B, C, D, E"),
    ("features.variant", ["A"], r"features.variant must be a string"),
    ("features.scale", [0.1, 0.1, 0.01, 0.01, 500.0], r"features.scale must be an object"),
    ("features.scale.dx", _DELETE, r"features.scale.dx must be a positive number"),
    ("features.scale.dy", "0.1", r"features.scale.dy must be a positive number"),
    ("features.scale.X", NAN, r"features.scale.X must be a positive number"),
    ("features.scale.inv_z", 0.0, r"features.scale.inv_z must be a positive number"),
    ("features.scale.depth", 1.0, r"features.scale has an unknown channel 'depth'"),
    ("features", _DELETE, r"no 'features'"),
    # uncertainty (Uncertainty raises ValueError: a ModelError here)
    ("uncertainty", [1, 2], r"uncertainty must be an object"),
    ("uncertainty.coef", [[0.0] * 5] * 3, r"uncertainty.coef must be 4 x 5 numbers"),
    ("uncertainty.coef", [[0.0] * 4] * 4, r"uncertainty.coef must be 4 x 5 numbers"),
    ("uncertainty.coef.0.0", NAN, r"uncertainty.coef must hold finite numbers"),
    (
        "uncertainty.coef.0.0",
        700.0,
        r"uncertainty.coef gives sigma_fx from .* px over plausible frames .* outside \[1e-06, 1e\+06\] px",
    ),
    ("uncertainty.coef.2.0", -700.0, r"sigma_cx from .*e-3.* px over plausible frames .* outside"),
    ("uncertainty.coef.0.0", 1e300, r"sigma_fx from exp\(1e\+300\) to exp\(1e\+300\) px"),
    ("uncertainty.coef.0.1", -1e308, r"sigma_fx from 0 to 8.4 px"),
    ("uncertainty.coef.3.3", 3.0, r"sigma_cy from .* outside"),  # PMD slope: 1000 px PMD gives sigma > 1e6 px
    ("uncertainty.coef.1.4", -2.0, r"sigma_fy from .* outside"),  # thickness slope: a plane gives sigma > 1e6 px
    ("uncertainty.coef", _DELETE, r"no 'coef'"),
    ("uncertainty.correlation", [[1.0, 0.0], [0.0, 1.0]], r"uncertainty.correlation must be 4 x 4 numbers"),
    ("uncertainty.correlation.0.1", INF, r"uncertainty.correlation must hold finite numbers"),
    ("uncertainty.correlation", (np.ones((4, 4))).tolist(), r"correlation matrix is not positive definite"),
    ("uncertainty.correlation.0.1", 0.5, r"uncertainty.correlation must be a symmetric matrix with a unit diagonal"),
    ("uncertainty.correlation", (4 * np.eye(4)).tolist(), r"symmetric matrix with a unit diagonal"),
    ("uncertainty.statistics", ["1", "log_points", "log_depth", "log_pmd", "log_thickness"], r"statistics must be"),
    ("uncertainty.statistics", ["log_points", "1", "log_cells", "log_pmd", "log_thickness"], r"statistics must be"),
    ("uncertainty.statistics", ["1", "log_points", "log_points", "log_pmd", "log_thickness"], r"statistics must be"),
    ("uncertainty.statistics", "1, log_points", r"statistics must be"),
    ("uncertainty.statistics", [], r"statistics must be"),
    ("uncertainty.data_correlation", [0.0, 0.0, 1.5, 0.5], r"data_correlation must be 4 values in \[0, 1\]"),
    ("uncertainty.data_correlation", [0.0, 0.0, 0.7], r"uncertainty.data_correlation must be 4 numbers"),
    ("uncertainty.data_correlation.0", NAN, r"uncertainty.data_correlation must hold finite numbers"),
    ("uncertainty.noise_scale_px", 0.0, r"uncertainty.noise_scale_px must be a positive number"),
    ("uncertainty.noise_scale_px", "2", r"uncertainty.noise_scale_px must be a positive number"),
    ("uncertainty.parameters", ["fy", "fx", "cx", "cy"], r"uncertainty.parameters must be \['fx', 'fy', 'cx', 'cy'\]"),
    # the rest
    ("provenance", ["seed", 0], r"provenance must be an object"),
    (WEIGHTS_SHA256_KEY, "abc", r"weights_sha256 must be 64 lowercase hex digits"),
    (WEIGHTS_SHA256_KEY, "A" * 64, r"weights_sha256 must be 64 lowercase hex digits"),
    (WEIGHTS_SHA256_KEY, 0, r"weights_sha256 must be 64 lowercase hex digits"),
    ("version", 1, r"spec version 1 is not supported"),
    ("version", "2.0.0", r"spec version '2.0.0' is not supported"),
    ("format", "dimenet-model/2", r"not a dimenet-model/1 spec"),
]


@pytest.mark.parametrize("path, value, message", MALFORMED, ids=[f"{p}={str(v)[:20]}" for p, v, _ in MALFORMED])
def test_a_malformed_spec_is_a_model_error_naming_the_source_and_field(base, path, value, message):
    bad = _edited(base, path, value)
    with pytest.raises(ModelError, match=rf"^{SOURCE}: .*{message}"):
        ModelSpec.from_dict(bad, source=SOURCE)
    if all(math.isfinite(v) for v in _floats(bad)):  # the same through the JSON reader
        with pytest.raises(ModelError, match=rf"^{SOURCE}: .*{message}"):
            ModelSpec.from_json(json.dumps(bad), source=SOURCE)


def _floats(value):
    if isinstance(value, float):
        yield value
    elif isinstance(value, dict):
        for v in value.values():
            yield from _floats(v)
    elif isinstance(value, list):
        for v in value:
            yield from _floats(v)


@pytest.mark.parametrize(
    "text",
    [
        '{"K_c": [Infinity, 3059.6, 2023.8, 1508.5]}',
        '{"K_c": [NaN, 3059.6, 2023.8, 1508.5]}',
        '{"K_c": [1e999, 3059.6, 2023.8, 1508.5]}',
    ],
)
def test_non_finite_json_numbers_are_model_errors(base, text):
    d = {k: v for k, v in base.items() if k != "K_c"}
    spliced = json.dumps(d)[:-1] + ", " + text[1:]
    with pytest.raises(ModelError, match=rf"^{SOURCE}: .*K_c must hold finite numbers"):
        ModelSpec.from_json(spliced, source=SOURCE)


@pytest.mark.parametrize(
    "text, message",
    [
        ("[" * 100_000, "nested deeper than"),
        ('{"format": "dimenet-model/1", "provenance": ' + "[" * 100_000 + "]" * 100_000 + "}", "nested deeper than"),
        ('{"image_size": [' + "1" * 5000 + ", 3024]}", "not valid JSON"),
        ("{", "not valid JSON"),
        ("[]", r"not a dimenet-model/1 spec \(format is a JSON list\)"),
        ("3", r"not a dimenet-model/1 spec \(format is a JSON int\)"),
        ("null", r"not a dimenet-model/1 spec \(format is a JSON NoneType\)"),
        ('"dimenet-model/1"', r"not a dimenet-model/1 spec \(format is a JSON str\)"),
    ],
    ids=["deep-list", "deep-provenance", "huge-int", "truncated", "list", "int", "null", "string"],
)
def test_unreadable_or_non_object_json_is_a_model_error(text, message):
    with pytest.raises(ModelError, match=rf"^{SOURCE}: .*{message}"):
        ModelSpec.from_json(text, source=SOURCE)


NON_OBJECTS = [None, True, 1, 1.5, "x", [], {}, [1, 2], {"a": 1}]
LEVELS = [
    "features",
    "features.grid",
    "features.variant",
    "features.scale",
    "features.scale.dx",
    "K_c",
    "K_c.0",
    "image_size",
    "image_size.0",
    "K_bounds",
    "K_bounds.0",
    "K_bounds.0.0",
    "hidden",
    "hidden.0",
    "provenance",
    "uncertainty",
    "uncertainty.coef",
    "uncertainty.coef.0",
    "uncertainty.coef.0.0",
    "uncertainty.correlation",
    "uncertainty.correlation.0",
    "uncertainty.statistics",
    "uncertainty.statistics.0",
    "uncertainty.data_correlation",
    "uncertainty.noise_scale_px",
    "uncertainty.parameters",
    WEIGHTS_SHA256_KEY,
    "version",
    "format",
]
# The replacements that leave a valid spec: another provenance object, null for weights_sha256
# (absent: no check), and plausible numbers where a number belongs.
VALID = {
    ("provenance", "{}"),
    ("provenance", "{'a': 1}"),
    (WEIGHTS_SHA256_KEY, "None"),
    ("hidden", "[1, 2]"),
    ("hidden.0", "1"),
    *((path, number) for number in ("1", "1.5") for path in ("features.scale.dx", "K_bounds.0.0")),
    *((path, number) for number in ("1", "1.5") for path in ("uncertainty.coef.0.0", "uncertainty.noise_scale_px")),
}


@pytest.mark.parametrize("path", LEVELS)
def test_any_json_value_at_any_level_is_a_model_error_not_a_traceback(base, path):
    loaded = set()
    for value in NON_OBJECTS:
        try:
            ModelSpec.from_dict(_edited(base, path, value), source=SOURCE)
        except ModelError as exc:
            assert str(exc).startswith(f"{SOURCE}: ")
        else:
            loaded.add((path, repr(value)))
    assert loaded == {case for case in VALID if case[0] == path}


def test_the_sigma_rule_is_the_documented_box(base):
    """sigma_p = exp(coef_p . z) must stay in [1e-6, 1e6] px at every corner of the box of
    plausible statistics; coef . z is linear, so an intercept just inside the bound loads."""
    low = [0.0, 0.0, math.log(D_FLOOR_PX), math.log(T_FLOOR)]
    high = [math.log(MAX_POINTS), math.log(48), math.log(MAX_PMD_PX), math.log(1 / 3)]  # 8x6 grid: 48 cells
    for margin, loads in ((-1e-9, True), (1e-9, False)):  # sigma grows with n only: largest at n = MAX_POINTS
        coef = [[math.log(SIGMA_MAX_PX) - 0.5 * high[0] + margin, 0.5, 0.0, 0.0, 0.0]] * 4
        d = _edited(base, "uncertainty.coef", coef)
        if loads:
            sigma = ModelSpec.from_dict(d).uncertainty.sigma(np.array([high]))
            assert np.all(sigma < SIGMA_MAX_PX) and np.all(sigma > SIGMA_MAX_PX * (1 - 1e-6))
        else:
            with pytest.raises(ModelError, match="sigma_fx from .* to 1e[+]06 px"):
                ModelSpec.from_dict(d, source=SOURCE)
    tiny = [[math.log(SIGMA_MIN_PX) - 1e-9 - low[2], 0.0, 0.0, 1.0, 0.0]] * 4  # smallest at the PMD floor
    with pytest.raises(ModelError, match=r"sigma_fx from 1e-06"):
        ModelSpec.from_dict(_edited(base, "uncertainty.coef", tiny), source=SOURCE)
    # the bundled model's sigma stays well inside at every corner
    sigma = ModelSpec.from_dict(base).uncertainty.sigma(np.array(list(itertools.product(*zip(low, high)))))
    assert 1e-3 < sigma.min() and sigma.max() < 1e6


def test_the_bundled_generic_model_is_spec_1_6_and_its_hash_verifies_without_onnx():
    blob = asset(DEFAULT_MODEL).read_bytes()
    model = onnx_model_from_bytes(blob, "bundled")
    assert model.spec.generic is not None and model.spec.K_c is None and model.spec.uncertainty is not None
    d = model.spec.to_dict(weights_sha256=model.spec.weights_sha256)
    assert d["version"] == VERSION == "1.11.0"
    # spec 1.6: what the do-no-harm rules read (the structure limit, the population spread)
    assert 0 < model.spec.residual_structure_px < 5 and model.spec.uncertainty.population_sigma_px.shape == (4,)
    digest = model.spec.weights_sha256
    assert hashlib.sha256(blob.replace(digest.encode(), WEIGHTS_SHA256_PLACEHOLDER.encode())).hexdigest() == digest


def test_the_earlier_device_model_is_spec_1_4_and_its_hash_verifies_without_onnx(bundled, base):
    assert base["version"] == "1.4.0"
    digest = base[WEIGHTS_SHA256_KEY]
    assert bundled.count(digest.encode()) == 1
    assert hashlib.sha256(bundled.replace(digest.encode(), WEIGHTS_SHA256_PLACEHOLDER.encode())).hexdigest() == digest
    model = onnx_model_from_bytes(bundled, "bundled")
    assert model.spec.weights_sha256 == digest and model.sha256 == hashlib.sha256(bundled).hexdigest()


def _flipped(blob: bytes, at: int) -> bytes:
    out = bytearray(blob)
    out[at] ^= 0x01
    return bytes(out)


def test_a_bit_flip_anywhere_in_the_bundled_model_is_a_model_error(bundled, tmp_path):
    # the largest weight (fc1, 240 x 256 float32) fills most of the file's first 250 KB
    weight = tmp_path / "weight_flip.onnx"
    weight.write_bytes(_flipped(bundled, len(bundled) // 3))
    assert ort.InferenceSession(weight.read_bytes(), providers=["CPUExecutionProvider"])  # ORT alone would run it
    with pytest.raises(
        ModelError, match=r"weight_flip\.onnx: the model file's bytes differ from the sha256 in its spec"
    ):
        Rectifier.load(weight)
    # a digit of K_c in the spec text, and the hash itself
    at = bundled.index(b"3059.61436426714") + 15
    spec_flip = tmp_path / "spec_flip.onnx"
    spec_flip.write_bytes(bundled[:at] + b"5" + bundled[at + 1 :])
    with pytest.raises(ModelError, match=r"spec_flip\.onnx: the model file's bytes differ from the sha256"):
        Rectifier.load(spec_flip)
    digest_at = bundled.index(b'"weights_sha256": "') + len(b'"weights_sha256": "')
    hex_flip = tmp_path / "hash_flip.onnx"
    other = b"0" if bundled[digest_at : digest_at + 1] != b"0" else b"1"
    hex_flip.write_bytes(bundled[:digest_at] + other + bundled[digest_at + 1 :])
    with pytest.raises(ModelError, match=r"hash_flip\.onnx: the model file's bytes differ from the sha256"):
        Rectifier.load(hex_flip)
    # every other byte position (a sample): refused, whatever the reason
    for at in np.linspace(0, len(bundled) - 1, 41).astype(int):
        with pytest.raises(ModelError, match=r"^flip: "):
            onnx_model_from_bytes(_flipped(bundled, int(at)), "flip")


def test_an_ambiguous_hash_entry_is_a_model_error(bundled):
    key = b'"weights_sha256"'
    at = len(bundled) // 3  # in the weights: the key now occurs twice, the spec is untouched
    twice = bundled[:at] + key + bundled[at + len(key) :]
    with pytest.raises(ModelError, match=r"^twice: its spec's weights_sha256 does not occur exactly once"):
        onnx_model_from_bytes(twice, "twice")


def test_metadata_that_is_not_utf8_is_a_model_error(bundled):
    at = bundled.index(b"3059.61436426714")
    broken = bundled[:at] + bytes([bundled[at] ^ 0x80]) + bundled[at + 1 :]
    with pytest.raises(ModelError, match=r"^latin\.onnx: the ONNX metadata is not UTF-8 text"):
        onnx_model_from_bytes(broken, "latin.onnx")


# --- files: need onnx to edit or build a graph ---------------------------------------------


def _with_spec_text(blob: bytes, edit) -> bytes:
    onnx = pytest.importorskip("onnx")
    proto = onnx.load_from_string(blob)
    entry = next(p for p in proto.metadata_props if p.key == METADATA_KEY)
    d = json.loads(entry.value)
    edit(d)
    entry.value = json.dumps(d, indent=1, sort_keys=True)
    return proto.SerializeToString()


def _example_frame():
    ds = read_dataset(asset("example_frames.npz"))
    v = ds.valid[0]
    return ds.points_2d[0][v], ds.points_3d[0][v]


@pytest.mark.parametrize(
    "path, value, message",
    [
        ("K_c.0", NAN, "K_c must hold finite numbers"),
        ("K_c.1", 0.0, "K_c must have fx, fy > 0"),
        ("image_size", [0, 0], "image_size must be 1 to 100000"),
        ("K_bounds.0", [3085.3, 3032.7], "K_bounds of fx must have low < high"),
        ("K_bounds.2", [NAN, 2268.2], "K_bounds must hold finite numbers"),
        ("uncertainty.coef.2.0", 700.0, "uncertainty.coef gives sigma_cx"),
    ],
)
def test_a_model_file_with_a_malformed_spec_is_refused_at_load(bundled, tmp_path, path, value, message):
    def edit(d):
        d.update(_edited(d, path, value))

    bad = tmp_path / "bad_spec.onnx"
    bad.write_bytes(_with_spec_text(bundled, edit))
    with pytest.raises(ModelError, match=rf"bad_spec\.onnx: malformed dimenet-model/1 spec: {message}"):
        Rectifier.load(bad)


def test_spec_1_3_and_unstamped_1_4_models_load_without_the_check(bundled, tmp_path):
    def as_1_3(d):
        d["version"] = "1.3.0"
        del d[WEIGHTS_SHA256_KEY]

    old = tmp_path / "v13.onnx"
    old.write_bytes(_with_spec_text(bundled, as_1_3))
    p2, p3 = _example_frame()
    expected = Rectifier.load(DEVICE_MODEL).rectify(p2, p3)
    for path in (old,):
        got = Rectifier.load(path).rectify(p2, p3)
        np.testing.assert_array_equal(got.K, expected.K)
        np.testing.assert_array_equal(got.K_cov, expected.K_cov)
    assert load_onnx_model(old).spec.weights_sha256 is None
    # no hash, no check: a weight flip in a 1.3 file goes unnoticed (re-export or re-stamp to get the check)
    assert load_onnx_model(old).spec.to_dict() == load_onnx_model(DEVICE_MODEL).spec.to_dict()
    unstamped = tmp_path / "v14_unstamped.onnx"
    unstamped.write_bytes(_with_spec_text(bundled, lambda d: d.pop(WEIGHTS_SHA256_KEY)))
    np.testing.assert_array_equal(Rectifier.load(unstamped).rectify(p2, p3).K, expected.K)


def _tiny_graph(spec_json: str, kind: str) -> bytes:
    """A graph features float [batch, 240] -> delta_k declared float [batch, 4] whose real
    output differs: 'wide' gives [batch, 5] (a data-dependent Slice hides it from shape
    inference; operators the exporter never writes), and of the exporter's operators: 'batch3'
    only runs on batches of 1 or 3 frames (Add of a [3, 4] constant), 'inf' gives inf."""
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper, numpy_helper

    def const(name, value):
        return helper.make_node("Constant", [], [name], value=numpy_helper.from_array(np.asarray(value)))

    width = 5 if kind == "wide" else 4
    nodes = [helper.make_node("MatMul", ["features", "W"], ["y"])]
    if kind == "wide":
        nodes += [
            helper.make_node("ReduceSum", ["features"], ["s"], keepdims=0),
            const("zero", np.float32(0)),
            helper.make_node("Mul", ["s", "zero"], ["s0"]),
            const("five", np.float32(5)),
            helper.make_node("Add", ["s0", "five"], ["e"]),
            helper.make_node("Cast", ["e"], ["ei"], to=TensorProto.INT64),
            const("one", np.array([1], np.int64)),
            helper.make_node("Reshape", ["ei", "one"], ["ends"]),
            const("starts", np.array([0], np.int64)),
            const("axes", np.array([1], np.int64)),
            helper.make_node("Slice", ["y", "starts", "ends", "axes"], ["delta_k"]),
        ]
    elif kind == "batch3":
        nodes += [const("rows", np.zeros((3, 4), np.float32)), helper.make_node("Add", ["y", "rows"], ["delta_k"])]
    elif kind == "inf":
        nodes += [const("inf", np.float32(np.inf)), helper.make_node("Add", ["y", "inf"], ["delta_k"])]
    graph = helper.make_graph(
        nodes,
        "tiny",
        [helper.make_tensor_value_info("features", TensorProto.FLOAT, ["batch", 240])],
        [helper.make_tensor_value_info("delta_k", TensorProto.FLOAT, ["batch", 4])],
        [numpy_helper.from_array(np.zeros((240, width), np.float32), "W")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    helper.set_model_props(model, {METADATA_KEY: spec_json})
    onnx.checker.check_model(model)
    return model.SerializeToString()


@pytest.mark.parametrize(
    "kind, message",
    [
        ("batch3", r"the graph fails on 2 zero feature frames, so it differs from the declared float32 \[batch, 4\]"),
        ("inf", r"graph output 'delta_k' on zero features is not finite"),
    ],
)
def test_the_load_probe_catches_a_graph_whose_real_output_differs(base, tmp_path, kind, message):
    spec = {k: v for k, v in base.items() if k != WEIGHTS_SHA256_KEY}
    path = tmp_path / f"{kind}.onnx"
    path.write_bytes(_tiny_graph(json.dumps(spec), kind))
    declared = ort.InferenceSession(path.read_bytes(), providers=["CPUExecutionProvider"]).get_outputs()[0]
    assert declared.type == "tensor(float)" and declared.shape[1] == 4  # the declared signature looks right
    with pytest.raises(ModelError, match=rf"{kind}\.onnx: {message}"):
        Rectifier.load(path)


def test_a_graph_hiding_its_real_output_from_shape_inference_is_refused_before_any_run(base, tmp_path, monkeypatch):
    spec = {k: v for k, v in base.items() if k != WEIGHTS_SHA256_KEY}
    path = tmp_path / "wide.onnx"
    path.write_bytes(_tiny_graph(json.dumps(spec), "wide"))
    declared = ort.InferenceSession(path.read_bytes(), providers=["CPUExecutionProvider"]).get_outputs()[0]
    assert declared.type == "tensor(float)" and declared.shape[1] == 4  # the declared signature looks right
    monkeypatch.setattr(ort, "InferenceSession", None)  # refused on its bytes: no session is made
    with pytest.raises(ModelError, match=r"wide\.onnx: node 1 \(''\) is the operator 'ReduceSum', which"):
        Rectifier.load(path)


def test_a_spec_file_that_is_not_utf8_is_a_model_error(tmp_path):
    path = tmp_path / "spec.json"
    path.write_bytes(b'{"format": "dimenet-model/1\xff"}')
    with pytest.raises(ModelError, match=r"spec\.json: model spec is not UTF-8 text"):
        ModelSpec.read(path)
