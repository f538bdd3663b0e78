"""Image metrics of the EchoPT paper (DESIGN.md §5), vectorised over any leading batch axes.

All functions take predicted and measured images with the image in the last two axes and return
one value per image.
"""

from __future__ import annotations

import numpy as np


def _flat(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    return x.reshape(*x.shape[:-2], -1)


def cc(pred: np.ndarray, meas: np.ndarray) -> np.ndarray:
    """2D Pearson correlation coefficient (MATLAB ``corr2``). NaN where an image is constant."""
    p, m = _flat(pred), _flat(meas)
    p = p - p.mean(-1, keepdims=True)
    m = m - m.mean(-1, keepdims=True)
    den = np.sqrt((p * p).sum(-1) * (m * m).sum(-1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return (p * m).sum(-1) / den


def nrmsd(pred: np.ndarray, meas: np.ndarray) -> np.ndarray:
    """Normalised root-mean-square difference ||p - m||_2 / ||m||_2 over all pixels."""
    p, m = _flat(pred), _flat(meas)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.linalg.norm(p - m, axis=-1) / np.linalg.norm(m, axis=-1)


def slip_error(pred: np.ndarray, meas: np.ndarray) -> np.ndarray:
    """The paper's slip signal: eps = ||p - m||_2 / sqrt(|CC(p, m)|)."""
    p, m = _flat(pred), _flat(meas)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.linalg.norm(p - m, axis=-1) / np.sqrt(np.abs(cc(pred, meas)))
