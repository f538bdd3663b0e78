"""The non-learned baselines.

They answer the predictor protocol (models/predictor.py: ``frames`` (B, n_in, R, A) and
``commands`` (B, n_in + 1, 2) to the next frame (B, R, A)) with only the last frame and the last
command, turned into image motion by the robot's rig (frame interval, sensor offset); EchoPT uses
them all. No torch here: the baselines run wherever NumPy and SciPy do (``backend="scipy"``).
``Predictor`` and ``rollout`` are imported here too, where they lived before models/predictor.py.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy import ndimage

from sonarset.format.attrs import RobotRig, SensorGrid
from sonarset.windows import N_IN

from sonarset.models.flow import arc_motion, sampling_grid, source_points
from sonarset.models.predictor import BasePredictor, Predictor, rollout  # noqa: F401 (re-exported)


def sample_polar(images: np.ndarray, grid: SensorGrid, r_src, th_src, backend: str = "torch") -> np.ndarray:
    """Bilinear resampling of images (B, R, A) at source positions in metres / radians.

    ``r_src`` and ``th_src`` broadcast to (B, R, A); they are torch tensors for the torch backend
    (``torch.nn.functional.grid_sample``, multi-threaded) and NumPy arrays for the SciPy one
    (``scipy.ndimage.map_coordinates``); both compute the same bilinear interpolation. Pixels whose
    source lies outside the field of view take the nearest edge value: at the far range edge that
    is the noise floor, which is what new territory looks like on average.
    """
    B, (R, A) = images.shape[0], grid.shape
    if backend == "torch":
        import torch
        import torch.nn.functional as F

        ir = (r_src - grid.range_centres()[0]) / grid.range_step
        ia = (th_src - grid.azimuth_centres()[0]) / grid.azimuth_step
        # align_corners=True: -1 and +1 are the centres of the first and last bins
        x = (2 * ia / max(A - 1, 1) - 1).expand(B, R, A)
        y = (2 * ir / max(R - 1, 1) - 1).expand(B, R, A)
        img = torch.from_numpy(np.asarray(images, dtype=np.float32))[:, None]
        out = F.grid_sample(img, sampling_grid(x, y), mode="bilinear", padding_mode="border", align_corners=True)
        return out[:, 0].numpy()
    ir = np.broadcast_to((r_src - grid.range_centres()[0]) / grid.range_step, (B, R, A))
    ia = np.broadcast_to((th_src - grid.azimuth_centres()[0]) / grid.azimuth_step, (B, R, A))
    ib = np.broadcast_to(np.arange(B, dtype=np.float64)[:, None, None], (B, R, A))
    return ndimage.map_coordinates(images, [ib, ir, ia], order=1, mode="nearest").astype(np.float32)


def _xp(backend: str):
    if backend == "torch":
        import torch

        return torch, (lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32))
    return np, (lambda a: np.asarray(a, dtype=np.float64))


def _pixel_polar(grid: SensorGrid, arr) -> tuple:
    """The pixel centres' range (1, R, 1) and azimuth (1, 1, A), as ``arr`` (from :func:`_xp`) makes arrays."""
    return arr(grid.range_centres())[None, :, None], arr(grid.azimuth_centres())[None, None, :]


class LastFrameBaseline(BasePredictor):
    """A baseline that reads only the last input frame (and the last command); it is fed the
    windows of the paper's geometry all the same, or those of a learned model with a longer
    context when it is evaluated beside one (``any_context``)."""

    n_in: ClassVar[int] = N_IN
    any_context: ClassVar[bool] = True  # reads the last frame of a window of any length


@dataclass
class Persistence(LastFrameBaseline):
    """The last frame, unchanged: the floor every predictor must beat."""

    grid: SensorGrid
    name: str = "persistence"

    def predict(self, frames: np.ndarray, commands: np.ndarray) -> np.ndarray:
        return np.array(frames[:, -1], dtype=np.float32)


@dataclass
class NaiveShift(LastFrameBaseline):
    """Shift the last frame by -v dt in range and -omega dt in azimuth (sub-bin, bilinear).

    Exact for a rotation about the sensor, wrong for translation (objects off-axis move along flow
    lines r sin(theta) = const, not straight down in range), as the paper notes.
    """

    grid: SensorGrid
    rig: RobotRig
    name: str = "naive"
    backend: str = "torch"

    def predict(self, frames: np.ndarray, commands: np.ndarray) -> np.ndarray:
        _, arr = _xp(self.backend)
        v = arr(commands[:, -1, 0])[:, None, None]
        w = arr(commands[:, -1, 1])[:, None, None]
        r, th = _pixel_polar(self.grid, arr)
        dt = self.rig.frame_interval_s
        return sample_polar(frames[:, -1], self.grid, r + v * dt, th + w * dt, self.backend)


@dataclass
class AcousticFlow(LastFrameBaseline):
    """Exact SE(2) warp of the last frame's pixels under the commanded motion (acoustic flow).

    Each pixel of the predicted frame is a point in the new sensor frame; moving it back through
    the robot's arc over the rig's frame interval (the sensor mounted ``sensor_offset_m`` ahead of
    the axle; models/flow.py) gives where it was in the last frame, which is sampled bilinearly. Under pure
    translation this moves reflectors along r sin(theta) = const. It keeps each pixel's value, so
    it deforms the sensor's point-spread function, which is the weakness the paper points out.
    """

    grid: SensorGrid
    rig: RobotRig
    name: str = "flow"
    backend: str = "torch"

    def predict(self, frames: np.ndarray, commands: np.ndarray) -> np.ndarray:
        xp, arr = _xp(self.backend)
        cmd = np.asarray(commands[:, -1], dtype=np.float64)
        # the motion in float64 NumPy on either backend, then the pixels in the backend's precision
        motion = arc_motion(np, cmd[:, 0], cmd[:, 1], self.rig.frame_interval_s)
        r, th = _pixel_polar(self.grid, arr)
        xo, yo = source_points(xp, r, th, tuple(arr(a)[:, None, None] for a in motion), self.rig.sensor_offset_m)
        return sample_polar(frames[:, -1], self.grid, xp.hypot(xo, yo), xp.arctan2(yo, xo), self.backend)
