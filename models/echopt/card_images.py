"""How the images (and the robot) a model was trained on compare with a store's: what a card says
of them and the one-line notes when they differ. Apart from models/echopt/cards.py so that the
evaluation can read them without importing the module that runs an evaluation (no import circle).
"""

from __future__ import annotations

from sonarset.format.arrays import FRAME_INTERVAL_TOLERANCE
from sonarset.format.attrs import Processing, RobotRig


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
    if processing.profile == "unknown" and not trained.same_images(processing):  # unknown matches unknown
        notes.append(f"note: {label} was trained on {describe_images(trained)}; this store's images are of "
                     "unknown processing: scores may not be comparable to its training")
    elif not trained.same_images(processing):
        notes.append(f"note: {label} was trained on {describe_images(trained)}; this store's images are "
                     f"{_quoted(processing)}: scores are not comparable to its training")
    if trained_rig is not None and rig is not None and trained_rig != rig:
        notes.append(f"note: {label} was trained on a robot with {trained_rig.describe()}; this store's robot has "
                     f"{rig.describe()}: scores are not comparable to its training")
    config = card.get("config")
    dt = config.get("dt") if isinstance(config, dict) else None  # a plugin's card is anyone's dict
    if not notes and isinstance(dt, (int, float)) and dt > 0 and frame_interval_s and \
            abs(frame_interval_s - dt) > FRAME_INTERVAL_TOLERANCE * dt:
        # a real sensor runs at its own rate (a bag import records it): one step of the model is not one frame
        notes.append(f"note: {label} was trained on {dt:g} s frames ({1 / dt:.3g} Hz); this store's are "
                     f"{frame_interval_s:.3g} s ({1 / frame_interval_s:.3g} Hz): it learned one step of its own "
                     "frame interval, so scores are not comparable to its training")
    return notes
