"""The paper's tables on the simulated profiles: simulate, train the models, evaluate every case,
and write results.json, the plots and REPRODUCTION.md (report.py) into OUT_DIR."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import numpy as np

from dimenet.runtime.errors import DimenetError
from dimenet.runtime.evaluation.conditions import add_noise, drop_inference_points, empty_cells, occupancy
from dimenet.runtime.evaluation.methods import ALL_METHODS, METHODS, evaluate, with_prior_oracle
from dimenet.runtime.evaluation.predictor import load_predictor
from dimenet.runtime.evaluation.prior_oracle import PRIOR_ORACLE
from dimenet.runtime.formats.atomic import atomic_write, atomic_write_text
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.jobs.engine import Engine
from dimenet.runtime.rectify.features import FeatureSpec
from dimenet.runtime.rectify.grid import Grid
from dimenet.runtime.rectify.model import MODEL_NAMES, load_model
from dimenet.runtime.sim.simulator import simulate

from ..config import ReproduceConfig, TrainConfig
from ..init_weights import initial_weights
from ..trainer import train
from .generic import GENERIC_MODEL, fine_tune_training, fresh_family, fresh_scenes, run_generic
from .paper import DEVICES, ETAS, GRIDS, NATURAL_FRAMES, NOISE_2D_PX, NOISE_3D_MM, PLANAR_FRAMES, POINTS, VARIANTS
from .report import STREAM_PLOT, plot_eta, plot_methods, plot_points, plot_stream, report
from .streams import QUICK_SECONDS, SECONDS, run_streams


def _row(ev) -> dict:
    s = ev.overall
    return {"n_frames": s.n_frames, "avg_e_c": s.avg_e_c, "avg_e": s.avg_e, "avg_e_star": s.avg_e_star, "rho": s.rho}


def _rig_test(ds: Dataset) -> Dataset:
    return ds.select(ds.frames_in("test") & (ds.scene == "rig"))


def _train(dataset: Dataset, cfg: TrainConfig, run_dir: Path, init: Optional[str]) -> str:
    return str(train(dataset, cfg, run_dir, init=None if init is None else initial_weights(init)).run_dir)


def _tables(data: dict, run_dirs: dict, config: ReproduceConfig) -> dict:
    """Tables 5, 4, 3 and 2 (dimenet rows) from the trained models in ``run_dirs`` (name -> dir)."""
    predictors = {name: load_predictor(d) for name, d in run_dirs.items()}

    def ev(frames, name):
        p = predictors[name]
        return evaluate(frames, p.K_c, p.predict_k)

    rng = lambda k: np.random.default_rng(config.seed + k)  # noqa: E731
    s8 = data["galaxy-s8"]
    s8_rig = _rig_test(s8)
    t5 = {d: _row(ev(_rig_test(data[d]), f"{d}-8x6-A")) for d in DEVICES}
    natural = s8.select(s8.frames_in("test") & (s8.scene == "natural"))
    if natural.n_frames:
        t5["galaxy-s8 (N)"] = _row(ev(natural, "galaxy-s8-8x6-A"))
    t4 = {"clean": {}, "noisy": {}}
    noisy = add_noise(s8_rig, NOISE_2D_PX, NOISE_3D_MM, rng(1))
    for n in POINTS:
        t4["clean"][n] = _row(ev(drop_inference_points(s8_rig, n, rng(2)), "galaxy-s8-8x6-A"))
        t4["noisy"][n] = _row(ev(drop_inference_points(noisy, n, rng(3)), "galaxy-s8-8x6-A"))
    t3 = {v: _row(ev(s8_rig, f"galaxy-s8-8x6-{v}")) for v in VARIANTS}
    t2 = {}
    for g in GRIDS:
        grid = Grid.parse(g)
        t2[g] = []
        for k, eta in enumerate(ETAS):
            frames = empty_cells(s8_rig, eta, grid, rng(10 + k)) if eta else s8_rig
            t2[g].append({"eta": eta, "gamma": occupancy(frames, grid), **_row(ev(frames, f"galaxy-s8-{g}-A"))})
    return {"table5": t5, "table4": t4, "table3": t3, "table2": t2}


def _baseline(frames: Dataset, run_dir: str) -> dict:
    """One baseline case: {"n_frames", "methods": method -> {avg_e, rho, fallbacks}, "coverage"
    and "coverage_true": method -> parameter -> share (against K* and against K_true)}."""
    p = load_predictor(run_dir)
    methods = METHODS if frames.K_platform is None else tuple(m for m in ALL_METHODS if m != PRIOR_ORACLE)
    ev = evaluate(frames, p.K_c, p, methods=with_prior_oracle(frames, methods)[0])  # natural frames: the prior oracle
    return {
        "n_frames": frames.n_frames,
        "methods": {
            m: {"avg_e": rows["overall"].avg_e, "rho": rows["overall"].rho, "fallbacks": ev.fallbacks[m]}
            for m, rows in ev.methods.items()
        },
        "coverage": ev.coverage,
        "coverage_true": ev.coverage_true,
    }


def _generic_rows(
    data: dict, run_dirs: dict, fine_tune_job: tuple, fresh: list, scenes: dict, config: ReproduceConfig
) -> dict:
    device = {d: load_predictor(run_dirs[f"{d}-8x6-A"]) for d in DEVICES}
    jobs = {"fine_tune": fine_tune_job, "fresh_family": fresh, "fresh_scenes": scenes}
    return run_generic(data, device, config, load_model(GENERIC_MODEL), jobs)


# The jobs of ``runtime.jobs.engine.Engine.run_all``: (kind, *arguments) -> JOBS[kind](*arguments). Each
# loads what it needs from run dirs, so the same jobs run in this process or as Ray tasks.
JOBS = {
    "train": _train,
    "fresh_family": fresh_family,
    "fresh_scenes": fresh_scenes,
    "tables": _tables,
    "baseline": _baseline,
    "generic": _generic_rows,
    "streams": run_streams,
}


def _job(item: tuple):
    return JOBS[item[0]](*item[1:])


def _run_jobs(engine: Engine, items: dict, cpus_per_job: int, desc: str) -> dict:
    """name -> (kind, *arguments) run on the engine -> name -> Outcome; DimenetError naming the
    first job that failed."""
    outcomes = dict(zip(items, engine.run_all(_job, list(items.values()), cpus_per_job=cpus_per_job, desc=desc)))
    for name, outcome in outcomes.items():
        if outcome.error is not None:
            raise DimenetError(f"reproduce: {name} failed: {outcome.error}")
    return outcomes


def run(config: ReproduceConfig, *, address: Optional[str] = None, cpus_per_job: int = 1) -> dict:
    """Train, evaluate and write the report; returns the results dictionary. Two batches of jobs
    (the trainings, then the evaluations of the trained models) run one after another, or as Ray
    jobs with ``address`` (``runtime.jobs.engine``): the same numbers either way, each model
    trained on one thread from its seed."""
    start = time.monotonic()
    out = Path(config.out_dir)
    runs = out / "runs"
    data = {
        d: simulate(
            d,
            seed=config.seed,
            natural_frames=NATURAL_FRAMES if d == "galaxy-s8" else 0,
            planar_frames=PLANAR_FRAMES if d == "galaxy-s8" else 0,
            platform_k=True,  # the SDK's K per frame, simulated: its own draws, the frames unchanged
        )
        for d in DEVICES
    }
    jobs = [(d, "8x6", "A", config.epochs) for d in DEVICES]
    jobs += [("galaxy-s8", "8x6", v, config.ablation_epochs) for v in VARIANTS[1:]]
    jobs += [("galaxy-s8", g, "A", config.ablation_epochs) for g in GRIDS[:2]]
    trainings = {
        f"{device}-{grid}-{variant}": (
            "train",
            data[device],
            TrainConfig(features=FeatureSpec(Grid.parse(grid), variant), epochs=epochs, seed=config.seed),
            runs / f"{device}-{grid}-{variant}",
            None,
        )
        for device, grid, variant, epochs in jobs
    }
    generic = load_model(GENERIC_MODEL).spec.generic is not None
    scene_jobs = {model: f"fresh scenes {model}" for model in MODEL_NAMES}  # each bundled model's job name
    if generic:  # the generic rows' own jobs, which need no trained model: beside the trainings
        trainings["fine-tune"] = ("train", *fine_tune_training(data, out, config))
        trainings["fresh family"] = ("fresh_family", None, config.held_out_cameras)
        trainings.update({job: ("fresh_scenes", model, config.held_out_cameras) for model, job in scene_jobs.items()})
    cases = _baseline_cases(data, config)
    with Engine(address) as engine:  # one Ray session for both batches
        trained = _run_jobs(engine, trainings, cpus_per_job, "reproduce: training")
        side_jobs = ("fine-tune", "fresh family", *scene_jobs.values())
        run_dirs = {name: trained[name].value for name in trainings if name not in side_jobs}
        evaluations = {}  # the longest first (generic ~12 s, tables ~9 s, each baseline case ~1 s)
        if generic:
            tune = (Path(trained["fine-tune"].value), trained["fine-tune"].seconds)
            scenes = {model: trained[job].value for model, job in scene_jobs.items()}
            side = (trained["fresh family"].value, scenes)
            evaluations["generic"] = ("generic", data, run_dirs, tune, *side, config)
        evaluations["tables"] = ("tables", data, run_dirs, config)
        evaluations["streams"] = ("streams", SECONDS if config.held_out_cameras is None else QUICK_SECONDS)
        evaluations.update({case: ("baseline", frames, run_dirs[name]) for case, (frames, name) in cases.items()})
        evaluated = _run_jobs(engine, evaluations, cpus_per_job, "reproduce: evaluation")
    results: dict = {"train_seconds": {name: trained[name].seconds for name in run_dirs}}
    results.update(evaluated["tables"].value)
    results["baselines"] = {case: evaluated[case].value for case in cases}
    if generic:
        results["generic"] = evaluated["generic"].value
    results["streams"] = evaluated["streams"].value
    results["seconds"] = time.monotonic() - start
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "results.json", json.dumps(results, indent=1, default=float))
    atomic_write(out / "rho_vs_points.png", lambda f: f.write(plot_points(results["table4"])))
    atomic_write(out / "e_vs_eta.png", lambda f: f.write(plot_eta(results["table2"])))
    atomic_write(out / "methods_vs_points.png", lambda f: f.write(plot_methods(results["baselines"])))
    atomic_write(out / STREAM_PLOT, lambda f: f.write(plot_stream(results["streams"]["plot"])))
    atomic_write_text(out / "REPRODUCTION.md", report(results, config))
    return results


def _baseline_cases(data: dict, config: ReproduceConfig) -> dict:
    """Every Table 4/5 case and the planar frames: case name -> (frames, model name)."""
    rng = lambda k: np.random.default_rng(config.seed + k)  # noqa: E731
    s8 = data["galaxy-s8"]
    s8_rig, test = _rig_test(s8), s8.select(s8.frames_in("test"))
    cases = {f"{d} rig": (_rig_test(data[d]), f"{d}-8x6-A") for d in DEVICES}
    for scene in ("natural", "planar"):
        frames = test.select(test.scene == scene)
        if frames.n_frames:
            cases[f"galaxy-s8 {scene}"] = (frames, "galaxy-s8-8x6-A")
    noisy = add_noise(s8_rig, NOISE_2D_PX, NOISE_3D_MM, rng(1))
    for n in POINTS:  # the same draws as Table 4
        cases[f"galaxy-s8 clean {n} pts"] = (drop_inference_points(s8_rig, n, rng(2)), "galaxy-s8-8x6-A")
        cases[f"galaxy-s8 noisy {n} pts"] = (drop_inference_points(noisy, n, rng(3)), "galaxy-s8-8x6-A")
    return cases
