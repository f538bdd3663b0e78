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

    def to_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in asdict(self).items()}


def compare(a: np.ndarray, b: np.ndarray, *, metric: str, horizon: int, names: tuple[str, str],
            n_resamples: int = 2000, seed: int = 0) -> Comparison:
    a, b = np.asarray(a, float), np.asarray(b, float)
    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok], b[ok]
    d = a - b
    n = len(d)
    if n < 3 or np.all(d == d[0]):
        nan = float("nan")
        return Comparison(metric, horizon, *names, n, float(d.mean()) if n else nan, nan, nan, nan, nan, nan)
    lo, hi = bootstrap_ci(d, n_resamples, seed)
    return Comparison(
        metric, horizon, *names, n, float(d.mean()), lo, hi,
        *_pvalues(a, b, d),
    )


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
                float(stats.wilcoxon(d).pvalue))


def wilcoxon_p(d: np.ndarray) -> float:
    """Wilcoxon signed-rank p of paired differences ``d``; NaN for fewer than 3 or all zero (the
    test is undefined there, and scipy would raise or warn)."""
    d = np.asarray(d, float)
    return float(stats.wilcoxon(d).pvalue) if len(d) >= 3 and np.any(d != 0) else float("nan")


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
