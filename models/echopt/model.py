"""EchoPT: a pretrained transformer that predicts the next 2D sonar image (the paper's Fig. 2).

Three parallel branches over n_in = 3 input frames and n_in + 1 = 4 velocity commands:

1. transformer: 25 x 5 patches of the frame stack are embedded to ``d_embed`` (376) dims, a learned
   positional embedding is added, the 8 command values are appended to every token (-> 384), and
   ``n_layers`` blocks of self-attention (6 heads) and a 500-wide feed-forward follow. Each token is
   un-embedded to its 25 x 5 pixels, and 20 x 5 convolutions refine the image;
2. convolutions straight over the frame stack;
3. an MLP on the commands (8 -> 10 -> 10 -> 200), its 200 outputs laid out as a 20 x 10 image and
   resized to the grid.

The branches are depth-concatenated and a convolution stack makes the output image. Layer sizes
follow the paper's appendix table; where the table is ambiguous the choice is noted inline. The
paper's stride-1 "transposed" convolutions are plain convolutions here (identical function).

Beyond the paper, a physics ``prior``: the network's output is a correction added to a prior
image: ``none`` (the paper: the output is the image), ``last`` (the last input frame) or ``flow``
(the acoustic-flow warp of the last frame along the newest command: the same SE(2) warp as the
``flow`` baseline, with the rig the model was trained for). With a prior, the last convolution
starts at zero, so an untrained model is exactly its prior.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import torch
import torch.nn as nn
import torch.nn.functional as F

from sonarset.errors import GridMismatchError
from sonarset.format.attrs import RobotRig
from sonarset.windows import N_IN

#: The robot a config describes when no store's rig is given (the record's defaults: the simulator's).
_DEFAULT_RIG = RobotRig()
V_SCALE, W_SCALE = 0.3, 1.0  # command ranges (m/s, rad/s): inputs are scaled to [-1, 1]


@dataclass(frozen=True)
class EchoPTConfig:
    n_range: int = 200
    n_azimuth: int = 90
    n_in: int = N_IN  # input frames: the paper's window
    patch: tuple[int, int] = (25, 5)
    d_embed: int = 376  # image part of a token; + 2 (n_in + 1) command values = d_model
    n_layers: int = 8
    n_heads: int = 6
    d_ff: int = 500
    max_tokens: int = 2000  # the paper's positional table (376 x 2000); the grid uses the first ones
    kernel: tuple[int, int] = (20, 5)
    tf_channels: tuple[int, int] = (16, 32)  # convolutions after un-embedding
    frame_channels: int = 16  # convolutional branch over the frame stack
    head_channels: tuple[int, int] = (16, 4)  # output stack: (65 -> 16 -> 4 -> 1 for the paper)
    mlp_hidden: int = 10
    mlp_out: int = 200  # laid out as a 20 x 10 image
    prior: str = "none"  # none (paper) | last | flow: the image the output corrects
    dropout: float = 0.0
    # The sensor grid's edges and the robot rig, which the flow prior needs (from the store).
    range_edges: tuple[float, float] = (0.5, 5.0)
    azimuth_edges: tuple[float, float] = (-math.pi / 2, math.pi / 2)
    dt: float = _DEFAULT_RIG.frame_interval_s
    sensor_offset: float = _DEFAULT_RIG.sensor_offset_m

    @property
    def n_cmd(self) -> int:
        return 2 * (self.n_in + 1)

    @property
    def d_model(self) -> int:
        return self.d_embed + self.n_cmd

    @property
    def grid_tokens(self) -> tuple[int, int]:
        return self.n_range // self.patch[0], self.n_azimuth // self.patch[1]

    def check(self) -> None:
        """ValueError (GridMismatchError for the grid) naming the first setting no network can have:
        a model card is data from a file, and a bad one must fail here, not deep in torch."""
        sizes = {"n_range": self.n_range, "n_azimuth": self.n_azimuth, "n_in": self.n_in, "d_embed": self.d_embed,
                 "n_layers": self.n_layers, "n_heads": self.n_heads, "d_ff": self.d_ff,
                 "max_tokens": self.max_tokens, "frame_channels": self.frame_channels,
                 "mlp_hidden": self.mlp_hidden, "mlp_out": self.mlp_out}
        pairs = {"patch": self.patch, "kernel": self.kernel, "tf_channels": self.tf_channels,
                 "head_channels": self.head_channels}
        for name, pair in pairs.items():
            if not (isinstance(pair, tuple) and len(pair) == 2):
                raise ValueError(f"{name} must be a pair of integers, got {pair!r}")
            sizes.update({f"{name}[{i}]": v for i, v in enumerate(pair)})
        for name, v in sizes.items():
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= _MAX_SIZE.get(name, 100_000):
                raise ValueError(f"{name} must be an integer in 1..{_MAX_SIZE.get(name, 100_000)}, got {v!r}")
        for name in ("dt", "sensor_offset", "dropout"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"{name} must be a finite number, got {v!r}")
        if self.dt <= 0:
            raise ValueError(f"dt (the frame interval) must be > 0 s, got {self.dt}")
        if not 0 <= self.dropout < 1:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout}")
        for name in ("range_edges", "azimuth_edges"):
            lo_hi = getattr(self, name)
            if not (isinstance(lo_hi, tuple) and len(lo_hi) == 2 and all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in lo_hi)
                    and lo_hi[0] < lo_hi[1]):
                raise ValueError(f"{name} must be two finite increasing numbers, got {lo_hi!r}")
        if self.n_range % self.patch[0] or self.n_azimuth % self.patch[1]:
            raise GridMismatchError(f"grid {self.n_range}x{self.n_azimuth} is not divisible by the "
                                    f"{self.patch[0]}x{self.patch[1]} patch")
        if self.grid_tokens[0] * self.grid_tokens[1] > self.max_tokens:
            raise GridMismatchError(f"grid {self.n_range}x{self.n_azimuth} needs more than {self.max_tokens} tokens")
        if self.d_model % self.n_heads:
            raise ValueError(f"d_model {self.d_model} is not divisible by {self.n_heads} heads")
        if self.prior not in PRIORS:
            raise ValueError(f"prior must be one of {', '.join(PRIORS)}, got {self.prior!r}")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "EchoPTConfig":
        names = {f.name for f in fields(cls)}
        kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items() if k in names}
        if "prior" not in d and "residual" in d:  # cards before the prior option: residual = last frame
            kw["prior"] = "last" if d["residual"] else "none"
        return cls(**kw)


PRIORS = ("none", "last", "flow")
# Upper bounds on a card's sizes, far above any network here (the paper's: 8 layers, 376 + 8 wide,
# 2000 tokens) but below what would exhaust memory building one; unlisted sizes: 100,000.
_MAX_SIZE = {"n_layers": 256, "n_heads": 256, "n_in": 64, "d_embed": 8192, "d_ff": 32768, "max_tokens": 100_000,
             "frame_channels": 1024, "mlp_hidden": 4096, "tf_channels[0]": 1024, "tf_channels[1]": 1024,
             "head_channels[0]": 1024, "head_channels[1]": 1024}


PRESETS: dict[str, dict] = {
    # The paper's model: ~9 M parameters, ~7.8 M of them in the 8 transformer blocks.
    "paper": {},
    # Sized by measurement to train on a 2-core CPU (BENCHMARKS.md): 0.62 M parameters, ~50
    # samples/s. Full-resolution 20 x 5 convolutions cost most of the paper model's time on a CPU,
    # so the small preset uses 5 x 3 kernels and 8 channels, and predicts a correction to a prior
    # (default: the acoustic-flow warp of the last frame), which starts training from that
    # prior's accuracy instead of from zero.
    "small": dict(d_embed=120, n_layers=4, n_heads=4, d_ff=256, max_tokens=144, kernel=(5, 3),
                  tf_channels=(4, 8), frame_channels=8, head_channels=(8, 4), prior="flow"),
    # For tests and smoke runs on tiny grids: seconds per hundred steps.
    "tiny": dict(d_embed=24, n_layers=2, n_heads=2, d_ff=32, max_tokens=64, kernel=(3, 3),
                 tf_channels=(2, 4), frame_channels=4, head_channels=(4, 2), mlp_hidden=8, mlp_out=50,
                 prior="flow"),
}


def make_config(preset: str, n_range: int = 200, n_azimuth: int = 90, **overrides) -> EchoPTConfig:
    """A preset's config on an ``n_range`` x ``n_azimuth`` grid; ``overrides`` set any field
    (``prior``, the grid's edges and the rig for the flow prior: ``config_for_store`` fills them)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose from {', '.join(PRESETS)}")
    cfg = EchoPTConfig(n_range=n_range, n_azimuth=n_azimuth, **{**PRESETS[preset], **overrides})
    cfg.check()
    return cfg


def grid_and_rig(grid, rig=None) -> dict:
    """Config fields for a store's grid (a SensorGrid) and robot rig (a RobotRig, or None: the
    simulator's), which the flow prior needs."""
    out = {"range_edges": (grid.range_min_m, grid.range_max_m), "azimuth_edges": (grid.azimuth_min_rad, grid.azimuth_max_rad)}
    if rig is not None:
        out.update(dt=rig.frame_interval_s, sensor_offset=rig.sensor_offset_m)
    return out


class Block(nn.Module):
    """Pre-norm transformer block: self-attention, then a feed-forward of width d_ff."""

    def __init__(self, cfg: EchoPTConfig):
        super().__init__()
        d = cfg.d_model
        self.n_heads = cfg.n_heads
        self.ln1 = nn.LayerNorm(d)
        self.qkv = nn.Linear(d, 3 * d)
        self.proj = nn.Linear(d, d)
        self.ln2 = nn.LayerNorm(d)
        self.ff = nn.Sequential(nn.Linear(d, cfg.d_ff), nn.GELU(), nn.Linear(cfg.d_ff, d))
        self.dropout = cfg.dropout

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, T, D = x.shape
        q, k, v = self.qkv(self.ln1(x)).split(D, dim=-1)
        q, k, v = (t.view(B, T, self.n_heads, D // self.n_heads).transpose(1, 2) for t in (q, k, v))
        # every patch attends to every other one: an image, not a causal sequence
        y = F.scaled_dot_product_attention(q, k, v, dropout_p=self.dropout if self.training else 0.0)
        x = x + self.proj(y.transpose(1, 2).reshape(B, T, D))
        return x + self.ff(self.ln2(x))


class GELU(nn.GELU):
    """``nn.GELU`` that runs a channels-last image as the dense (B, H, W, C) tensor it is: the
    elementwise kernel is ~1.8x faster on it than on the strided NCHW view (bf16, 16 x 8 x 200 x 90,
    one thread), with the same values."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() == 4 and not x.is_contiguous() and x.is_contiguous(memory_format=torch.channels_last):
            return F.gelu(x.permute(0, 2, 3, 1), approximate=self.approximate).permute(0, 3, 1, 2)
        return F.gelu(x, approximate=self.approximate)


def conv(cin: int, cout: int, kernel: tuple[int, int]) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, kernel, padding="same")


class EchoPT(nn.Module):
    def __init__(self, cfg: EchoPTConfig):
        super().__init__()
        cfg.check()
        self.cfg = cfg
        pr, pa = cfg.patch
        k = cfg.kernel
        # transformer branch
        self.embed = nn.Conv2d(cfg.n_in, cfg.d_embed, kernel_size=cfg.patch, stride=cfg.patch)
        self.pos = nn.Parameter(torch.zeros(cfg.max_tokens, cfg.d_embed))
        self.blocks = nn.ModuleList(Block(cfg) for _ in range(cfg.n_layers))
        self.ln_f = nn.LayerNorm(cfg.d_model)
        self.unembed = nn.Linear(cfg.d_model, pr * pa, bias=False)
        c1, c2 = cfg.tf_channels
        self.tf_convs = nn.Sequential(conv(1, c1, k), GELU(), conv(c1, c2, k), GELU())
        # convolutional branch over the frame stack (two layers; both feed the head: 16 + 16)
        fc = cfg.frame_channels
        self.frame_conv1 = conv(cfg.n_in, fc, k)
        self.frame_conv2 = conv(fc, fc, k)
        self.frame_act = GELU()
        # command MLP
        self.mlp = nn.Sequential(nn.Linear(cfg.n_cmd, cfg.mlp_hidden), nn.GELU(),
                                 nn.Linear(cfg.mlp_hidden, cfg.mlp_hidden), nn.GELU(),
                                 nn.Linear(cfg.mlp_hidden, cfg.mlp_out))
        # head over the depth-concatenation: c2 + 2 fc + 1 channels (32 + 32 + 1 = 65 in the paper)
        h1, h2 = cfg.head_channels
        self.head = nn.Sequential(conv(c2 + 2 * fc + 1, h1, k), GELU(), conv(h1, h2, k), GELU(), conv(h2, 1, k))
        self.register_buffer("cmd_scale", torch.tensor([1 / V_SCALE, 1 / W_SCALE] * (cfg.n_in + 1)), persistent=False)
        # pixel centres of the grid (range [m], azimuth [rad]) for the flow prior
        (r0, r1), (a0, a1) = cfg.range_edges, cfg.azimuth_edges
        dr, da = (r1 - r0) / cfg.n_range, (a1 - a0) / cfg.n_azimuth
        self.register_buffer("r_c", r0 + (torch.arange(cfg.n_range, dtype=torch.float64) + 0.5) * dr, persistent=False)
        self.register_buffer("th_c", a0 + (torch.arange(cfg.n_azimuth, dtype=torch.float64) + 0.5) * da, persistent=False)
        # the first centre (as float32) and the step, as Python numbers: a graph export (ONNX) must not
        # read them out of tensors
        self._pixel_steps = tuple((float(c[0].float()), float(c[1] - c[0]) if len(c) > 1 else step)
                                  for c, step in ((self.r_c, dr), (self.th_c, da)))
        self.apply(self._init)
        nn.init.normal_(self.pos, std=0.02)
        if cfg.prior != "none":  # an untrained model is exactly its prior
            nn.init.zeros_(self.head[-1].weight)
            nn.init.zeros_(self.head[-1].bias)

    @staticmethod
    def _init(m: nn.Module) -> None:
        if isinstance(m, nn.Linear):
            nn.init.normal_(m.weight, std=0.02)
            if m.bias is not None:
                nn.init.zeros_(m.bias)

    def n_params(self, part: str | None = None) -> int:
        mod = self.blocks if part == "blocks" else self
        return sum(p.numel() for p in mod.parameters())

    def forward(self, frames: torch.Tensor, commands: torch.Tensor) -> torch.Tensor:
        """frames (B, n_in, R, A) in [0, 1]; commands (B, n_in + 1, 2) in m/s, rad/s -> (B, R, A)."""
        cfg = self.cfg
        B, n_in, R, A = frames.shape
        if (R, A) != (cfg.n_range, cfg.n_azimuth) or n_in != cfg.n_in:
            raise GridMismatchError(f"EchoPT was built for {cfg.n_in} frames of {cfg.n_range}x{cfg.n_azimuth}, "
                                    f"got {n_in} of {R}x{A}")
        c = commands.reshape(B, -1) * self.cmd_scale
        # transformer branch
        tok = self.embed(frames)  # (B, d_embed, R/pr, A/pa)
        gr, ga = tok.shape[-2:]
        tok = tok.flatten(2).transpose(1, 2) + self.pos[: gr * ga]
        tok = torch.cat([tok, c[:, None, :].expand(B, gr * ga, cfg.n_cmd)], dim=-1)
        for block in self.blocks:
            tok = block(tok)
        pix = self.unembed(self.ln_f(tok))  # (B, tokens, pr * pa)
        pr, pa = cfg.patch
        img = pix.view(B, gr, ga, pr, pa).permute(0, 1, 3, 2, 4).reshape(B, 1, R, A)
        t = self.tf_convs(img)
        # convolutional branch
        f1 = self.frame_act(self.frame_conv1(frames))
        f2 = self.frame_act(self.frame_conv2(f1))
        # command branch, resized to the grid
        side = int(math.sqrt(cfg.mlp_out / 2))
        m = self.mlp(c).view(B, 1, 2 * side, side) if 2 * side * side == cfg.mlp_out else self.mlp(c).view(B, 1, cfg.mlp_out, 1)
        m = F.interpolate(m, size=(R, A), mode="bilinear", align_corners=False)
        if f1.is_contiguous(memory_format=torch.channels_last):
            # a one-channel tensor has contiguous strides, and torch.cat then lays the head's input
            # out contiguously: one copy of it back to channels-last per forward (~10% of inference)
            m = torch.empty_like(m, memory_format=torch.channels_last).copy_(m)
        out = self.head(torch.cat([t, f1, f2, m], dim=1))[:, 0]
        if cfg.prior == "none":
            return out
        return out + (frames[:, -1] if cfg.prior == "last" else self.flow_prior(frames[:, -1], commands[:, -1]))

    def flow_prior(self, last: torch.Tensor, command: torch.Tensor) -> torch.Tensor:
        """The acoustic-flow warp of ``last`` (B, R, A) under ``command`` (B, 2): each pixel of the next
        frame, moved back along the robot's arc over dt (sensor ``sensor_offset`` ahead of the axle),
        sampled bilinearly (edge values outside the field of view), as ``baselines.AcousticFlow``."""
        cfg = self.cfg
        cmd = command.double()
        v, w = cmd[:, 0], cmd[:, 1]
        phi = w * cfg.dt
        small = w.abs() < 1e-9
        w_safe = torch.where(small, torch.ones_like(w), w)
        dx = torch.where(small, v * cfg.dt, v / w_safe * torch.sin(phi))
        dy = torch.where(small, torch.zeros_like(v), v / w_safe * (1 - torch.cos(phi)))
        c, s, dx, dy = (t.float()[:, None, None] for t in (torch.cos(phi), torch.sin(phi), dx, dy))
        r, th = self.r_c.float()[None, :, None], self.th_c.float()[None, None, :]
        xn, yn = r * torch.cos(th) + cfg.sensor_offset, r * torch.sin(th)
        xo = c * xn - s * yn + dx - cfg.sensor_offset
        yo = s * xn + c * yn + dy
        R, A = cfg.n_range, cfg.n_azimuth
        (r_first, r_step), (th_first, th_step) = self._pixel_steps
        ir = (torch.hypot(xo, yo) - r_first) / r_step  # ONNX has no hypot: models/onnx_export.py translates it
        ia = (torch.atan2(yo, xo) - th_first) / th_step
        B = last.shape[0]
        grid = torch.stack([(2 * ia / max(A - 1, 1) - 1).expand(B, R, A), (2 * ir / max(R - 1, 1) - 1).expand(B, R, A)], -1)
        return F.grid_sample(last[:, None].float(), grid.to(last.device), mode="bilinear", padding_mode="border",
                             align_corners=True)[:, 0].to(last.dtype)
