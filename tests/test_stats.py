"""aesplat.stats (which benchmarks/common.py names for the scripts): the 95 % t-interval the experiments'
tables report over seeds, and the order-statistic interval of a median that ``aesplat bench`` reports."""

import math

import pytest

from aesplat.stats import interval_contains, mean_difference, median_interval, order_statistic_rank

from .script_loader import load_benchmark

common = load_benchmark("common")
T95, holm, paired_t_p, t_interval = common.T95, common.holm, common.paired_t_p, common.t_interval
t_quantile_95, t_two_sided_p = common.t_quantile_95, common.t_two_sided_p


def test_median_interval_from_order_statistics():
    # n = 6: only the smallest and the largest bracket the median with >= 95 % (1 - 2/64 = 96.9 %).
    assert median_interval([3.0, 1.0, 2.0, 6.0, 5.0, 4.0]) == (3.5, 1.0, 6.0)
    # n = 9: the 2nd smallest and 2nd largest do (1 - 2 * 10/512 = 96.1 %); the 3rd would not (82 %).
    assert order_statistic_rank(9) == 2 and median_interval(range(1, 10)) == (5, 2, 8)
    assert [order_statistic_rank(n) for n in (5, 6, 8, 9, 12, 17)] == [0, 1, 1, 2, 3, 5]
    median, lo, hi = median_interval([1.0, 2.0, float("nan"), 4.0])  # too few for any 95 % interval
    assert median == 2.0 and math.isnan(lo) and math.isnan(hi)
    assert all(math.isnan(v) for v in median_interval([]))
    assert interval_contains(0.9, 1.1, 1.0) and not interval_contains(1.01, 1.1, 1.0)
    assert interval_contains(math.nan, 1.1, 1.0) is None


def test_mean_difference_is_paired():
    mean, lo, hi = mean_difference([11.0, 12.0, 14.0], [10.0, 10.0, 10.0])
    want_mean, half, _ = t_interval([1.0, 2.0, 4.0])
    assert (mean, lo, hi) == pytest.approx((want_mean, want_mean - half, want_mean + half))
    assert mean_difference([5.0, 6.0], [4.0, 5.0]) == (1.0, 1.0, 1.0)  # the same change in every pair
    with pytest.raises(ValueError):
        mean_difference([1.0], [1.0, 2.0])


def test_t_interval_by_hand():
    mean, half, n = t_interval([1.0, 2.0, 4.0, float("nan"), None])
    sd = math.sqrt(((1 - 7 / 3) ** 2 + (2 - 7 / 3) ** 2 + (4 - 7 / 3) ** 2) / 2)
    assert (mean, n) == (pytest.approx(7 / 3), 3)
    assert half == pytest.approx(4.303 * sd / math.sqrt(3))  # t(0.975, df=2) = 4.303
    assert t_quantile_95(1) == 12.706 and t_quantile_95(30) == 2.042
    assert t_quantile_95(1000) == 1.96
    one = t_interval([5.0])
    assert one[0] == 5.0 and math.isnan(one[1]) and one[2] == 1
    assert t_interval([])[2] == 0
    with pytest.raises(ValueError, match="at least 2 values"):
        t_quantile_95(0)


def test_t_p_value_is_five_percent_at_the_tabulated_quantiles():
    for df, quantile in enumerate(T95, start=1):  # the table's t(0.975, df) values, rounded to 3 decimals
        assert t_two_sided_p(quantile, df) == pytest.approx(0.05, abs=2e-4), df
        assert t_two_sided_p(-quantile, df) == t_two_sided_p(quantile, df)
    assert t_two_sided_p(0.0, 4) == 1.0
    assert t_two_sided_p(1.0, 1) == pytest.approx(0.5)  # Cauchy: P(|T| > 1) = 1/2
    assert t_two_sided_p(2.0, 2) == pytest.approx(1 - 2 / math.sqrt(6))  # df 2: P(|T| <= t) = t/sqrt(2+t^2)
    with pytest.raises(ValueError, match="df >= 1"):
        t_two_sided_p(1.0, 0)


def test_paired_t_p_and_holm_by_hand():
    p, n = paired_t_p([1.0, 2.0, 3.0, None, float("nan")])
    assert n == 3 and p == pytest.approx(t_two_sided_p(2.0 / (1.0 / math.sqrt(3)), 2))
    assert math.isnan(paired_t_p([1.0])[0])
    assert paired_t_p([0.5, 0.5]) == (0.0, 2) and paired_t_p([0.0, 0.0]) == (1.0, 2)
    # Holm: sorted 0.01, 0.02, 0.04 -> 3*0.01, max(0.03, 2*0.02), max(0.04, 1*0.04); NaN is left out.
    adjusted = holm([0.04, 0.01, float("nan"), 0.02])
    assert adjusted == pytest.approx([0.04, 0.03, float("nan"), 0.04], nan_ok=True)
    assert holm([0.5, 0.6]) == [1.0, 1.0] and holm([]) == []
    assert holm([0.03, 0.001]) == pytest.approx([0.03, 0.002])  # the running maximum keeps the order
