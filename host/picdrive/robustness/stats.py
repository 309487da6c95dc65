"""The statistics of a tolerance study: the yield and its interval, the parameters that drive failures.

* :func:`wilson_interval` -- the yield's 95 % confidence interval (Wilson's
  score interval: it stays inside [0, 1] and keeps its coverage at 0 or n
  passes, where the normal approximation collapses).
* :func:`failure_drivers` -- each parameter's Spearman rank correlation with
  failing (1 failed, 0 passed) and with the sample's worst ratio of a figure to
  its limit, with the two-sided p-value of the first; a parameter that drives
  failures has a large ``|rho|`` and a small p-value.  The rank correlation sees
  any monotone dependence, not only a linear one, and needs no model.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["wilson_interval", "failure_drivers", "Z95"]

#: the normal quantile of a two-sided 95 % interval
Z95 = 1.959963984540054


def wilson_interval(passed: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson's score interval of a proportion ``passed / n`` (95 % by default); ``(0, 1)`` for n = 0."""
    if n <= 0:
        return 0.0, 1.0
    p = passed / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    lo, hi = max(0.0, centre - half), min(1.0, centre + half)
    # exact at the ends: no pass cannot exclude 0, all passes cannot exclude 1
    return (0.0 if passed == 0 else lo), (1.0 if passed == n else hi)


def failure_drivers(deviations: dict[str, np.ndarray], failed: np.ndarray, worst_ratio: np.ndarray) -> list[dict]:
    """Each parameter's rank correlation with failing and with the worst ratio, strongest first.

    Parameters
    ----------
    deviations : dict of numpy.ndarray
        Parameter name -> its deviation in each sample (% or deg).
    failed : numpy.ndarray of bool
        Whether each sample failed (a limit, a fault, or its simulation).
    worst_ratio : numpy.ndarray
        Each sample's largest figure-to-limit ratio (inf for a failed simulation).

    Returns
    -------
    list of dict
        ``{"parameter", "rho_fail", "p_fail", "rho_margin"}``; ``rho_fail`` is nan when the
        parameter does not vary or every sample has the same verdict.
    """
    from scipy.stats import spearmanr
    out = []
    y = np.asarray(failed, float)
    r = np.asarray(worst_ratio, float)
    r = np.where(np.isfinite(r), r, np.nanmax(np.where(np.isfinite(r), r, np.nan)) * 2 if np.any(np.isfinite(r))
                 else 1.0)
    for name, x in deviations.items():
        x = np.asarray(x, float)
        rho_f = p_f = rho_m = math.nan
        if x.size >= 3 and np.ptp(x) > 0:
            if np.ptp(y) > 0:
                res = spearmanr(x, y)
                rho_f, p_f = float(res.statistic), float(res.pvalue)
            if np.ptp(r) > 0:
                rho_m = float(spearmanr(x, r).statistic)
        out.append({"parameter": name, "rho_fail": rho_f, "p_fail": p_f, "rho_margin": rho_m})
    out.sort(key=lambda d: (-(abs(d["rho_fail"]) if math.isfinite(d["rho_fail"]) else -1),
                            -(abs(d["rho_margin"]) if math.isfinite(d["rho_margin"]) else -1)))
    return out
