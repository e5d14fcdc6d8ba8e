"""The generic default model beside the per-device ones (issue 21's targets): zero-shot on the
paper's three profiles, on every camera of a fresh camera family, fine-tuned from a few frames,
and its invariance to the stream's resolution and the world unit; and on held-out scene families
(issue 35's): random rigs of seeds and framings the training never drew, and cameras without OIS, for
each bundled model (the default, any-scene, and the paper's grid model, paper-rig)."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Optional

import numpy as np

from dimenet.runtime.evaluation.calibration import dataset_camera
from dimenet.runtime.evaluation.conditions import drop_inference_points
from dimenet.runtime.evaluation.methods import evaluate, runtime_estimate, with_prior_oracle
from dimenet.runtime.evaluation.predictor import Predictor, load_predictor
from dimenet.runtime.evaluation.prior_oracle import PRIOR_ORACLE
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.geometry import k_matrix, k_params, rescaled_k, rescaled_px
from dimenet.runtime.jobs.progress import progress
from dimenet.runtime.rectify.model import OnnxModel
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.user_camera import Camera
from dimenet.runtime.sim.family import family_member, family_profiles, has_ois, hfov_deg, simulate_family
from dimenet.runtime.sim.scenes import FILL

from ..config import ReproduceConfig, TrainConfig
from .paper import DEVICES

# The generic model of the rows beside the paper's: the paper's grid model (the default before 0.7.0, whose
# figures training/REPRODUCTION.md carries; the default's own are in models_spec/any-scene-model.md).
GENERIC_MODEL = "paper-rig"
# The family the bundled model was trained on is seed 0 (models_spec/paper-rig-model.md); this
# one it never saw.
FRESH_FAMILY_SEED = 101
FRESH_FAMILY_CAMERAS = 20
# Held-out scene families: name -> (seed, cameras, fill), random scenes of seeds the default never drew (it
# trains on seed 0), one framed as the training's, one far (a fifth to a third of the image width); and the
# cameras without OIS of a third (OIS_OFF_FAMILY: seed, cameras; about a fifth of them).
FRESH_SCENES = {"rig": (101, 12, FILL), "far": (202, 12, (0.2, 1 / 3))}
# Held-out natural scenes: seed, cameras, natural test frames each (a room, a street or a table of the camera's
# own around a board; sim.natural), read on the frames' board corners as the paper's LEGO test is; 200 frames a camera
# so that each mode's rho over the prior oracle's has an interval narrow enough to judge (issue 50).
FRESH_NATURAL = (404, 12, 200)
OIS_OFF_FAMILY = (11, 40)
OIS_OFF_SIGMAS = 2.0  # a frame of a camera without OIS is right when K is within this many sigma of K_true
FINE_TUNE_FRAMES = 30
SMALL_POINTS = 64


def _rho(ev, method: str = "dimenet") -> float:
    return ev.methods[method]["overall"].rho


def _test(ds: Dataset, scene: str) -> Dataset:
    return ds.select(ds.frames_in("test") & (ds.scene == scene))


def zero_shot(data: dict, generic: Predictor, device: dict, config: ReproduceConfig) -> dict:
    """Per paper profile: rho of the generic model (its camera from the train split) and of the
    device model on the same frames: rig at all points and at 64, galaxy-s8 natural and planar
    in both modes; the 1-sigma coverage against K_true on rig and planar."""
    rng = lambda k: np.random.default_rng(config.seed + k)  # noqa: E731
    rows = {}
    for d in DEVICES:
        p = generic.for_camera(dataset_camera(data[d]))
        rig = _test(data[d], "rig")
        # The 64-point draw of Table 4 (seed + 2), so the per-device row is Table 4's.
        cases = {"rig": rig, f"rig {SMALL_POINTS} pts": drop_inference_points(rig, SMALL_POINTS, rng(2))}
        for scene in ("natural", "planar"):
            if np.any(data[d].frames_in("test") & (data[d].scene == scene)):
                cases[scene] = _test(data[d], scene)
        for case, frames in cases.items():
            methods = with_prior_oracle(frames, ("dimenet", "map"))[0]  # natural frames: the prior oracle beside
            ev = evaluate(frames, p.K_c, p, methods=methods)
            ev_device = evaluate(frames, device[d].K_c, device[d], methods=methods)
            rows[f"{d} {case}"] = {
                "n_frames": frames.n_frames,
                "generic": {m: _rho(ev, m) for m in ("dimenet", "map")},
                "device": {m: _rho(ev_device, m) for m in ("dimenet", "map")},
                "coverage_true": ev.coverage_true,
                **{f"generic_{k}": v for k, v in _beside_prior_oracle(ev).items()},
                **{f"device_{k}": v for k, v in _beside_prior_oracle(ev_device).items()},
            }
    return rows


def _first(n: int, cameras: Optional[int]) -> int:
    """The cameras of a held-out family of ``n`` that a run measures: all, or the first ``cameras``
    (``ReproduceConfig.held_out_cameras``; a family's first m cameras are the family of m)."""
    return n if cameras is None else min(n, cameras)


def fresh_family(generic: Optional[Predictor] = None, cameras: Optional[int] = None) -> list:
    """rho (rig, all points) of the generic model (default: the bundled one) on each camera (or the first
    ``cameras``) of a family it never saw. A job of ``runtime.jobs.engine.run_all`` too (it needs no other
    result)."""
    generic = generic or load_predictor(GENERIC_MODEL)
    rows = []
    n = _first(FRESH_FAMILY_CAMERAS, cameras)
    family = simulate_family(n, FRESH_FAMILY_SEED)
    for camera, ds in progress(family, total=n, desc="reproduce: fresh family"):
        p = generic.for_camera(dataset_camera(ds))
        ev = evaluate(_test(ds, "rig"), p.K_c, p, methods=("dimenet",))
        w, h = camera.image_size_px
        rows.append({"camera": camera.name, "size": [w, h], "hfov_deg": hfov_deg(camera), "rho": _rho(ev)})
    return rows


def fresh_scenes(model: str = GENERIC_MODEL, cameras: Optional[int] = None) -> dict:
    """A generic model (a bundled model's name, or what ``load_predictor`` takes) on held-out scene
    families: per FRESH_SCENES family and camera, rho of both modes on its rig test frames at every
    point and at SMALL_POINTS; per camera of the FRESH_NATURAL family, rho of both modes on its natural
    test frames (``natural``); and, on the cameras without OIS of OIS_OFF_FAMILY, the share of frames
    whose K (as `rectify` returns it, fallbacks included) is within OIS_OFF_SIGMAS of K_true on every
    parameter. Each camera's K_c is calibrated on its train split; ``cameras``: only each family's first
    (``_first``). A job of ``runtime.jobs.engine.run_all`` too."""
    generic = load_predictor(model)
    out: dict = {}
    for name, (seed, n, fill) in FRESH_SCENES.items():
        rows = []
        n = _first(n, cameras)
        family = simulate_family(n, seed, scenes="random", fill=fill)
        for i, (camera, ds) in enumerate(progress(family, total=n, desc=f"reproduce: held-out {name} scenes")):
            p = generic.for_camera(dataset_camera(ds))
            rig = _test(ds, "rig")
            row = {"camera": camera.name, "ois": has_ois(seed, i)}
            cases = {"all": rig, "small": drop_inference_points(rig, SMALL_POINTS, np.random.default_rng(seed + i))}
            for case, frames in cases.items():
                ev = evaluate(frames, p.K_c, p, methods=("dimenet", "map"))
                row[case] = {m: _rho(ev, m) for m in ("dimenet", "map")}
            rows.append(row)
        out[name] = rows
    out["natural"] = natural_scenes(generic, cameras)
    out["ois_off"] = ois_off_coverage(generic, cameras)
    return out


def _beside_prior_oracle(ev) -> dict:
    """The prior oracle's rho and each mode's rho over it with its interval (``metrics.RatioInterval`` as a dict)
    on an evaluation's frames (``overall``), or {} when the frames had no prior oracle."""
    if PRIOR_ORACLE not in ev.methods:
        return {}
    return {
        "prior_oracle": _rho(ev, PRIOR_ORACLE),
        "ratio": {m: asdict(ev.ratios[m]["overall"]) for m in ("dimenet", "map")},
    }


def natural_scenes(generic: Predictor, cameras: Optional[int] = None) -> list:
    """Per camera of the FRESH_NATURAL family (or its first ``cameras``): its scene's kind, features and label noise,
    rho of both modes on its natural test frames (``all``; None where the frames' e_c is within noise of e*: cameras
    without OIS), and beside them the prior oracle's rho and each mode's rho over it (``_beside_prior_oracle``)."""
    seed, n, frames = FRESH_NATURAL
    n = _first(n, cameras)
    rows = []
    family = simulate_family(n, seed, scenes="random", natural_frames=frames)
    for i, (camera, ds) in enumerate(progress(family, total=n, desc="reproduce: held-out natural scenes")):
        p = generic.for_camera(dataset_camera(ds))
        frames = _test(ds, "natural")
        ev = evaluate(frames, p.K_c, p, methods=with_prior_oracle(frames, ("dimenet", "map"))[0])
        scene = ds.meta["natural_scene"]
        rows.append(
            {
                "camera": camera.name,
                "ois": has_ois(seed, i),
                "kind": scene["kind"],
                "features": scene["features"],
                "label_noise_px": float(np.median(frames.label_noise_px)),
                "all": {m: _rho(ev, m) for m in ("dimenet", "map")},
                "small": {"dimenet": None, "map": None},
                **_beside_prior_oracle(ev),
            }
        )
    return rows


def ois_off_coverage(generic: Predictor, cameras: Optional[int] = None) -> dict:
    """On the cameras without OIS of OIS_OFF_FAMILY (or the first ``cameras`` of them), K_c calibrated on each
    camera's train split: per mode, the frames and the share of them whose move |K - K_c| is within OIS_OFF_SIGMAS
    on every parameter (``within``: with no OIS the right move is none), the share whose K is within
    OIS_OFF_SIGMAS of K_true (``within_true``: K_c's own calibration error counts there too), and how many kept
    K_c."""
    seed, n = OIS_OFF_FAMILY
    profiles = family_profiles(n, seed)
    off = [i for i in range(n) if not has_ois(seed, i)][: _first(n, cameras)]
    within = {"dimenet": [], "map": []}
    within_true = {"dimenet": [], "map": []}
    kept = {"dimenet": 0, "map": 0}
    for i in progress(off, desc="reproduce: cameras without OIS"):
        ds = family_member(profiles[i], i, seed, n, scenes="random")
        camera = dataset_camera(ds)
        p = generic.for_camera(camera)
        frames = _test(ds, "rig")
        for mode in within:
            est = runtime_estimate(frames, p, mode)
            reach = OIS_OFF_SIGMAS * np.sqrt(np.diagonal(est.K_cov, axis1=1, axis2=2))
            k = k_params(est.K)
            within[mode] += (np.abs(k - k_params(camera.K)) <= reach).all(1).tolist()
            within_true[mode] += (np.abs(k - k_params(frames.K_true)) <= reach).all(1).tolist()
            kept[mode] += est.fallbacks
    return {
        "cameras": len(off),
        "frames": len(within["dimenet"]),
        "within": {m: float(np.mean(v)) for m, v in within.items()},
        "within_true": {m: float(np.mean(v)) for m, v in within_true.items()},
        "kept_k_c": kept,
    }


def fine_tune_training(data: dict, out: Path, config: ReproduceConfig) -> tuple:
    """The fine-tuning of GENERIC_MODEL on the first FINE_TUNE_FRAMES galaxy-s8 train frames, as
    (dataset, TrainConfig, run dir, init): reproduce trains it beside its other models."""
    cfg = TrainConfig(epochs=config.epochs, seed=config.seed, train_frames=FINE_TUNE_FRAMES)
    return data["galaxy-s8"], cfg, out / "runs" / f"galaxy-s8-{GENERIC_MODEL}-{FINE_TUNE_FRAMES}", GENERIC_MODEL


def fine_tune(data: dict, device: dict, run_dir: Path, seconds: float, config: ReproduceConfig) -> dict:
    """The fine-tuned model (``fine_tune_training``'s, in ``run_dir``, trained in ``seconds``)
    against the device model trained on all frames: rho on rig at 64 points and on natural frames."""
    s8 = data["galaxy-s8"]
    tuned = load_predictor(run_dir).for_camera(dataset_camera(s8))
    cases = {
        f"rig {SMALL_POINTS} pts": drop_inference_points(
            _test(s8, "rig"), SMALL_POINTS, np.random.default_rng(config.seed + 2)
        ),
        "natural": _test(s8, "natural"),
    }
    rows = {}
    for case, frames in cases.items():
        mine = evaluate(frames, tuned.K_c, tuned, methods=("dimenet",))
        theirs = evaluate(frames, device["galaxy-s8"].K_c, device["galaxy-s8"], methods=("dimenet",))
        rows[case] = {"fine_tuned": _rho(mine), "device": _rho(theirs)}
    return {"frames": FINE_TUNE_FRAMES, "seconds": seconds, "rows": rows}


def invariance(data: dict, model: OnnxModel) -> dict:
    """The bundled model on the galaxy-s8 rig test frames: mean |K_half (scaled up) - K_full| px,
    max |K_m - K_mm| px, and how many frames of half-resolution points under the full-resolution
    K_c get a K (silently: any is wrong) rather than a fallback."""
    s8 = data["galaxy-s8"]
    camera = dataset_camera(s8)
    frames = _test(s8, "rig")
    w, h = camera.image_size
    half = Camera(_half_k(camera.K), (w // 2, h // 2))
    p2, p3, valid = frames.points_2d, frames.points_3d, frames.valid
    p2_half = np.where(valid[..., None], rescaled_px(p2, 0.5), 0.0)
    rectifier = Rectifier(model, "dimenet", camera)
    full = rectifier.rectify_batch(p2, p3, valid)
    halved = Rectifier(model, "dimenet", half).rectify_batch(p2_half, p3, valid)
    metres = rectifier.rectify_batch(p2, p3 / 1000.0, valid)
    mismatched = rectifier.rectify_batch(p2_half, p3, valid)
    k_half = k_params(halved.K)
    k_up = rescaled_k(k_half, 2.0)
    return {
        "n_frames": frames.n_frames,
        "half_vs_full_mean_px": float(np.abs(k_up - k_params(full.K)).mean()),
        "m_vs_mm_max_px": float(np.abs(k_params(metres.K) - k_params(full.K)).max()),
        "half_points_full_k_c_silent": int(sum(r is None for r in mismatched.fallback)),
        "fallbacks_full": int(sum(r is not None for r in full.fallback)),
    }


def _half_k(K: np.ndarray) -> np.ndarray:
    return k_matrix(rescaled_k(k_params(K), 0.5))


def run_generic(data: dict, device: dict, config: ReproduceConfig, model: OnnxModel, jobs: dict) -> dict:
    """Every row of the generic comparison of ``model`` (the bundled default; ``report`` writes
    them); ``jobs``: what ran beside the trainings, the fine-tuning's run dir and seconds
    (``fine_tune``), the ``fresh_family`` rows and per bundled model's name its ``fresh_scenes``."""
    generic = Predictor.of_model(model)
    return {
        "model": model.source,
        "zero_shot": zero_shot(data, generic, device, config),
        "fresh_family": jobs["fresh_family"],
        "fresh_scenes": jobs["fresh_scenes"],
        "fine_tune": fine_tune(data, device, *jobs["fine_tune"], config),
        "invariance": invariance(data, model),
    }
