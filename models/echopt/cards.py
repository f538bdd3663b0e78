"""What a model card says about the data a model was trained on (no torch needed), and its test
section.

A card (``NAME.json`` beside the weights, models/echopt/checkpoint.py) records the training store's
grid, ``processing`` and ``rig``. Cards written before format 1.1 have no ``processing``: their
models were trained on 'raw' images.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING

from sonarset.errors import SonarSetError
from sonarset.format.arrays import FRAME_INTERVAL_TOLERANCE
from sonarset.format.attrs import Processing, RobotRig
from sonarset.store.atomic import atomic_text

if TYPE_CHECKING:
    from sonarset.store.store import SonarStore

    from sonarset.models.echopt.train_config import TrainConfig


def read_card(spec: str | os.PathLike) -> dict:
    """The card of a checkpoint spec (``pretrained``, a directory, a path, or an ONNX export), without
    loading weights."""
    if str(spec).endswith(".onnx"):
        from sonarset.models.echopt.onnx_runtime import read_onnx_card

        return read_onnx_card(spec)
    from sonarset.models.echopt.checkpoint import resolve

    path = resolve(spec).with_suffix(".json")
    if not path.is_file():
        raise SonarSetError(f"{path.with_suffix('.safetensors')}: no EchoPT checkpoint here (need {path.name})")
    try:
        card = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise SonarSetError(f"{path}: no readable EchoPT model card ({exc})") from None
    if not isinstance(card, dict):
        raise SonarSetError(f"{path}: not an EchoPT model card (not a JSON object)")
    return card


def card_processing(card: dict) -> Processing:
    """How the images a model was trained on were made; cards without it (before format 1.1) mean 'raw'."""
    raw = card.get("processing")
    return Processing.raw() if raw is None else Processing.model_validate(raw)


def card_rig(card: dict) -> RobotRig | None:
    """The robot rig of the model's training store, None when not recorded."""
    raw = card.get("rig")
    return None if raw is None else RobotRig.model_validate(raw)


def _quoted(p: Processing, noun: str = "") -> str:
    return f"'{p.profile}'{noun}{p.describe()[len(p.profile):]}"


def describe_images(p: Processing) -> str:
    """A processing in a sentence: "'raw' images (das, no post-processing)"."""
    return _quoted(p, " images")


def training_notices(label: str, card: dict, processing: Processing, rig: RobotRig | None = None,
                     frame_interval_s: float | None = None) -> list[str]:
    """One-line notes when a model meets images (or a robot) other than those it was trained on.

    Not errors: evaluating across processings is legitimate, but the scores then say nothing
    about the model on its own kind of images.
    """
    try:
        trained, trained_rig = card_processing(card), card_rig(card)
    except ValueError as exc:  # pydantic's ValidationError
        return [f"note: {label}'s model card has an invalid processing or rig ({str(exc).splitlines()[0]})"]
    notes = []
    if processing.profile == "unknown":
        notes.append(f"note: {label} was trained on {describe_images(trained)}; this store's images are of "
                     "unknown processing: scores may not be comparable to its training")
    elif not trained.same_images(processing):
        notes.append(f"note: {label} was trained on {describe_images(trained)}; this store's images are "
                     f"{_quoted(processing)}: scores are not comparable to its training")
    if trained_rig is not None and rig is not None and trained_rig != rig:
        notes.append(f"note: {label} was trained on a robot with {trained_rig.describe()}; this store's robot has "
                     f"{rig.describe()}: scores are not comparable to its training")
    dt = (card.get("config") or {}).get("dt")
    if not notes and isinstance(dt, (int, float)) and dt > 0 and frame_interval_s and \
            abs(frame_interval_s - dt) > FRAME_INTERVAL_TOLERANCE * dt:
        # a real sensor runs at its own rate (a bag import records it): one step of the model is not one frame
        notes.append(f"note: {label} was trained on {dt:g} s frames ({1 / dt:.3g} Hz); this store's are "
                     f"{frame_interval_s:.3g} s ({1 / frame_interval_s:.3g} Hz): it learned one step of its own "
                     "frame interval, so scores are not comparable to its training")
    return notes


def add_test_metrics(out_dir: str | os.PathLike, store: SonarStore, cfg: TrainConfig, seed: int = 0) -> dict:
    """Evaluate a training run's best model (of any kind: its card's) against the baselines on
    ``cfg.test_samples`` windows of the store's test split (drawn with ``seed``, not the training's),
    on ``cfg``'s device and precision; record the results in its card. The results name the model by
    its kind (``test["model"]``); ``{kind}_vs_flow`` holds its comparisons with flow."""
    from sonarset.models.echopt.predictor import load_learned_predictor
    from sonarset.models.echopt.recipes import portable_path
    from sonarset.models.eval.evaluate import evaluate
    from sonarset.models.registry import BASELINES

    path = Path(out_dir) / "model.safetensors"
    model = load_learned_predictor(str(path), store.grid, device=cfg.device, precision=cfg.precision)
    kind = model.name
    res = evaluate(store, list(BASELINES), samples=cfg.test_samples, seed=seed, device=cfg.device,
                   precision=cfg.precision, stream=cfg.stream, predictors={kind: model})
    card_path = path.with_suffix(".json")
    card = json.loads(card_path.read_text())
    # the store as seen from the run directory, as in the card's training.store (no path of this machine)
    card["test"] = {"store": portable_path(store.location, out_dir), "split": "test", "windows": len(res.window_ids),
                    "seed": seed,
                    "model": kind, "precision": res.precision.get(kind),
                    "results": res.summary(),
                    f"{kind}_vs_flow": [c.to_dict() for c in res.comparisons if {c.a, c.b} == {kind, "flow"}]}
    atomic_text(card_path, json.dumps(card, indent=2) + "\n")
    return card["test"]
