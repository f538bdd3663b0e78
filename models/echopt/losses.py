"""The image losses of training: per-pixel terms and their weighted sums (``--loss``)."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from sonarset.errors import SonarSetError

from sonarset.models.eval.evaluate import ECHO_FLOOR

LOSSES = ("mse", "l1", "gdl", "cc", "w1", "energy")


def parse_loss(spec: str) -> dict[str, float]:
    """``"mse"`` -> {"mse": 1}; ``"mse=1,gdl=0.5"`` -> {"mse": 1.0, "gdl": 0.5}."""
    terms: dict[str, float] = {}
    for part in spec.split(","):
        name, _, w = part.strip().partition("=")
        if name not in LOSSES:
            raise SonarSetError(f"--loss {spec!r}: unknown term {name!r}; choose from {', '.join(LOSSES)}")
        try:
            terms[name] = float(w) if w else 1.0
        except ValueError:
            raise SonarSetError(f"--loss {spec!r}: weight of {name!r} is not a number") from None
    return terms


def value_distribution_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """1-D Wasserstein distance between each forecast's and its target's pixel values (mean absolute
    difference of the sorted values), averaged over the batch.

    Blind to where the energy is (MSE's job), it sees only how it is distributed: the conditional
    mean of an uncertain echo position, which MSE converges to, spreads a bright echo into a wider,
    dimmer one, and so has too many middling pixels and too few bright ones. Penalising that keeps a
    rollout's peak and echo energy, which is what fades otherwise.
    """
    return (pred.flatten(1).sort(dim=1).values - target.flatten(1).sort(dim=1).values).abs().mean()


def echo_energy_loss(pred: torch.Tensor, target: torch.Tensor, floor: float = ECHO_FLOOR) -> torch.Tensor:
    """The batch's relative echo-energy deficit or excess: |sum E(pred) - sum E(target)| / sum E(target),
    with E an image's echo energy, the sum of its pixels above ``floor`` (the quantity of the "no
    fade" check, ``models.evaluate.peak_and_energy``).

    A forecast cannot know which echoes will enter the field of view during a rollout; any loss
    that scores each pixel draws such an echo as faint as its probability, so a deterministic model
    loses a little energy at every step. This term calibrates the total over the batch, not any
    one image or pixel. Its gradient reaches only pixels above the floor, so it brightens echoes the
    model already draws and never lifts the background into new ones.
    """
    e_pred = (pred * (pred > floor)).sum()
    e_target = (target * (target > floor)).sum()
    return (e_pred - e_target).abs() / e_target.clamp_min(1e-6)


def image_loss(pred: torch.Tensor, target: torch.Tensor, terms: dict[str, float]) -> torch.Tensor:
    """Weighted sum of per-pixel losses over (B, R, A) images."""
    total = pred.new_zeros(())
    for name, w in terms.items():
        if name == "mse":
            v = F.mse_loss(pred, target)
        elif name == "l1":
            v = F.l1_loss(pred, target)
        elif name == "gdl":  # image-gradient difference (Mathieu et al. 2016): keeps edges sharp
            v = (F.l1_loss(pred.diff(dim=-1), target.diff(dim=-1)) + F.l1_loss(pred.diff(dim=-2), target.diff(dim=-2))) / 2
        elif name == "w1":
            v = value_distribution_loss(pred, target)
        elif name == "energy":
            v = echo_energy_loss(pred, target)
        else:  # 1 - CC (the paper's metric) per image
            p = pred.flatten(1) - pred.flatten(1).mean(1, keepdim=True)
            t = target.flatten(1) - target.flatten(1).mean(1, keepdim=True)
            v = 1 - ((p * t).sum(1) / (p.norm(dim=1) * t.norm(dim=1) + 1e-8)).mean()
        total = total + w * v
    return total
