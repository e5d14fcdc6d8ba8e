"""Training DIME-Net with the paper's reprojection loss through the BPnP layer.

Per step: grid features (the runtime's numpy code) from each frame's inference points ->
MLP -> K = K_c + Delta K -> pose by the BPnP layer under K on all valid points -> loss =
mean squared reprojection error (px^2) over those points (paper eq. L_rep), plus a focal term
beyond the paper: focal_weight times the mean squared error (px^2) of (fx, fy) against the
frame's K*. L_rep is nearly flat along f (the pose's depth absorbs it), so without that term
the net barely learns focus breathing and its f drifts by up to +7 px on clustered or planar
inputs (training/METHOD.md).

Robust by construction: every epoch each training frame is re-drawn with a random number of
inference points (min_points..all) and a random fraction (0..max_eta) of its occupied grid
cells emptied, so one model serves 320 down to 64 points and eta up to 80%; a share of the
frames keeps only clustered, noisily labelled inference points, like natural-object labels.
Early stopping on the val split, or on a held-back part of train when there is no val.
Then the uncertainty model of Delta K (``rectify.uncertainty``; the fit is
``evaluation.uncertainty_fit``'s) is fitted on those same frames, clean, reduced to 64
points, under several draws of the augmentation, with the points of one plane and with
those of two objects under label noise.
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch

from dimenet.runtime import __version__
from dimenet.runtime.errors import DatasetError
from dimenet.runtime.evaluation.calibration import calibrate_dataset
from dimenet.runtime.evaluation.conditions import add_noise, drop_inference_points, empty_cells, one_plane, two_objects
from dimenet.runtime.evaluation.uncertainty_fit import coverage, fit_data_correlation, fit_uncertainty
from dimenet.runtime.formats.dataset import Dataset, read_dataset
from dimenet.runtime.geometry import MIN_POINTS, k_params, project
from dimenet.runtime.jobs.progress import progress
from dimenet.runtime.rectify.camera import Camera, generic_pixel_map
from dimenet.runtime.rectify.features import FeatureSpec, grid_features
from dimenet.runtime.rectify.grid import Grid
from dimenet.runtime.rectify.map_fit import map_rectify
from dimenet.runtime.rectify.spec import GenericCamera, ModelSpec
from dimenet.runtime.rectify.uncertainty import Uncertainty

from . import bpnp
from .config import TrainConfig
from .init_weights import InitialWeights
from .model import DimeNet
from .predictor import torch_predictor
from .run_dir import write_run

# Training clamps Delta K to +-this (px) inside the loss; OIS moves K by tens of px.
DELTA_K_LIMIT_PX = 300.0
# Plausible K: the train frames' K* range widened by this many times its span on each side.
K_BOUNDS_MARGIN = 1.0
# The uncertainty model is fitted on >= this many (frame, condition) samples: the val frames,
# re-imaged, under as many augmentation draws as it takes (at least 8), plus a third as many
# draws each clean, at 64 points and of one plane, and as many two-object draws.
UNCERTAINTY_SAMPLES = 240
# Fewer early-stopping frames than this fit no uncertainty model of their own when fine-tuning:
# the init's is kept (training/METHOD.md, "Fine-tuning").
MIN_UNCERTAINTY_FRAMES = 20
# A generic model's canonical camera: fx (px) and scene depth (mm) of the features; the paper's
# phones' f and rig distance, so the device models' constants (noise, scales, limits) carry over.
GENERIC_FOCAL_PX = 3000.0
GENERIC_DEPTH_MM = 500.0
# Per-axis std range (px) of the label noise on the two-object draws: hand labels of natural
# features are a few px off (the paper's LEGO test; the simulator's natural scene: 4.9 px).
OBJECT_LABEL_NOISE_PX = (2.0, 8.0)


@dataclass(frozen=True)
class TrainResult:
    run_dir: Path
    best_epoch: int
    best_val_e: float  # px, mean over val frames (clean and reduced) at the best epoch
    seconds: float
    history: list = field(default_factory=list)


def split_train_val(dataset: Dataset, config: TrainConfig) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the fitting frames and of the early-stopping frames (the val split, else a
    seeded part of train)."""
    train = dataset.frames_in("train")
    if train.sum() < 2:
        raise DatasetError("split: training needs at least 2 train frames")
    val = dataset.frames_in("val")
    if val.any():
        return np.flatnonzero(train), np.flatnonzero(val)
    idx = np.flatnonzero(train)
    rng = np.random.default_rng(config.seed)
    n_val = max(1, int(round(config.val_fraction * len(idx))))
    held = np.sort(rng.choice(idx, n_val, replace=False))
    return np.setdiff1d(idx, held), held


def k_bounds(K_star: np.ndarray) -> np.ndarray:
    """(4, 2) px plausible range of (fx, fy, cx, cy): the K* range widened by its span."""
    return parameter_bounds(k_params(K_star))


def parameter_bounds(p: np.ndarray) -> np.ndarray:
    """(4, 2) plausible range of (F, 4) parameters (px): their range widened by its span."""
    lo, hi = p.min(0), p.max(0)
    span = np.maximum(hi - lo, 1.0)
    return np.stack([lo - K_BOUNDS_MARGIN * span, hi + K_BOUNDS_MARGIN * span], -1)


@dataclass(frozen=True)
class FrameTruth:
    """Per-frame calibration of the train frames: K* (F, 3, 3) px, pose* {W}->{C}, and the
    residuals x - pi(K*, pose*) (F, P, 2) px that the calibration leaves (the frame's noise)."""

    K_star: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    residual: np.ndarray


def frame_truth(frames: Dataset, cal_K, cal_rvec, cal_tvec) -> FrameTruth:
    residual = frames.points_2d - project(frames.points_3d, cal_K, cal_rvec, cal_tvec)
    return FrameTruth(cal_K, cal_rvec, cal_tvec, np.where(frames.valid[..., None], residual, 0.0))


def resynthesise(
    frames: Dataset, truth: FrameTruth, rng: np.random.Generator, share: float
) -> tuple[Dataset, np.ndarray]:
    """K-resynthesis augmentation: frame i re-imaged under the principal point of a random
    frame j of ``frames`` (its own focal length kept, so focus breathing stays tied to
    distance): x' = pi(K', pose*_i) + residual_i. The OIS state is independent of the
    hand-held pose, so this is a draw from the same joint distribution, with frame i's real
    noise. A random ``share`` of the frames is re-imaged; the others stay as captured.
    Returns the frames and the K' (F, 3, 3) px each is now imaged under (K*_i if not re-imaged)."""
    j = rng.integers(0, frames.n_frames, frames.n_frames)
    j = np.where(rng.random(frames.n_frames) < share, j, np.arange(frames.n_frames))
    K_new = truth.K_star.copy()
    K_new[:, :2, 2] = truth.K_star[j, :2, 2]
    x_new = project(frames.points_3d, K_new, truth.rvec, truth.tvec) + truth.residual
    return replace(frames, points_2d=np.where(frames.valid[..., None], x_new, np.nan)), K_new


def cluster_inference_points(
    frames: Dataset,
    candidates: np.ndarray,
    share: float,
    n_points: tuple,
    max_noise_px: float,
    rng: np.random.Generator,
) -> Dataset:
    """Natural-object-like inference points in a random ``share`` of the frames: only the
    n ~ U(n_points) ``candidates`` ((F, P) bool, e.g. the frame's own inference points) nearest
    (px) to one or two random candidates stay inference points, and they get hand-labelling
    noise, std ~ U(0, max_noise_px) per image axis (px). The other valid points keep their
    values and still count in the loss, as the boards do in the paper's LEGO test."""
    picked = np.flatnonzero(rng.random(frames.n_frames) < share)
    infer, points_2d = frames.infer_mask.copy(), frames.points_2d.copy()
    for f in picked:
        idx = np.flatnonzero(candidates[f])
        centres = points_2d[f, rng.choice(idx, rng.integers(1, 3), replace=False)]
        dist = np.linalg.norm(points_2d[f, idx, None] - centres, axis=-1).min(1)
        keep = idx[np.argsort(dist)[: rng.integers(n_points[0], n_points[1] + 1)]]
        infer[f] = False
        infer[f, keep] = True
        points_2d[f, keep] += rng.normal(0.0, rng.uniform(0.0, max_noise_px), (len(keep), 2))
    return replace(frames, infer_mask=infer, points_2d=points_2d)


def augment(frames: Dataset, config: TrainConfig, grid: Grid, rng: np.random.Generator) -> Dataset:
    """Each frame with random extra 2D noise, a random inference-point count and a random share
    of emptied cells, except a ``full_share`` of the frames that keep all their points and
    cells; a share of the frames with clustered, noisily labelled inference points."""
    n_infer = frames.infer_mask.sum(1)
    low = np.minimum(max(config.min_points, MIN_POINTS), n_infer)
    n = rng.integers(low, n_infer + 1)
    eta = rng.uniform(0.0, config.max_eta, frames.n_frames)
    # Full frames, as the rig's at test time: without them the net sees 320 points too rarely.
    full = rng.random(frames.n_frames) < config.full_share
    n, eta = np.where(full, n_infer, n), np.where(full, 0.0, eta)
    noisy = add_noise(frames, rng.uniform(0.0, config.max_noise_px, frames.n_frames), 0.0, rng)
    dropped = drop_inference_points(noisy, n, rng)
    emptied = empty_cells(dropped, eta, grid, rng)
    # A frame the emptying left with too few points keeps its points (the runtime would fall back).
    too_few = emptied.infer_mask.sum(1) < MIN_POINTS
    kept = replace(emptied, infer_mask=np.where(too_few[:, None], dropped.infer_mask, emptied.infer_mask))
    return cluster_inference_points(
        kept, frames.infer_mask, config.cluster_share, config.cluster_points, config.max_label_noise_px, rng
    )


def fit_network_uncertainty(
    model: DimeNet, spec: ModelSpec, units: list, config: TrainConfig, rng: np.random.Generator
) -> tuple[Uncertainty, dict]:
    """The uncertainty model of the trained network's K - K' on the early-stopping frames of
    ``units`` (each camera's ``val``, ``val_truth`` their calibration; in model px), each
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
    other draws' K' was fitted to the very points MAP reads). Returns the model and its
    1-sigma coverage there."""
    draws = max(8, -(-UNCERTAINTY_SAMPLES // sum(unit.val.n_frames for unit in units)))
    few = -(-draws // 3)
    conditions = [(False, lambda ds: ds)] * few
    conditions += [(False, lambda ds: drop_inference_points(ds, config.min_points, rng))] * few
    conditions += [(True, lambda ds: augment(ds, config, spec.features.grid, rng))] * draws
    conditions += [(False, lambda ds: one_plane(ds, rng))] * few
    conditions += [
        (True, lambda ds: add_noise(two_objects(ds, rng), rng.uniform(*OBJECT_LABEL_NOISE_PX, ds.n_frames), 0.0, rng))
    ] * draws
    residuals, stats, noisy = [], [], []
    for unit in units:
        predictor = torch_predictor(model, spec, "training").for_camera(unit.camera)
        for added_noise, condition in conditions:
            reimaged, K_reimaged = resynthesise(unit.val, unit.val_truth, rng, 1.0)
            drawn = condition(reimaged)
            pred = predictor.predict(drawn)
            residuals.append((k_params(pred.K) - k_params(K_reimaged))[pred.predicted])
            stats.append(pred.stats[pred.predicted])
            if added_noise:
                noisy.append((drawn, pred, K_reimaged, predictor))
    residuals, stats = np.concatenate(residuals), np.concatenate(stats)
    uncertainty = fit_uncertainty(residuals, stats)
    uncertainty = replace(uncertainty, data_correlation=fit_data_correlation(*_map_errors(noisy, uncertainty)))
    return uncertainty, coverage(residuals, np.zeros_like(residuals), uncertainty.covariance(stats))


def _map_errors(draws: list, uncertainty: Uncertainty) -> tuple:
    """Over the frames of ``draws`` [(frames, prediction, K' (F, 3, 3), predictor)] that MAP
    rectifies under ``uncertainty`` (not widened): the MAP K's errors against K' (F, 4) px, its
    posterior standard deviations (F, 4) px, its variances over the prior's (F, 4), the frames'
    2D noise (F,) px."""
    errors, sigma, ratio, noise = [], [], [], []
    for frames, pred, K_ref, predictor in draws:
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
                errors.append(fit.k - k_params(K_ref[f]))
                sigma.append(np.sqrt(np.diag(fit.K_cov)))
                ratio.append(np.diag(fit.K_cov) / np.diag(K_cov[f]))
                noise.append(fit.noise_px)
    return tuple(np.array(a).reshape(-1, 4) for a in (errors, sigma, ratio)) + (np.array(noise),)


@dataclass(frozen=True)
class Unit:
    """One camera's training frames, in the model's pixels (a generic model's canonical camera,
    ``rectify.camera``): fit and val the fitting and early-stopping frames, truth and
    val_truth their calibration, camera the camera the predictor serves (K_c, its prior, and
    the image size, in the model's pixels), train_K_star (T, 3, 3) px every train frame's K*."""

    name: str
    fit: Dataset
    val: Dataset
    truth: FrameTruth
    val_truth: FrameTruth
    camera: Camera
    train_K_star: np.ndarray


def first_train_frames(dataset: Dataset, n: int) -> Dataset:
    """The dataset with only its first ``n`` train frames in file order (the other splits kept)."""
    train = dataset.frames_in("train")
    if train.sum() < n:
        raise DatasetError(f"split: --train-frames {n} asks for more than the {int(train.sum())} train frames")
    return dataset.select(~train | (np.cumsum(train) <= n))


def training_unit(dataset: Dataset, config: TrainConfig, focal_px: Optional[float], name: str) -> Unit:
    """A dataset as a Unit: its train split calibrated as ``calibrate`` does, then (for a generic
    model, ``focal_px`` its canonical fx) every 2D point and K mapped onto the canonical camera;
    the image size rounds to whole canonical pixels (<= 0.5 px of a ~4000 px image). A dataset
    with a lens trains on its undistorted points; every train frame must give K* (the target)."""
    dataset = dataset.undistorted()
    cal = calibrate_dataset(dataset)
    for b in np.flatnonzero(dataset.frames_in("train")):
        if cal.reasons[b] is not None:
            name = dataset.frame_id[b] if dataset.frame_id is not None else f"frame {b}"
            raise DatasetError(f"{name}: a train frame must give K* (the training target): {cal.reasons[b]}")
    K_c, K_star, frames = cal.K_c, cal.K_star, dataset
    if focal_px is not None:
        pixels = generic_pixel_map(Camera(K_c, tuple(int(v) for v in dataset.image_size)), focal_px)
        K_c, K_star = pixels.K_to_model(K_c), pixels.K_to_model(K_star)
        frames = replace(
            dataset,
            points_2d=pixels.points_to_model(dataset.points_2d),
            image_size=np.round(dataset.image_size * pixels.scale).astype(np.int64),
        )
    fit_idx, val_idx = split_train_val(frames, config)
    return Unit(
        name=name,
        fit=frames.select(fit_idx),
        val=frames.select(val_idx),
        truth=frame_truth(frames.select(fit_idx), K_star[fit_idx], cal.rvec[fit_idx], cal.tvec[fit_idx]),
        val_truth=frame_truth(frames.select(val_idx), K_star[val_idx], cal.rvec[val_idx], cal.tvec[val_idx]),
        camera=Camera(K_c, tuple(int(v) for v in frames.image_size)),
        train_K_star=K_star[frames.frames_in("train")],
    )


def _tensors(frames: Dataset):
    w = torch.from_numpy(frames.valid.astype(np.float64))
    p2 = torch.from_numpy(np.where(frames.valid[..., None], frames.points_2d, 0.0))
    p3 = torch.from_numpy(np.where(frames.valid[..., None], frames.points_3d, 0.0))
    return p2, p3, w


def focal_loss(delta_k: torch.Tensor, delta_f_star: torch.Tensor) -> torch.Tensor:
    """Mean squared error (px^2) of the predicted (dfx, dfy) against the frames' K* focal
    lengths minus K_c's (B, 2) px."""
    return ((delta_k[:, :2].double() - delta_f_star) ** 2).mean()


def reprojection_loss(delta_k: torch.Tensor, K_c: torch.Tensor, p2, p3, w) -> tuple[torch.Tensor, torch.Tensor]:
    """(mean squared error px^2 over frames, per-frame mean Euclidean error px) under K = K_c + delta_k."""
    # An untrained net may emit a wild Delta K under which PnP has no solution; the clamp is
    # the identity on realistic values (the runtime uses Delta K unclamped).
    dk = delta_k.double().clamp(-DELTA_K_LIMIT_PX, DELTA_K_LIMIT_PX)
    K = K_c.expand(len(dk), 3, 3).clone()  # K_c (3, 3), or (B, 3, 3) one per frame
    K[:, 0, 0] = K[:, 0, 0] + dk[:, 0]
    K[:, 1, 1] = K[:, 1, 1] + dk[:, 1]
    K[:, 0, 2] = K[:, 0, 2] + dk[:, 2]
    K[:, 1, 2] = K[:, 1, 2] + dk[:, 3]
    rvec, tvec = bpnp.solve_pnp(p2, p3, w, K)
    r = (bpnp.project(p3, K, rvec, tvec) - p2) * w[..., None]
    n = w.sum(1)
    mse = ((r**2).sum((1, 2)) / n).mean()
    e = (torch.linalg.norm(r, dim=-1) * w).sum(1) / n
    return mse, e.detach()


@contextmanager
def torch_threads(n: int):
    """Run torch on n threads, restoring the previous setting: the BPnP layer's many tiny batched
    ops run faster on one thread than contending for two cores."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def train(
    dataset: Union[Dataset, Sequence[Dataset]],
    config: TrainConfig,
    run_dir: str | Path,
    *,
    dataset_sha256: str = "",
    command: str = "",
    init: Optional[InitialWeights] = None,
) -> TrainResult:
    """Train on the dataset's train split and write RUN_DIR (weights, spec.json, curve.png).

    One dataset and no ``init``: a device model of that camera. Several datasets (a camera
    family), or ``init`` from a generic model: a generic model (canonical fx
    ``GENERIC_FOCAL_PX``, scale-free depth ``GENERIC_DEPTH_MM``; the init's, when given), each
    dataset calibrated on its own train split. ``init`` starts from a model's weights (its
    grid, variant and hidden sizes replace the config's)."""
    with torch_threads(1):
        return _train(dataset, config, run_dir, dataset_sha256, command, init)


def _feature_spec(config: TrainConfig, generic: bool, init: Optional[InitialWeights]) -> FeatureSpec:
    if init is not None:
        return init.spec.features
    return FeatureSpec(
        grid=Grid.parse(config.grid), variant=config.variant, depth_mm=GENERIC_DEPTH_MM if generic else None
    )


def _units(datasets: list, config: TrainConfig, focal_px: Optional[float]) -> list:
    if config.train_frames is not None:
        datasets = [first_train_frames(ds, config.train_frames) for ds in datasets]
    named = [(ds.meta.get("profile") or f"dataset {i}", ds) for i, ds in enumerate(datasets)]
    if len(named) == 1:
        return [training_unit(named[0][1], config, focal_px, named[0][0])]
    return [training_unit(ds, config, focal_px, name) for name, ds in progress(named, desc="calibrate")]


def _stack(parts: list) -> tuple:
    """Concatenate per-camera (features, p2, p3, w, K_c) tensors, padding p2, p3, w's point axis."""
    P = max(p[1].shape[1] for p in parts)
    pad = lambda t: torch.nn.functional.pad(t, (0, 0) * (t.dim() - 2) + (0, P - t.shape[1]))  # noqa: E731
    return tuple(torch.cat([pad(p[k]) if k in (1, 2, 3) else p[k] for p in parts]) for k in range(len(parts[0])))


def _inputs(unit: Unit, frames: Dataset, spec_features: FeatureSpec) -> tuple:
    """(features, p2, p3, w, K_c per frame) tensors of one camera's frames (model px)."""
    feats = grid_features(
        frames.points_2d, frames.points_3d, frames.infer_mask, unit.camera.K, frames.image_size, spec_features
    )
    K_c = torch.from_numpy(np.broadcast_to(unit.camera.K, (frames.n_frames, 3, 3)).copy())
    return (torch.from_numpy(feats.astype(np.float32)), *_tensors(frames), K_c)


def _uncertainty_fields(model: DimeNet, spec: ModelSpec, units: list, config: TrainConfig, init) -> dict:
    """The spec's uncertainty model and its provenance: fitted on the early-stopping frames; a
    fine-tuned model keeps its init's when they are fewer than MIN_UNCERTAINTY_FRAMES or the fit
    breaks the spec's sigma range rule (a few frames cannot fit five slopes per parameter). A
    fit that breaks the rule with nothing to keep is a DatasetError: the model would not load."""
    inherited = init.spec.uncertainty if init is not None else None
    n_val = sum(u.val.n_frames for u in units)
    if inherited is not None and n_val < MIN_UNCERTAINTY_FRAMES:
        return {"uncertainty": inherited, "provenance": {**spec.provenance, "uncertainty": f"from {init.source}"}}
    rng = np.random.default_rng(config.seed + 2)
    uncertainty, val_coverage = fit_network_uncertainty(model, spec, units, config, rng)
    try:
        Uncertainty.from_dict(uncertainty.to_dict(), spec.features.grid.n_cells)
    except ValueError as exc:
        if inherited is None:
            raise DatasetError(
                f"split: {n_val} early-stopping frames fit no usable uncertainty model ({exc})"
            ) from None
        return {"uncertainty": inherited, "provenance": {**spec.provenance, "uncertainty": f"from {init.source}"}}
    return {"uncertainty": uncertainty, "provenance": {**spec.provenance, "uncertainty_val_coverage": val_coverage}}


def _train(datasets, config: TrainConfig, run_dir, dataset_sha256: str, command: str, init) -> TrainResult:
    start = time.monotonic()
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    datasets = [datasets] if isinstance(datasets, Dataset) else list(datasets)
    generic = len(datasets) > 1 if init is None else init.spec.generic is not None
    if init is not None and not generic and len(datasets) > 1:
        raise DatasetError(
            f"--init {init.source} is a device model: it fine-tunes on one dataset of its camera, "
            f"not on {len(datasets)} (start a family from a generic model, or from scratch)"
        )
    focal_px = None
    if generic:
        focal_px = init.spec.generic.focal_px if init is not None and init.spec.generic else GENERIC_FOCAL_PX
    spec_features = _feature_spec(config, generic, init)
    units = _units(datasets, config, focal_px)
    # Re-imaging keeps a frame's own focal length, so its K* f stays the target of every draw.
    delta_f_star = torch.from_numpy(
        np.concatenate([k_params(u.truth.K_star)[:, :2] - k_params(u.camera.K)[:2] for u in units])
    )
    val_inputs = []
    for reduced in (False, True):
        parts = []
        for u in units:
            frames = u.val
            if reduced:
                frames = drop_inference_points(frames, config.min_points, np.random.default_rng(config.seed + 1))
            parts.append(_inputs(u, frames, spec_features))
        val_inputs.append(_stack(parts))

    hidden = tuple(init.spec.hidden) if init is not None else tuple(config.hidden)
    model = DimeNet(spec_features.size, hidden)
    if init is not None:
        model.load_state_dict(init.state_dict)
    lr = config.lr if init is None else config.fine_tune_lr
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=config.weight_decay)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=config.epochs)
    best = (np.inf, 0, None)
    history = []
    for epoch in progress(range(1, config.epochs + 1), desc="train"):
        parts = []
        for u in units:
            frames = augment(resynthesise(u.fit, u.truth, rng, config.resynthesis)[0], config, spec_features.grid, rng)
            parts.append(_inputs(u, frames, spec_features))
        feats, p2, p3, w, K_c = _stack(parts)
        order = torch.from_numpy(rng.permutation(len(feats)))
        model.train()
        losses = []
        for i in range(0, len(order), config.batch_size):
            b = order[i : i + config.batch_size]
            delta_k = model(feats[b])
            mse = reprojection_loss(delta_k, K_c[b], p2[b], p3[b], w[b])[0]
            loss = mse + config.focal_weight * focal_loss(delta_k, delta_f_star[b])
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(mse.item())
        sched.step()
        model.eval()
        with torch.no_grad():
            val_e = float(np.mean([reprojection_loss(model(f), K, *t)[1].mean() for f, *t, K in val_inputs]))
        history.append({"epoch": epoch, "train_mse_px2": float(np.mean(losses)), "val_e_px": val_e})
        if val_e < best[0]:
            best = (val_e, epoch, {k: v.detach().clone() for k, v in model.state_dict().items()})
        elif config.patience is not None and epoch - best[1] >= config.patience:
            break
    model.load_state_dict(best[2])
    provenance = {
        "dataset_sha256": dataset_sha256,
        "seed": config.seed,
        "dimenet_version": __version__,
        "torch_version": torch.__version__,
        "config": asdict(config),
        "command": command,
        "best_epoch": best[1],
        "best_val_e_px": best[0],
    }
    if init is not None:
        provenance["init"] = init.source
    if generic:
        delta = np.concatenate([k_params(u.train_K_star) - k_params(u.camera.K) for u in units])
        generic_camera = GenericCamera(focal_px, parameter_bounds(delta))
        camera = {"K_c": None, "image_size": None, "K_bounds": None, "generic": generic_camera}
        provenance["cameras"] = [u.name for u in units]
    else:
        u = units[0]
        camera = {"K_c": u.camera.K, "image_size": u.camera.image_size, "K_bounds": k_bounds(u.train_K_star)}
    spec = ModelSpec(features=spec_features, hidden=hidden, provenance=provenance, **camera)
    spec = replace(spec, **_uncertainty_fields(model, spec, units, config, init))
    run_dir = write_run(run_dir, model, spec, history)
    return TrainResult(
        run_dir=Path(run_dir), best_epoch=best[1], best_val_e=best[0], seconds=time.monotonic() - start, history=history
    )


def read_training_data(path: str | Path) -> tuple[list, str]:
    """The datasets of ``dimenet train DATA``: one .npz file, or every .npz file of a folder (a
    camera family) in name order; and the sha256 of the file (of a folder: of its files' names
    and sha256s). DatasetError when a folder has none."""
    path = Path(path)
    if not path.is_dir():
        return [read_dataset(path)], file_sha256(path)
    files = sorted(path.glob("*.npz"))
    if not files:
        raise DatasetError(f"{path}: a folder without dataset files (*.npz)")
    h = hashlib.sha256()
    datasets = []
    for f in progress(files, desc="read"):
        datasets.append(read_dataset(f))
        h.update(f"{f.name} {file_sha256(f)}\n".encode())
    return datasets, h.hexdigest()


def file_sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
