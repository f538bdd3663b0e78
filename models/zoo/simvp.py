"""SimVP, action-conditioned: the recurrence-free reference method of video prediction.

Gao, Tan, Wu & Li 2022, "SimVP: simpler yet better video prediction", CVPR: a convolutional encoder
applied to every input frame, a translator over the frames' features stacked along the channels
(time x channels), and a decoder per output frame, all horizons from one forward pass. The
translator is SimVP v2's gated spatiotemporal attention (gSTA: Tan, Gao, Li & Li 2022, "SimVP:
towards simple yet powerful spatiotemporal predictive learning", arXiv:2211.12509), the large-kernel
attention that TAU (Tan et al. 2023, "Temporal attention unit", CVPR) also builds on: a depth-wise
5 x 5 convolution, a depth-wise 7 x 7 one dilated by 3 (a 21 x 21 reach), a gate, and a depth-wise
convolutional MLP. Normalisation is per sample (GroupNorm with one group) where SimVP uses batch
norm, so that a window's forecast never depends on the other windows of its batch.

Commands enter as channels: the n_in + K commands of a K-step forecast (K up to ``max_horizon``,
the protocol's longest horizon) are tiled into the translator's input. Each output step j is
decoded from its own slot, whose input holds the frames' features, the commands up to the one that
reaches step j (the later ones zero) and a one-hot of j; the slots run as one batch through the
translator and the decoder. So a forecast is causal in its commands: step j never sees a later
command, and a forecast of any length begins with the one-step forecast, which is what the
protocol's one-shot scores and what training at one length and evaluating at another relies on.

Each step's output corrects its prior: the flow baseline's own rollout of the last frame along the
commands (``prior="flow"``, the default), the last frame (``last``), or nothing (``none``); the
output layer starts at zero, so an untrained SimVP forecasts exactly its prior.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn

from sonarset.models.echopt.config import ConfigError
from sonarset.models.echopt.model import GELU
from sonarset.models.zoo.common import ConvAct, Up, ZooConfig, ZooModel, command_planes, conv, zero_init

#: The protocol's longest horizon (AR-10): a forecast of up to this many steps is one pass.
MAX_HORIZON = 10


@dataclass(frozen=True)
class SimVPConfig(ZooConfig):
    # the first at full resolution, each further one halves it: the translator at 1/8 (25 x 12 on the
    # default grid), where its 21 x 21 reach spans the field of view and its weights cost least
    enc_channels: tuple[int, ...] = (8, 16, 32, 64)
    hidden: int = 96  # the translator's width
    n_blocks: int = 2  # gSTA blocks
    mlp_ratio: int = 4  # of the blocks' feed-forward
    max_horizon: int = MAX_HORIZON  # the most steps one forward pass forecasts

    def check(self) -> None:
        super().check()
        if len(self.enc_channels) < 2:
            raise ConfigError("enc_channels", f"enc_channels needs at least 2 layers, got {self.enc_channels!r}")


PRESETS: dict[str, dict] = {
    # 0.34 M parameters, 1.4 GFLOP per training sample (forward and backward, one step) on the default
    # grid; EchoPT-small: 0.62 M, 1.06 GFLOP (bench/bench_zoo.py)
    "small": {},
    "tiny": dict(enc_channels=(4, 8), hidden=8, n_blocks=1, mlp_ratio=2),
}


class LargeKernelGate(nn.Module):
    """gSTA's spatial gating: a 21 x 21 depth-wise reach decomposed into a 5 x 5 and a 7 x 7 dilated
    by 3 (Guo et al. 2022's large-kernel attention), then a 1 x 1 convolution into a value and a
    sigmoid gate."""

    def __init__(self, dim: int):
        super().__init__()
        self.local = nn.Conv2d(dim, dim, 5, padding=2, groups=dim)
        self.wide = nn.Conv2d(dim, dim, 7, padding=9, dilation=3, groups=dim)
        self.mix = nn.Conv2d(dim, 2 * dim, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        value, gate = self.mix(self.wide(self.local(x))).chunk(2, 1)
        return torch.sigmoid(gate) * value


class GSTABlock(nn.Module):
    """SimVP v2's gSTA block: x + s1 attn(norm x), then x + s2 mlp(norm x), the scales s starting at 0.01."""

    def __init__(self, dim: int, mlp_ratio: int):
        super().__init__()
        self.norm1 = nn.GroupNorm(1, dim)
        self.attn = nn.Sequential(nn.Conv2d(dim, dim, 1), GELU(), LargeKernelGate(dim), nn.Conv2d(dim, dim, 1))
        self.norm2 = nn.GroupNorm(1, dim)
        wide = dim * mlp_ratio
        self.mlp = nn.Sequential(nn.Conv2d(dim, wide, 1), nn.Conv2d(wide, wide, 3, padding=1, groups=wide), GELU(),
                                 nn.Conv2d(wide, dim, 1))
        self.scale1 = nn.Parameter(torch.full((dim, 1, 1), 0.01))
        self.scale2 = nn.Parameter(torch.full((dim, 1, 1), 0.01))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # OpenSTL's attention also adds its own input back; beside the block's residual that is left out
        x = x + self.scale1 * self.attn(self.norm1(x))
        return x + self.scale2 * self.mlp(self.norm2(x))


class SimVP(ZooModel):
    kind = "simvp"
    title = "SimVP"

    def __init__(self, cfg: SimVPConfig):
        super().__init__(cfg)
        enc, K = cfg.enc_channels, cfg.max_horizon
        self.encoder = nn.ModuleList(ConvAct(cin, cout, 3, stride=1 if i == 0 else 2)
                                     for i, (cin, cout) in enumerate(zip((1, *enc), enc)))
        # a slot's input: the n_in frames' features, 2 (n_in + K) command channels, a one-hot of its step
        slot_in = cfg.n_in * enc[-1] + 2 * (cfg.n_in + K) + K
        self.translator = nn.Sequential(nn.Conv2d(slot_in, cfg.hidden, 1),
                                        *(GSTABlock(cfg.hidden, cfg.mlp_ratio) for _ in range(cfg.n_blocks)),
                                        nn.Conv2d(cfg.hidden, enc[-1], 1))
        # up through the last frame's encoder features; at full resolution its skip also holds the step's prior
        skips = [*enc[:-1]]
        skips[0] += 1
        ups, cin = [], enc[-1]
        for skip, cout in zip(reversed(skips), reversed(enc[:-1])):
            ups.append(Up(cin, skip, cout))
            cin = cout
        self.decoder = nn.ModuleList(ups)
        self.head = conv(enc[0], 1)
        if cfg.prior != "none":
            zero_init(self.head)

    @property
    def max_horizon(self) -> int:
        return self.cfg.max_horizon

    def forecast(self, frames: torch.Tensor, commands: torch.Tensor, k: int) -> torch.Tensor:
        """frames (B, n_in, R, A) in [0, 1]; commands (B, n_in + k, 2) -> the next ``k`` frames (B, k, R, A),
        1 <= k <= max_horizon, from one forward pass."""
        return self(frames, commands, k)

    def forward(self, frames: torch.Tensor, commands: torch.Tensor, k: int | None = None) -> torch.Tensor:
        """frames (B, n_in, R, A), commands (B, n_in + 1, 2) -> the next frame (B, R, A); with ``k``,
        commands (B, n_in + k, 2) -> the next k frames (B, k, R, A) (:meth:`forecast`; an argument of
        the forward pass, so that a DistributedDataParallel wrapper runs it)."""
        cfg = self.cfg
        steps, n_in = self.forecast_steps(commands, k), cfg.n_in
        frames, prior = self.inputs_and_prior(frames, commands)
        B, _, R, A = frames.shape
        x = frames.reshape(B * n_in, 1, R, A)
        feats = []
        for layer in self.encoder:
            x = layer(x)
            feats.append(x)
        h, w = x.shape[-2:]
        z = x.reshape(B, n_in * x.shape[1], h, w)
        slots = torch.cat([z[:, None].expand(B, steps, *z.shape[1:]).reshape(B * steps, *z.shape[1:]),
                           command_planes(self._slot_commands(commands, steps), (h, w)).to(z.dtype)], 1)
        y = self.translator(slots)
        priors = self._priors(frames, commands, prior, steps)  # (B, steps, R, A)
        # the last frame's features, once per slot; at full resolution beside the step's prior
        skips = [f.reshape(B, n_in, *f.shape[1:])[:, -1] for f in feats[:-1]]
        skips = [s[:, None].expand(B, steps, *s.shape[1:]).reshape(B * steps, *s.shape[1:]) for s in skips]
        skips[0] = torch.cat([skips[0], priors.reshape(B * steps, 1, R, A).to(skips[0].dtype)], 1)
        for up, skip in zip(self.decoder, reversed(skips)):
            y = up(y, skip)
        out = self.head(y).reshape(B, steps, R, A)
        if prior is not None:
            out = out + priors
        return out[:, 0] if k is None else out

    def _slot_commands(self, commands: torch.Tensor, steps: int) -> torch.Tensor:
        """(B x steps, 2 (n_in + K) + K): slot j's scaled commands up to ``n_in + j`` (the later ones
        and those beyond the forecast zero), then the one-hot of j."""
        cfg = self.cfg
        B, n_cmd, K = commands.shape[0], cfg.n_in + cfg.max_horizon, cfg.max_horizon
        cmds = commands.new_zeros(B, n_cmd, 2)
        cmds[:, :cfg.n_in + steps] = self.scaled(commands[:, :cfg.n_in + steps])
        index = torch.arange(n_cmd, device=commands.device)
        known = index[None] <= cfg.n_in + index[:steps, None]  # (steps, n_cmd): slot j's commands
        per_slot = (cmds[:, None] * known[None, :, :, None]).flatten(2)  # (B, steps, 2 n_cmd)
        one_hot = torch.eye(K, device=commands.device, dtype=per_slot.dtype)[:steps].expand(B, steps, K)
        return torch.cat([per_slot, one_hot], -1).reshape(B * steps, -1)

    def _priors(self, frames: torch.Tensor, commands: torch.Tensor, prior: torch.Tensor | None,
                steps: int) -> torch.Tensor:
        """Each step's prior (B, steps, R, A): the flow baseline's rollout of the last frame, the last
        frame, or (no prior) the last input frame, which the decoder then sees in its place."""
        step = frames[:, -1] if prior is None else prior
        out = [step]
        for j in range(1, steps):
            if prior is not None:
                step = self.next_prior(step, commands[:, self.cfg.n_in + j])
            out.append(step)
        return torch.stack(out, 1)
