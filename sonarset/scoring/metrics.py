"""Image metrics of the EchoPT paper (docs/metrics.md), vectorised over any leading batch axes.

All functions take predicted and measured images with the image in the last two axes and return
one value per image.
"""

from __future__ import annotations

import numpy as np


def _flat(x: np.ndarray) -> np.ndarray:
    """A float64 copy of ``x`` with each image flattened (a copy: callers may change it)."""
    x = np.array(x, dtype=np.float64)
    return x.reshape(*x.shape[:-2], -1)


def cc(pred: np.ndarray, meas: np.ndarray) -> np.ndarray:
    """2D Pearson correlation coefficient (MATLAB ``corr2``). NaN where an image is constant."""
    return cc_and_nrmsd(pred, meas)[0]


def nrmsd(pred: np.ndarray, meas: np.ndarray) -> np.ndarray:
    """Normalised root-mean-square difference ||p - m||_2 / ||m||_2 over all pixels."""
    return cc_and_nrmsd(pred, meas)[1]


def cc_and_nrmsd(pred: np.ndarray, meas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``cc`` and ``nrmsd`` from one pass over the images (evaluation scores every prediction
    with both): both follow from the means and the centred second moments, in float64."""
    p, m = _flat(pred), _flat(meas)
    n = p.shape[-1]
    with np.errstate(invalid="ignore", over="ignore"):  # a forecast of inf or NaN pixels is undefined, not a warning
        mean_p, mean_m = p.mean(-1), m.mean(-1)
        p -= mean_p[..., None]  # in place: _flat made copies
        m -= mean_m[..., None]
        pp, mm, pm = (np.einsum("...i,...i->...", a, b) for a, b in ((p, p), (m, m), (p, m)))
        # ||p - m||^2 = |p_c - m_c|^2 + n (mean_p - mean_m)^2: exact algebra, and float64 keeps the
        # cancellation of near-identical images (NRMSD ~0.03) at ~1e-13
        diff2 = np.maximum(pp + mm - 2 * pm + n * (mean_p - mean_m) ** 2, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return pm / np.sqrt(pp * mm), np.sqrt(diff2 / (mm + n * mean_m ** 2))


def slip_error(pred: np.ndarray, meas: np.ndarray) -> np.ndarray:
    """The paper's slip signal: eps = ||p - m||_2 / sqrt(|CC(p, m)|)."""
    p, m = _flat(pred), _flat(meas)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.linalg.norm(p - m, axis=-1) / np.sqrt(np.abs(cc(pred, meas)))
