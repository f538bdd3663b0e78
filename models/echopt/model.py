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

Also beyond the paper, ``inputs="aligned"``: every branch sees the input frames registered to the
pose of the frame to predict (each warped along the window's commands, :meth:`EchoPT.align`),
instead of as measured, so what changed between frames (a wall's specular arc, an occlusion)
lies at one pixel across the stack rather than along a motion the network must learn.
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from sonarset.errors import GridMismatchError
from sonarset.models.echopt.config import EchoPTConfig
from sonarset.models.flow import arc_motion, sampling_grid, source_points

# Command ranges (m/s, rad/s): inputs are scaled to [-1, 1]. The simulator's limits (RobotRig's
# defaults) when written, but fixed here, not read from a rig: trained weights expect these scales.
V_SCALE, W_SCALE = 0.3, 1.0
# The geometry branch (config.geometry_channels): its frame filters' size (range x azimuth pixels, the
# reach of a one-step warp's error on the default grid), the least width of its per-pixel MLP (never
# narrower than its output), and its inputs:
# sin and cos of the azimuth, the range, the newest command (v, omega) and the warp's shift (range, azimuth).
GEOMETRY_KERNEL = (7, 5)
GEOMETRY_HIDDEN = 16
N_GEOMETRY = 7
GEOMETRY_SHIFT_SCALE = 4.0  # pixels: a one-step shift is a few pixels; scaled to about [-1, 1]
GEOMETRY_PREFIX = "geo_"  # the branch's parameter names start with it (a fine-tune adds or trains just those)


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
        if cfg.geometry_channels:
            g = cfg.geometry_channels
            self.geo_filters = nn.Conv2d(cfg.n_in, g, GEOMETRY_KERNEL, padding="same")
            hidden = max(GEOMETRY_HIDDEN, g)
            self.geo_weights = nn.Sequential(nn.Conv2d(N_GEOMETRY, hidden, 1), GELU(), nn.Conv2d(hidden, g, 1))
        self.register_buffer("cmd_scale", torch.tensor([1 / V_SCALE, 1 / W_SCALE] * (cfg.n_in + 1)), persistent=False)
        self._register_grid(cfg)
        self.apply(self._init)
        nn.init.normal_(self.pos, std=0.02)
        if cfg.prior != "none":  # an untrained model is exactly its prior
            nn.init.zeros_(self.head[-1].weight)
            nn.init.zeros_(self.head[-1].bias)
        if cfg.geometry_channels:  # the branch starts at zero: added to a trained model, it changes nothing yet
            nn.init.zeros_(self.geo_weights[-1].weight)
            nn.init.zeros_(self.geo_weights[-1].bias)

    def _register_grid(self, cfg) -> None:
        """The pixel centres of ``cfg``'s grid (range [m], azimuth [rad]), which the flow prior and
        :meth:`align` sample at. ``cfg``: any config with the grid's sizes and edges (the reference
        models of models/zoo/ share this plumbing)."""
        (r0, r1), (a0, a1) = cfg.range_edges, cfg.azimuth_edges
        dr, da = (r1 - r0) / cfg.n_range, (a1 - a0) / cfg.n_azimuth
        self.register_buffer("r_c", r0 + (torch.arange(cfg.n_range, dtype=torch.float64) + 0.5) * dr, persistent=False)
        self.register_buffer("th_c", a0 + (torch.arange(cfg.n_azimuth, dtype=torch.float64) + 0.5) * da, persistent=False)
        # the first centre (as float32) and the step, as Python numbers: a graph export (ONNX) must not
        # read them out of tensors
        self._pixel_steps = tuple((float(c[0].float()), float(c[1] - c[0]) if len(c) > 1 else step)
                                  for c, step in ((self.r_c, dr), (self.th_c, da)))

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
        last = frames[:, -1]
        # where the newest command moves each pixel from: the flow prior (the aligned newest frame) and
        # the geometry branch both need it, computed once
        uses_source = cfg.prior == "flow" or cfg.inputs == "aligned" or cfg.geometry_channels
        newest = self._source(self._centres(), commands[:, -1]) if uses_source else None
        if cfg.inputs == "aligned":
            frames = self.align(frames, commands, newest)
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
        if cfg.geometry_channels:
            out = out + (self.geo_weights(self.geometry(commands[:, -1], newest)) * self.geo_filters(frames)).sum(1)
        if cfg.prior == "none":
            return out
        if cfg.prior == "last":
            return out + last
        # with aligned inputs the last one is the flow prior already
        return out + (frames[:, -1] if cfg.inputs == "aligned" else self._sample(last, *newest))

    def flow_prior(self, last: torch.Tensor, command: torch.Tensor) -> torch.Tensor:
        """The acoustic-flow warp of ``last`` (B, R, A) under ``command`` (B, 2): each pixel of the next
        frame, moved back along the robot's arc over dt (sensor ``sensor_offset`` ahead of the axle;
        models/flow.py), sampled bilinearly (edge values outside the field of view), as
        ``baselines.AcousticFlow``. The sampling is this model's own: its pixel constants are Python
        numbers, which a graph export (ONNX) needs."""
        return self._sample(last, *self._source(self._centres(), command))

    def geometry(self, command: torch.Tensor, source: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """The geometry branch's per-pixel inputs (B, N_GEOMETRY, R, A) for the newest ``command`` (B, 2):
        the pixel's sine and cosine of azimuth and its range (-1 at the grid's first range, 1 at its
        last), the command scaled as the other branches see it, and how far the command's warp moves
        the pixel's source (range and azimuth pixels, / GEOMETRY_SHIFT_SCALE). ``source``: that source
        (:meth:`_source` of the pixel centres), when the caller has it already."""
        cfg = self.cfg
        R, A, B = cfg.n_range, cfg.n_azimuth, command.shape[0]
        r, th = self._centres()
        r_src, th_src = source if source is not None else self._source((r, th), command)
        (_, r_step), (_, th_step) = self._pixel_steps
        # a source behind the sensor (atan2 near +-pi) is no shift the filters can use: clamped
        shift = torch.stack([(r_src - r) / r_step, (th_src - th) / th_step], -1)
        shift = shift.clamp(-8 * GEOMETRY_SHIFT_SCALE, 8 * GEOMETRY_SHIFT_SCALE) / GEOMETRY_SHIFT_SCALE
        r0, r1 = cfg.range_edges
        pos = torch.stack([torch.sin(th).expand(1, R, A), torch.cos(th).expand(1, R, A),
                           ((r - r0) / (r1 - r0) * 2 - 1).expand(1, R, A)], -1)
        cmd = (command.float() * self.cmd_scale[:2])[:, None, None, :]
        # built as (B, R, A, channels) and viewed as (B, channels, R, A): channels-last, the layout the
        # 1 x 1 convolutions run fastest on (3x against a contiguous NCHW input)
        return torch.cat([pos.expand(B, R, A, 3), cmd.expand(B, R, A, 2), shift], -1).permute(0, 3, 1, 2)

    def align(self, frames: torch.Tensor, commands: torch.Tensor,
              newest: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """Every frame of ``frames`` (B, n_in, R, A) warped to the pose of the frame to predict: the
        predicted frame's pixels are moved back along the window's commands, newest first
        (``commands[:, k]`` moves the robot from frame k - 1 to frame k), and each frame is sampled
        where they were when it was taken. The last one is :meth:`flow_prior`'s image, the older
        ones its chain over more commands (one bilinear sampling each, no accumulated blur).
        ``newest``: the newest command's :meth:`_source` of the pixel centres, when the caller has it."""
        n_in = frames.shape[1]
        points = self._centres()
        newest_first = []
        for k in range(n_in - 1, -1, -1):
            points = newest if k == n_in - 1 and newest is not None else self._source(points, commands[:, k + 1])
            newest_first.append(self._sample(frames[:, k], *points))
        return torch.stack(newest_first[::-1], 1)

    def _centres(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The pixel centres' range (1, R, 1) and azimuth (1, 1, A), float32."""
        return self.r_c.float()[None, :, None], self.th_c.float()[None, None, :]

    def _source(self, points: tuple[torch.Tensor, torch.Tensor], command: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(range, azimuth) in the previous sensor frame of ``points`` (range, azimuth) after ``command``."""
        xo, yo = self._step_back(*points, command)
        return torch.hypot(xo, yo), torch.atan2(yo, xo)  # ONNX has no hypot: models/echopt/onnx_export.py translates it

    def _step_back(self, r: torch.Tensor, th: torch.Tensor, command: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(x, y) in the previous sensor frame of the points at range ``r``, azimuth ``th`` (float32,
        broadcasting to (B, R, A)) after ``command`` (B, 2) over one frame interval."""
        cmd = command.double()
        motion = arc_motion(torch, cmd[:, 0], cmd[:, 1], self.cfg.dt)  # in float64, then the pixels in float32
        return source_points(torch, r, th, tuple(t.float()[:, None, None] for t in motion), self.cfg.sensor_offset)

    def _sample(self, image: torch.Tensor, r: torch.Tensor, th: torch.Tensor) -> torch.Tensor:
        """``image`` (B, R, A) sampled bilinearly at the points (range ``r``, azimuth ``th``) of its
        sensor frame, edge values outside the field of view."""
        R, A = self.cfg.n_range, self.cfg.n_azimuth
        (r_first, r_step), (th_first, th_step) = self._pixel_steps
        ir = (r - r_first) / r_step
        ia = (th - th_first) / th_step
        B = image.shape[0]
        grid = sampling_grid((2 * ia / max(A - 1, 1) - 1).expand(B, R, A), (2 * ir / max(R - 1, 1) - 1).expand(B, R, A))
        return F.grid_sample(image[:, None].float(), grid.to(image.device), mode="bilinear", padding_mode="border",
                             align_corners=True)[:, 0].to(image.dtype)
