"""The ``threads`` of a model's session (``rectify.model.session_options``, what ``Rectifier.load`` takes):
an int or a numpy integer from 1 to MAX_THREADS (issue 48: ``np.int64(2)`` was refused as "not an
integer"); a bool, a float or a number out of range is an InputError naming the value."""

from __future__ import annotations

import numpy as np
import pytest

from dimenet.runtime.errors import InputError
from dimenet.runtime.rectify.model import MAX_THREADS, load_model, session_options


@pytest.mark.parametrize("threads", [1, np.int64(2), np.int32(1), np.uint16(MAX_THREADS)])
def test_an_int_or_a_numpy_integer_is_a_thread_count(threads):
    assert session_options(threads).intra_op_num_threads == int(threads)


def test_a_model_loads_on_numpy_integer_threads():
    assert load_model("default", threads=np.int64(2)).session.get_session_options().intra_op_num_threads == 2


@pytest.mark.parametrize("threads", [True, np.bool_(True), 2.0, np.float64(2.0), "2", 0, np.int64(MAX_THREADS + 1)])
def test_a_bool_a_float_or_a_count_out_of_range_is_refused(threads):
    with pytest.raises(InputError, match=rf"threads must be an integer from 1 to {MAX_THREADS} .*, got "):
        session_options(threads)


def test_a_pool_of_threads_sleeps_between_calls_and_one_thread_needs_no_setting():
    assert session_options(2).get_session_config_entry("session.intra_op.allow_spinning") == "0"
    with pytest.raises(RuntimeError, match="allow_spinning"):  # ONNX Runtime: the entry is not set for one thread
        session_options(1).get_session_config_entry("session.intra_op.allow_spinning")


def test_loading_warms_the_frame_path_up():
    model = load_model("default")
    assert hasattr(model._frame_io, "binding")  # the loading thread's IO binding is made at load
