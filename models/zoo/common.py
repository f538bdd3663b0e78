"""What the reference methods share: the grid and robot a config describes, the prior each corrects
(EchoPT's own acoustic-flow plumbing, so every learned model warps bit for bit alike), commands as
image channels, and the convolutions the three networks are built from.

A zoo model maps ``frames`` (B, n_in, R, A) in [0, 1] and ``commands`` (B, n_in + 1, 2) (v m/s,
omega rad/s; ``commands[:, -1]`` moves the robot from the last frame to the predicted one) to the
next frame (B, R, A), like EchoPT, and is trained by the same trainer (models/echopt/train.py).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import ClassVar

import torch
import torch.nn as nn
import torch.nn.functional as F

from sonarset.errors import GridMismatchError
from sonarset.format.attrs import RobotRig, SensorGrid
from sonarset.windows import N_IN

from sonarset.models.echopt.config import ConfigError, check_rig_and_inputs, config_fields
from sonarset.models.echopt.model import GELU, V_SCALE, W_SCALE, EchoPT

_DEFAULT_RIG = RobotRig()
_DEFAULT_GRID = SensorGrid.default()
#: The largest size any network setting may have: far above the presets, below what would exhaust
#: memory building one from a bad card.
_MAX_SIZE = 4096


@dataclass(frozen=True)
class ZooConfig:
    """The fields every reference method has: the grid, the context, the prior and how its inputs
    are prepared (as EchoPTConfig), and the grid's edges and the rig the flow prior needs. A
    method's config adds its network's sizes: integers or tuples of integers, checked alike."""

    n_range: int = _DEFAULT_GRID.n_range
    n_azimuth: int = _DEFAULT_GRID.n_azimuth
    n_in: int = N_IN
    prior: str = "flow"  # none | last | flow (models/echopt/config.PRIORS)
    inputs: str = "raw"  # raw | aligned (models/echopt/config.INPUTS)
    range_edges: tuple[float, float] = (_DEFAULT_GRID.range_min_m, _DEFAULT_GRID.range_max_m)
    azimuth_edges: tuple[float, float] = (_DEFAULT_GRID.azimuth_min_rad, _DEFAULT_GRID.azimuth_max_rad)
    dt: float = _DEFAULT_RIG.frame_interval_s
    sensor_offset: float = _DEFAULT_RIG.sensor_offset_m

    #: The sizes that may be 0: a part of the network switched off (an ablation).
    switches: ClassVar[tuple[str, ...]] = ()
    #: Fields a method adds that are no size (a named mode): its own ``check`` checks them.
    modes: ClassVar[tuple[str, ...]] = ()

    def sizes(self) -> dict[str, int | tuple[int, ...]]:
        """The network's sizes: the fields a method's config adds, its modes aside."""
        other = {f.name for f in fields(ZooConfig)} | set(self.modes)
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name not in other}

    def check(self) -> None:
        """ConfigError (GridMismatchError for the grid) naming the first setting no network can have:
        a model card is data from a file, and a bad one must fail here, not deep in torch."""
        for name in ("n_range", "n_azimuth", "n_in"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 100_000:
                error = GridMismatchError if name != "n_in" else None
                message = f"{name} must be an integer in 1..100000, got {v!r}"
                raise (error(message) if error else ConfigError(name, message))
        for name, v in self.sizes().items():
            values = v if isinstance(v, tuple) else (v,)
            least = 0 if name in self.switches else 1
            if not values or any(isinstance(x, bool) or not isinstance(x, int) or not least <= x <= _MAX_SIZE
                                 for x in values):
                raise ConfigError(name, f"{name} must be an integer in {least}..{_MAX_SIZE} (or a tuple of them), "
                                        f"got {v!r}")
        check_rig_and_inputs(self)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict):
        return cls(**config_fields(cls, d))


def make_config(cls: type[ZooConfig], presets: dict[str, dict], preset: str, n_range: int, n_azimuth: int,
                **overrides) -> ZooConfig:
    """A method's ``preset`` on an ``n_range`` x ``n_azimuth`` grid; ``overrides`` set any field
    (EchoPT's config.grid_and_rig makes the grid's edges and the rig)."""
    if preset not in presets:
        raise ValueError(f"unknown preset {preset!r}; choose from {', '.join(presets)}")
    cfg = cls(n_range=n_range, n_azimuth=n_azimuth, **{**presets[preset], **overrides})
    cfg.check()
    return cfg


class ZooModel(nn.Module):
    """The base of the reference methods: the prior they correct and the frames they see, both as
    EchoPT makes them (its methods, borrowed: one warp for every learned model), and commands as
    image channels.

    With a prior, a subclass's output layer starts at zero (:func:`zero_init`): an untrained model
    is exactly its prior, and training starts from that prior's accuracy."""

    kind = ""  # the name sonarset train --model and the model card use
    title = ""  # the name in messages

    # EchoPT's grid plumbing (models/echopt/model.py), shared rather than copied
    _register_grid = EchoPT._register_grid
    flow_prior = EchoPT.flow_prior
    align = EchoPT.align
    _centres = EchoPT._centres
    _source = EchoPT._source
    _step_back = EchoPT._step_back
    _sample = EchoPT._sample

    def __init__(self, cfg: ZooConfig):
        super().__init__()
        cfg.check()
        self.cfg = cfg
        self._register_grid(cfg)
        self.register_buffer("cmd_scale", torch.tensor([1 / V_SCALE, 1 / W_SCALE]), persistent=False)

    def n_params(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def forecast_steps(self, commands: torch.Tensor, k: int | None) -> int:
        """The steps a forward pass of a multi-step model forecasts (1 without ``k``), checked against
        its ``max_horizon`` and the commands given (ValueError naming what is wrong)."""
        steps, most = 1 if k is None else k, self.cfg.max_horizon
        if not 1 <= steps <= most:
            raise ValueError(f"{self.title} forecasts 1..{most} steps in one pass, not {steps}")
        if commands.shape[1] < self.cfg.n_in + steps:
            raise ValueError(f"a {steps}-step forecast needs {self.cfg.n_in + steps} commands, got {commands.shape[1]}")
        return steps

    def inputs_and_prior(self, frames: torch.Tensor, commands: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The frames the network sees (as measured, or each registered to the predicted frame's pose:
        ``inputs="aligned"``) and the prior image of the next frame (None for ``prior="none"``), after
        checking the frames' shape against the config."""
        cfg = self.cfg
        B, n_in, R, A = frames.shape
        if (R, A) != (cfg.n_range, cfg.n_azimuth) or n_in != cfg.n_in:
            raise GridMismatchError(f"{self.title} was built for {cfg.n_in} frames of {cfg.n_range}x{cfg.n_azimuth}, "
                                    f"got {n_in} of {R}x{A}")
        last = frames[:, -1]
        newest = self._source(self._centres(), commands[:, n_in]) if cfg.prior == "flow" or cfg.inputs == "aligned" else None
        if cfg.inputs == "aligned":
            frames = self.align(frames, commands[:, :n_in + 1], newest)
        if cfg.prior == "none":
            return frames, None
        if cfg.prior == "last":
            return frames, last
        # with aligned inputs the last one is the flow prior already
        return frames, frames[:, -1] if cfg.inputs == "aligned" else self._sample(last, *newest)

    def next_prior(self, prior: torch.Tensor, command: torch.Tensor) -> torch.Tensor:
        """The prior one step further along ``command``, from this step's ``prior``: the flow warp of
        it (the flow baseline's own rollout), the last measured frame again, or nothing."""
        return self.flow_prior(prior, command) if self.cfg.prior == "flow" else prior

    def scaled(self, commands: torch.Tensor) -> torch.Tensor:
        """Commands (..., 2) scaled to about [-1, 1], as EchoPT's command branch sees them."""
        return commands.float() * self.cmd_scale


def command_planes(values: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """``values`` (B, C) tiled into C constant image channels (B, C, H, W) of ``size``: how an
    action enters a convolutional predictor (Finn, Goodfellow & Levine 2016, "Unsupervised
    learning for physical interaction through video prediction", NeurIPS: the action is tiled and
    concatenated to the lowest-resolution activations)."""
    B, C = values.shape
    return values[:, :, None, None].expand(B, C, *size)


def conv(cin: int, cout: int, kernel: int = 3, stride: int = 1) -> nn.Conv2d:
    """A ``kernel`` x ``kernel`` convolution keeping the size (stride 1) or halving it, rounding up."""
    return (nn.Conv2d if stride == 1 else StridedConv)(cin, cout, kernel, stride=stride, padding=kernel // 2)


class StridedConv(nn.Conv2d):
    """A strided convolution that, on a CPU under bf16 autocast, convolves an input at most 2 pixels
    wide in fp32: oneDNN's bf16 kernel (torch 2.13, AMX and AVX-512 bf16) returns garbage or NaN
    for a stride-2 convolution of such an input 16 or more pixels tall, as a narrow grid's U-Net
    levels are (a 64 x 3 grid trained to NaN). The same parameters and, elsewhere, the same code."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-1] <= 2 and x.device.type == "cpu" and torch.is_autocast_enabled("cpu"):
            with torch.autocast("cpu", enabled=False):
                return super().forward(x.float())
        return super().forward(x)


class ConvAct(nn.Sequential):
    """Convolution, then GELU."""

    def __init__(self, cin: int, cout: int, kernel: int = 3, stride: int = 1):
        super().__init__(conv(cin, cout, kernel, stride), GELU())


class _ChannelsLastGrad(torch.autograd.Function):
    """The identity, whose backward hands on its gradient as a dense channels-last tensor."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        return grad.contiguous(memory_format=torch.channels_last)


def channels_last_grad(x: torch.Tensor) -> torch.Tensor:
    """``x``, with its gradient made dense channels-last on the way back. The gradient of one part
    of a concatenation is a strided slice of the whole's, and ``upsample_bilinear2d``'s backward on
    that slice was 4-5x slower than on a dense copy (bf16 on an AMX CPU: BENCHMARKS, "Training speed
    against the roof"); with the copy (17 ms there) one ``Up``'s forward and backward went from 371
    to 223 ms. Values are unchanged."""
    return _ChannelsLastGrad.apply(x) if x.requires_grad else x


def cat_channels(tensors: list[torch.Tensor]) -> torch.Tensor:
    """``torch.cat(tensors, 1)``; when every tensor is a channels-last image, the concatenation is
    made on their dense (N, H, W, C) views: the same values and layout, 1.2-2.2x faster in repeated
    timings (bf16, 20 x 96 x 100 x 45, one thread of an AMX CPU: channels-last ``cat`` takes a slow strided path)."""
    if all(t.dim() == 4 and t.is_contiguous(memory_format=torch.channels_last) for t in tensors):
        return torch.cat([t.permute(0, 2, 3, 1) for t in tensors], 3).permute(0, 3, 1, 2)
    return torch.cat(tensors, 1)


class Up(nn.Module):
    """Resize ``x`` to its skip's size (bilinear: a resize-convolution, free of the checkerboard of
    a transposed one; Odena et al. 2016, Distill), concatenate the skip, convolve."""

    def __init__(self, cin: int, skip: int, cout: int, n_convs: int = 1):
        super().__init__()
        self.convs = nn.Sequential(*(ConvAct(cin + skip if i == 0 else cout, cout) for i in range(n_convs)))

    def forward(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        x = channels_last_grad(F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False))
        return self.convs(cat_channels([x, skip.to(x.dtype)]))


def zero_init(layer: nn.Conv2d) -> None:
    """Start ``layer`` at zero: with a prior, the model it ends is exactly that prior until trained."""
    nn.init.zeros_(layer.weight)
    if layer.bias is not None:
        nn.init.zeros_(layer.bias)
