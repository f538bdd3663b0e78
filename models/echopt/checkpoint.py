"""Trained weights as safetensors with a JSON model card; no pickle is ever loaded.

A checkpoint is two files: ``NAME.safetensors`` (the weights) and ``NAME.json`` (the card: the
network's kind (``model``: echopt, or a reference method of models/zoo/; cards without it are
EchoPT's), preset, config, grid, the training store's image processing and robot rig
(models/echopt/cards.py), training store and command, epochs, validation loss, test metrics).
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
from pathlib import Path

import torch
import torch.nn as nn
from safetensors.torch import load_file, save_file

from sonarset.store.atomic import atomic_text, atomic_write
from sonarset.errors import GridMismatchError, SonarSetError
from sonarset.format.attrs import SensorGrid

from sonarset.models.echopt.networks import A_TITLE, KINDS, TITLES, from_config, kind_of

PRETRAINED = Path(__file__).resolve().parents[1] / "pretrained" / "echopt-small.safetensors"


@contextlib.contextmanager
def disk_errors(path: str | os.PathLike, what: str):
    """A failed write of ``what`` to ``path`` (a full disk, a lost mount) as one line naming the file;
    the write is atomic (sonarset/store/atomic.py), so the previous file is still whole."""
    try:
        yield
    except OSError as exc:
        code = exc.errno
        reason = "no space left on the device" if code in (errno.ENOSPC, errno.EDQUOT) else \
            exc.strerror or (os.strerror(code) if code else str(exc))
        raise SonarSetError(f"{path}: cannot write the {what}: {reason}; the previous one is kept") from None
    except Exception as exc:
        if type(exc).__name__ != "SafetensorError":  # the Rust writer's I/O errors
            raise
        reason = "no space left on the device" if "os error 28" in str(exc) else str(exc)
        raise SonarSetError(f"{path}: cannot write the {what}: {reason}; the previous one is kept") from None


def save_checkpoint(path: str | os.PathLike, model: nn.Module, card: dict, after_weights=None) -> Path:
    """Weights, then the card (``after_weights(phase)`` is called between the two: tests kill there)."""
    kind = kind_of(model)
    path = Path(path).with_suffix(".safetensors")
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().contiguous().cpu() for k, v in model.state_dict().items()}
    with disk_errors(path, "checkpoint"):
        atomic_write(path, lambda p: save_file(state, str(p), metadata={"format": kind,
                                                                        "card": path.with_suffix(".json").name}))
    if after_weights is not None:
        after_weights("best-weights")
    card = {**card, "model": kind, "config": model.cfg.to_dict(), "n_params": model.n_params()}
    with disk_errors(path.with_suffix(".json"), "model card"):
        atomic_text(path.with_suffix(".json"), json.dumps(card, indent=2) + "\n")
    return path


def resolve(spec: str | os.PathLike, kind: str | None = None) -> Path:
    """The weights file of a checkpoint spec: ``pretrained`` (``kind``'s shipped checkpoint, EchoPT's by
    default), a run directory, or a ``.safetensors`` path."""
    if str(spec) in ("", "pretrained"):
        if kind in (None, "echopt"):
            return PRETRAINED
        from sonarset.models.registry import shipped_checkpoint

        shipped = shipped_checkpoint(kind)
        if shipped is None:
            raise SonarSetError(f"{kind}:pretrained: sonarset ships no {TITLES[kind]} model; train one (model "
                                f"{kind}) and name its run directory, {kind}:RUN")
        return shipped
    p = Path(spec)
    if p.is_dir():
        p = p / "model.safetensors"
    return p.with_suffix(".safetensors")


def load_checkpoint(spec: str | os.PathLike, grid: SensorGrid | None = None, device: str = "cpu",
                    kind: str | None = None) -> tuple[nn.Module, dict]:
    """Load weights and card into the network the card's ``model`` names (EchoPT where a card, from
    before the reference methods, names none); refuse a model trained on another grid, and with
    ``kind``, a checkpoint of another kind, with a clear message."""
    path = resolve(spec, kind)
    card_path = path.with_suffix(".json")
    expected = kind or "echopt"
    title = TITLES.get(expected, expected)
    if not path.is_file() or not card_path.is_file():
        raise SonarSetError(f"{path}: no {title} checkpoint here (need {path.name} and {card_path.name})")
    try:
        card = json.loads(card_path.read_text())
        found = card.get("model", "echopt")
        if found not in KINDS:
            raise SonarSetError(f"{card_path}: a model of unknown kind {found!r} (this sonarset builds "
                                f"{', '.join(KINDS)})")
        if kind is not None and found != kind:
            raise SonarSetError(f"{path}: {A_TITLE[found]} checkpoint, not {title}'s; name it {found}:{spec}")
        expected, title = found, TITLES[found]
        model = from_config(found, card["config"])
    except GridMismatchError as exc:
        raise GridMismatchError(f"{card_path}: {exc}") from None
    except (ValueError, KeyError, TypeError, AttributeError, RecursionError) as exc:
        raise SonarSetError(f"{card_path}: not {A_TITLE.get(expected, 'a')} model card ({exc})") from None
    trained = SensorGrid.model_validate(card["grid"]) if "grid" in card else None
    if grid is not None and trained is not None and not trained.matches(grid):
        raise GridMismatchError(f"{path}: {title} was trained on grid {trained.describe()}, "
                                f"the data has {grid.describe()}; retrain on this grid")
    try:
        state = load_file(str(path), device="cpu")
        model.load_state_dict(state)
    except Exception as exc:  # safetensors raises its own error types
        raise SonarSetError(f"{path}: cannot load weights ({type(exc).__name__}: {exc})") from None
    # NaN weights make every prediction NaN, which scores as "undefined" rather than failing.
    broken = [k for k, v in state.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if broken:
        raise SonarSetError(f"{path}: {len(broken)} of {len(state)} weight tensors hold NaN or infinite values "
                            f"(first: {broken[0]}); a diverged training? use another checkpoint")
    return model.to(device).eval(), card
