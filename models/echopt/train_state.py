"""The crash-safe training state: one file, replaced atomically.

``state.safetensors`` holds the weights and the optimizer's moments as tensors, and in its JSON
header the step, the best validation loss, the training config and the metrics history. A kill at
any point leaves either the previous state or the new one; ``metrics.jsonl`` is derived from it
and rewritten on resume.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from sonarset.store.atomic import atomic_text, atomic_write
from sonarset.errors import SonarSetError

from sonarset.models.echopt.checkpoint import disk_errors

STATE = "state.safetensors"
METRICS = "metrics.jsonl"


def save_state(out: Path, model: torch.nn.Module, opt: torch.optim.Optimizer, meta: dict) -> None:
    """The whole training state in one file, replaced atomically: weights, Adam moments and, in
    the header, ``meta`` (step, best loss, config and metrics history) and the optimizer's settings."""
    tensors = {f"model.{k}": v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    sd = opt.state_dict()
    for idx, st in sd["state"].items():
        for k, v in st.items():
            tensors[f"opt.{idx}.{k}"] = (v if torch.is_tensor(v) else torch.tensor(v)).detach().cpu().contiguous()
    meta = {**meta, "param_groups": [{k: v for k, v in g.items() if k != "params"} for g in sd["param_groups"]]}
    with disk_errors(out / STATE, "training state"):
        atomic_write(out / STATE, lambda p: save_file(tensors, str(p), metadata={"state": json.dumps(meta)}))


def load_state(out: Path, model: torch.nn.Module, opt: torch.optim.Optimizer) -> dict:
    """Restore ``model`` and ``opt`` from ``out``'s state; returns the header's metadata."""
    from safetensors import safe_open

    path = out / STATE
    try:
        with safe_open(str(path), "pt") as f:
            meta = json.loads(f.metadata()["state"])
        tensors = load_file(str(path))
    except Exception as exc:  # safetensors raises its own error types
        raise SonarSetError(f"{path}: unreadable training state ({type(exc).__name__}: {exc})") from None
    model.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("model.")})
    sd = opt.state_dict()
    state: dict = {}
    for k, v in tensors.items():
        if k.startswith("opt."):
            _, idx, name = k.split(".", 2)
            state.setdefault(int(idx), {})[name] = v
    sd["state"] = state
    for g, saved in zip(sd["param_groups"], meta["param_groups"]):
        g.update(saved)
    opt.load_state_dict(sd)
    return meta


def write_metrics(out: Path, history: list[dict]) -> None:
    with disk_errors(out / METRICS, "metrics"):
        atomic_text(out / METRICS, "".join(json.dumps(h) + "\n" for h in history))
