"""A decaying flow: the acoustic-flow warp of the last frame, shrunk toward that frame's median
level (its noise floor) by ``decay`` per step.

Flow keeps every echo at full strength wherever the commanded motion puts it; when the motion or
the scene is uncertain, a forecast that hedges toward the floor has a smaller expected squared
error, and the hedge compounds over an auto-regressive rollout, as the uncertainty does.
"""

import numpy as np

from sonarset.errors import SonarSetError
from sonarset.models import BasePredictor
from sonarset.models.baselines import AcousticFlow


class DecayingFlow(BasePredictor):
    name = "example-decay"
    any_context = True  # reads only the last frame, as flow does

    def __init__(self, grid, rig, decay: float = 0.1):
        self.flow, self.decay = AcousticFlow(grid, rig), decay

    def predict(self, frames: np.ndarray, commands: np.ndarray) -> np.ndarray:
        warped = self.flow.predict(frames, commands)
        floor = np.median(frames[:, -1], axis=(1, 2), keepdims=True)
        return (floor + (1.0 - self.decay) * (warped - floor)).astype(np.float32)


def factory(grid, rig, arg: str | None = None) -> DecayingFlow:
    """``example-decay`` (decay 0.1 per step) or ``example-decay:0.25``."""
    try:
        decay = 0.1 if arg is None else float(arg)
    except ValueError:
        decay = -1.0
    if not 0.0 <= decay <= 1.0:
        raise SonarSetError(f"example-decay: the decay after ':' must be a number in [0, 1], got {arg!r}")
    return DecayingFlow(grid, rig, decay)
