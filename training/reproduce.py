"""`dimenet reproduce`: the paper's Tables 2-5 on the three simulated device profiles, and
the baselines beyond the paper.

Trains one model per device (8x6, features A, full epochs), plus the ablation models on
galaxy-s8 (features B-E; grids 16x12 and 12x9) with fewer epochs, evaluates every case of
the paper on the test split, then every method (kc, self, dimenet, map, oracle) on every
Table 4/5 case and on planar frames, and writes REPRODUCTION.md (ours beside the paper's
numbers), results.json and three plots into OUT_DIR.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dimenet.runtime.cli.progress import progress
from dimenet.runtime.evaluation.conditions import add_noise, drop_inference_points, empty_cells, occupancy
from dimenet.runtime.evaluation.methods import METHODS, evaluate
from dimenet.runtime.evaluation.predictor import load_predictor
from dimenet.runtime.formats.atomic import atomic_write, atomic_write_text
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.rectify.grid import Grid
from dimenet.runtime.sim.simulator import simulate

from .trainer import TrainConfig, train

DEVICES = ("galaxy-s8", "iphone-12-pro", "ipad-mini-6")
NATURAL_FRAMES = 34
PLANAR_FRAMES = 40  # galaxy-s8 test frames whose K is inferred from one board (not in the paper)
POINTS = (320, 256, 192, 128, 64)
ETAS = (0.0, 0.2, 0.4, 0.6, 0.8)
GRIDS = ("16x12", "12x9", "8x6")
VARIANTS = ("A", "B", "C", "D", "E")

# The paper's numbers (Avg errors in px, rho and gamma in %).
PAPER_T2 = {  # grid -> [(gamma, Avg(e)) per eta]
    "16x12": [(64.5, 0.73), (52.1, 0.87), (38.9, 1.29), (26.6, 1.77), (13.4, 2.47)],
    "12x9": [(78.6, 0.75), (62.6, 0.97), (46.0, 1.33), (30.5, 1.88), (14.8, 2.49)],
    "8x6": [(96.4, 0.68), (79.3, 0.92), (57.7, 1.45), (36.6, 2.05), (19.7, 2.52)],
}
PAPER_T3 = {"A": 0.68, "B": 0.78, "C": 0.78, "D": 0.75, "E": 2.58}
PAPER_T4 = {  # noise -> points -> (Avg(e_c), Avg(e), Avg(e*), rho)
    "clean": {
        320: (3.44, 0.68, 0.45, 92.2),
        256: (3.34, 0.67, 0.45, 92.5),
        192: (3.43, 0.69, 0.45, 92.2),
        128: (3.45, 0.85, 0.46, 87.0),
        64: (3.40, 1.35, 0.45, 69.8),
    },
    "noisy": {
        320: (5.28, 3.90, 3.86, 97.2),
        256: (5.27, 3.89, 3.82, 95.0),
        192: (5.28, 3.88, 3.83, 96.8),
        128: (5.31, 3.84, 3.81, 97.7),
        64: (5.56, 4.01, 3.81, 88.2),
    },
}
PAPER_T5 = {
    "galaxy-s8": (3.44, 0.68, 0.45, 91.7),
    "iphone-12-pro": (2.36, 0.61, 0.46, 92.3),
    "ipad-mini-6": (1.61, 0.36, 0.32, 96.8),
    "galaxy-s8 (N)": (4.26, 3.74, 3.45, 64.0),
}
NOISE_2D_PX, NOISE_3D_MM = 3.0, 0.1


@dataclass(frozen=True)
class ReproduceConfig:
    out_dir: Path
    epochs: int = 600
    ablation_epochs: int = 150
    seed: int = 0


def _row(ev) -> dict:
    s = ev.overall
    return {"n_frames": s.n_frames, "avg_e_c": s.avg_e_c, "avg_e": s.avg_e, "avg_e_star": s.avg_e_star, "rho": s.rho}


def _rig_test(ds: Dataset) -> Dataset:
    return ds.select(ds.frames_in("test") & (ds.scene == "rig"))


def run(config: ReproduceConfig) -> dict:
    """Train, evaluate and write the report; returns the results dictionary."""
    start = time.monotonic()
    out = Path(config.out_dir)
    runs = out / "runs"
    data = {
        d: simulate(
            d,
            seed=config.seed,
            natural_frames=NATURAL_FRAMES if d == "galaxy-s8" else 0,
            planar_frames=PLANAR_FRAMES if d == "galaxy-s8" else 0,
        )
        for d in DEVICES
    }
    jobs = [(d, "8x6", "A", config.epochs) for d in DEVICES]
    jobs += [("galaxy-s8", "8x6", v, config.ablation_epochs) for v in VARIANTS[1:]]
    jobs += [("galaxy-s8", g, "A", config.ablation_epochs) for g in GRIDS[:2]]
    predictors, train_seconds = {}, {}
    for device, grid, variant, epochs in progress(jobs, desc="reproduce: training"):
        name = f"{device}-{grid}-{variant}"
        t0 = time.monotonic()
        cfg = TrainConfig(grid=grid, variant=variant, epochs=epochs, seed=config.seed)
        predictors[name] = load_predictor(train(data[device], cfg, runs / name).run_dir)
        train_seconds[name] = time.monotonic() - t0

    def ev(frames, name):
        p = predictors[name]
        return evaluate(frames, p.spec.K_c, p.predict_k)

    rng = lambda k: np.random.default_rng(config.seed + k)  # noqa: E731
    s8 = data["galaxy-s8"]
    s8_rig = _rig_test(s8)
    results: dict = {"train_seconds": train_seconds}
    t5 = {d: _row(ev(_rig_test(data[d]), f"{d}-8x6-A")) for d in DEVICES}
    natural = s8.select(s8.frames_in("test") & (s8.scene == "natural"))
    if natural.n_frames:
        t5["galaxy-s8 (N)"] = _row(ev(natural, "galaxy-s8-8x6-A"))
    results["table5"] = t5
    t4 = {"clean": {}, "noisy": {}}
    noisy = add_noise(s8_rig, NOISE_2D_PX, NOISE_3D_MM, rng(1))
    for n in POINTS:
        t4["clean"][n] = _row(ev(drop_inference_points(s8_rig, n, rng(2)), "galaxy-s8-8x6-A"))
        t4["noisy"][n] = _row(ev(drop_inference_points(noisy, n, rng(3)), "galaxy-s8-8x6-A"))
    results["table4"] = t4
    results["table3"] = {v: _row(ev(s8_rig, f"galaxy-s8-8x6-{v}")) for v in VARIANTS}
    t2 = {}
    for g in GRIDS:
        grid = Grid.parse(g)
        t2[g] = []
        for k, eta in enumerate(ETAS):
            frames = empty_cells(s8_rig, eta, grid, rng(10 + k)) if eta else s8_rig
            t2[g].append({"eta": eta, "gamma": occupancy(frames, grid), **_row(ev(frames, f"galaxy-s8-{g}-A"))})
    results["table2"] = t2
    results["baselines"] = _baselines(data, predictors, config)
    results["seconds"] = time.monotonic() - start
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "results.json", json.dumps(results, indent=1, default=float))
    atomic_write(out / "rho_vs_points.png", lambda f: f.write(_plot_points(t4)))
    atomic_write(out / "e_vs_eta.png", lambda f: f.write(_plot_eta(t2)))
    atomic_write(out / "methods_vs_points.png", lambda f: f.write(_plot_methods(results["baselines"])))
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


def _baselines(data: dict, predictors: dict, config: ReproduceConfig) -> dict:
    """case -> {"methods": method -> {avg_e, rho, fallbacks}, "coverage" and "coverage_true":
    method -> parameter -> share (against K* and against the simulator's K_true)}."""
    out = {}
    for case, (frames, name) in progress(_baseline_cases(data, config).items(), desc="reproduce: baselines"):
        p = predictors[name]
        ev = evaluate(frames, p.spec.K_c, p, methods=METHODS)
        out[case] = {
            "n_frames": frames.n_frames,
            "methods": {
                m: {"avg_e": rows["overall"].avg_e, "rho": rows["overall"].rho, "fallbacks": ev.fallbacks[m]}
                for m, rows in ev.methods.items()
            },
            "coverage": ev.coverage,
            "coverage_true": ev.coverage_true,
        }
    return out


def _pct(v) -> str:
    return "–" if v is None else f"{100 * v:.1f}"


def _px(v) -> str:
    return "–" if v is None else f"{v:.2f}"


def report(results: dict, config: ReproduceConfig) -> str:
    """The markdown report: each of the paper's tables with ours beside it."""
    L = [
        "# DIME-Net reproduction on the simulated OIS profiles",
        "",
        f"Generated by `dimenet reproduce` (seed {config.seed}; {config.epochs} epochs for the three device models, "
        f"{config.ablation_epochs} for the "
        "ablation models of Tables 2 and 3). Simulated data stands in for the paper's phones "
        "(models_spec/simulator.md); every error is in px on the test split, ρ in %. "
        "Ours | paper.",
        "",
        "## Table 5 — inference accuracy per device (8×6, features A)",
        "",
        "| device | Avg(e_c) | Avg(e) | Avg(e*) | ρ % |",
        "|---|---|---|---|---|",
    ]
    for name, r in results["table5"].items():
        p = PAPER_T5[name]
        L.append(
            f"| {name} | {_px(r['avg_e_c'])} \\| {p[0]} | {_px(r['avg_e'])} \\| {p[1]} | "
            f"{_px(r['avg_e_star'])} \\| {p[2]} | **{_pct(r['rho'])}** \\| {p[3]} |"
        )
    L += [
        "",
        "## Table 4 — fewer inference points, and injected noise (galaxy-s8)",
        "",
        f"Upper half clean; lower half σ⁺ₓ = {NOISE_2D_PX} px, σ⁺_X = {NOISE_3D_MM} mm on every point. "
        "Only the inference points are dropped; errors use all valid points.",
        "",
        "| noise | #points | Avg(e_c) | Avg(e) | Avg(e*) | ρ % |",
        "|---|---|---|---|---|---|",
    ]
    for noise in ("clean", "noisy"):
        for n, r in results["table4"][noise].items():
            p = PAPER_T4[noise][int(n)]
            L.append(
                f"| {noise} | {n} | {_px(r['avg_e_c'])} \\| {p[0]} | {_px(r['avg_e'])} \\| {p[1]} | "
                f"{_px(r['avg_e_star'])} \\| {p[2]} | **{_pct(r['rho'])}** \\| {p[3]} |"
            )
    L += [
        "",
        "![rho vs points](rho_vs_points.png)",
        "",
        "## Table 3 — feature variants (galaxy-s8, 8×6)",
        "",
        "A all; B PMD only; C PMD + 1/Z; D PMD + X, Y; E X, Y, 1/Z only.",
        "",
        "| variant | Avg(e) | ρ % | paper Avg(e) |",
        "|---|---|---|---|",
    ]
    for v, r in results["table3"].items():
        L.append(f"| {v} | {_px(r['avg_e'])} | {_pct(r['rho'])} | {PAPER_T3[v]} |")
    L += [
        "",
        "## Table 2 — grid resolution and occupancy (galaxy-s8)",
        "",
        "η: share of occupied cells emptied; γ: occupancy after. Avg(e) ours \\| paper.",
        "",
        "| η % | " + " | ".join(f"{g} γ % | {g} Avg(e)" for g in GRIDS) + " |",
        "|---|" + "---|---|" * len(GRIDS),
    ]
    for k, eta in enumerate(ETAS):
        cells = []
        for g in GRIDS:
            r, p = results["table2"][g][k], PAPER_T2[g][k]
            cells.append(f"{100 * r['gamma']:.1f} \\| {p[0]} | {_px(r['avg_e'])} \\| {p[1]}")
        L.append(f"| {100 * eta:.0f} | " + " | ".join(cells) + " |")
    L += ["", "![Avg(e) vs eta](e_vs_eta.png)", ""]
    L += _baselines_report(results["baselines"])
    L += ["## Cost", "", "| model | training s |", "|---|---|"]
    L += [f"| {k} | {v:.0f} |" for k, v in results["train_seconds"].items()]
    L += ["", f"Whole run: {results['seconds'] / 60:.1f} min on this machine.", ""]
    return "\n".join(L)


def _baselines_report(baselines: dict) -> list:
    L = [
        "## Baselines beyond the paper — ρ % of every method",
        "",
        "`kc` the fixed K_c; `self` per-frame joint K + pose on the inference points alone (falls back "
        "to K_c where K is not observable: planar or < 6 points; its fallbacks in brackets); `dimenet` "
        "the paper's method; `map` the network's K and covariance as a prior fused with the frame's "
        "points (models_spec/model-v1.md); `oracle` K*. Planar: rig frames whose K is inferred from one "
        "board, errors on all valid points as in the natural scene.",
        "",
        "| case | frames | " + " | ".join(METHODS) + " |",
        "|---|---|" + "---|" * len(METHODS),
    ]
    for case, r in baselines.items():
        cells = []
        for m in METHODS:
            row = r["methods"][m]
            cell = _pct(row["rho"])
            if m == "self" and row["fallbacks"]:
                cell += f" ({row['fallbacks']})"
            cells.append(f"**{cell}**" if m == "map" else cell)
        L.append(f"| {case} | {r['n_frames']} | " + " | ".join(cells) + " |")
    L += [
        "",
        "![rho vs points, every method](methods_vs_points.png)",
        "",
        "### 1σ coverage of K's uncertainty",
        "",
        "Share of frames within 1σ per parameter (68 % expected for a calibrated Gaussian), "
        "`dimenet` with the network's covariance, `map` with its posterior; against K* (the "
        "issue's definition) and against the simulator's true K. Where every valid point also "
        "infers K (rig cases), K* is fitted to the same noisy points as the map estimate, so "
        "|K − K*| understates the error the posterior describes: compare those against K_true. "
        "A case holds 34–57 frames, so a share here is ± 7 points (one standard error); "
        'training/METHOD.md, "Calibration on fresh frames", measures it on 690 fresh frames.',
        "",
        "| case | dimenet vs K* fx / fy / cx / cy % | map vs K* | dimenet vs K_true | map vs K_true |",
        "|---|---|---|---|---|",
    ]
    for case, r in baselines.items():
        cells = [
            " / ".join(f"{100 * v:.0f}" for v in r[key][m].values())
            for key in ("coverage", "coverage_true")
            for m in ("dimenet", "map")
        ]
        L.append(f"| {case} | " + " | ".join(cells) + " |")
    return L + [""]


def _plot_methods(baselines: dict) -> bytes:
    plt = _figure()
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5), dpi=100, sharey=True)
    for ax, noise in zip(axes, ("clean", "noisy")):
        for m in METHODS[1:-1]:
            rhos = [100 * (baselines[f"galaxy-s8 {noise} {n} pts"]["methods"][m]["rho"] or 0) for n in POINTS]
            ax.plot(POINTS, rhos, "o-", label=m)
        ax.set_title(
            f"galaxy-s8, {noise}" + (f" (+{NOISE_2D_PX} px, +{NOISE_3D_MM} mm)" if noise == "noisy" else ""), fontsize=9
        )
        ax.set_xlabel("inference points per frame")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("ρ (%)")
    axes[0].legend(fontsize=8)
    return _png(fig, plt)


def _figure():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _png(fig, plt) -> bytes:
    import io

    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()


def _plot_points(t4: dict) -> bytes:
    plt = _figure()
    fig, ax = plt.subplots(figsize=(5.5, 3.5), dpi=100)
    for noise, style in (("clean", "o-"), ("noisy", "s-")):
        ns = sorted(t4[noise], key=int)
        ax.plot(ns, [100 * (t4[noise][n]["rho"] or 0) for n in ns], style, label=f"ours, {noise}")
        ax.plot(ns, [PAPER_T4[noise][int(n)][3] for n in ns], style, alpha=0.35, label=f"paper, {noise}")
    ax.set_xlabel("inference points per frame")
    ax.set_ylabel("ρ (%)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _png(fig, plt)


def _plot_eta(t2: dict) -> bytes:
    plt = _figure()
    fig, ax = plt.subplots(figsize=(5.5, 3.5), dpi=100)
    for g, rows in t2.items():
        (line,) = ax.plot([100 * r["eta"] for r in rows], [r["avg_e"] for r in rows], "o-", label=f"ours {g}")
        ax.plot(
            [100 * e for e in ETAS],
            [p[1] for p in PAPER_T2[g]],
            "o--",
            color=line.get_color(),
            alpha=0.4,
            label=f"paper {g}",
        )
    ax.set_xlabel("emptied occupied cells η (%)")
    ax.set_ylabel("Avg(e) (px)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    return _png(fig, plt)
