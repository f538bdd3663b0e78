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
from sonarset.store.atomic import atomic_text

from sonarset.models.echopt.card_images import (  # noqa: F401 (the card's faces, read from here too)
    card_processing, card_rig, describe_images, training_notices)

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
        raise SonarSetError(f"{path.with_suffix('.safetensors')}: no model checkpoint here (need {path.name})")
    try:
        card = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise SonarSetError(f"{path}: no readable model card ({exc})") from None
    if not isinstance(card, dict):
        raise SonarSetError(f"{path}: not a model card (not a JSON object)")
    return card


def add_test_metrics(out_dir: str | os.PathLike, store: SonarStore, cfg: TrainConfig, seed: int = 0) -> dict:
    """Evaluate a training run's best model (of any kind: its card's) against the baselines on
    ``cfg.test_samples`` windows of the store's test split (drawn with ``seed``, not the training's),
    on ``cfg``'s device and precision; record the results in its card. The results name the model by
    its kind (``test["model"]``); ``{kind}_vs_flow`` holds its comparisons with flow. With
    ``cfg.stream`` only the drawn windows' frames are read, held compressed (``evaluate(stream=True)``),
    and freed memory is handed back to the OS before and batch by batch (``release_free_memory``)."""
    from sonarset.models.echopt.predictor import load_learned_predictor
    from sonarset.models.echopt.recipes import portable_path
    from sonarset.models.eval.evaluate import evaluate
    from sonarset.models.registry import BASELINES
    from sonarset.perf import release_free_memory

    release_free_memory()
    path = Path(out_dir) / "model.safetensors"
    model = load_learned_predictor(str(path), store.grid, device=cfg.device, precision=cfg.precision)
    kind = model.name
    # evaluate reports after each method's batch, when its rollout is freed: that memory goes back too
    res = evaluate(store, list(BASELINES), samples=cfg.test_samples, seed=seed, device=cfg.device,
                   precision=cfg.precision, stream=cfg.stream, predictors={kind: model},
                   progress=lambda name, done, total: release_free_memory())
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
