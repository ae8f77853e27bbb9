"""aesplat.stats: the 95 % t-interval the experiments' tables report over seeds."""

import math

import pytest

from aesplat.stats import t_interval, t_quantile_95


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
