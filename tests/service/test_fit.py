"""The fit total(n) ≈ b·(n − 5)! (packings.service.fit)."""

from __future__ import annotations

import math

import pytest

from packings.service.fit import fit_factorial, predicted

#: the paper's totals (Holmes-Cerfon 2016, Table 1), n = 5 .. 14
PAPER_TOTALS = dict(zip(range(5, 15), [1, 2, 5, 13, 52, 263, 1659, 11980, 98529, 895478]))


@pytest.mark.parametrize("b", [0.3, 1.0, 2.5, 7.25])
def test_exact_data_gives_b_exactly(b):
    totals = {n: b * math.factorial(n - 5) for n in range(6, 16)}
    fit = fit_factorial(totals)
    assert fit["b"] == pytest.approx(b, rel=1e-12)
    assert fit["points"] == 10 and fit["ns"] == list(range(6, 16))
    assert fit["rms_log_residual"] == pytest.approx(0.0, abs=1e-12)
    assert predicted(fit["b"], 12) == pytest.approx(b * math.factorial(7), rel=1e-12)


def test_paper_totals():
    fit = fit_factorial(PAPER_TOTALS)
    assert 1 < fit["b"] < 5
    assert fit["b"] == pytest.approx(2.29, abs=0.01)  # the geometric mean of total / (n - 5)! over n = 6 .. 14
    assert fit["points"] == 9 and fit["ns"] == list(range(6, 15))  # n = 5 is left out when there is more
    assert 0 < fit["rms_log_residual"] < 0.2
    # the ratios approach the paper's 2.5 from below
    assert PAPER_TOTALS[14] / math.factorial(9) == pytest.approx(2.47, abs=0.01)


def test_least_squares_on_logs():
    totals = {6: 3, 7: 4, 9: 100}
    logs = [math.log(t) - math.log(math.factorial(n - 5)) for n, t in totals.items()]
    mean = sum(logs) / 3
    fit = fit_factorial(totals)
    assert math.log(fit["b"]) == pytest.approx(mean, rel=1e-12)
    assert fit["rms_log_residual"] == pytest.approx(math.sqrt(sum((v - mean) ** 2 for v in logs) / 3), rel=1e-12)
    # b minimises the sum of squared log residuals
    cost = lambda lb: sum((v - lb) ** 2 for v in logs)  # noqa: E731
    assert cost(math.log(fit["b"])) < min(cost(math.log(fit["b"]) + d) for d in (-1e-3, 1e-3))


def test_which_points_are_used():
    assert fit_factorial({5: 1})["ns"] == [5]  # n = 5 only when there is nothing else
    assert fit_factorial({5: 1})["b"] == pytest.approx(1.0)
    assert fit_factorial({4: 1, 5: 1, 8: 12})["ns"] == [8]
    assert fit_factorial({6: 2, 7: 0})["ns"] == [6]  # no log of zero
    single = fit_factorial({10: 263})
    assert single["points"] == 1 and single["rms_log_residual"] == 0.0
    assert single["b"] == pytest.approx(263 / 120)


@pytest.mark.parametrize("totals", [{}, {4: 1}, {3: 1, 4: 1}, {6: 0}])
def test_nothing_to_fit(totals):
    assert fit_factorial(totals) is None
