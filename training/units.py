"""The training's frames: one camera's dataset as a ``Unit`` (calibrated, in the model's pixels,
split into fitting and early-stopping frames) and the per-epoch augmentation of its frames
(K-resynthesis, noise, fewer points, emptied cells, clustered natural-like labels)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from dimenet.runtime.errors import DatasetError
from dimenet.runtime.evaluation.calibration import calibrate_dataset
from dimenet.runtime.evaluation.conditions import add_noise, drop_inference_points, empty_cells, one_plane
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.geometry import MIN_POINTS, k_params, project
from dimenet.runtime.rectify.grid import Grid
from dimenet.runtime.rectify.user_camera import Camera, generic_pixel_map

from .config import TrainConfig

# Plausible K: the train frames' K* range widened by this many times its span on each side.
K_BOUNDS_MARGIN = 1.0


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
    """Per-frame calibration of the train frames: K* (F, 3, 3) px, pose* {W}->{C}, the
    residuals x - pi(K*, pose*) (F, P, 2) px that the calibration leaves (the frame's noise and
    the build errors its rig file does not hold), and k_bias (F, 4) px: K* - K_true (fx, fy, cx,
    cy) where the dataset holds the simulator's K_true, else 0 (what the frame's own fit gets
    wrong, which the uncertainty model must cover; training/METHOD.md, "Do no harm with a model that
    follows the frame")."""

    K_star: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    residual: np.ndarray
    k_bias: np.ndarray


def frame_truth(frames: Dataset, cal_K, cal_rvec, cal_tvec, K_true: Optional[np.ndarray]) -> FrameTruth:
    """The frames' FrameTruth from their calibration (K* (F, 3, 3) px and pose*) and the
    simulator's K_true (F, 3, 3) px, or None for a capture."""
    residual = frames.points_2d - project(frames.points_3d, cal_K, cal_rvec, cal_tvec)
    k_bias = np.zeros((len(cal_K), 4)) if K_true is None else k_params(cal_K) - k_params(K_true)
    return FrameTruth(cal_K, cal_rvec, cal_tvec, np.where(frames.valid[..., None], residual, 0.0), k_bias)


def clean(truth: FrameTruth) -> FrameTruth:
    """``truth`` without its residuals: frames re-imaged under it are exactly what K and the pose
    make, so only the augmentation's noise is left on them."""
    return replace(truth, residual=np.zeros_like(truth.residual))


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
    cells; a share of the frames with clustered, noisily labelled inference points, and (``plane_share``) a share
    with those of one plane."""
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
    clustered = cluster_inference_points(
        kept, frames.infer_mask, config.cluster_share, config.cluster_points, config.max_label_noise_px, rng
    )
    return one_plane_share(clustered, config.plane_share, rng)


def one_plane_share(frames: Dataset, share: float, rng: np.random.Generator) -> Dataset:
    """A random ``share`` of the frames keeps only the inference points of one plane (``conditions.one_plane``),
    the others all theirs: a single board or wall, where the frame's points do not fix K. A share of 0 draws
    nothing from ``rng``, so the augmentation's other draws stay those of a training without it."""
    if share <= 0:
        return frames
    picked = rng.random(frames.n_frames) < share
    if not picked.any():
        return frames
    infer = frames.infer_mask.copy()
    infer[picked] = one_plane(frames.select(picked), rng).infer_mask
    return replace(frames, infer_mask=infer)


@dataclass(frozen=True)
class Unit:
    """One camera's training frames, in the model's pixels (a generic model's canonical camera,
    ``rectify.user_camera``): fit and val the fitting and early-stopping frames, truth and
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
    K_c, K_star, K_true, frames = cal.K_c, cal.K_star, dataset.K_true, dataset
    if focal_px is not None:
        pixels = generic_pixel_map(Camera(K_c, tuple(int(v) for v in dataset.image_size)), focal_px)
        K_c, K_star = pixels.K_to_model(K_c), pixels.K_to_model(K_star)
        K_true = None if K_true is None else pixels.K_to_model(K_true)
        frames = replace(
            dataset,
            points_2d=pixels.points_to_model(dataset.points_2d),
            image_size=np.round(dataset.image_size * pixels.scale).astype(np.int64),
        )
    fit_idx, val_idx = split_train_val(frames, config)

    def at(idx):
        return K_star[idx], cal.rvec[idx], cal.tvec[idx], None if K_true is None else K_true[idx]

    return Unit(
        name=name,
        fit=frames.select(fit_idx),
        val=frames.select(val_idx),
        truth=frame_truth(frames.select(fit_idx), *at(fit_idx)),
        val_truth=frame_truth(frames.select(val_idx), *at(val_idx)),
        camera=Camera(K_c, tuple(int(v) for v in frames.image_size)),
        train_K_star=K_star[frames.frames_in("train")],
    )
