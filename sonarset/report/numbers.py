"""How reports write numbers: p-values, horizon names and JSON-safe floats, the same in every report."""

from __future__ import annotations

import math

import numpy as np


def format_p(p: float | None) -> str:
    """A p-value for a table: 3 decimals, scientific below 1e-3, 'n/a' when there is none."""
    if p is None or not math.isfinite(p):
        return "n/a"
    return "< 1e-300" if p < 1e-300 else f"{p:.1e}" if p < 1e-3 else f"{p:.3f}"


def format_value(x: float | None, spec: str, why: str = "n/a") -> str:
    """``x`` as ``spec`` formats it (``"+.4f"``), or ``why``, in words, where it is undefined (None,
    NaN, infinite): a report never prints nan."""
    if x is None or not math.isfinite(x):
        return why
    return format(x, spec)


def format_interval(low: float | None, high: float | None, spec: str, why: str = "n/a") -> str:
    """``[low, high]`` as ``spec`` formats them, or ``why`` where either is undefined."""
    if low is None or high is None or not (math.isfinite(low) and math.isfinite(high)):
        return why
    return f"[{format(low, spec)}, {format(high, spec)}]"


def horizon_name(h: int) -> str:
    """'one-shot' for one step ahead, 'AR-h' for an auto-regressive rollout of h steps."""
    return "one-shot" if h == 1 else f"AR-{h}"


def finite_or_none(x):
    """JSON-safe floats, recursively through dicts, lists and tuples: NaN and infinities become
    null (JSON has no NaN); NumPy scalars become Python numbers."""
    if isinstance(x, dict):
        return {k: finite_or_none(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [finite_or_none(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x
