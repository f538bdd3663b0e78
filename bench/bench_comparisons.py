"""The cost of one paired comparison on a few windows: scipy's Wilcoxon against sonarset's.

    python bench/bench_comparisons.py [--cases 200] [--rounds 3]

Per-window scores of a few windows hold ties (echo F1 of a handful of echoes is 0, 1/2, 2/3, 1) and
zeros. There scipy's ``wilcoxon`` runs an exact permutation test over all 2**n signs (n <= 13),
calling its statistic once per sign pattern; ``sonarset.scoring.stats.wilcoxon_p`` runs the same
test with a vectorised statistic. Each case's two p-values must be equal to the last bit; the
figures are the mean time per test (the best of ``--rounds`` rounds) and the ratio. An evaluation
of four predictors at four horizons makes 168 such tests (``sonarset eval --samples 10``, the
test suite's and the guides' quick runs).
"""

from __future__ import annotations

import argparse
import platform

import numpy as np
from scipy import stats

from bench_scoring import per_image_ms

from sonarset.scoring.stats import wilcoxon_p


def cases(count: int, seed: int = 0) -> list[np.ndarray]:
    """Differences of two models' per-window echo F1 on 5 to 13 windows: fractions of few echoes."""
    rng = np.random.default_rng(seed)
    shares = np.array([0, 1 / 3, 1 / 2, 2 / 3, 3 / 4, 4 / 5, 1])
    out = []
    while len(out) < count:
        n = int(rng.integers(5, 14))
        d = rng.choice(shares, n) - rng.choice(shares, n)
        if np.any(d != 0):
            out.append(d)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, {platform.python_version()}, "
          f"scipy {__import__('scipy').__version__}")
    data = cases(args.cases)
    unequal = [d for d in data if wilcoxon_p(d) != stats.wilcoxon(d).pvalue]
    assert not unequal, f"p differs from scipy's on {len(unequal)} cases, e.g. {unequal[0]}"
    scipy_ms = per_image_ms(lambda d: stats.wilcoxon(d).pvalue, data, len(data), args.rounds)  # per test
    ours_ms = per_image_ms(wilcoxon_p, data, len(data), args.rounds)
    print(f"{len(data)} cases of 5-13 windows, every p equal to scipy's")
    print(f"scipy.stats.wilcoxon: {scipy_ms:.2f} ms per test ({168 * scipy_ms / 1e3:.1f} s for 168 tests)")
    print(f"wilcoxon_p:           {ours_ms:.2f} ms per test ({168 * ours_ms / 1e3:.2f} s for 168 tests), "
          f"{scipy_ms / ours_ms:.1f}x faster")


if __name__ == "__main__":
    main()
