"""Step-response metrics: rise time, settling time, overshoot, steady-state error.

One implementation used everywhere a step is judged: the design verifier,
the report, the HIL suite and the console's ``step`` command.

Definitions (step from ``y0`` to ``target`` applied at ``t_step``):

* rise time: from the first crossing of 10 % to the first crossing of 90 %
  of the step (linear interpolation between samples), s;
* settling time: from ``t_step`` to the last time the response is outside
  ``target +- band * |step|`` (band 2 % by default), s; ``inf`` if it never
  settles within the record;
* overshoot: peak excursion beyond the target in the step's direction, in
  percent of the step (0 if none);
* steady-state error: ``target - mean(y)`` over the final ``tail`` fraction
  of the record, absolute and in percent of the target.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["StepMetrics", "step_metrics"]


@dataclass(frozen=True)
class StepMetrics:
    rise_time_s: float
    settling_time_s: float
    overshoot_pct: float
    steady_state_error: float
    steady_state_error_pct: float
    peak: float
    final_value: float

    def to_dict(self) -> dict:
        return asdict(self)

    def summary(self, unit: str = "") -> str:
        u = f" {unit}" if unit else ""
        return (f"rise {self.rise_time_s * 1e3:.2f} ms, settling {self.settling_time_s * 1e3:.2f} ms, "
                f"overshoot {self.overshoot_pct:.2f} %, steady-state error {self.steady_state_error:.4g}{u} "
                f"({self.steady_state_error_pct:.3f} %)")


def _first_crossing(t: np.ndarray, x: np.ndarray, level: float) -> float:
    """First time the normalised response x reaches level (interpolated)."""
    idx = np.nonzero(x >= level)[0]
    if idx.size == 0:
        return math.inf
    k = int(idx[0])
    if k == 0:
        return float(t[0])
    x0, x1 = x[k - 1], x[k]
    f = (level - x0) / (x1 - x0) if x1 != x0 else 0.0
    return float(t[k - 1] + f * (t[k] - t[k - 1]))


def step_metrics(t, y, target: float, *, y0: float | None = None, t_step: float | None = None,
                 band: float = 0.02, tail: float = 0.1) -> StepMetrics:
    """Metrics of a recorded step response.

    ``t``, ``y``: samples (same length, t increasing).  ``y0`` defaults to the
    first sample, ``t_step`` to the first time stamp.
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    if t.shape != y.shape or t.ndim != 1 or t.size < 3:
        raise ValueError("t and y must be 1-D arrays of the same length (>= 3 samples)")
    if t_step is None:
        t_step = float(t[0])
    sel = t >= t_step
    t, y = t[sel], y[sel]
    if y0 is None:
        y0 = float(y[0])
    step = target - y0
    if step == 0:
        raise ValueError("target equals the initial value: no step to measure")
    x = (y - y0) / step                      # normalised: 0 -> 1
    rise = _first_crossing(t, x, 0.9) - _first_crossing(t, x, 0.1)
    outside = np.nonzero(np.abs(x - 1.0) > band)[0]
    if outside.size == 0:
        settle = 0.0
    elif outside[-1] == x.size - 1:
        settle = math.inf
    else:
        settle = float(t[outside[-1] + 1] - t_step)
    peak_x = float(np.max(x))
    overshoot = max(0.0, (peak_x - 1.0) * 100.0)
    n_tail = max(1, int(round(tail * y.size)))
    final = float(np.mean(y[-n_tail:]))
    sse = target - final
    sse_pct = abs(sse) / abs(target) * 100.0 if target != 0 else abs(sse / step) * 100.0
    peak = float(y0 + peak_x * step)
    return StepMetrics(rise, settle, overshoot, sse, sse_pct, peak, final)
