"""Gross mislabels among natural labels (sim.mislabels, issue 50 item 4): only the natural frames' labelled points
move, by 10-50 px, inside the image, in about the share asked; every other array is the same seed's without them."""

from __future__ import annotations

import numpy as np
import pytest

from dimenet.runtime.errors import InputError
from dimenet.runtime.sim.family import family_profiles
from dimenet.runtime.sim.mislabels import MISLABEL_PX, checked_share
from dimenet.runtime.sim.simulator import simulate


@pytest.fixture(scope="module")
def pair():
    """The galaxy-s8 set of seed 4 with 60 natural frames, without mislabels and with 10 %."""
    clean = simulate("galaxy-s8", seed=4, natural_frames=60)
    return clean, simulate("galaxy-s8", seed=4, natural_frames=60, mislabel_share=0.1)


def test_only_natural_labels_move_by_a_gross_mislabel_and_stay_in_the_image(pair):
    clean, dirty = pair
    for name in ("points_3d", "valid", "infer_mask", "K_true", "label_noise_px", "split", "scene"):
        np.testing.assert_array_equal(getattr(clean, name), getattr(dirty, name), err_msg=name)
    both = clean.valid
    moved = both & np.any(clean.points_2d != dirty.points_2d, -1)
    assert np.all(moved <= (clean.infer_mask & (clean.scene == "natural")[:, None]))  # labels of natural frames only
    shift = np.linalg.norm(dirty.points_2d[moved] - clean.points_2d[moved], axis=-1)
    assert np.all((shift >= MISLABEL_PX[0] - 1e-9) & (shift <= MISLABEL_PX[1] + 1e-9))
    labels = int((clean.infer_mask & (clean.scene == "natural")[:, None]).sum())
    share = moved.sum() / labels
    assert abs(share - 0.1) < 4 * np.sqrt(0.1 * 0.9 / labels), (share, labels)  # binomial, 4 sigma
    w, h = clean.image_size
    p = dirty.points_2d[moved]
    assert np.all((p >= -0.5) & (p <= [w - 0.5, h - 0.5]))
    assert dirty.meta["mislabels"] == {"share": 0.1, "px": list(MISLABEL_PX)} and "mislabels" not in clean.meta


def test_no_share_is_the_dataset_without_and_a_bad_share_is_refused():
    a, b = (
        simulate("galaxy-s8", seed=2, natural_frames=5),
        simulate("galaxy-s8", seed=2, natural_frames=5, mislabel_share=0),
    )
    np.testing.assert_array_equal(a.points_2d, b.points_2d)
    for share in (-0.1, 0.6, float("nan"), True, "0.1"):
        with pytest.raises(InputError, match="mislabel share"):
            checked_share(share)


def test_a_family_member_passes_its_share_on():
    from dimenet.runtime.sim.family import family_member

    profile = family_profiles(1, 7)[0]
    ds = family_member(profile, 0, 7, 1, natural_frames=8, scenes="random", mislabel_share=0.2)
    assert ds.meta["mislabels"]["share"] == 0.2
