"""The console's step test: ``step <from> <to> --hold <s>``.

A step test brings the drive to ``from`` rpm, changes the setpoint to ``to``
rpm, records the speed for ``hold`` seconds, and judges the response with
:func:`picdrive.analysis.metrics.step_metrics` -- the one implementation of rise
time, settling time, overshoot and steady-state error, shared with the
design verifier and the HIL suite, so a step measured here and a step
measured by the HIL suite agree.

This module holds the data and the analysis (:class:`StepRecord`,
:func:`analyse_step`, :func:`save_step_plot`); running the step on a board
(through :mod:`picdrive.link`) is the console's job.

Conventions (the same as the HIL suite's):

* time ``t_s`` is 0 at the sample where the new setpoint takes effect;
* ``y0`` is the mean measured speed over the pre-step samples (the last
  ``pre_s`` seconds before the step) when there are any, otherwise the
  commanded ``from`` speed;
* the metrics are in rpm (mechanical) with the 2 % settling band.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import PicdriveError
from ..analysis.metrics import StepMetrics, step_metrics

__all__ = ["StepError", "StepRecord", "analyse_step", "save_step_plot", "parse_step_args"]


class StepError(PicdriveError):
    """A step test was asked for with bad arguments or could not be judged."""


@dataclass
class StepRecord:
    """A recorded speed step.

    ``t_s``: sample times (s), 0 at the step; ``speed_rpm``: measured speed;
    ``signals``: further recorded signals by name (same length), with
    ``units``; ``source``: ``"capture"`` (the board's triggered capture) or
    ``"telemetry"``; ``sample_period_s``: the spacing of the samples.
    """

    from_rpm: float
    to_rpm: float
    hold_s: float
    t_s: np.ndarray = field(repr=False)
    speed_rpm: np.ndarray = field(repr=False)
    sample_period_s: float
    source: str = "telemetry"
    signals: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    units: dict[str, str] = field(default_factory=dict)
    metrics: StepMetrics | None = None
    firmware: str = ""
    profile: str = ""
    controller: str = ""
    dropped: int = 0
    fault: str = ""                      # fault latched during the step ("" = none)
    interrupted: bool = False            # Ctrl-C ended the step: partial data, no metrics
    gains: dict[str, float] = field(default_factory=dict)   # the board's gains during the step
    speed_basis: str = "raw speed"       # what the metrics were judged on

    def summary(self) -> str:
        m = self.metrics
        if m is None:
            return "not analysed"
        settle = "did not settle" if not math.isfinite(m.settling_time_s) else f"{m.settling_time_s * 1e3:.1f} ms"
        rise = "did not reach 90 %" if not math.isfinite(m.rise_time_s) else f"{m.rise_time_s * 1e3:.1f} ms"
        return (f"step {self.from_rpm:g} -> {self.to_rpm:g} rpm ({self.source}, "
                f"{len(self.t_s)} samples at {1.0 / self.sample_period_s:g} Hz): "
                f"rise {rise}, settling {settle}, overshoot {m.overshoot_pct:.2f} %, "
                f"steady-state error {m.steady_state_error:+.2f} rpm ({m.steady_state_error_pct:.3f} %); "
                f"judged on the {self.speed_basis}")

    def identity_lines(self) -> list[str]:
        """What produced the record: firmware, profile, controller and gains (CSV header, PNG)."""
        out = [x for x in (self.firmware, self.profile and f"profile {self.profile}",
                           self.controller and f"controller {self.controller}") if x]
        if self.gains:
            out.append("gains " + ", ".join(f"{k} {v:.6g}" for k, v in self.gains.items()))
        return out


def parse_step_args(args: list[str]) -> tuple[float, float, float, str | None]:
    """``<from> <to> [--hold <s>] [--png <file>]`` -> (from_rpm, to_rpm, hold_s, png or None).

    ``hold`` defaults to 1 s.
    """
    pos, given = split_options(args, ("--hold", "--png"), "step", STEP_USAGE, StepError)
    opts = {"--hold": None, "--png": None, **given}
    if len(pos) != 2:
        raise StepError(f"usage: {STEP_USAGE}, e.g. 'step 0 2400 --hold 1.0'")
    f, t = _number(pos[0], "from"), _number(pos[1], "to")
    hold = 1.0 if opts["--hold"] is None else _number(opts["--hold"], "--hold")
    if f == t:
        raise StepError(f"from and to are both {f:g} rpm: no step to measure")
    if not 0.05 <= hold <= 60.0:
        raise StepError(f"--hold {hold:g} s is outside 0.05..60 s")
    png = opts["--png"]
    if png is not None and not png.lower().endswith(".png"):
        raise StepError(f"--png {png!r} must end in .png")
    return f, t, hold, png


STEP_USAGE = "step <from_rpm> <to_rpm> [--hold <s>] [--png <file.png>]"


def split_options(args: list[str], known: tuple[str, ...], command: str, usage: str,
                  error: type[PicdriveError] = PicdriveError) -> tuple[list[str], dict[str, str]]:
    """A console command's positional words and its ``--key value`` / ``--key=value`` options.

    Only ``known`` keys are accepted; a key without a value or an unknown
    ``--option`` raises ``error`` with the command's ``usage``."""
    pos: list[str] = []
    opts: dict[str, str] = {}
    it = iter(args)
    for a in it:
        key = a.split("=", 1)[0]
        if key in known:
            v = a.split("=", 1)[1] if "=" in a else next(it, None)
            if v is None:
                raise error(f"{key} needs a value; usage: {usage}")
            opts[key] = v
        elif a.startswith("--"):
            raise error(f"unknown option {a!r} for {command}; usage: {usage}")
        else:
            pos.append(a)
    return pos, opts


def parse_number(s: str, what: str, error: type[PicdriveError] = PicdriveError) -> float:
    """A finite number typed by the user, or ``error`` saying which argument is wrong."""
    try:
        v = float(s)
    except ValueError:
        raise error(f"{what} {s!r} is not a number") from None
    if not math.isfinite(v):
        raise error(f"{what} {s!r} is not a finite number")
    return v


def _number(s: str, what: str) -> float:
    return parse_number(s, what, StepError)


def analyse_step(rec: StepRecord, *, pre_t_s: np.ndarray | None = None,
                 pre_speed_rpm: np.ndarray | None = None, profile=None) -> StepMetrics:
    """Compute the step metrics of ``rec`` (stored in ``rec.metrics`` and returned).

    ``pre_*``: samples before the step (t < 0) used for ``y0``.  With the board's
    ``profile`` the metrics are judged on the speed averaged over one hall sector at
    the target (:func:`picdrive.design.verify.sector_mean`, as the verifier and the HIL suite
    do: the commutation ripple is no regulation error), over the samples after the
    step only (the mean never looks across the step); ``rec.speed_basis`` says which.
    """
    t = np.asarray(rec.t_s, float)
    y = np.asarray(rec.speed_rpm, float)
    sel = t >= 0.0
    if np.count_nonzero(sel) < 3:
        raise StepError(f"only {np.count_nonzero(sel)} samples after the step; "
                        "raise --hold or the telemetry rate")
    if pre_speed_rpm is not None and len(pre_speed_rpm):
        y0 = float(np.mean(pre_speed_rpm))
    else:
        y0 = float(rec.from_rpm)
    if y0 == rec.to_rpm:
        y0 = float(rec.from_rpm)
    ya = y[sel]
    rec.speed_basis = "raw speed"
    if profile is not None:
        from ..design.verify import sector_mean, sector_period_s
        ya = sector_mean(profile, ya, rec.sample_period_s, float(rec.to_rpm))
        n = max(1, int(round(sector_period_s(profile, float(rec.to_rpm)) / rec.sample_period_s)))
        if n > 1:
            rec.speed_basis = f"sector-mean speed ({n} samples = one hall sector at {rec.to_rpm:g} rpm)"
    rec.metrics = step_metrics(t[sel], ya, float(rec.to_rpm), y0=y0, t_step=0.0)
    return rec.metrics


def save_step_plot(rec: StepRecord, path: str | Path, *, band: float = 0.02) -> Path:
    """Save the step response as a PNG (written whole or not at all).

    Top: speed and setpoint with the settling band and the metrics marked;
    below: one panel per further signal (a ``setpoint`` signal is drawn in the top panel).
    """
    from matplotlib.figure import Figure
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    p = Path(path)
    if p.suffix.lower() != ".png":
        raise StepError(f"step plot file {str(p)!r} must end in .png")
    others = [k for k in rec.signals if k not in ("speed", "speed_rpm", "setpoint")]
    n = 1 + len(others)
    fig = Figure(figsize=(8, 3.6 + 1.5 * (n - 1)))
    FigureCanvasAgg(fig)
    axes = fig.subplots(n, 1, sharex=True, squeeze=False)[:, 0]
    ax = axes[0]
    t = np.asarray(rec.t_s) * 1e3
    ax.plot(t, rec.speed_rpm, lw=1.2, label="speed")
    if "setpoint" in rec.signals:          # the board's setpoint (after its ramp)
        ax.plot(t, rec.signals["setpoint"], lw=1.0, ls="--", color="k", label="setpoint")
    else:
        sp = np.where(np.asarray(rec.t_s) < 0, rec.from_rpm, rec.to_rpm)
        ax.step(t, sp, where="post", lw=1.0, ls="--", color="k", label="setpoint")
    step = rec.to_rpm - rec.from_rpm
    ax.axhspan(rec.to_rpm - band * abs(step), rec.to_rpm + band * abs(step), color="g", alpha=0.12,
               label=f"±{band * 100:g} % band")
    m = rec.metrics
    if rec.fault or rec.interrupted:
        why = (f"FAULT {rec.fault.upper()} latched during the step: outputs off, no metrics" if rec.fault
               else "INTERRUPTED (Ctrl-C): motor stopped, partial data, no metrics")
        ax.text(0.5, 0.5, why, transform=ax.transAxes, ha="center", va="center", fontsize=11, color="r",
                bbox=dict(boxstyle="round", fc="w", ec="r", alpha=0.9))
    elif m is not None:
        if math.isfinite(m.settling_time_s):
            ax.axvline(m.settling_time_s * 1e3, color="g", lw=0.8, ls=":")
        txt = ("rise " + ("—" if not math.isfinite(m.rise_time_s) else f"{m.rise_time_s * 1e3:.1f} ms")
               + "\nsettling "
               + ("—" if math.isinf(m.settling_time_s) else f"{m.settling_time_s * 1e3:.1f} ms")
               + f"\novershoot {m.overshoot_pct:.2f} %\nsteady-state error {m.steady_state_error:+.2f} rpm")
        ax.text(0.98, 0.04, txt, transform=ax.transAxes, ha="right", va="bottom", fontsize=8,
                bbox=dict(boxstyle="round", fc="w", alpha=0.85))
    ax.set_ylabel("speed [rpm]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    for a, k in zip(axes[1:], others):
        a.plot(t, rec.signals[k], lw=1.0)
        a.set_ylabel(f"{k}\n[{rec.units.get(k, '') or '1'}]")
        a.grid(True, alpha=0.3)
    axes[-1].set_xlabel("time from step [ms]")
    title = f"step {rec.from_rpm:g} → {rec.to_rpm:g} rpm ({rec.source}; metrics on the {rec.speed_basis})"
    import textwrap
    ident = textwrap.wrap("; ".join(rec.identity_lines()), 130)
    fig.suptitle("\n".join([title] + ident), fontsize=7.5)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.012 * len(ident)))
    from .files import output_path, write_png
    p = output_path(p, ".png", "step plot")
    try:
        write_png(fig, p, dpi=110)
    except OSError as e:
        raise StepError(f"cannot write step plot {p}: {e.strerror}") from None
    return p
