"""The uncertainty model of a trained network's Delta K (``rectify.uncertainty``; the fit is
``evaluation.uncertainty_fit``'s), fitted on the early-stopping frames under many draws of
test-like conditions, and the rule for when a fine-tuned model keeps its init's."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from dimenet.runtime.errors import DatasetError
from dimenet.runtime.evaluation.conditions import add_noise, drop_inference_points, one_plane, two_objects
from dimenet.runtime.evaluation.uncertainty_fit import coverage, fit_data_bias, fit_data_correlation, fit_uncertainty
from dimenet.runtime.geometry import k_params
from dimenet.runtime.jobs.progress import progress
from dimenet.runtime.rectify.map_fit import map_rectify
from dimenet.runtime.rectify.spec import ModelSpec
from dimenet.runtime.rectify.uncertainty import Uncertainty

from .config import TrainConfig
from .model import DimeNet
from .predictor import torch_predictor
from .scene_limits import population_sigma, structure_limit
from .units import augment, resynthesise

# The uncertainty model is fitted on >= this many (frame, condition) samples: the val frames,
# re-imaged, under as many augmentation draws as it takes (at least 8), plus a third as many
# draws each clean, at 64 points and of one plane, and as many two-object draws.
UNCERTAINTY_SAMPLES = 240


# Fewer early-stopping frames than this fit no uncertainty model of their own when fine-tuning:
# the init's is kept (training/METHOD.md, "Fine-tuning").
MIN_UNCERTAINTY_FRAMES = 20


# Per-axis std range (px) of the label noise on the two-object draws: hand labels of natural
# features are a few px off (the paper's LEGO test; the simulator's natural scene: 4.9 px).
OBJECT_LABEL_NOISE_PX = (2.0, 8.0)


def fit_network_uncertainty(
    model: DimeNet, spec: ModelSpec, units: list, config: TrainConfig, rng: np.random.Generator
) -> tuple[Uncertainty, dict]:
    """The uncertainty model of the trained network's K - K' on the early-stopping frames of
    ``units`` (each camera's ``val``, ``val_truth`` their calibration; in model px), K' the
    simulator's true K where the dataset holds it (K' - the frame's ``k_bias``: the network
    follows what the frame's points say, and the uncertainty must cover what they get wrong), each
    draw on the frames re-imaged by ``resynthesise``
    (every frame under another's principal point; K' the K it is then imaged under): so the
    fit sees many pairings of pose and OIS state, not only the few frames' own. The draws:
    clean, at 64 points and with the points of one plane (a third as many each as there are
    augmentation draws; a single view of a plane leaves K partly unobservable, and only such
    inputs teach the model how little the network then knows), under ``augment``'s test-like
    conditions, and with the points of two objects under label noise (as many: hand-labelled
    natural features, whose sparse and noisy spread the augmentation's compact clusters do not
    show). Its data correlation is fitted on the MAP estimates of the draws with added noise
    (the augmentation's and the two-object ones: their K' does not know that noise, while the
    other draws' K' was fitted to the very points MAP reads); its data bias, where the dataset holds
    the true K, on the draws without added noise (what MAP gets wrong there is the frame's build
    errors, which no noise model knows; elsewhere 0). Returns the model and its 1-sigma coverage there."""
    draws = max(8, -(-UNCERTAINTY_SAMPLES // sum(unit.val.n_frames for unit in units)))
    few = -(-draws // 3)
    conditions = [(False, lambda ds: ds)] * few
    conditions += [(False, lambda ds: drop_inference_points(ds, config.min_points, rng))] * few
    conditions += [(True, lambda ds: augment(ds, config, spec.features.grid, rng))] * draws
    conditions += [(False, lambda ds: one_plane(ds, rng))] * few
    conditions += [
        (True, lambda ds: add_noise(two_objects(ds, rng), rng.uniform(*OBJECT_LABEL_NOISE_PX, ds.n_frames), 0.0, rng))
    ] * draws
    residuals, stats, map_draws = [], [], []
    for unit in progress(units, desc="fit sigma"):
        predictor = torch_predictor(model, spec, "training").for_camera(unit.camera)
        for added_noise, condition in conditions:
            reimaged, K_reimaged = resynthesise(unit.val, unit.val_truth, rng, 1.0)
            drawn = condition(reimaged)
            pred = predictor.predict(drawn)
            k_true = k_params(K_reimaged) - unit.val_truth.k_bias
            residuals.append((k_params(pred.K) - k_true)[pred.predicted])
            stats.append(pred.stats[pred.predicted])
            if added_noise or unit.val_truth.k_bias.any():
                map_draws.append((added_noise, drawn, pred, k_true, predictor))
    residuals, stats = np.concatenate(residuals), np.concatenate(stats)
    uncertainty = fit_uncertainty(residuals, stats)
    *map_errors, added = _map_errors(map_draws, uncertainty)
    rho = fit_data_correlation(*(a[added] for a in map_errors[:4]))
    bias = np.zeros(4) if added.all() else fit_data_bias(*(a[~added] for a in map_errors), rho)
    uncertainty = replace(uncertainty, data_correlation=rho, data_bias=bias)
    return uncertainty, coverage(residuals, np.zeros_like(residuals), uncertainty.covariance(stats))


def _map_errors(draws: list, uncertainty: Uncertainty) -> tuple:
    """Over the frames of ``draws`` [(noise added, frames, prediction, K' (F, 4) px, predictor)]
    that MAP rectifies under ``uncertainty`` (not widened): the MAP K's errors against K' (F, 4)
    px, its posterior standard deviations (F, 4) px, its variances over the prior's (F, 4), the
    frames' 2D noise (F,) px, the network's standard deviations (F, 4) px, and (F,) bool: the
    frame's draw added noise."""
    errors, sigma, ratio, noise, net, added = [], [], [], [], [], []
    for added_noise, frames, pred, k_ref, predictor in draws:
        K_cov = uncertainty.covariance(pred.stats)
        for f in np.flatnonzero(pred.predicted):
            m = frames.infer_mask[f]
            fit, _ = map_rectify(
                frames.points_2d[f][m],
                frames.points_3d[f][m],
                k_params(pred.K[f]),
                K_cov[f],
                predictor.K_bounds,
                predictor.K_c,
            )
            if fit is not None:
                errors.append(fit.k - k_ref[f])
                sigma.append(np.sqrt(np.diag(fit.K_cov)))
                ratio.append(np.diag(fit.K_cov) / np.diag(K_cov[f]))
                noise.append(fit.noise_px)
                net.append(np.sqrt(np.diag(K_cov[f])))
                added.append(added_noise)
    four = tuple(np.array(a).reshape(-1, 4) for a in (errors, sigma, ratio))
    return four + (np.array(noise), np.array(net).reshape(-1, 4), np.array(added, bool))


def uncertainty_fields(model: DimeNet, spec: ModelSpec, units: list, config: TrainConfig, init) -> dict:
    """The spec's uncertainty model (with the population spread of K* - K_c), its structure
    limit (``scene_limits``) and provenance: the uncertainty fitted on the early-stopping frames; a
    fine-tuned model keeps its init's when they are fewer than MIN_UNCERTAINTY_FRAMES or the fit
    breaks the spec's sigma range rule (a few frames cannot fit five slopes per parameter). A
    fit that breaks the rule with nothing to keep is a DatasetError: the model would not load."""
    inherited = init.spec.uncertainty if init is not None else None
    n_val = sum(u.val.n_frames for u in units)
    structure_rng = np.random.default_rng(config.seed + 3)
    limit = {"residual_structure_px": structure_limit(units, config, spec.features.grid, structure_rng)}
    if inherited is not None:
        provenance = {**spec.provenance, "uncertainty": f"from {init.source}"}
        kept = {**limit, "uncertainty": inherited, "provenance": provenance}
    if inherited is not None and n_val < MIN_UNCERTAINTY_FRAMES:
        return kept
    rng = np.random.default_rng(config.seed + 2)
    uncertainty, val_coverage = fit_network_uncertainty(model, spec, units, config, rng)
    uncertainty = replace(uncertainty, population_sigma_px=population_sigma(units))
    try:
        Uncertainty.from_dict(uncertainty.to_dict(), spec.features.grid.n_cells)
    except ValueError as exc:
        if inherited is None:
            raise DatasetError(
                f"split: {n_val} early-stopping frames fit no usable uncertainty model ({exc})"
            ) from None
        return kept
    provenance = {**spec.provenance, "uncertainty_val_coverage": val_coverage}
    return {**limit, "uncertainty": uncertainty, "provenance": provenance}
