"""`dimenet fleet train MANIFEST --out DIR`: many models at once, each the same `dimenet train`.

The manifest (JSON, models_spec/fleet.md):
``{"jobs": [{"name": "s8", "dataset": "s8.npz", "init": "default", "seed": 0, "epochs": 600}, ...]}``
with per job a unique ``name`` (its run dir ``DIR/<name>``), a ``dataset`` (a .npz file or a
family folder, relative to the manifest) and any of `dimenet train`'s options: ``init``,
``seed``, ``epochs``, ``grid``, ``features``, ``focal_weight``, ``train_frames``, ``data_step``, ``moments``,
``k_c_error``, ``plane_share``, ``head``.

Every value goes through the argparse type `dimenet train` gives its flag (training/config.py),
so a manifest passes nothing the command line refuses; a job name may not be one of the files
the fleet writes into DIR (RESERVED, in any case).

Each job trains into ``DIR/.<name>.partial`` and is renamed to ``DIR/<name>`` when it is done
(with ``fleet.json``: its rho and errors on the dataset's test split, its seconds, and its
configuration and dataset sha256), so a run dir is there whole or not at all, and a second run
skips the jobs already done with the same configuration on the same data (resume); a job whose
configuration or dataset changed is trained again and the summary says why. A failed job is
reported by name; the others finish. The jobs run one after another, or as Ray
jobs with ``--address`` (``runtime.jobs.engine``).
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Optional

from dimenet.runtime.cli.arguments import grid_size, seed
from dimenet.runtime.errors import DimenetError, InputError
from dimenet.runtime.formats.atomic import atomic_write_text
from dimenet.runtime.formats.text import read_text
from dimenet.runtime.json_text import JsonProblem, an_object, parse_json, required, shown
from dimenet.runtime.rectify.grid import Grid
from dimenet.runtime.rectify.model import BUNDLED_MODELS
from dimenet.runtime.rectify.spec import HEADS

from .config import FEATURE_VARIANTS, TrainConfig, epochs, focal_weight, k_c_error, plane_share, train_frames

FLEET_FILE, SUMMARY_MD, SUMMARY_JSON = "fleet.json", "summary.md", "summary.json"
RESERVED = (SUMMARY_MD, SUMMARY_JSON)  # what the fleet itself writes into DIR, besides the run dirs
MAX_MANIFEST_BYTES = 4 << 20
MAX_JOBS = 10_000
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")


def _features(text: str) -> str:
    if text not in FEATURE_VARIANTS:
        raise argparse.ArgumentTypeError(f"must be one of {', '.join(FEATURE_VARIANTS)}, got {text!r}")
    return text


def _head(text: str) -> str:
    if text not in HEADS:
        raise argparse.ArgumentTypeError(f"must be one of {', '.join(HEADS)}, got {text!r}")
    return text


# Manifest key -> (TrainConfig field, JSON type, the argparse type of `dimenet train`'s flag).
_OPTIONS = {
    "seed": ("seed", int, seed),
    "epochs": ("epochs", int, epochs),
    "focal_weight": ("focal_weight", float, focal_weight),
    "train_frames": ("train_frames", int, train_frames),
    "k_c_error": ("k_c_error", float, k_c_error),
    "plane_share": ("plane_share", float, plane_share),
    "head": ("head", str, _head),
}
# Manifest key -> (FeatureSpec field of TrainConfig.features, JSON type, the flag's argparse type).
_FEATURE_OPTIONS = {
    "grid": ("grid", str, lambda text: Grid.parse(grid_size(text))),
    "features": ("variant", str, _features),
    "data_step": ("data_step", bool, None),  # `dimenet train --data-step`: a switch, no argparse type
    "moments": ("moments", bool, None),  # `dimenet train --moments`
}
_KEYS = {attr: key for key, (attr, _, _) in _OPTIONS.items()}  # TrainConfig field -> manifest key


class ManifestError(DimenetError):
    """A fleet manifest does not conform (the message names the file, the job and the field)."""


@dataclass(frozen=True)
class FleetJob:
    """One job: its name, dataset path, init (None: from scratch) and training settings."""

    name: str
    dataset: str
    init: Optional[str]
    config: TrainConfig


def _option(key: str, value):
    """A manifest value through the argparse type of `dimenet train`'s flag (JsonProblem naming the key)."""
    _, kind, parse = {**_OPTIONS, **_FEATURE_OPTIONS}[key]
    if kind is str and not isinstance(value, str):
        raise JsonProblem(f"{key} must be a string, got {shown(value)}")
    if kind is int and not (isinstance(value, int) and not isinstance(value, bool)):
        raise JsonProblem(f"{key} must be an integer, got {shown(value)}")
    if kind is float and not (isinstance(value, (int, float)) and not isinstance(value, bool)):
        raise JsonProblem(f"{key} must be a number, got {shown(value)}")
    if kind is bool:
        if not isinstance(value, bool):
            raise JsonProblem(f"{key} must be true or false, got {shown(value)}")
        return value
    try:
        return parse(value if kind is str else str(value))
    except argparse.ArgumentTypeError as exc:
        raise JsonProblem(f"{key}: {exc}") from None


def _job(d, base: Path, names: set) -> FleetJob:
    d = an_object(d, "a job")
    name = required(d, "name")
    if not (isinstance(name, str) and _NAME.fullmatch(name)):
        raise JsonProblem(f"name must be letters, digits, '.', '_' or '-' (a folder name), got {shown(name)}")
    if name.casefold() in {r.casefold() for r in RESERVED}:
        raise JsonProblem(f"name {name!r} is a file the fleet writes into its folder ({', '.join(RESERVED)})")
    if name.casefold() in names:
        raise JsonProblem(f"name {name!r} is used twice, in any case (each job has its own run dir)")
    known = {**_OPTIONS, **_FEATURE_OPTIONS}
    unknown = sorted(set(d) - {"name", "dataset", "init", *known})
    if unknown:
        raise JsonProblem(f"{unknown[0]!r} is not a job field (known: name, dataset, init, {', '.join(known)})")
    dataset = required(d, "dataset")
    if not (isinstance(dataset, str) and dataset.strip()):
        raise JsonProblem(f"dataset must be a path, got {shown(dataset)}")
    init = d.get("init")
    if init is not None and not (isinstance(init, str) and init.strip()):
        bundled = ", ".join(map(repr, BUNDLED_MODELS))
        raise JsonProblem(f"init must be a bundled model ({bundled}), a RUN_DIR or a MODEL.onnx, got {shown(init)}")
    if init is not None and init not in BUNDLED_MODELS:
        init = str(base / init)
    options = {_OPTIONS[key][0]: _option(key, d[key]) for key in _OPTIONS if key in d}
    features = {_FEATURE_OPTIONS[key][0]: _option(key, d[key]) for key in _FEATURE_OPTIONS if key in d}
    try:
        config = replace(TrainConfig(), **options, features=replace(TrainConfig().features, **features))
    except InputError as exc:  # a pairing of fields TrainConfig refuses (head gated_step without data_step)
        raise JsonProblem(str(exc)) from None
    return FleetJob(name=name, dataset=str(base / dataset), init=init, config=config)


def read_manifest(path: str | Path) -> list:
    """The jobs of a manifest file, every field checked (ManifestError names the job and field)."""
    path = Path(path)
    text = read_text(path, MAX_MANIFEST_BYTES, "fleet manifest", ManifestError)
    try:
        d = an_object(parse_json(text, max_chars=MAX_MANIFEST_BYTES), "the manifest")
        jobs = required(d, "jobs")
        if not isinstance(jobs, list) or not 1 <= len(jobs) <= MAX_JOBS:
            raise JsonProblem(f"jobs must be a list of 1 to {MAX_JOBS} jobs, got {shown(jobs)}")
    except JsonProblem as exc:
        raise ManifestError(f"{path}: {exc}") from None
    out, names = [], set()
    for i, d in enumerate(jobs):
        try:
            job = _job(d, path.parent, names)
        except (JsonProblem, ValueError) as exc:
            label = f"job {i}" + (f" ({d['name']!r})" if isinstance(d, dict) and isinstance(d.get("name"), str) else "")
            raise ManifestError(f"{path}: {label}: {exc}") from None
        names.add(job.name.casefold())
        out.append(job)
    return out


def _job_config(job: FleetJob) -> dict:
    """What a finished job was trained with, as its fleet.json records it (JSON values): every
    TrainConfig field (``TrainConfig.to_dict``) and the init."""
    return json.loads(json.dumps({**job.config.to_dict(), "init": job.init}))


def _flat(config: dict) -> dict:
    """A job's config with the features' fields as their own keys (features.grid, ...), so a change names them."""
    features = config.get("features")
    if not isinstance(features, dict):
        return config
    return {**{k: v for k, v in config.items() if k != "features"}, **{f"features.{k}": v for k, v in features.items()}}


def _changed(record: dict, config: dict, dataset_sha256: str) -> Optional[str]:
    """Why a finished job's record (its fleet.json) does not fit the job now, or None when it
    does: "config changed: epochs 10 -> 20, ...", "dataset changed", or no record of either."""
    if not isinstance(record.get("config"), dict) or "dataset_sha256" not in record:
        return "finished without a record of its configuration and dataset (an older release)"
    old, config = _flat(record["config"]), _flat(config)
    edits = [
        f"{_KEYS.get(key, key)} {shown(old.get(key))} -> {shown(config.get(key))}"
        for key in sorted(set(old) | set(config))
        if old.get(key) != config.get(key)
    ]
    if edits:
        return "config changed: " + ", ".join(edits)
    if record["dataset_sha256"] != dataset_sha256:
        return "dataset changed"
    return None


def run_job(item: tuple) -> dict:
    """One job (a job of ``runtime.jobs.engine.run_all``): item = (FleetJob, out dir). Trains into
    ``.<name>.partial``, evaluates on the dataset's test split, writes fleet.json and renames
    the folder to ``<name>``; a finished job (its fleet.json there) is read, not retrained,
    when its configuration and dataset sha256 are the job's (else ``retrained_because`` says why)."""
    from .init_weights import initial_weights
    from .trainer import read_training_data, train

    job, out = item
    final = Path(out) / job.name
    datasets, sha256 = read_training_data(job.dataset)
    config = _job_config(job)
    reason = None
    if (final / FLEET_FILE).is_file():
        try:
            record = json.loads((final / FLEET_FILE).read_text(encoding="utf-8"))
        except ValueError:  # not UTF-8 or not JSON
            record = None
        reason = _changed(record, config, sha256) if isinstance(record, dict) else f"its {FLEET_FILE} is unreadable"
        if reason is None:
            return {**record, "resumed": True}
    partial = Path(out) / f".{job.name}.partial"
    shutil.rmtree(partial, ignore_errors=True)  # a job killed before: start it again
    init = None if job.init is None else initial_weights(job.init)
    result = train(
        datasets, job.config, partial, dataset_sha256=sha256, command=f"dimenet fleet train ({job.name})", init=init
    )
    report = {
        "name": job.name,
        "seconds": result.seconds,
        "best_epoch": result.best_epoch,
        **_test_errors(partial, datasets),
        "config": config,
        "dataset_sha256": sha256,
    }
    atomic_write_text(partial / FLEET_FILE, json.dumps(report, indent=1))
    shutil.rmtree(final, ignore_errors=True)
    partial.rename(final)
    return {**report, "resumed": False, **({} if reason is None else {"retrained_because": reason})}


def _test_errors(run_dir: Path, datasets: list) -> dict:
    """Avg(e_c), Avg(e) px and rho over the test frames of the job's datasets (each with its
    train split's camera); all None without test frames."""
    import numpy as np

    from dimenet.runtime.evaluation.calibration import dataset_camera
    from dimenet.runtime.evaluation.methods import evaluate
    from dimenet.runtime.evaluation.metrics import reduction_ratio
    from dimenet.runtime.evaluation.predictor import load_predictor

    predictor = load_predictor(run_dir)
    e_c, e, e_star = [], [], []
    for ds in datasets:
        test = ds.frames_in("test")
        if not test.any():
            continue
        p = predictor.for_camera(dataset_camera(ds)) if predictor.spec.generic is not None else predictor
        ev = evaluate(ds.select(test), p.K_c, p)
        e_c.append(ev.frames.e_c), e.append(ev.frames.e), e_star.append(ev.frames.e_star)
    if not e_c:
        return {"avg_e_c": None, "avg_e": None, "rho": None}
    avg = [float(np.concatenate(a).mean()) for a in (e_c, e, e_star)]
    return {"avg_e_c": avg[0], "avg_e": avg[1], "rho": reduction_ratio(*avg)}


def fleet_train(
    manifest: str | Path,
    out: str | Path,
    *,
    address: Optional[str] = None,
    cpus_per_job: int = 1,
    epochs: Optional[int] = None,
) -> dict:
    """Every job of the manifest (``run_job``), then DIR/summary.md and DIR/summary.json: per job
    its rho, errors and seconds, or the error it failed with. ``epochs``: every job's, in place of the
    manifest's (`dimenet fleet train --quick`)."""
    from dimenet.runtime.jobs.engine import run_all

    jobs = read_manifest(manifest)
    if epochs is not None:
        jobs = [replace(job, config=replace(job.config, epochs=epochs)) for job in jobs]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    outcomes = run_all(
        run_job, [(job, str(out)) for job in jobs], address=address, cpus_per_job=cpus_per_job, desc="fleet"
    )
    rows = []
    for job, o in zip(jobs, outcomes):
        rows.append({"name": job.name, "error": o.error, **(o.value or {})})
    summary = {"jobs": rows, "failed": [r["name"] for r in rows if r["error"] is not None]}
    atomic_write_text(out / SUMMARY_JSON, json.dumps(summary, indent=1))
    atomic_write_text(out / SUMMARY_MD, summary_table(rows))
    return summary


def summary_table(rows: list) -> str:
    """The fleet's markdown table: job, rho %, Avg(e_c) and Avg(e) px, seconds, or its error."""
    fmt = lambda v, spec: "–" if v is None else format(v, spec)  # noqa: E731
    lines = ["| job | ρ % | Avg(e_c) px | Avg(e) px | s | status |", "|---|---|---|---|---|---|"]
    for r in rows:
        if r["error"] is not None:
            lines.append(f"| {r['name']} | – | – | – | – | failed: {r['error']} |")
            continue
        rho = None if r.get("rho") is None else 100 * r["rho"]
        status = "done before (resumed)" if r.get("resumed") else "trained"
        if r.get("retrained_because"):
            status += f" again: {r['retrained_because']}"
        lines.append(
            f"| {r['name']} | {fmt(rho, '.1f')} | {fmt(r.get('avg_e_c'), '.3f')} | {fmt(r.get('avg_e'), '.3f')} | "
            f"{r['seconds']:.0f} | {status} |"
        )
    return "\n".join(lines) + "\n"
