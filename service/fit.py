"""How the number of rigid clusters grows with n: a fit of ``total(n) ≈ b·(n − 5)!``.

Holmes-Cerfon (SIAM Review 2016) observes that the number of rigid clusters of
n spheres grows like 2.5·(n − 5)!.  :func:`fit_factorial` finds the one
parameter b by least squares on the logarithms, where the model is linear:

    log total(n) = log b + log (n − 5)!

so the least-squares log b is the mean over the points used of
``log total(n) − log (n − 5)!`` (that is, b is the geometric mean of
``total(n) / (n − 5)!``).  Working on logarithms weights every n alike; a fit
on the totals themselves would be decided by the largest n alone.

Which points are used: every n ≥ 6 with a positive total.  n = 5 (one
cluster, 0! = 1) sits below the asymptotic form and would pull b down, so it
is used only when there is no n ≥ 6 at all; n < 5 has no (n − 5)! and is never
used.  With no usable point there is nothing to fit and the result is None.
"""

from __future__ import annotations

import math

MIN_N = 6  #: the smallest n used when there is any n >= MIN_N (see the module doc)
FALLBACK_MIN_N = 5  #: the smallest n for which (n - 5)! exists


def log_factorial(k: int) -> float:
    """log(k!) for k >= 0."""
    return math.lgamma(k + 1)


def fit_factorial(totals: dict[int, int] | dict[int, float]) -> dict | None:
    """Fit ``totals[n] ≈ b·(n − 5)!`` by least squares on log totals.

    Returns ``{"b": b, "points": k, "rms_log_residual": r, "ns": [n, ...]}``:
    the fitted b, the number k of points used and which n they were, and the
    root-mean-square of ``log total − log(b·(n − 5)!)`` over them (natural
    log; 0 for an exact fit or a single point).  None when no point is usable
    (no n ≥ 5 with a positive total).
    """
    usable = {int(n): float(t) for n, t in totals.items() if int(n) >= FALLBACK_MIN_N and t and t > 0}
    points = {n: t for n, t in usable.items() if n >= MIN_N} or usable
    if not points:
        return None
    ns = sorted(points)
    logs = [math.log(points[n]) - log_factorial(n - 5) for n in ns]
    log_b = sum(logs) / len(logs)
    rms = math.sqrt(sum((v - log_b) ** 2 for v in logs) / len(logs))
    return {"b": math.exp(log_b), "points": len(ns), "rms_log_residual": rms, "ns": ns}


def predicted(b: float, n: float) -> float:
    """``b·(n − 5)!``, for real n > 4 through the gamma function."""
    return b * math.gamma(n - 4)
