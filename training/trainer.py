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
import json
import time
from collections.abc import Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch

from dimenet.runtime import __version__
from dimenet.runtime.errors import DatasetError, InputError
from dimenet.runtime.evaluation.conditions import drop_inference_points
from dimenet.runtime.formats.dataset import Dataset, read_dataset
from dimenet.runtime.geometry import k_matrix, k_params
from dimenet.runtime.jobs.progress import progress
from dimenet.runtime.rectify.features import FeatureSpec, c0_poses, grid_features
from dimenet.runtime.rectify.spec import GenericCamera, ModelSpec
from dimenet.runtime.rectify.user_camera import Camera

from . import bpnp
from .config import TrainConfig
from .init_weights import InitialWeights
from .model import dime_net
from .run_dir import CHECKPOINT, read_checkpoint, write_checkpoint, write_run
from .uncertainty import uncertainty_fields
from .units import Unit, augment, first_train_frames, k_bounds, parameter_bounds, resynthesise, training_unit

# Training clamps Delta K to +-this (px) inside the loss; OIS moves K by tens of px.
DELTA_K_LIMIT_PX = 300.0
# A generic model's canonical camera: fx (px) and scene depth (mm) of the features; the paper's
# phones' f and rig distance, so the device models' constants (noise, scales, limits) carry over.
GENERIC_FOCAL_PX = 3000.0
GENERIC_DEPTH_MM = 500.0
# A factory K_c (the platform's, not calibrated; ``TrainConfig.k_c_error``): f off by up to this fraction ...
FACTORY_F_REL = 0.03
# ... and the principal point by up to this fraction of the image width, per axis (uniform draws).
FACTORY_C_WIDTH = 0.01


@dataclass(frozen=True)
class TrainResult:
    run_dir: Path
    best_epoch: int
    best_val_e: float  # px, mean over val frames (clean and reduced) at the best epoch
    seconds: float
    history: list = field(default_factory=list)


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
    origin: Optional[dict] = None,
    resume: bool = False,
) -> TrainResult:
    """Train on the dataset's train split and write RUN_DIR (weights, spec.json, curve.png).

    One dataset and no ``init``: a device model of that camera. Several datasets (a camera
    family), or ``init`` from a generic model: a generic model (canonical fx
    ``GENERIC_FOCAL_PX``, scale-free depth ``GENERIC_DEPTH_MM``; the init's, when given), each
    dataset calibrated on its own train split. ``init`` starts from a model's weights (its
    grid, variant and hidden sizes replace the config's).

    After each epoch RUN_DIR/checkpoint.safetensors holds the training's whole state (weights, the best
    epoch's, the optimizer's and the scheduler's state, both random generators, the history), written
    atomically and removed once the run is written; ``origin`` (the data and init paths, JSON) rides in
    it for `dimenet train --resume`. ``resume`` continues from it: the same config, data and init give
    the same weights, bit for bit, as a training never stopped (InputError when the checkpoint is of
    another training)."""
    with torch_threads(1):
        return _train(dataset, config, run_dir, dataset_sha256, command, init, origin or {}, resume)


def _feature_spec(config: TrainConfig, generic: bool, init: Optional[InitialWeights]) -> FeatureSpec:
    if init is not None:
        return init.spec.features
    return replace(config.features, depth_mm=GENERIC_DEPTH_MM if generic else None)


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


def _inputs(unit: Unit, frames: Dataset, spec_features: FeatureSpec, K_c: Optional[np.ndarray] = None) -> tuple:
    """(features, p2, p3, w, K_c per frame) tensors of one camera's frames (model px) under K_c (3, 3) (None: the
    unit's calibrated one), and kept (F,) bool: the frames with a C0 pose, the only ones in the tensors (an
    augmented frame of a few noisy clustered points can have none under a drawn K_c)."""
    K_c = unit.camera.K if K_c is None else K_c
    rvec, tvec, reasons = c0_poses(frames.points_2d, frames.points_3d, frames.infer_mask, K_c)
    kept = np.array([r is None for r in reasons])
    if not kept.all():
        frames, rvec, tvec = frames.select(kept), rvec[kept], tvec[kept]

    def features(frames: Dataset, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
        p2, p3, mask = frames.points_2d, frames.points_3d, frames.infer_mask
        return grid_features(p2, p3, mask, K_c, frames.image_size, spec_features, poses=(rvec, tvec))

    try:
        feats = features(frames, rvec, tvec)
    except InputError:  # a frame whose points fix no data step (a singular Hessian): dropped as one without a pose
        one = np.eye(frames.n_frames, dtype=bool)  # row b selects frame b alone
        steps = np.array(
            [_has_step(features, frames.select(one[b]), rvec[one[b]], tvec[one[b]]) for b in range(len(one))]
        )
        frames, rvec, tvec = frames.select(steps), rvec[steps], tvec[steps]
        kept[np.flatnonzero(kept)[~steps]] = False
        feats = features(frames, rvec, tvec)
    K_c = torch.from_numpy(np.broadcast_to(K_c, (frames.n_frames, 3, 3)).copy())
    return (torch.from_numpy(feats.astype(np.float32)), *_tensors(frames), K_c), kept


def _has_step(features, frame: Dataset, rvec: np.ndarray, tvec: np.ndarray) -> bool:
    """Whether one frame's feature can be formed by ``features`` (its data step's Hessian is positive definite)."""
    try:
        features(frame, rvec, tvec)
    except InputError:
        return False
    return True


def _identity(config: TrainConfig, dataset_sha256: str, init: Optional[InitialWeights]) -> dict:
    """What a checkpoint must share with the training that resumes it (JSON's own values: tuples as lists)."""
    return json.loads(
        json.dumps({"config": config.to_dict(), "dataset_sha256": dataset_sha256, "init": init and init.source})
    )


def _checkpoint(run_dir, epoch: int, model, opt, sched, rng, best: tuple, history: list, record: dict) -> None:
    """Write the state after ``epoch`` (``run_dir.write_checkpoint``), with ``record``: the training's
    identity (``_identity``), its origin and command."""
    opt_state = opt.state_dict()
    tensors = {f"model.{k}": v for k, v in model.state_dict().items()}
    if best[2] is not None:
        tensors.update({f"best.{k}": v for k, v in best[2].items()})
    tensors.update({f"optimizer.{i}.{name}": v for i, state in opt_state["state"].items() for name, v in state.items()})
    tensors["torch_rng"] = torch.get_rng_state()
    state = {
        **record,
        "epoch": epoch,
        "best_val_e": best[0],
        "best_epoch": best[1],
        "history": history,
        "param_groups": opt_state["param_groups"],
        "scheduler": sched.state_dict(),
        "numpy_rng": rng.bit_generator.state,
    }
    write_checkpoint(run_dir, tensors, state)


def _resumed(run_dir, model, opt, sched, rng, identity: dict) -> tuple[int, tuple, list]:
    """Load RUN_DIR's checkpoint into the model, optimizer, scheduler and random generators; (the epoch
    it was written after, best, history). InputError when it is of another training."""
    tensors, state = read_checkpoint(run_dir)
    differs = [k for k in identity if state.get(k) != identity[k]]
    if differs:
        raise InputError(
            f"{Path(run_dir) / CHECKPOINT}: the checkpoint of another training ({', '.join(differs)} differ): resume "
            "with the settings, data and init it was written with (`dimenet train --resume RUN_DIR` reads them)"
        )
    part = lambda prefix: {k[len(prefix) :]: v for k, v in tensors.items() if k.startswith(prefix)}  # noqa: E731
    model.load_state_dict(part("model."))
    fresh = opt.state_dict()["param_groups"]
    groups = [
        {k: tuple(v) if isinstance(g0.get(k), tuple) else v for k, v in g.items()}
        for g, g0 in zip(state["param_groups"], fresh)
    ]
    opt_tensors = {}
    for key, v in part("optimizer.").items():
        index, name = key.split(".", 1)
        opt_tensors.setdefault(int(index), {})[name] = v
    opt.load_state_dict({"state": opt_tensors, "param_groups": groups})
    sched.load_state_dict(state["scheduler"])
    rng.bit_generator.state = state["numpy_rng"]
    torch.set_rng_state(tensors["torch_rng"])
    best = (state["best_val_e"], state["best_epoch"], part("best.") or None)
    return state["epoch"], best, state["history"]


def _train(
    datasets, config: TrainConfig, run_dir, dataset_sha256: str, command: str, init, origin: dict, resume: bool
) -> TrainResult:
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
    f_star = [k_params(u.truth.K_star)[:, :2] for u in units]
    val_inputs = []
    for reduced in (False, True):
        parts = []
        for u in units:
            frames = u.val
            if reduced:
                frames = drop_inference_points(frames, config.min_points, np.random.default_rng(config.seed + 1))
            parts.append(_inputs(u, frames, spec_features)[0])
        val_inputs.append(_stack(parts))

    hidden = tuple(init.spec.hidden) if init is not None else tuple(config.hidden)
    head = init.spec.head if init is not None else config.head
    model = dime_net(spec_features, hidden, head)
    if init is not None:
        model.load_state_dict(init.state_dict)
    lr = config.lr if init is None else config.fine_tune_lr
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=config.weight_decay)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=config.epochs)
    identity = _identity(config, dataset_sha256, init)
    record = {**identity, "origin": origin, "command": command}
    done, best, history = 0, (np.inf, 0, None), []
    if resume:
        done, best, history = _resumed(run_dir, model, opt, sched, rng, identity)
    for epoch in progress(range(done + 1, config.epochs + 1), desc="train"):
        parts, delta_f_star, unposed = [], [], 0
        for u, f in zip(units, f_star):
            frames = augment(resynthesise(u.fit, u.truth, rng, config.resynthesis)[0], config, spec_features.grid, rng)
            K_c = u.camera.K
            if config.k_c_error and rng.random() < config.k_c_error:
                K_c = factory_k_c(u.camera, rng)
            tensors, kept = _inputs(u, frames, spec_features, K_c)
            parts.append(tensors)
            delta_f_star.append(f[kept] - k_params(K_c)[:2])
            unposed += int((~kept).sum())
        feats, p2, p3, w, K_c = _stack(parts)
        delta_f_star = torch.from_numpy(np.concatenate(delta_f_star))
        order = torch.from_numpy(rng.permutation(len(feats)))
        model.train()
        losses, skipped = [], 0
        for i in range(0, len(order), config.batch_size):
            b = order[i : i + config.batch_size]
            delta_k = model(feats[b])
            try:
                mse = reprojection_loss(delta_k, K_c[b], p2[b], p3[b], w[b])[0]
            except InputError:  # a frame has no pose under the net's K: no gradient from this batch
                skipped += 1
                continue
            loss = mse + config.focal_weight * focal_loss(delta_k, delta_f_star[b])
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(mse.item())
        sched.step()
        model.eval()
        with torch.no_grad():
            try:
                val_e = float(np.mean([reprojection_loss(model(f), K, *t)[1].mean() for f, *t, K in val_inputs]))
            except InputError:  # a val frame has no pose under the net's K: not a best epoch
                val_e = float("inf")
        history.append({"epoch": epoch, "train_mse_px2": float(np.mean(losses)), "val_e_px": val_e})
        if skipped:
            history[-1]["skipped_batches"] = skipped
        if unposed:
            history[-1]["unposed_frames"] = unposed
        if val_e < best[0]:
            best = (val_e, epoch, {k: v.detach().clone() for k, v in model.state_dict().items()})
        elif config.patience is not None and epoch - best[1] >= config.patience:
            break
        _checkpoint(run_dir, epoch, model, opt, sched, rng, best, history, record)
    model.load_state_dict(best[2])
    provenance = {
        "dataset_sha256": dataset_sha256,
        "seed": config.seed,
        "dimenet_version": __version__,
        "torch_version": torch.__version__,
        "config": config.to_dict(),
        "command": command,
        "best_epoch": best[1],
        "best_val_e_px": best[0],
    }
    if init is not None:
        provenance["init"] = init.source
    if generic:
        delta = np.concatenate([k_params(u.train_K_star) - k_params(u.camera.K) for u in units])
        generic_camera = GenericCamera(focal_px, _with_factory_span(parameter_bounds(delta), units, config))
        camera = {"K_c": None, "image_size": None, "K_bounds": None, "generic": generic_camera}
        provenance["cameras"] = [u.name for u in units]
    else:
        u = units[0]
        bounds = _with_factory_span(k_bounds(u.train_K_star), [u], config)
        camera = {"K_c": u.camera.K, "image_size": u.camera.image_size, "K_bounds": bounds}
    spec = ModelSpec(features=spec_features, hidden=hidden, provenance=provenance, head=head, **camera)
    spec = replace(spec, **uncertainty_fields(model, spec, units, config, init))
    run_dir = write_run(run_dir, model, spec, history)
    (run_dir / CHECKPOINT).unlink(missing_ok=True)  # the run is written: nothing left to resume
    return TrainResult(
        run_dir=Path(run_dir), best_epoch=best[1], best_val_e=best[0], seconds=time.monotonic() - start, history=history
    )


def factory_k_c(camera: Camera, rng: np.random.Generator) -> np.ndarray:
    """(3, 3) px a factory-like K_c of ``camera`` (model px): its calibrated K with f scaled by one
    U(1 +- FACTORY_F_REL) and each principal-point coordinate moved by U(+-FACTORY_C_WIDTH) x its width."""
    k = k_params(camera.K)
    k[:2] *= 1.0 + rng.uniform(-FACTORY_F_REL, FACTORY_F_REL)
    k[2:] += rng.uniform(-FACTORY_C_WIDTH, FACTORY_C_WIDTH, 2) * camera.image_size[0]
    return k_matrix(k)


def _with_factory_span(bounds: np.ndarray, units: list, config: TrainConfig) -> np.ndarray:
    """(4, 2) px ``bounds`` of the plausible (Delta) K, widened either way by the largest offset ``factory_k_c``
    can give the units' cameras when the training drew factory K_c (``config.k_c_error``), else as they are."""
    if not config.k_c_error:
        return bounds
    k = np.array([k_params(u.camera.K) for u in units])
    width = max(u.camera.image_size[0] for u in units)
    span = np.array([*(FACTORY_F_REL * k[:, :2].max(0)), FACTORY_C_WIDTH * width, FACTORY_C_WIDTH * width])
    return bounds + np.stack([-span, span], -1)


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
