"""The acoustic flow: where each pixel of the next frame was in the last one, under the robot's SE(2)
motion over one frame interval.

The geometry is written once, for any array module ``xp`` (NumPy or torch), and used by the
``flow`` baseline (models/baselines.py) and by EchoPT's flow prior (models/echopt/model.py).
Each caller keeps its own precision between the two steps (the motion in float64; the pixels in
float32 on torch, float64 on NumPy) and its own sampling, so both compute what they always have,
bit for bit. No torch is imported here.
"""

from __future__ import annotations

import sys


def arc_motion(xp, v, w, dt: float) -> tuple:
    """(cos phi, sin phi, dx, dy): the heading change phi = w dt and the displacement of a robot
    driving at ``v`` (m/s) and ``w`` (rad/s) for ``dt`` seconds from the origin, integrated exactly
    along its arc (a straight line where |w| < 1e-9). ``v`` and ``w`` are (B,) arrays of ``xp``."""
    phi = w * dt
    small = xp.abs(w) < 1e-9
    w_safe = xp.where(small, xp.ones_like(w), w)
    dx = xp.where(small, v * dt, v / w_safe * xp.sin(phi))
    dy = xp.where(small, xp.zeros_like(v), v / w_safe * (1 - xp.cos(phi)))
    return xp.cos(phi), xp.sin(phi), dx, dy


def source_points(xp, r, th, motion: tuple, offset: float) -> tuple:
    """(x, y) in the last sensor frame of the points at range ``r``, azimuth ``th`` in the next one,
    for the robot ``motion`` (:func:`arc_motion`'s four arrays, shaped to broadcast against ``r``
    and ``th``) and a sensor ``offset`` metres ahead of the wheel axle: new sensor frame -> new
    robot frame -> old robot frame -> old sensor frame."""
    c, s, dx, dy = motion
    xn, yn = r * xp.cos(th) + offset, r * xp.sin(th)
    xo = c * xn - s * yn + dx - offset
    yo = s * xn + c * yn + dy
    return xo, yo


def sampling_grid(x, y):
    """``grid_sample``'s grid (..., 2) from the normalised sampling coordinates ``x`` (azimuth) and
    ``y`` (range), tensors of one shape, dtype and device: the same values as ``torch.stack([x, y], -1)``, written
    into the pairs' slices, which is 3-5x faster on a CPU than ``stack``'s interleaving kernel
    (60 x 200 x 90, one thread; BENCHMARKS, "EchoWarp"). In a graph being exported it is ``stack``:
    the slices' writes become ONNX ScatterElements, which made onnxruntime's batch-1 EchoWarp
    forecast 1.37x slower (18.6 against 13.6 ms on one core)."""
    torch = sys.modules.get("torch")  # loaded wherever x is a tensor; not imported here
    if torch is not None and torch.compiler.is_exporting():
        return torch.stack([x, y], -1)
    grid = x.new_empty((*x.shape, 2))
    grid[..., 0] = x
    grid[..., 1] = y
    return grid
