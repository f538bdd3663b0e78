"""ConvLSTM, action-conditioned: the recurrent reference method of video prediction.

Shi, Chen, Wang, Yeung, Wong & Woo 2015, "Convolutional LSTM network: a machine learning approach
for precipitation nowcasting", NeurIPS: an LSTM whose state is an image and whose gates are
convolutions, so that it learns motion as local transitions. Gates are one convolution over the
input and the hidden state (no peephole terms, as in most later uses, e.g. PredRNN's baselines:
Wang et al. 2022, "PredRNN: a recurrent neural network for spatiotemporal predictive learning",
TPAMI).

Conditioned on the robot's commands as Finn, Goodfellow & Levine 2016 ("Unsupervised learning for
physical interaction through video prediction", NeurIPS) condition on actions: each step's
command is tiled into two constant channels beside that step's frame. Step t reads frame t and
``commands[:, t + 1]``, the command that moves the robot from frame t to frame t + 1, so the last
step's state holds what the next frame needs.

On a CPU's budget the recurrence runs at a low resolution: stride-2 convolutions encode each frame
(200 x 90 -> 100 x 45 -> 50 x 23 -> 25 x 12 on the default grid), the ConvLSTM stack runs there, and
a decoder brings its last state back to the grid through the last frame's encoder features
(U-Net skips) and the full-resolution input frames and prior. Its output is a correction added to
the prior (default: the acoustic-flow warp of the last frame), starting at zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn

from sonarset.models.echopt.config import ConfigError
from sonarset.models.zoo.common import ConvAct, Up, ZooConfig, ZooModel, command_planes, conv, zero_init


@dataclass(frozen=True)
class ConvLSTMConfig(ZooConfig):
    enc_channels: tuple[int, ...] = (8, 16, 32)  # one stride-2 convolution each: the recurrence at 1 / 2^len
    hidden: tuple[int, ...] = (48, 48)  # the ConvLSTM stack's state channels, bottom first
    kernel: int = 3  # the gates' convolution (odd)
    out_channels: int = 8  # the full-resolution layer before the output

    def check(self) -> None:
        super().check()
        if self.kernel % 2 == 0:
            raise ConfigError("kernel", f"kernel must be odd, got {self.kernel}")


PRESETS: dict[str, dict] = {
    # 0.32 M parameters, 1.9 GFLOP per training sample (forward and backward, one step) on the default
    # grid; EchoPT-small: 0.62 M, 1.06 GFLOP (bench/bench_zoo.py)
    "small": {},
    "tiny": dict(enc_channels=(4, 8), hidden=(8,), out_channels=4),
}


class ConvLSTMCell(nn.Module):
    """One ConvLSTM layer (Shi et al. 2015, eq. 3 without the peepholes): input, forget and output
    gates and the candidate from one convolution over [input, hidden state]."""

    def __init__(self, cin: int, hidden: int, kernel: int):
        super().__init__()
        self.hidden = hidden
        self.gates = conv(cin + hidden, 4 * hidden, kernel)

    def forward(self, x: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor] | None) -> tuple[torch.Tensor, torch.Tensor]:
        if state is None:
            h = c = x.new_zeros(x.shape[0], self.hidden, *x.shape[-2:])
        else:
            h, c = state
        i, f, o, g = self.gates(torch.cat([x, h.to(x.dtype)], 1)).chunk(4, 1)
        c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        return torch.sigmoid(o) * torch.tanh(c), c


class ConvLSTM(ZooModel):
    kind = "convlstm"
    title = "ConvLSTM"

    def __init__(self, cfg: ConvLSTMConfig):
        super().__init__(cfg)
        enc = cfg.enc_channels
        # frame + its step's command (2 tiled channels)
        self.encoder = nn.ModuleList(ConvAct(cin, cout, 3, stride=2) for cin, cout in zip((3, *enc), enc))
        self.cells = nn.ModuleList(ConvLSTMCell(cin, h, cfg.kernel) for cin, h in zip((enc[-1], *cfg.hidden), cfg.hidden))
        # back up through the last frame's encoder features, then to the grid beside the frames and the prior
        ups, cin = [], cfg.hidden[-1]
        for skip in reversed(enc[:-1]):
            ups.append(Up(cin, skip, skip))
            cin = skip
        self.decoder = nn.ModuleList(ups)
        self.full = Up(cin, cfg.n_in + 1, cfg.out_channels)
        self.head = conv(cfg.out_channels, 1)
        if cfg.prior != "none":
            zero_init(self.head)

    def forward(self, frames: torch.Tensor, commands: torch.Tensor) -> torch.Tensor:
        """frames (B, n_in, R, A) in [0, 1]; commands (B, n_in + 1, 2) in m/s, rad/s -> (B, R, A)."""
        frames, prior = self.inputs_and_prior(frames, commands)
        B, n_in, R, A = frames.shape
        cmds = self.scaled(commands)
        states: list = [None] * len(self.cells)
        for t in range(n_in):
            x = torch.cat([frames[:, t:t + 1], command_planes(cmds[:, t + 1], (R, A)).to(frames.dtype)], 1)
            skips = []
            for layer in self.encoder:
                x = layer(x)
                skips.append(x)
            for i, cell in enumerate(self.cells):
                states[i] = cell(x, states[i])
                x = states[i][0]
        # the last step's encoder features are the decoder's skips: where the newest echoes are
        for up, skip in zip(self.decoder, reversed(skips[:-1])):
            x = up(x, skip)
        # without a prior, its channel holds the last frame again
        context = torch.cat([frames, (frames[:, -1] if prior is None else prior)[:, None].to(frames.dtype)], 1)
        out = self.head(self.full(x, context))[:, 0]
        return out if prior is None else out + prior
