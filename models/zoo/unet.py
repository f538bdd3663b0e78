"""A U-Net that corrects the acoustic-flow warp of the last frame: the reference method of
nowcasting by image-to-image regression.

Ronneberger, Fischer & Brox 2015, "U-Net: convolutional networks for biomedical image
segmentation", MICCAI: an encoder of convolutions and max-pooling, a decoder that upsamples and
concatenates the encoder's features of the same scale. Used for forecasting as RainNet (Ayzel,
Scheffer & Heistermann 2020, "RainNet v1.0: a convolutional neural network for radar-based
precipitation nowcasting", Geosci. Model Dev.): the recent frames in, the next frame out, two 3 x 3
convolutions per level, five levels, bilinear upsampling.

Here the input is the n_in frames (as measured, or each registered to the predicted frame's pose:
``inputs="aligned"``), the flow warp of the last frame, and the window's n_in + 1 commands tiled
into constant channels (Finn et al. 2016's action tiling: models/zoo/common.py); the output is a
residual added to the prior (default: that same flow warp), its last layer starting at zero so the
untrained model is exactly the prior.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from sonarset.models.zoo.common import ConvAct, Up, ZooConfig, ZooModel, command_planes, zero_init


@dataclass(frozen=True)
class UNetConfig(ZooConfig):
    channels: tuple[int, ...] = (8, 16, 32, 64, 128)  # per level, full resolution first; each further one halves it


PRESETS: dict[str, dict] = {
    # 0.49 M parameters, 1.5 GFLOP per training sample (forward and backward, one step) on the default
    # grid; EchoPT-small: 0.62 M, 1.06 GFLOP (bench/bench_zoo.py)
    "small": {},
    "tiny": dict(channels=(4, 8, 16)),
}


class UNet(ZooModel):
    kind = "unet"
    title = "U-Net"

    def __init__(self, cfg: UNetConfig):
        super().__init__(cfg)
        ch = cfg.channels
        cin = cfg.n_in + 1 + 2 * (cfg.n_in + 1)  # frames, flow warp, commands
        self.down = nn.ModuleList(nn.Sequential(ConvAct(a, b), ConvAct(b, b)) for a, b in zip((cin, *ch), ch))
        self.up = nn.ModuleList(Up(deep, skip, skip, n_convs=2) for deep, skip in zip(ch[:0:-1], ch[-2::-1]))
        self.head = nn.Conv2d(ch[0], 1, 1)
        if cfg.prior != "none":
            zero_init(self.head)

    def forward(self, frames: torch.Tensor, commands: torch.Tensor) -> torch.Tensor:
        """frames (B, n_in, R, A) in [0, 1]; commands (B, n_in + 1, 2) in m/s, rad/s -> (B, R, A)."""
        n_in = self.cfg.n_in
        frames, prior = self.inputs_and_prior(frames, commands)
        # the network always sees the flow warp, whatever it corrects
        if self.cfg.prior == "flow":
            warp = prior
        elif self.cfg.inputs == "aligned":  # the aligned last frame is its warp
            warp = frames[:, -1]
        else:
            warp = self.flow_prior(frames[:, -1], commands[:, n_in])
        B, _, R, A = frames.shape
        cmds = self.scaled(commands[:, :n_in + 1]).reshape(B, -1)
        x = torch.cat([frames, warp[:, None].to(frames.dtype), command_planes(cmds, (R, A)).to(frames.dtype)], 1)
        skips = []
        for i, level in enumerate(self.down):
            if i:
                x = F.max_pool2d(x, 2, ceil_mode=True)
            x = level(x)
            skips.append(x)
        for up, skip in zip(self.up, reversed(skips[:-1])):
            x = up(x, skip)
        out = self.head(x)[:, 0]
        return out if prior is None else out + prior
