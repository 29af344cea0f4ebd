"""Student-t quantiles against closed forms, at the levels a comparison can ask for.

A review found the old quantile (Simpson's rule over ``[0, t]``) 55 times too narrow at
1 degree of freedom and ``alpha = 1e-6``, and 13 times too wide at 2: ``imitrl compare
--episodes 2 --alpha 1e-6`` then decided what its data could not show."""

from __future__ import annotations

import math

import pytest

from imitrl.evaluation.statistics import student_t_quantile, t_two_sided_tail

LEVELS = [0.75, 0.9, 0.95, 0.975, 0.995, 1 - 5e-4, 1 - 5e-7, 1 - 5e-13]


@pytest.mark.parametrize("p", LEVELS)
def test_one_and_two_degrees_of_freedom_match_their_closed_forms(p):
    tail = 2 * (1 - p)  # exact in floating point: 1 - p has no rounding here
    cauchy = 1 / math.tan(math.pi * tail / 2)  # df 1: tan(pi (p - 1/2)), without its pole
    assert student_t_quantile(p, 1) == pytest.approx(cauchy, rel=1e-9)
    u = 1 - tail  # df 2: F(t) = 1/2 + t / (2 sqrt(2 + t^2)), so t = u sqrt(2 / (1 - u^2))
    two = u * math.sqrt(2 / (tail * (2 - tail)))
    assert student_t_quantile(p, 2) == pytest.approx(two, rel=1e-9)


@pytest.mark.parametrize("df", [1, 2, 3, 4, 5, 9, 30, 1000])
def test_four_degrees_and_the_tail_function_agree_with_closed_forms(df):
    # P(|T| > t) in closed form (Abramowitz and Stegun 26.7.3-4): df 1, 2, 3 and 4
    closed = {
        1: lambda t: 1 - 2 / math.pi * math.atan(t),
        2: lambda t: 1 - t / math.sqrt(2 + t * t),
        3: lambda t: (
            1 - 2 / math.pi * (math.atan(t / math.sqrt(3)) + math.sqrt(3) * t / (3 + t * t))
        ),
        4: lambda t: 1 - t / math.sqrt(4 + t * t) * (1 + 2 / (4 + t * t)),
    }
    for t in (0.1, 1.0, 2.5, 10.0):
        if df in closed:
            assert t_two_sided_tail(t, df) == pytest.approx(closed[df](t), rel=1e-12)
    for t in (0.1, 1.0, 2.5):  # p = 1 - tail / 2 keeps the tail's digits
        q = student_t_quantile(1 - t_two_sided_tail(t, df) / 2, df)
        assert q == pytest.approx(t, rel=1e-9)  # the quantile inverts the tail
    assert t_two_sided_tail(0.0, df) == 1.0 and t_two_sided_tail(math.inf, df) == 0.0


def test_a_tiny_tail_keeps_its_digits_and_large_df_reaches_the_normal():
    # df 1 at t = 1e6: 2/pi * atan(1/t), where 1 - (...) would cancel to nothing
    assert t_two_sided_tail(1e6, 1) == pytest.approx(2 / math.pi * math.atan(1e-6), rel=1e-12)
    # the normal's 97.5% quantile, approached as 1/df
    assert student_t_quantile(0.975, 10**6) == pytest.approx(1.959963984540054, rel=1e-5)
    assert student_t_quantile(0.5, 7) == 0.0
    with pytest.raises(ValueError, match=r"0\.5 <= p < 1"):
        student_t_quantile(1.0, 3)
