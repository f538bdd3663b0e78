"""Grow a trained EchoWarp into a wider one that computes the same function (Net2WiderNet: Chen,
Goodfellow & Shlens 2016, "Net2Net: accelerating learning via knowledge transfer", ICLR).

Each new channel of a widened layer copies one of the layer's old channels (its incoming weights
and bias); the next layers read the copies of an old channel with weights that sum to what they
gave that channel. The split is random and unequal, so that the copies receive different gradients
and part ways in training (an equal split keeps them twins for ever), while the sum keeps the
function: the widened model starts where the trained one ended, up to float rounding. Bilinear
resizes and GELU act channel by channel, so they commute with the copying.

``sonarset train`` uses it when ``init`` names a narrower EchoWarp than the run's preset
(models/echopt/train_model.py): a fine-tune that only adds channels to the U-Net.
"""

from __future__ import annotations

import torch
import torch.nn as nn

#: The config fields a fine-tune may grow (the U-Net's widths), each level at least as wide as before.
WIDENABLE_FIELDS = ("channels",)


def can_widen(old_cfg, new_cfg) -> bool:
    """Whether ``new_cfg`` is ``old_cfg`` with each U-Net level as wide or wider."""
    return (len(new_cfg.channels) == len(old_cfg.channels)
            and all(n >= o for n, o in zip(new_cfg.channels, old_cfg.channels)))


def _copies(old: int, new: int, g: torch.Generator) -> torch.Tensor:
    """Which old channel each of ``new`` channels copies: the old ones first, then random picks."""
    return torch.cat([torch.arange(old), torch.randint(old, (new - old,), generator=g)])


def _shares(source: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """Per new channel, its share of its old channel's outgoing weights: random, summing to 1 over
    the copies of each old channel (1 where a channel has no copy)."""
    raw = 0.5 + torch.rand(len(source), generator=g, dtype=torch.float64)
    total = torch.zeros(int(source.max()) + 1, dtype=torch.float64).index_add_(0, source, raw)
    return raw / total[source]


@torch.no_grad()
def widen_into(wide: nn.Module, narrow: nn.Module, seed: int = 0) -> None:
    """Write ``narrow``'s weights, widened, into ``wide`` (an EchoWarp of the same config but for wider
    ``channels``), so that ``wide`` computes ``narrow``'s function."""
    g = torch.Generator().manual_seed(seed)
    written: set[int] = set()
    n_in_features = narrow.down[0][0][0].in_channels
    identity = torch.arange(n_in_features)

    def group(old: int, new: int) -> tuple[torch.Tensor, torch.Tensor]:
        source = _copies(old, new, g)
        return source, _shares(source, g)

    def inputs(*groups: tuple[torch.Tensor, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """A concatenation's channels: each part's sources offset by the old widths before it."""
        sources, shares, offset = [], [], 0
        for source, share in groups:
            sources.append(source + offset)
            shares.append(share)
            offset += int(source.max()) + 1
        return torch.cat(sources), torch.cat(shares)

    def copy(new: nn.Conv2d, old: nn.Conv2d, into: tuple[torch.Tensor, torch.Tensor],
             out: torch.Tensor | None) -> None:
        src_in, share = into
        w = old.weight.double()[:, src_in] * share[None, :, None, None]
        rows = out if out is not None else torch.arange(old.out_channels)
        new.weight.copy_(w[rows].to(new.weight.dtype))
        new.bias.copy_(old.bias[rows])
        written.update((id(new.weight), id(new.bias)))

    plain = (identity, torch.ones(n_in_features, dtype=torch.float64))
    skips, current = [], plain
    for level_new, level_old, (c_old, c_new) in zip(wide.down, narrow.down,
                                                    zip(narrow.cfg.channels, wide.cfg.channels)):
        for layer_new, layer_old in zip(level_new, level_old):
            out = group(c_old, c_new)
            copy(layer_new[0], layer_old[0], current, out[0])
            current = out
        skips.append(current)
    for up_new, up_old, skip in zip(wide.up, narrow.up, reversed(skips[:-1])):
        c_old, c_new = up_old.convs[0][0].out_channels, up_new.convs[0][0].out_channels
        out = group(c_old, c_new)
        copy(up_new.convs[0][0], up_old.convs[0][0], inputs(current, skip), out[0])
        current = out
    copy(wide.full[0][0], narrow.full[0][0], inputs(current, plain), None)
    wide.full[1].load_state_dict(narrow.full[1].state_dict())
    wide.head.load_state_dict(narrow.head.state_dict())
    written.update(id(p) for p in (*wide.full[1].parameters(), *wide.head.parameters()))
    # a parameter this function does not know (a part added to EchoWarp later) would stay random
    left = [name for name, p in wide.named_parameters() if id(p) not in written]
    if left:
        raise ValueError(f"widening does not know the parameters {', '.join(left)}")
