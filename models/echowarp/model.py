"""EchoWarp: every horizon forecast from the measured frames by the cumulative commanded motion,
the motion corrected, a source term added.

Designed from what the measurements say (BENCHMARKS.md, "A predictor that uses its context"):

- **Correct the motion, not only the pixels.** The acoustic flow moves every pixel as a fixed point
  of the world; the echo of a wall is its foot point, which slides along the wall as the robot
  moves, and an occluded reflector reappears. An intensity residual cannot move a sparse echo
  without blurring it, so the network outputs, per horizon, a correction (in pixels) to where each
  pixel is sampled from in the last frame, gates that add the older frames registered to the same
  pose (reflectors heard earlier and hidden now), and an additive source term, composed through a
  differentiable warp (``grid_sample``), as NowcastNet composes motion fields and intensity
  (Zhang et al. 2023, "Skilful nowcasting of extreme precipitation with NowcastNet", Nature).
- **No compounding resampling.** Horizon h samples the measured frames once, at the robot's
  composed motion over the h commands (exact SE(2) composition of the arcs; models/flow.py), and
  every horizon up to ``max_horizon`` is one batch of slots in one pass, trained on the horizons it
  is scored on (the ego-motion factored out, as Khurana et al. 2023 do for lidar forecasting).
- **The FLOPs where the matrix units are.** A U-Net of 32-128 channels at 1/2 to 1/8 resolution,
  channels-last, bf16 under autocast; full resolution only for the inputs, one narrow
  convolution and the warp.

With every output layer at zero an untrained model is the composite flow: the last frame warped
once along the composed motion.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch
import torch.nn as nn
import torch.nn.functional as F

from sonarset.errors import GridMismatchError

from sonarset.models.echopt.config import ConfigError
from sonarset.models.flow import arc_motion, sampling_grid, source_points
from sonarset.models.predictor import checked_horizons
from sonarset.models.zoo.common import ConvAct, Up, ZooConfig, ZooModel, cat_channels, conv, zero_init

#: The protocol's longest horizon (AR-10): a forecast of up to this many steps is one pass.
MAX_HORIZON = 10
#: Scales that bring the inputs to about [-1, 1]: the composed motion (rad, m) and a pixel's shift
#: (pixels) over a horizon.
MOTION_SCALE = (0.5, 0.5, 0.5)
SHIFT_SCALE = 16.0
#: What the warp reads outside the view (EchoWarpConfig.outside): grid_sample's padding modes.
OUTSIDE = ("border", "zeros")


@dataclass(frozen=True)
class EchoWarpConfig(ZooConfig):
    inputs: str = "aligned"  # by design: the older frames registered to the predicted pose
    channels: tuple[int, ...] = (32, 64, 128)  # the U-Net's widths at 1/2, 1/4, 1/8 resolution
    full_channels: int = 16  # the one convolution at full resolution (with patch > 1: at 1/patch)
    # the side of the square of pixels the network reads and writes as one position: 1, a U-Net from
    # 1/2 resolution under a full-resolution layer; p > 1, each p x p patch folded into channels
    # (``folded``) so that every convolution runs at 1/p resolution or coarser, its outputs
    # unfolded per pixel (``unfolded``) for the full-resolution warp
    patch: int = 1
    max_shift: int = 6  # pixels: the largest correction of where a pixel is sampled from (0: none)
    older_frames: int = 1  # 1: gates add the registered older frames; 0: the last frame alone
    # what the warp reads where a pixel's source lies outside the view: "border", the edge's value
    # (the flow's choice; legs 1-11), or "zeros", nothing heard there (the source term adds what enters)
    outside: str = "border"
    max_horizon: int = MAX_HORIZON
    switches: ClassVar[tuple[str, ...]] = ("max_shift", "older_frames")  # the ablation's parts
    modes: ClassVar[tuple[str, ...]] = ("outside",)

    def check(self) -> None:
        super().check()
        if self.prior != "flow":
            raise ConfigError("prior", f"EchoWarp corrects the flow warp (prior flow), not prior {self.prior}")
        if self.inputs != "aligned":
            raise ConfigError("inputs", f"EchoWarp registers its inputs to the predicted pose (inputs aligned), "
                              f"not inputs {self.inputs}")
        if self.outside not in OUTSIDE:
            raise ConfigError("outside", f"outside must be one of {', '.join(OUTSIDE)}, got {self.outside!r}")
        if len(self.channels) < 2:
            raise ConfigError("channels", f"channels needs at least 2 levels, got {self.channels!r}")
        if self.patch > 16:  # its square multiplies the first and last layers' widths
            raise ConfigError("patch", f"patch must be at most 16 pixels, got {self.patch}")


PRESETS: dict[str, dict] = {
    # 0.43 M parameters; 0.99 GFLOP per horizon forward on the default grid (bench/bench_train.py)
    "small": {},
    "tiny": dict(channels=(4, 8), full_channels=4, max_horizon=4),
    # small with its U-Net 1.5x wider (0.96 M parameters, 2.1x the FLOPs): grown from a trained
    # small by ``init`` (models/echowarp/widen.py), to see whether small's plateau is its capacity
    "wide": dict(channels=(48, 96, 192)),
    # every convolution at 1/4 resolution or coarser (4 x 4 patches): the elementwise passes at full
    # and half resolution, most of small's training step on a CPU with matrix units, are gone; the
    # shipped model's network since 2026-12-08 (1.87 M parameters)
    "patch4": dict(patch=4, channels=(64, 128, 256), full_channels=64),
    # the ablation (recipes/echowarp/ablation/): small without one part each
    "small-no-correction": dict(max_shift=0),  # the network's output is an intensity residual on the warp
    "small-last-frame": dict(older_frames=0),  # the older registered frames are inputs only
    "small-chained": dict(max_horizon=1),  # one step at a time, each from the last prediction: resampled h times
    # small, reading nothing outside the view: an echo at the edge is not smeared into a turn's new
    # view; leg 10's twin (recipes/echowarp/small-10-zeros-outside.toml), behind it in the walled worlds
    "small-zeros-outside": dict(outside="zeros"),
}


def n_features(n_in: int) -> int:
    """The per-pixel inputs of a slot: the n_in registered frames, whether the last frame's source is
    outside the view, that source's shift (range, azimuth), the pixel's sine of azimuth and range,
    the horizon, and the composed motion (heading, x, y)."""
    return n_in + 1 + 2 + 2 + 1 + 3


class EchoWarp(ZooModel):
    kind = "echowarp"
    title = "EchoWarp"

    def __init__(self, cfg: EchoWarpConfig):
        super().__init__(cfg)
        ch, fc, p = cfg.channels, cfg.full_channels, cfg.patch
        cin = n_features(cfg.n_in) * p * p  # a patch's inputs
        # down: the first level halves the grid (with patches: keeps the patches' grid), each
        # further one halves it again
        self.down = nn.ModuleList(nn.Sequential(ConvAct(a, b, 3, stride=2 if i or p == 1 else 1), ConvAct(b, b))
                                  for i, (a, b) in enumerate(zip((cin, *ch), ch)))
        self.up = nn.ModuleList(Up(deep, skip, skip) for deep, skip in zip(ch[:0:-1], ch[-2::-1]))
        self.full = nn.Sequential(ConvAct(ch[0] + cin, fc, 1), ConvAct(fc, fc))
        # the warp's correction (range, azimuth pixels), a gate per older frame, the source term;
        # with patches, those of each of a patch's pixels
        self.head = conv(fc, (2 + (cfg.n_in - 1) + 1) * p * p, 1)
        zero_init(self.head)

    @property
    def max_horizon(self) -> int:
        return self.cfg.max_horizon

    def forecast(self, frames: torch.Tensor, commands: torch.Tensor, k: int) -> torch.Tensor:
        """frames (B, n_in, R, A) in [0, 1]; commands (B, n_in + k, 2) -> the next ``k`` frames
        (B, k, R, A), 1 <= k <= max_horizon, from one forward pass."""
        return self(frames, commands, k)

    def forecast_at(self, frames: torch.Tensor, commands: torch.Tensor, horizons: tuple[int, ...]) -> torch.Tensor:
        """The frames ``horizons`` steps ahead (B, len(horizons), R, A), increasing horizons up to
        ``max_horizon``, commands (B, n_in + horizons[-1], 2): ``forecast``'s images at those steps
        (each horizon is its own slot of the pass; equal to the rounding of another batch size),
        without computing the others."""
        return self.composed(self.parts(frames, commands, horizons=horizons))

    @staticmethod
    def composed(parts: dict[str, torch.Tensor]) -> torch.Tensor:
        """The forecast the terms of ``parts`` (or ``slot_parts``) sum to."""
        pred = parts["source"] + parts["warp"]
        return pred + parts["older"] if "older" in parts else pred

    def forward(self, frames: torch.Tensor, commands: torch.Tensor, k: int | None = None,
                horizons: tuple[int, ...] | None = None) -> torch.Tensor:
        """frames (B, n_in, R, A), commands (B, n_in + 1, 2) -> the next frame (B, R, A); with ``k``,
        commands (B, n_in + k, 2) -> the next k frames (B, k, R, A); with ``horizons`` instead, the
        frames those steps ahead (``forecast_at``: training on chosen horizons goes through here)."""
        if horizons is not None:
            return self.forecast_at(frames, commands, horizons)
        pred = self.forecast_at(frames, commands, tuple(range(1, self.forecast_steps(commands, k) + 1)))
        return pred[:, 0] if k is None else pred

    def parts(self, frames: torch.Tensor, commands: torch.Tensor, k: int | None = None,
              horizons: tuple[int, ...] | None = None) -> dict[str, torch.Tensor]:
        """The terms of the forecast of steps 1..k (or of ``horizons``), each (B, steps, R, A) in
        float32, steps = k (len(horizons)): ``source`` (the additive
        source term), ``warp`` (the last frame through the corrected warp, or with ``max_shift`` 0 the
        composite warp), ``older`` (the gated older registered frames, where ``older_frames``), and
        for diagnosis ``composite`` (the last frame through the composite warp alone) and, where
        the warp is corrected, ``shift`` (B, steps, 2, R, A): the correction in range and azimuth
        pixels."""
        horizons = self.checked_horizons(commands, k, horizons)
        self._check_frames(frames)
        steps = torch.tensor(horizons, device=commands.device)
        return self.slot_parts(frames, commands[:, :self.cfg.n_in + horizons[-1]], steps)

    def slot_parts(self, frames: torch.Tensor, commands: torch.Tensor, horizons: torch.Tensor) -> dict[str, torch.Tensor]:
        """``parts`` for ``horizons`` given as a 1-D integer tensor, unchecked: the traceable core
        (an ONNX export takes the horizons as an input; ``parts`` checks them and calls this)."""
        cfg = self.cfg
        steps, n_in = horizons.shape[0], cfg.n_in
        B, _, R, A = frames.shape
        ir, ia, motion = self.sources(commands, n_in, horizons)  # (B, steps, n_in, R, A) each
        slots = frames[:, None].expand(B, steps, n_in, R, A).reshape(B * steps, n_in, R, A)
        ir, ia = ir.reshape(B * steps, n_in, R, A), ia.reshape(B * steps, n_in, R, A)
        registered = self.sample(slots, ir, ia)  # every frame at the target's pose
        x = self.folded(self.features(registered, ir[:, -1], ia[:, -1], motion.reshape(B * steps, 3), horizons))
        skips, y = [], x
        for level in self.down:
            y = level(y)
            skips.append(y)
        for up, skip in zip(self.up, reversed(skips[:-1])):
            y = up(y, skip)
        out = self.unfolded(self.head(self.full_resolution(y, x)), R, A)
        # one plane per output, each read whole below (a channels-last slice is strided: tanh was 3x slower)
        out = out.to(torch.float32, memory_format=torch.contiguous_format)
        composite = registered[:, -1].float()
        parts = {"source": out[:, n_in + 1], "composite": composite}
        if cfg.max_shift:  # the last frame through the corrected warp
            shift = torch.tanh(out[:, :2]) * cfg.max_shift
            parts["warp"] = self.sample(slots[:, -1:], ir[:, -1:] + shift[:, :1], ia[:, -1:] + shift[:, 1:2])[:, 0]
            parts["shift"] = shift
        else:  # through the composite warp alone: the correction is an intensity residual
            parts["warp"] = composite
        if cfg.older_frames:
            parts["older"] = (out[:, 2:n_in + 1] * registered[:, :-1].float()).sum(1)
        return {name: v.reshape(B, steps, *v.shape[1:]) for name, v in parts.items()}

    def folded(self, x: torch.Tensor) -> torch.Tensor:
        """The inputs ``x`` (N, C, R, A) as patches, channels-last (N, patch**2 * C, ceil(R / patch),
        ceil(A / patch)), the grid padded with zeros to whole patches (itself with ``patch`` 1). A
        patch's channels are its pixels' inputs, row by row: each pixel's C inputs, contiguous in a
        channels-last ``x``, are copied whole (``pixel_unshuffle``'s order, the channel outermost,
        copies one value at a time: 4x slower)."""
        p = self.cfg.patch
        if p == 1:
            return x
        x = F.pad(x, (0, -x.shape[-1] % p, 0, -x.shape[-2] % p)).permute(0, 2, 3, 1)  # (N, R, A, C)
        N, R, A, C = x.shape
        x = x.reshape(N, R // p, p, A // p, p, C).transpose(2, 3).reshape(N, R // p, A // p, p * p * C)
        return x.permute(0, 3, 1, 2)

    def unfolded(self, out: torch.Tensor, R: int, A: int) -> torch.Tensor:
        """The head's outputs per patch (N, patch**2 * C, ...) on the R x A grid (N, C, R, A): ``folded``'s
        inverse."""
        p = self.cfg.patch
        if p == 1:
            return out
        N, _, r, a = out.shape
        out = out.permute(0, 2, 3, 1).reshape(N, r, a, p, p, -1).transpose(2, 3).reshape(N, r * p, a * p, -1)
        return out[:, :R, :A].permute(0, 3, 1, 2)

    def full_resolution(self, y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``self.full`` on ``y`` resized to the grid of the inputs ``x``, concatenated with them.
        With patches both are on the patches' grid: ``self.full`` on the two concatenated.

        Its first layer is a 1x1 convolution, which commutes with a bilinear resize (both linear, the
        resize's weights summing to 1), so the part of it that reads ``y`` runs at ``y``'s resolution
        and its ``full_channels`` outputs are resized instead of ``y``'s wider channels, and no
        full-resolution concatenation is made: the same function and parameters, in less time (the
        resize's backward was the step's costliest non-matrix kernel: BENCHMARKS, "EchoWarp")."""
        if self.cfg.patch > 1:
            return self.full(cat_channels([y, x]))
        first, act = self.full[0]
        c = y.shape[1]
        z = F.interpolate(F.conv2d(y, first.weight[:, :c]), size=x.shape[-2:], mode="bilinear", align_corners=False)
        z = z + F.conv2d(x, first.weight[:, c:], first.bias)
        return self.full[1](act(z))

    def _check_frames(self, frames: torch.Tensor) -> None:
        cfg = self.cfg
        _, n_in, R, A = frames.shape
        if (R, A) != (cfg.n_range, cfg.n_azimuth) or n_in != cfg.n_in:
            raise GridMismatchError(f"{self.title} was built for {cfg.n_in} frames of {cfg.n_range}x{cfg.n_azimuth}, "
                                    f"got {n_in} of {R}x{A}")

    def checked_horizons(self, commands: torch.Tensor, k: int | None, horizons: tuple[int, ...] | None) -> tuple[int, ...]:
        """The steps a pass forecasts: 1..k (1 without ``k``), or ``horizons``, increasing, each
        1..max_horizon, with the commands they need (ValueError naming what is wrong)."""
        if horizons is None:
            return tuple(range(1, self.forecast_steps(commands, k) + 1))
        horizons = checked_horizons(horizons)
        self.forecast_steps(commands, horizons[-1])
        return horizons

    def sources(self, commands: torch.Tensor, n_in: int, horizons: torch.Tensor | tuple[int, ...]):
        """Where each pixel of the frame ``h`` steps ahead (h in ``horizons``, a 1-D integer tensor or a tuple)
        lies in each input frame, in (fractional) pixel indices ``ir``, ``ia`` (B, steps, n_in, R, A),
        and the composed motion from the last input frame's pose to it (heading change, x, y; B,
        steps, 3). ``commands[:, t]`` moves the robot from frame t - 1 to frame t; the poses are
        composed exactly in float64 (cumulative sums over the commands, in their order), then each
        pixel's source is computed once (no chain of resamplings)."""
        horizons = torch.as_tensor(horizons, device=commands.device)
        cmd = commands.double()
        _, _, dx, dy = arc_motion(torch, cmd[..., 0], cmd[..., 1], self.cfg.dt)  # (B, T): frame t-1 -> t
        # poses of every frame in frame 0's robot frame (commands[:, 0] leads into frame 0: not used)
        phi = F.pad(cmd[:, 1:, 1] * self.cfg.dt, (1, 0))  # the heading change, as arc_motion's
        heading = torch.cumsum(phi, 1)
        before = F.pad(heading[:, :-1], (1, 0))  # the heading each step starts from
        c0, s0 = torch.cos(before), torch.sin(before)
        px = torch.cumsum(F.pad((c0 * dx - s0 * dy)[:, 1:], (1, 0)), 1)
        py = torch.cumsum(F.pad((s0 * dx + c0 * dy)[:, 1:], (1, 0)), 1)
        tgt = horizons + (n_in - 1)
        # the target's pose in each input frame's robot frame: (B, steps, n_in)
        d_h = heading[:, tgt, None] - heading[:, None, :n_in]
        ex, ey = px[:, tgt, None] - px[:, None, :n_in], py[:, tgt, None] - py[:, None, :n_in]
        ci, si = torch.cos(heading[:, None, :n_in]), torch.sin(heading[:, None, :n_in])
        rel_x, rel_y = ci * ex + si * ey, -si * ex + ci * ey
        motion = tuple(t.float()[..., None, None] for t in (torch.cos(d_h), torch.sin(d_h), rel_x, rel_y))
        r, th = self._centres()
        xo, yo = source_points(torch, r[:, None], th[:, None], motion, self.cfg.sensor_offset)
        (r_first, r_step), (th_first, th_step) = self._pixel_steps
        ir = (torch.hypot(xo, yo) - r_first) / r_step
        ia = (torch.atan2(yo, xo) - th_first) / th_step
        last_motion = torch.stack([d_h[:, :, -1], rel_x[:, :, -1], rel_y[:, :, -1]], -1).float()
        return ir, ia, last_motion / last_motion.new_tensor(MOTION_SCALE)

    def sample(self, images: torch.Tensor, ir: torch.Tensor, ia: torch.Tensor) -> torch.Tensor:
        """``images`` (N, C, R, A) each sampled bilinearly at the pixel indices ``ir``, ``ia`` (N, C, R, A),
        for C images at once; outside the view, the edge's values (the flow's sampling) or zeros
        (``cfg.outside``)."""
        N, C, R, A = images.shape
        grid = sampling_grid(2 * ia / max(A - 1, 1) - 1, 2 * ir / max(R - 1, 1) - 1)
        out = F.grid_sample(images.reshape(N * C, 1, R, A).float(), grid.reshape(N * C, R, A, 2), mode="bilinear",
                            padding_mode=self.cfg.outside, align_corners=True)
        return out.reshape(N, C, R, A)

    def outside_view(self, ir: torch.Tensor, ia: torch.Tensor) -> torch.Tensor:
        """Whether each source pixel index (``ir``, ``ia``, as ``sources`` gives them) lies outside the view."""
        R, A = self.cfg.n_range, self.cfg.n_azimuth
        return (ir < -0.5) | (ir > R - 0.5) | (ia < -0.5) | (ia > A - 0.5)

    def features(self, registered: torch.Tensor, ir: torch.Tensor, ia: torch.Tensor, motion: torch.Tensor,
                 horizons: torch.Tensor) -> torch.Tensor:
        """A slot's per-pixel inputs (N, n_features, R, A), channels-last (``n_features``), in
        autocast's dtype where it is on."""
        cfg = self.cfg
        N, n_in, R, A = registered.shape
        outside = self.outside_view(ir, ia).float()
        r_idx = torch.arange(R, device=ir.device, dtype=ir.dtype)[:, None]
        a_idx = torch.arange(A, device=ir.device, dtype=ir.dtype)[None, :]
        shift = torch.stack([ir - r_idx, ia - a_idx], 1).clamp(-2 * SHIFT_SCALE, 2 * SHIFT_SCALE) / SHIFT_SCALE
        r, th = self._centres()
        r0, r1 = cfg.range_edges
        pos = torch.stack([torch.sin(th).expand(1, R, A), ((r - r0) / (r1 - r0) * 2 - 1).expand(1, R, A)], 1)
        horizon = horizons.to(torch.float32)[None].expand(N // horizons.shape[0], -1).reshape(N) / cfg.max_horizon
        planes = torch.cat([horizon[:, None], motion], 1)[:, :, None, None].expand(N, 4, R, A)
        x = torch.cat([registered, outside[:, None], shift, pos.expand(N, 2, R, A), planes], 1)
        # in autocast's dtype once: both convolutions that read x would each cast it again
        dtype = torch.get_autocast_dtype(x.device.type) if torch.is_autocast_enabled(x.device.type) else x.dtype
        return x.to(dtype, memory_format=torch.channels_last)
