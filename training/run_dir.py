"""RUN_DIR layout written by `dimenet train`: weights.safetensors, spec.json (dimenet-model/1),
history.json and curve.png; while it trains, checkpoint.safetensors (the state after the last finished
epoch, for `dimenet train --resume`; removed once the run is written). Loading never unpickles
(safetensors only)."""

from __future__ import annotations

import io
import json
from pathlib import Path

from safetensors import safe_open
from safetensors.torch import load as load_safetensors
from safetensors.torch import save as save_safetensors

from dimenet.runtime.errors import ModelError
from dimenet.runtime.formats.atomic import atomic_write, atomic_write_text
from dimenet.runtime.rectify.spec import ModelSpec

from .model import DimeNet, dime_net

WEIGHTS, SPEC, HISTORY, CURVE = "weights.safetensors", "spec.json", "history.json", "curve.png"
CHECKPOINT = "checkpoint.safetensors"
CHECKPOINT_FORMAT = "dimenet-checkpoint/1"  # safetensors metadata: "format" and "state" (JSON)


def write_run(run_dir: str | Path, model: DimeNet, spec: ModelSpec, history: list) -> Path:
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    blob = save_safetensors({k: v.detach().contiguous() for k, v in model.state_dict().items()})
    atomic_write(run_dir / WEIGHTS, lambda f: f.write(blob))
    atomic_write_text(run_dir / SPEC, spec.to_json())
    atomic_write_text(run_dir / HISTORY, json.dumps(history))
    atomic_write(run_dir / CURVE, lambda f: f.write(curve_png(history)))
    return run_dir


def curve_png(history: list) -> bytes:
    """Training curve: train loss (px^2) and val error (px) per epoch, as PNG bytes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    epochs = [h["epoch"] for h in history]
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
    ax.semilogy(epochs, [h["train_mse_px2"] for h in history], label="train loss, mean sq. error (px²)")
    ax.semilogy(epochs, [h["val_e_px"] for h in history], label="val Avg(e) (px)")
    best = min(history, key=lambda h: h["val_e_px"])
    ax.axvline(best["epoch"], color="grey", ls=":", label=f"best epoch {best['epoch']}: {best['val_e_px']:.3f} px")
    ax.set_xlabel("epoch")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()


def load_run(run_dir: str | Path) -> tuple[DimeNet, ModelSpec]:
    """The trained model (eval mode) and its spec. Raises ModelError naming the file."""
    run_dir = Path(run_dir)
    spec = ModelSpec.read(run_dir / SPEC)
    path = run_dir / WEIGHTS
    if not path.is_file():
        raise ModelError(f"{path}: no weights file")
    try:
        state = load_safetensors(path.read_bytes())
        model = dime_net(spec.features, spec.hidden, spec.head)
        model.load_state_dict(state)
    except Exception as exc:  # safetensors raises its own error types for corrupt files
        raise ModelError(f"{path}: unreadable or mismatched weights ({type(exc).__name__}: {exc})") from None
    return model.eval(), spec


def write_checkpoint(run_dir: str | Path, tensors: dict, state: dict) -> Path:
    """RUN_DIR/checkpoint.safetensors, atomically: ``tensors`` (name -> tensor) and ``state``, a
    JSON-able dict, in the file's metadata."""
    meta = {"format": CHECKPOINT_FORMAT, "state": json.dumps(state)}
    blob = save_safetensors({k: v.detach().contiguous() for k, v in tensors.items()}, metadata=meta)
    return atomic_write(Path(run_dir) / CHECKPOINT, lambda f: f.write(blob))


def read_checkpoint(run_dir: str | Path) -> tuple[dict, dict]:
    """(tensors, state) of RUN_DIR/checkpoint.safetensors (``write_checkpoint``'s). ModelError naming
    the file when it is absent (no training to resume: it is removed once the run is written) or unreadable."""
    path = Path(run_dir) / CHECKPOINT
    if not path.is_file():
        raise ModelError(
            f"{path}: no checkpoint, so no training to resume (`dimenet train` writes one each epoch and "
            "removes it once the run is written)"
        )
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
        if meta.get("format") != CHECKPOINT_FORMAT:
            raise ValueError(f"format {meta.get('format')!r}, not {CHECKPOINT_FORMAT}")
        state = json.loads(meta["state"])
    except Exception as exc:  # safetensors raises its own error types for corrupt files
        raise ModelError(f"{path}: unreadable checkpoint ({type(exc).__name__}: {exc})") from None
    return tensors, state
