"""The full graph's subgraph builders are keyed by the runtime registry's encoder names (``rectify.encoders``)."""

import pytest

pytest.importorskip("onnx")

from dimenet.export.full_graph import GRAM_BUILDERS
from dimenet.runtime.rectify.encoders import ENCODERS, grid


def test_every_encoder_after_the_grid_has_one_builder():
    assert list(GRAM_BUILDERS) == [name for name in ENCODERS if name != grid.NAME]
