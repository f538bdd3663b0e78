"""Statistics for comparing predictors on the same windows (scipy.stats)."""

from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass

import numpy as np
from scipy import stats


@dataclass
class Comparison:
    """Method ``a`` against ``b`` on one metric and horizon, over the same windows."""

    metric: str
    horizon: int
    a: str
    b: str
    n: int
    mean_diff: float  # mean of a - b
    ci_low: float  # bootstrap 95% CI of the mean difference
    ci_high: float
    t_two_sample_p: float  # the paper's test: two-sample (Welch) t-test, ignores the pairing
    t_paired_p: float
    wilcoxon_p: float
    p_holm: float = float("nan")  # paired t-test p, Holm-corrected over all comparisons made
    # the paired test with the windows' serial correlation in its variance (hac_t_p), and Holm of it
    t_hac_p: float = float("nan")
    p_hac_holm: float = float("nan")

    def to_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in asdict(self).items()}


def compare(a: np.ndarray, b: np.ndarray, *, metric: str, horizon: int, names: tuple[str, str],
            n_resamples: int = 2000, seed: int = 0, windows: "WindowPlaces | None" = None) -> Comparison:
    """``a`` against ``b``, per-window values of the same windows (NaN where undefined, dropped
    pairwise). With ``windows``, where each window lies, the comparison also gets ``t_hac_p``."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok], b[ok]
    d = a - b
    n = len(d)
    if n < 3 or np.all(d == d[0]):
        nan = float("nan")
        return Comparison(metric, horizon, *names, n, float(d.mean()) if n else nan, nan, nan, nan, nan, nan)
    lo, hi = bootstrap_ci(d, n_resamples, seed)
    hac = float("nan") if windows is None else hac_t_p(d, windows.frames[ok], windows.runs[ok], windows.bandwidth)
    return Comparison(metric, horizon, *names, n, float(d.mean()), lo, hi, *_pvalues(a, b, d), t_hac_p=hac)


@dataclass(frozen=True)
class WindowPlaces:
    """Where each compared window lies: its run (any label) and start frame in that run, and the
    kernel's reach in frames (:data:`HAC_SPANS` window spans)."""

    runs: np.ndarray
    frames: np.ndarray
    bandwidth: float

    @classmethod
    def of(cls, window_ids: list[tuple[str, int]], span: int) -> "WindowPlaces":
        runs = np.array([r for r, _ in window_ids], dtype=object)
        return cls(np.unique(runs, return_inverse=True)[1], np.array([k for _, k in window_ids], float),
                   float(HAC_SPANS * span))


def bootstrap_ci(x: np.ndarray, n_resamples: int = 2000, seed: int = 0) -> tuple[float, float]:
    """Bootstrap 95% CI of the mean of ``x`` (finite values): BCa, percentile where BCa
    degenerates; (mean, mean) when every value is the same; NaNs for fewer than 3 values."""
    x = np.asarray(x, float)
    if len(x) < 3:
        return float("nan"), float("nan")
    if np.ptp(x) <= 1e-12 * max(1.0, abs(float(x.mean()))):
        return float(x.mean()), float(x.mean())  # no spread to resample
    for method in ("BCa", "percentile"):  # BCa is better; it degenerates on near-constant data
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ci = stats.bootstrap((x,), np.mean, n_resamples=n_resamples, confidence_level=0.95,
                                 random_state=np.random.default_rng(seed), method=method).confidence_interval
        if np.isfinite(ci.low) and np.isfinite(ci.high):
            return float(ci.low), float(ci.high)
    return float("nan"), float("nan")


def _pvalues(a: np.ndarray, b: np.ndarray, d: np.ndarray) -> tuple[float, float, float]:
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # scipy warns on near-constant input; the p-values stand
        return (float(stats.ttest_ind(a, b, equal_var=False).pvalue), float(stats.ttest_rel(a, b).pvalue),
                _signed_rank_p(d))


def wilcoxon_p(d: np.ndarray) -> float:
    """Wilcoxon signed-rank p of paired differences ``d``; NaN for fewer than 3 or all zero (the
    test is undefined there, and scipy would raise or warn)."""
    d = np.asarray(d, float)
    return _signed_rank_p(d) if len(d) >= 3 and np.any(d != 0) else float("nan")


#: scipy's ``wilcoxon`` (1.15 on) tests up to this many differences holding ties or zeros by its
#: exact permutation test, over all 2**n signs
_PERMUTED_UP_TO = 13


def _signed_rank_p(d: np.ndarray) -> float:
    """``scipy.stats.wilcoxon(d).pvalue``, the same value. Where scipy runs its exact permutation
    test (a few windows with ties or zeros: tests, quick runs, the experiments' few runs) it calls
    the statistic once per sign pattern, 0.1-0.3 s a test; here the statistic is vectorised."""
    nonzero = d[d != 0]
    if (len(d) > _PERMUTED_UP_TO or not np.all(np.isfinite(d))  # scipy's NaN, or its own test
            or (len(nonzero) == len(d) and len(np.unique(np.abs(d))) == len(d))):
        return float(stats.wilcoxon(d).pvalue)
    # |d| and so its ranks are the same under every sign pattern; zeros rank lowest and drop out
    ranks = stats.rankdata(np.abs(d)) - (len(d) - len(nonzero))

    def rank_sum_of_positives(x: np.ndarray, axis: int = -1) -> np.ndarray:
        return np.sum(ranks * (x > 0), axis=axis)

    return float(stats.permutation_test((d,), rank_sum_of_positives, permutation_type="samples", vectorized=True,
                                        alternative="two-sided").pvalue)


def auc(pos: np.ndarray, neg: np.ndarray) -> float:
    """ROC AUC of a score separating ``pos`` from ``neg``: P(pos > neg) + P(tie) / 2 (Mann-Whitney U);
    non-finite scores are dropped, NaN when either side is left empty."""
    pos, neg = pos[np.isfinite(pos)], neg[np.isfinite(neg)]
    if len(pos) == 0 or len(neg) == 0:
        return float("nan")
    return float(stats.mannwhitneyu(pos, neg).statistic / (len(pos) * len(neg)))


def wilson_interval(k: int, n: int) -> tuple[float, float]:
    """Wilson score 95% CI of the proportion k / n; NaNs for n = 0."""
    if not n:
        return float("nan"), float("nan")
    ci = stats.binomtest(k, n).proportion_ci(method="wilson")
    return float(ci.low), float(ci.high)


def mcnemar_p(a: np.ndarray, b: np.ndarray) -> float:
    """McNemar's exact test of paired outcomes (booleans, one pair per run): a binomial test on the
    discordant pairs; NaN when there are none."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    n01, n10 = int((~a & b).sum()), int((a & ~b).sum())
    return float(stats.binomtest(n10, n01 + n10).pvalue) if n01 + n10 else float("nan")


def holm(pvalues: list[float]) -> list[float]:
    """Holm-Bonferroni adjusted p-values (family-wise error), NaNs passed through."""
    p = np.asarray(pvalues, float)
    out = np.full_like(p, np.nan)
    idx = np.flatnonzero(np.isfinite(p))
    if not len(idx):
        return out.tolist()
    order = idx[np.argsort(p[idx])]
    m = len(order)
    adj = np.maximum.accumulate((m - np.arange(m)) * p[order])
    out[order] = np.minimum(adj, 1.0)
    return out.tolist()


#: The serial-correlation-robust test's kernel reaches this many window spans: windows closer than
#: one span share frames, and the scene a robot drives through persists for a few more (on protocol
#: v1's runs the HAC t of CC at AR-10 stops falling at about four spans; BENCHMARKS.md).
HAC_SPANS = 4


def hac_variance(d: np.ndarray, positions: np.ndarray, groups: np.ndarray, bandwidth: float) -> float:
    """The variance of the mean of ``d`` when values close in time are correlated: a Newey-West
    (Bartlett kernel) estimate over irregularly spaced windows, weighting each pair of the same
    group (run) by ``1 - |distance| / bandwidth`` in ``positions`` (frames). Pairs of different
    groups, or ``bandwidth`` or more apart, count as independent; with no such pair it is the
    paired t-test's ``var(d, ddof=1) / n``. The triangular kernel is a positive-definite function,
    so the estimate is never negative. NaN for fewer than 2 values."""
    d = np.asarray(d, float)
    n = len(d)
    if np.shape(positions) != d.shape or np.shape(groups) != d.shape:
        raise ValueError(f"{n} values, {np.shape(positions)} positions and {np.shape(groups)} groups: one each per window")
    if not (np.isfinite(bandwidth) and bandwidth > 0):
        raise ValueError(f"bandwidth {bandwidth}: a positive number of frames")
    if n < 2:
        return float("nan")
    order = np.lexsort((positions, groups))
    dc, s, g = d[order] - d.mean(), np.asarray(positions, float)[order], np.asarray(groups)[order]
    total = float(dc @ dc)
    # Sorted by run, then frame: each window's k-th successor is no closer than its (k-1)-th, so
    # the first lag with no pair in reach ends the sum.
    for lag in range(1, n):
        w = np.where(g[lag:] == g[:-lag], 1.0 - (s[lag:] - s[:-lag]) / bandwidth, 0.0)
        if not np.any(w > 0):
            break
        total += 2.0 * float(np.sum(np.clip(w, 0.0, None) * dc[lag:] * dc[:-lag]))
    return total / (n * (n - 1))


def hac_t_p(d: np.ndarray, positions: np.ndarray, groups: np.ndarray, bandwidth: float) -> float:
    """Two-sided p of mean(d) = 0 with :func:`hac_variance` (the Diebold-Mariano test of forecast
    comparison, on windows drawn at irregular times), from Student's t with n - 1 degrees of
    freedom; NaN, as :func:`compare` has it, for fewer than 3 values or all of them equal."""
    d = np.asarray(d, float)
    if len(d) < 3 or np.all(d == d[0]):
        return float("nan")
    var = hac_variance(d, positions, groups, bandwidth)
    if not var > 0:
        return float("nan")
    t = float(np.mean(d)) / np.sqrt(var)
    return float(2.0 * stats.t.sf(abs(t), len(d) - 1))


def windows_to_pass(p: float, n: int, alpha: float) -> float:
    """The windows at which a two-sided t-test that gave ``p`` on ``n`` windows would give ``alpha``,
    the mean difference and its spread staying as they are (for :func:`hac_t_p`'s p, also its
    serial correlation: the windows added as more runs of the same length). The t statistic grows
    with the root of the windows, to Student's t quantile of ``alpha`` at the new degrees of
    freedom (a fixed point, from the normal quantile). A power question at the observed effect,
    itself uncertain, not a test: where a cell of a benchmark is unresolved, it says whether a
    larger sample would resolve it. NaN for an undefined p or fewer than 3 windows; inf for p 1."""
    if not (np.isfinite(p) and 0 < p <= 1 and n >= 3 and 0 < alpha < 1):
        return float("nan")
    t = stats.t.isf(p / 2, n - 1)
    if t <= 0:
        return float("inf")
    need = n * (stats.norm.isf(alpha / 2) / t) ** 2
    for _ in range(20):
        need = n * (stats.t.isf(alpha / 2, max(need, 3.0) - 1) / t) ** 2
    return float(need)
