"""How reports write numbers: p-values and horizon names, the same in every table."""

from __future__ import annotations

import math


def format_p(p: float | None) -> str:
    """A p-value for a table: 3 decimals, scientific below 1e-3, 'n/a' when there is none."""
    if p is None or not math.isfinite(p):
        return "n/a"
    return "< 1e-300" if p < 1e-300 else f"{p:.1e}" if p < 1e-3 else f"{p:.3f}"


def horizon_name(h: int) -> str:
    """'one-shot' for one step ahead, 'AR-h' for an auto-regressive rollout of h steps."""
    return "one-shot" if h == 1 else f"AR-{h}"
