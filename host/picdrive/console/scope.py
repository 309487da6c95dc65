"""The console's ``scope``: the firmware's triggered capture, X2Cscope-style.

The board records into its own buffer (``capture_words`` 16-bit words: samples
x signals) at the speed-loop rate divided by a decimation, keeping
``pre_trigger`` samples from before the trigger, so a capture is exact in time
whatever the serial link does; the host reads it once it is done.  This module
holds the options (:func:`parse_scope_args`), the plot (:func:`save_scope_plot`:
signals of one unit share an axis, t = 0 at the trigger, marked) and the text
summary; arming and reading go through :mod:`picdrive.link`
(``capture_arm`` / ``capture_read``).

Triggers are the firmware's: ``immediate``, ``setpoint`` (any write of the
speed setpoint), ``rising`` / ``falling`` (the measured speed crossing
``--level`` rpm).  A level or edge on another signal is not in the firmware.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .step import parse_number, split_options
from ..errors import PicdriveError

__all__ = ["ScopeError", "ScopeSetup", "parse_scope_args", "save_scope_plot", "TRIGGERS", "SCOPE_USAGE"]

TRIGGERS = {"immediate": "immediate", "setpoint": "setpoint_change", "rising": "speed_rising",
            "falling": "speed_falling"}
"""Console trigger word -> the link's trigger name."""

SCOPE_USAGE = ("scope [single|normal|arm|read|stop] [SIGNALS] [--trigger immediate|setpoint|rising|falling] "
               "[--level RPM] [--speed RPM[,RPM...]] [--pre N|P%] [--samples N] [--decimation D] [--count N] "
               "[--timeout S] [--png FILE] [--csv FILE]")

DEFAULT_TIMEOUT_S = 5.0
"""Board-clock wait for a capture beyond its own length, s, when ``--timeout`` is not given."""


class ScopeError(PicdriveError):
    """A scope command with bad options."""


@dataclass
class ScopeSetup:
    """What to capture: ``signals``, ``trigger`` (console word), ``level_rpm`` (speed triggers),
    ``pre`` (samples, or a fraction of ``samples`` when ``pre_fraction``), ``samples``
    (None = as many as the buffer holds), ``decimation``, ``count`` (normal mode), ``timeout_s``
    (board clock; None = the capture's length + :data:`DEFAULT_TIMEOUT_S`), ``speed_rpm`` (setpoints
    the console writes right after arming, the k-th capture the k-th value, cycling: the step that
    fires the trigger while the prompt waits), ``png`` / ``csv`` paths (None = default names)."""

    mode: str = "single"
    signals: list[str] = field(default_factory=list)
    trigger: str = "immediate"
    level_rpm: float | None = None
    pre: float = 0.0
    pre_fraction: bool = False
    samples: int | None = None
    decimation: int = 1
    count: int | None = None
    timeout_s: float | None = None
    speed_rpm: list[float] = field(default_factory=list)
    png: str | None = None
    csv: str | None = None

    def pre_samples(self, n: int) -> int:
        return int(round(self.pre * n)) if self.pre_fraction else int(self.pre)


def _int(s: str, what: str, lo: int, hi: int) -> int:
    v = parse_number(s, what, ScopeError)
    if v != int(v) or not lo <= v <= hi:
        raise ScopeError(f"{what} {s!r}: expected a whole number in {lo}..{hi}")
    return int(v)


def parse_scope_args(args: list[str]) -> ScopeSetup:
    """Parse ``scope`` arguments (see :data:`SCOPE_USAGE`)."""
    st = ScopeSetup()
    rest = list(args)
    if rest and rest[0].lower() in ("single", "normal", "arm", "read", "stop"):
        st.mode = rest.pop(0).lower()
    if st.mode == "stop":
        if rest:
            raise ScopeError(f"scope stop takes no arguments; got {' '.join(rest)}")
        return st
    known = ("--trigger", "--level", "--speed", "--pre", "--samples", "--decimation", "--count", "--timeout",
             "--png", "--csv")
    pos, opts = split_options(rest, known, "scope", SCOPE_USAGE, ScopeError)
    if len(pos) > 1:
        raise ScopeError(f"scope: signals are one comma-separated word (e.g. speed,setpoint); usage: {SCOPE_USAGE}")
    if pos:
        st.signals = [n for n in pos[0].split(",") if n]
    if st.mode == "read":
        bad = [k for k in opts if k not in ("--png", "--csv", "--timeout")] + (["signals"] if pos else [])
        if bad:
            raise ScopeError(f"scope read takes only --png, --csv and --timeout (the capture was set up by "
                             f"'scope arm'); got {', '.join(bad)}")
    trig = opts.get("--trigger", "immediate").lower()
    if trig not in TRIGGERS:
        raise ScopeError(f"--trigger {trig!r}: expected one of {', '.join(TRIGGERS)} (the firmware's triggers)")
    st.trigger = trig
    if "--level" in opts:
        st.level_rpm = parse_number(opts["--level"], "--level", ScopeError)
    if "--speed" in opts:
        if st.mode not in ("single", "normal"):
            raise ScopeError(f"--speed applies to 'scope single' and 'scope normal' (after 'scope {st.mode}', "
                             "type the 'speed' command yourself)")
        st.speed_rpm = [parse_number(v, "--speed", ScopeError) for v in opts["--speed"].split(",") if v]
        if not st.speed_rpm:
            raise ScopeError("--speed needs a setpoint in rpm (or several, comma-separated)")
    if trig == "setpoint" and st.mode in ("single", "normal") and not st.speed_rpm:
        raise ScopeError(f"--trigger setpoint with 'scope {st.mode}' would never fire: the prompt waits for the "
                         "capture, so no setpoint can be typed; give --speed RPM (written right after arming), "
                         "or 'scope arm ...', then 'speed RPM', then 'scope read'")
    if trig in ("rising", "falling") and st.level_rpm is None:
        raise ScopeError(f"--trigger {trig} needs --level <rpm> (the speed the edge crosses)")
    if trig not in ("rising", "falling") and st.level_rpm is not None:
        raise ScopeError(f"--level applies to the rising/falling speed triggers, not to {trig}")
    if "--pre" in opts:
        p = opts["--pre"]
        if p.endswith("%"):
            v = parse_number(p[:-1], "--pre", ScopeError)
            if not 0 <= v < 100:
                raise ScopeError(f"--pre {p}: expected 0..99 %")
            st.pre, st.pre_fraction = v / 100.0, True
        else:
            st.pre = _int(p, "--pre", 0, 65535)
        if trig == "immediate" and st.pre:
            raise ScopeError("--pre needs a trigger (setpoint, rising, falling): an immediate capture has no "
                             "'before'")
    if "--samples" in opts:
        st.samples = _int(opts["--samples"], "--samples", 2, 65535)
    if "--decimation" in opts:
        st.decimation = _int(opts["--decimation"], "--decimation", 1, 65535)
    if "--count" in opts:
        if st.mode != "normal":
            raise ScopeError("--count applies to 'scope normal' (repeated captures)")
        st.count = _int(opts["--count"], "--count", 1, 100000)
    if "--timeout" in opts:
        st.timeout_s = parse_number(opts["--timeout"], "--timeout", ScopeError)
        if not 0 < st.timeout_s <= 3600:
            raise ScopeError(f"--timeout {st.timeout_s:g} s: expected 0 < timeout <= 3600 s")
    st.png, st.csv = opts.get("--png"), opts.get("--csv")
    return st


def unit_groups(signals: list[tuple[str, str]]) -> list[list[tuple[str, str]]]:
    """Signals grouped by unit, in first-seen order: one plot axis each."""
    groups: dict[str, list] = {}
    for n, u in signals:
        groups.setdefault(u, []).append((n, u))
    return list(groups.values())


def save_scope_plot(path: str | Path, t_s: np.ndarray, data: dict[str, np.ndarray], units: dict[str, str], *,
                    title: str, trigger_note: str, level: tuple[str, float] | None = None) -> Path:
    """The capture as a PNG (whole or not at all): one axis per unit, t = 0 at the trigger, marked.

    ``level``: (signal, value) of a level trigger, drawn as a dotted line on that signal's axis."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from .files import output_path, write_png

    p = output_path(path, ".png", "scope --png")
    groups = unit_groups([(n, units.get(n, "")) for n in data])
    fig = Figure(figsize=(8, 1.6 + 1.9 * len(groups)))
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(groups), 1, sharex=True, squeeze=False)[:, 0]
    t = np.asarray(t_s) * 1e3
    for ax, grp in zip(axes, groups):
        for n, _ in grp:
            ax.plot(t, data[n], lw=1.1, marker="." if len(t) <= 80 else None, ms=3, label=n)
        u = grp[0][1]
        ax.set_ylabel(f"[{u or '1'}]")
        ax.axvline(0.0, color="r", lw=0.9, ls="--", label="trigger")
        if level is not None and level[0] in dict(grp):
            ax.axhline(level[1], color="r", lw=0.8, ls=":", label=f"level {level[1]:g}")
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best", fontsize=7)
    axes[-1].set_xlabel("time from trigger [ms]")
    fig.suptitle(f"{title}\n{trigger_note}", fontsize=8)
    fig.tight_layout()
    try:
        write_png(fig, p, dpi=110)
    except OSError as e:
        raise ScopeError(f"cannot write scope plot {p}: {e.strerror}") from None
    return p
