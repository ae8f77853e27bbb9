"""Small-sample statistics: the mean and its 95 % Student-t interval (over seeds, over scenes), the paired
t-test's p-value, Holm's adjustment of a family of p-values, and the distribution-free 95 % interval of a
median from order statistics (over timing rounds). Pure Python: nothing here imports torch."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

# Two-sided 95 % quantiles of Student's t, by degrees of freedom (beyond 30: the normal 1.96).
T95 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160, 2.145,
       2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045,
       2.042)  # fmt: skip


def t_quantile_95(df: int) -> float:
    """Two-sided 95 % quantile of Student's t with ``df`` >= 1 degrees of freedom."""
    if df < 1:
        raise ValueError(f"a t-interval needs at least 2 values (df >= 1), got df={df}")
    return T95[df - 1] if df <= len(T95) else 1.96


def t_interval(values: Iterable[float | None]) -> tuple[float, float, int]:
    """(mean, half-width of the 95 % t-interval, n) of the finite values; half-width NaN below 2 values."""
    finite = [v for v in values if v is not None and math.isfinite(v)]
    n = len(finite)
    if n == 0:
        return math.nan, math.nan, 0
    mean = sum(finite) / n
    if n < 2:
        return mean, math.nan, n
    sd = math.sqrt(sum((v - mean) ** 2 for v in finite) / (n - 1))
    return mean, t_quantile_95(n - 1) * sd / math.sqrt(n), n


def t_two_sided_p(t: float, df: int) -> float:
    """Two-sided p-value of Student's t statistic ``t`` with ``df`` >= 1 (integer) degrees of freedom.

    Exact closed form for integer df (Abramowitz & Stegun 26.7.3-4): with theta = atan(|t| / sqrt(df)),
    P(|T| <= |t|) is a finite series in sin(theta) and cos(theta)^2.
    """
    if df < 1:
        raise ValueError(f"a t-test needs df >= 1, got df={df}")
    if not math.isfinite(t):
        return 0.0 if math.isinf(t) else math.nan
    theta = math.atan(abs(t) / math.sqrt(df))
    s, c2 = math.sin(theta), math.cos(theta) ** 2
    if df % 2 == 1:  # odd: 2/pi * (theta + sin cos * [1 + 2/3 c^2 + 2*4/(3*5) c^4 + ... up to c^(df-3)])
        term, series = 1.0, 1.0 if df > 1 else 0.0
        for k in range(1, (df - 1) // 2):
            term *= c2 * (2 * k) / (2 * k + 1)
            series += term
        inside = 2.0 / math.pi * (theta + s * math.cos(theta) * series)
    else:  # even: sin * [1 + 1/2 c^2 + 1*3/(2*4) c^4 + ... up to c^(df-2)]
        term, series = 1.0, 1.0
        for k in range(1, df // 2):
            term *= c2 * (2 * k - 1) / (2 * k)
            series += term
        inside = s * series
    return min(1.0, max(0.0, 1.0 - inside))


def paired_t_p(differences: Iterable[float | None]) -> tuple[float, int]:
    """(two-sided p-value of the paired t-test that the mean difference is 0, n) over the finite values; NaN
    below 2 values, 0 when every difference is the same non-zero value."""
    finite = [v for v in differences if v is not None and math.isfinite(v)]
    n = len(finite)
    if n < 2:
        return math.nan, n
    mean = sum(finite) / n
    sd = math.sqrt(sum((v - mean) ** 2 for v in finite) / (n - 1))
    if sd == 0.0:
        return (1.0 if mean == 0.0 else 0.0), n
    return t_two_sided_p(mean / (sd / math.sqrt(n)), n - 1), n


def holm(p_values: list[float]) -> list[float]:
    """Holm's step-down adjustment of a family of p-values (same order as given; NaN stays NaN and does not
    count towards the family's size). Rejecting where the adjusted value is <= alpha keeps the family-wise
    error rate at alpha."""
    order = sorted((i for i, p in enumerate(p_values) if math.isfinite(p)), key=lambda i: p_values[i])
    m, out, running = len(order), [math.nan] * len(p_values), 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p_values[i]))
        out[i] = running
    return out


def median_interval(values: Iterable[float], level: float = 0.95) -> tuple[float, float, float]:
    """(median, low, high) of the finite values; (low, high) the distribution-free interval for the median
    from order statistics: the j-th smallest and the j-th largest value, j the largest index whose interval
    covers the median with probability >= ``level`` (1 - 2 P(Binomial(n, 1/2) < j)). NaN bounds when n is too
    small for any such interval (n < 6 at 95 %); NaN throughout with no finite value."""
    finite = sorted(v for v in values if math.isfinite(v))
    n = len(finite)
    if n == 0:
        return math.nan, math.nan, math.nan
    mid = n // 2
    median = finite[mid] if n % 2 else 0.5 * (finite[mid - 1] + finite[mid])
    j = order_statistic_rank(n, level)
    if j == 0:
        return median, math.nan, math.nan
    return median, finite[j - 1], finite[n - j]


def order_statistic_rank(n: int, level: float = 0.95) -> int:
    """The largest j (1-based) such that the j-th smallest and j-th largest of n values bracket the median with
    probability >= ``level``; 0 when not even the smallest and largest do."""
    best, below = 0, 0.0  # below: P(Binomial(n, 1/2) <= j - 1)
    for j in range(1, n // 2 + 1):
        below += math.comb(n, j - 1) / 2.0**n
        if 1.0 - 2.0 * below < level:
            break
        best = j
    return best


def interval_contains(low: float, high: float, value: float) -> bool | None:
    """Whether [low, high] holds ``value``; None when the interval is unknown (a NaN bound)."""
    if not (math.isfinite(low) and math.isfinite(high)):
        return None
    return low <= value <= high


def mean_difference(values: Sequence[float], reference: Sequence[float]) -> tuple[float, float, float]:
    """(mean, low, high) of the paired differences ``values - reference`` with the 95 % t-interval (NaN bounds
    below two pairs; a zero-width interval when every difference is the same)."""
    mean, half, _ = t_interval(v - r for v, r in zip(values, reference, strict=True))
    return mean, mean - half, mean + half
