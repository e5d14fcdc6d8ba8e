"""The prior oracle (issue 50): the MAP (K, pose) under the true population prior, against answers known
without it: the truth on a noise-free frame, the prior's mean under a tight prior, the stationary point of
the cost it minimises (by finite differences), and the population's mean and covariance by hand."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dimenet.runtime.errors import DatasetError
from dimenet.runtime.evaluation.methods import evaluate, with_prior_oracle
from dimenet.runtime.evaluation.prior_oracle import (
    JITTER_PX,
    PRIOR_ORACLE,
    oracle_frame,
    population_prior,
    prior_oracle,
)
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.geometry import k_matrix, k_params
from tests.helpers import K_TEST, random_frames

K_COV = np.diag([40.0, 40.0, 25.0, 25.0]) ** 2  # px^2: a prior as wide as OIS moves K


def _frame(noise_px: float, seed: int = 0):
    x, X, K, _, _ = random_frames(np.random.default_rng(seed), frames=1, points=40, noise_px=noise_px)
    return x[0], X[0], K[0]


def _cost(params, x, X, k_mean, precision, noise_px):
    """The MAP cost |r|^2 / s^2 + (k - k_mean)^T P (k - k_mean) at params = (rvec, tvec, k), by OpenCV's projection."""
    rvec, tvec, k = params[:3], params[3:6], params[6:]
    r = cv2.projectPoints(X, rvec, tvec, k_matrix(k), None)[0].reshape(-1, 2) - x
    d = k - k_mean
    return float(np.sum(r**2)) / noise_px**2 + float(d @ precision @ d)


def test_a_noise_free_frame_with_the_prior_at_the_truth_gives_the_truth():
    x, X, K = _frame(0.0)
    fit = oracle_frame(x, X, k_params(K) + [0.0, 0.0, 0.0, 0.0], K_COV, 1.0)
    np.testing.assert_allclose(fit.k, k_params(K), atol=1e-6)


def test_a_tight_prior_gives_its_mean():
    x, X, K = _frame(1.0)
    k_mean = k_params(K) + [25.0, 25.0, -12.0, 9.0]
    fit = oracle_frame(x, X, k_mean, np.eye(4) * 1e-6, 1.0)
    np.testing.assert_allclose(fit.k, k_mean, atol=1e-3)


def test_the_answer_is_the_minimum_of_the_map_cost():
    noise_px = 2.0
    x, X, K = _frame(noise_px, seed=3)
    k_mean = k_params(K) + [30.0, 30.0, -15.0, 10.0]
    fit = oracle_frame(x, X, k_mean, K_COV, noise_px)
    precision = np.linalg.inv(K_COV)
    best = np.r_[fit.rvec, fit.tvec, fit.k]
    cost = _cost(best, x, X, k_mean, precision, noise_px)
    # the gradient vanishes: each parameter's central difference is tiny against the cost's own curvature
    for i, h in enumerate([1e-6] * 3 + [1e-3] * 3 + [1e-2] * 4):
        step = np.zeros(10)
        step[i] = h
        up, down = (_cost(best + s, x, X, k_mean, precision, noise_px) for s in (step, -step))
        slope, curvature = (up - down) / (2 * h), (up + down - 2 * cost) / h**2
        assert abs(slope) * h <= 1e-3 * max(curvature * h**2, 1e-9) + 1e-7, (i, slope, curvature)
    # and the fit neither stays at the prior's mean nor jumps to the truth: it weighs both
    assert np.all(np.abs(fit.k - k_mean) > 0.1) and np.any(np.abs(fit.k - k_params(K)) > 0.1)


def test_the_population_prior_by_hand():
    k = np.array([[1000.0, 1001.0, 640.0, 360.0], [1010.0, 1011.0, 642.0, 356.0], [1020.0, 1021.0, 638.0, 358.0]])
    mean, cov = population_prior(k_matrix(k))
    np.testing.assert_allclose(mean, [1010.0, 1011.0, 640.0, 358.0])
    assert cov[0, 0] == pytest.approx(100.0 + JITTER_PX**2)  # (10^2 + 0 + 10^2) / 2
    assert cov[0, 1] == pytest.approx(100.0) and cov[2, 3] == pytest.approx(-2.0)  # (0 + 2*-2 + -2*0) / 2
    with pytest.raises(DatasetError, match="needs >= 2 frames"):
        population_prior(k_matrix(k[:1]))


def _dataset(n: int = 12, noise_px: float = 1.5, label_noise=True) -> Dataset:
    rng = np.random.default_rng(5)
    x, X, _, rvec, tvec = random_frames(rng, frames=n, points=30)
    k = k_params(K_TEST) + rng.normal(0.0, [15.0, 15.0, 10.0, 10.0], (n, 4))
    k[:, 1] = k[:, 0] * 1.003
    K = k_matrix(k)
    x = np.stack([cv2.projectPoints(X[f], rvec[f], tvec[f], K[f], None)[0][:, 0] for f in range(n)])
    x += rng.normal(0.0, noise_px, x.shape)
    valid = np.ones(x.shape[:2], bool)
    return Dataset(
        image_size=np.array([4032, 3024]),
        points_2d=x,
        points_3d=X,
        valid=valid,
        infer_mask=valid.copy(),
        split=np.array(["test"] * n),
        scene=np.array(["natural"] * n),
        K_true=K,
        label_noise_px=np.full(n, noise_px) if label_noise else None,
    )


def test_the_oracle_of_a_dataset_uses_its_scene_population_and_is_better_than_k_c():
    frames = _dataset()
    po = prior_oracle(frames)
    np.testing.assert_allclose(po.priors["natural"][0], k_params(frames.K_true).mean(0))
    K_c = k_matrix(po.priors["natural"][0])
    ev = evaluate(frames, K_c, methods=("kc", PRIOR_ORACLE))
    assert ev.methods[PRIOR_ORACLE]["overall"].rho > 0.3
    kc = ev.ratios["kc"]["natural"]
    assert kc.ratio == pytest.approx(0.0, abs=1e-12) and kc.low <= 0.0 <= kc.high
    assert PRIOR_ORACLE not in ev.ratios and "ratios_to_prior_oracle" in ev.to_json()


def test_without_label_noise_the_oracle_says_what_is_missing():
    frames = _dataset(label_noise=False)
    with pytest.raises(DatasetError, match="prior-oracle.*label_noise_px"):
        prior_oracle(frames)
    methods, why = with_prior_oracle(frames, ("dimenet", "map"))
    assert methods == ("dimenet", "map") and "label_noise_px" in why
    assert with_prior_oracle(_dataset(), ("dimenet", "map")) == (("dimenet", "map", PRIOR_ORACLE), None)
    assert with_prior_oracle(_dataset(), ("kc",)) == (("kc",), None)  # no mode: nothing to go beside


def test_extra_noise_grows_the_label_noise_or_drops_it():
    from dimenet.runtime.evaluation.conditions import add_noise

    frames = _dataset(n=3, noise_px=1.5)
    noisier = add_noise(frames, 2.0, 0.0, np.random.default_rng(0))
    np.testing.assert_allclose(noisier.label_noise_px, 2.5)  # hypot(1.5, 2)
    assert add_noise(frames, 2.0, 0.1, np.random.default_rng(0)).label_noise_px is None  # 3D noise: unknown in px
