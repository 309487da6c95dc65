"""Live telemetry views for the console: a plot window and a compact text view.

:class:`LivePlot` draws the selected telemetry signals in a matplotlib window
that updates while the console prompt stays responsive: the window lives in a
separate process (``multiprocessing``, spawn start method, so no state of the
console's threads or serial port is inherited) fed through a bounded queue.
Samples are sent in batches of at most ``batch_s`` seconds; if the plot
process falls behind, whole batches are dropped (counted in
:attr:`LivePlot.dropped_batches`) rather than ever blocking the telemetry
reader.

Where no display exists (no ``DISPLAY``/``WAYLAND_DISPLAY`` on Linux, or
only non-interactive matplotlib backends installed), the same process renders
with the Agg backend into a PNG file that it rewrites (atomically) about once
a second; an image viewer that reloads on change then shows a live plot, e.g.
over ssh.

:class:`TextView` is the compact text alternative: one line per refresh with
the time, each signal's latest value with its unit and its min..max over the
window, and a sparkline of the first signal.
"""
from __future__ import annotations

import math
import multiprocessing as mp
import os
import queue
import sys
import time
from collections import deque
from pathlib import Path
from typing import Sequence

from ..errors import PicdriveError

__all__ = ["PlotError", "LivePlot", "PlotBuffer", "TextView", "display_available", "sparkline", "unit_axes"]

_NON_INTERACTIVE = {"agg", "pdf", "ps", "svg", "pgf", "cairo", "template", "module://matplotlib_inline.backend_inline"}


class PlotError(PicdriveError):
    """The plot process could not be started."""


def display_available() -> bool:
    """True when a GUI window can be opened (Windows/macOS, or X11/Wayland on Linux)."""
    if sys.platform in ("win32", "darwin"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


# ---------------------------------------------------------------------------
# plot process
# ---------------------------------------------------------------------------

ENVELOPE_POINTS = 1500
"""Above this many samples in the window a trace is drawn as a min/max envelope per pixel column
(and its mean), not as a line zig-zagging into a solid band."""


class PlotBuffer:
    """The samples a live plot shows: ``window_s`` seconds, one segment.

    A sample earlier than the last one (the telemetry was reconfigured: the board's sample
    counter or the rate changed) starts a new segment: the history is cleared, so the plot
    never draws a line back in time; :attr:`segments` counts them.  Samples older than the
    window are dropped as they leave it (no fixed cap)."""

    def __init__(self, n_signals: int, window_s: float):
        self.n = n_signals
        self.window_s = float(window_s)
        self.segments = 1
        self.total = 0
        self.clear()

    def clear(self) -> None:
        self.t: deque = deque()
        self.y = [deque() for _ in range(self.n)]

    def feed(self, t: float, vals) -> None:
        if self.t and t < self.t[-1]:
            self.clear()
            self.segments += 1
        self.t.append(t)
        for d, v in zip(self.y, vals):
            d.append(v)
        self.total += 1
        while self.t and self.t[0] < t - self.window_s:
            self.t.popleft()
            for d in self.y:
                d.popleft()

    def traces(self, points: int = ENVELOPE_POINTS):
        """(t, [(mean, lo, hi) or (y, None, None) per signal]): the envelope when dense."""
        import numpy as np
        t = np.fromiter(self.t, float, len(self.t))
        ys = [np.fromiter(d, float, len(d)) for d in self.y]
        if t.size <= points:
            return t, [(y, None, None) for y in ys]
        k = t.size // points
        m = (t.size // k) * k
        tb = t[t.size - m:].reshape(-1, k).mean(axis=1)
        out = []
        for y in ys:
            yb = y[y.size - m:].reshape(-1, k)
            out.append((np.nanmean(yb, axis=1), np.nanmin(yb, axis=1), np.nanmax(yb, axis=1)))
        return tb, out


def unit_axes(signals):
    """Axis index of each signal: signals of one unit share an axis (first-seen order)."""
    units: list[str] = []
    out = []
    for _, u in signals:
        if u not in units:
            units.append(u)
        out.append(units.index(u))
    return out, units


def _plot_main(q, status, signals, window_s, png_path, backend, png_interval_s):
    """Body of the plot process: drain the queue, redraw, until None or window closed.

    Queue items: a list of (t, values) samples, or a control tuple: ("signals", [(name, unit)]),
    ("window", s), ("pause", bool), ("ylim", unit, lo, hi) (lo = hi = None: automatic)."""
    try:
        import matplotlib
        if backend:
            matplotlib.use(backend, force=True)
        import matplotlib.pyplot as plt
        import numpy as np
        be = matplotlib.get_backend().lower()
        interactive = be not in _NON_INTERACTIVE
        if not interactive and not png_path:
            status.put(("error", f"matplotlib backend {be!r} cannot open a window and no PNG file was given"))
            return
        fig = plt.figure(figsize=(8, 5))
        state = {"paused": False, "ylim": {}}

        def build(sigs):
            fig.clf()
            ax_of, units = unit_axes(sigs)
            axes = fig.subplots(len(units), 1, sharex=True, squeeze=False)[:, 0]
            lines = []
            for (name, unit), k in zip(sigs, ax_of):
                (ln,) = axes[k].plot([], [], lw=1.0, label=name)
                lines.append((ln, axes[k], None))
            for ax, unit in zip(axes, units):
                ax.set_ylabel(f"[{unit or '1'}]")
                ax.grid(True, alpha=0.3)
                ax.legend(loc="upper left", fontsize=7)
            axes[-1].set_xlabel("board time t [s]")
            return axes, lines, units, ax_of

        axes, lines, units, ax_of = build(signals)
        buf = PlotBuffer(len(signals), window_s)
        if interactive:
            plt.show(block=False)
        status.put(("ready", be))
    except Exception as e:                      # report, never hang the console
        status.put(("error", f"{type(e).__name__}: {e}"))
        return

    last_png = 0.0
    dirty = False
    running = True
    while running:
        if interactive and not plt.fignum_exists(fig.number):
            break                               # the user closed the window
        try:
            item = q.get(timeout=0.05)
        except queue.Empty:
            item = ()
        while item is not None:
            if isinstance(item, tuple) and item:
                kind = item[0]
                if kind == "signals":
                    signals = item[1]
                    axes, lines, units, ax_of = build(signals)
                    buf = PlotBuffer(len(signals), buf.window_s)
                elif kind == "window":
                    buf.window_s = float(item[1])
                elif kind == "pause":
                    state["paused"] = bool(item[1])
                elif kind == "ylim":
                    state["ylim"][item[1]] = (item[2], item[3])
                dirty = True
            else:
                for t, vals in item:
                    buf.feed(t, vals)
                    dirty = True
            try:
                item = q.get_nowait()
            except queue.Empty:
                break
        if item is None:
            running = False
        if dirty and buf.t and not state["paused"]:
            t, tr = buf.traces()
            for (ln, ax, fill), (y, lo, hi) in zip(lines, tr):
                ln.set_data(t, y)
            for i, (ln, ax, fill) in enumerate(lines):
                if fill is not None:
                    fill.remove()
                y, lo, hi = tr[i]
                fill = ax.fill_between(t, lo, hi, alpha=0.3, color=ln.get_color(), lw=0) if lo is not None else None
                lines[i] = (ln, ax, fill)
            for k, ax in enumerate(axes):
                fixed = state["ylim"].get(units[k])
                if fixed and fixed[0] is not None:
                    ax.set_ylim(*fixed)
                    continue
                ys = [np.concatenate([a for a in tr[i] if a is not None]) for i in range(len(lines)) if ax_of[i] == k]
                y = np.concatenate(ys) if ys else np.empty(0)
                y = y[np.isfinite(y)]
                if y.size:
                    lo, hi = float(y.min()), float(y.max())
                    pad = 0.05 * (hi - lo) if hi > lo else max(1.0, abs(hi) * 0.05)
                    ax.set_ylim(lo - pad, hi + pad)
            t_end = buf.t[-1]
            axes[-1].set_xlim(t_end - buf.window_s, t_end)
            dense = " (min/max envelope)" if tr and tr[0][1] is not None else ""
            fig.suptitle(f"picdrive telemetry (live): last {buf.window_s:g} s{dense}"
                         + (f", segment {buf.segments}" if buf.segments > 1 else ""), fontsize=9)
            dirty = False
            if interactive:
                fig.canvas.draw_idle()
        if interactive:
            plt.pause(0.01)
        now = time.monotonic()
        if png_path and (now - last_png >= png_interval_s or not running) and buf.t:
            _save_png(fig, png_path)
            last_png = now
    status.put(("done", buf.total))
    plt.close(fig)


def _save_png(fig, path: str) -> None:
    from .files import write_png
    try:
        write_png(fig, Path(path), dpi=90)
    except OSError:                  # the folder went away: keep plotting on screen, never a traceback
        pass


class LivePlot:
    """A live plot of telemetry signals in a separate process.

    ``signals``: ``(name, unit)`` pairs; ``window_s``: seconds of history
    shown; ``png_path``: where to render when there is no display (or in
    addition to the window when given); ``backend``: force a matplotlib
    backend (``"Agg"`` for headless).  Call :meth:`feed` from the telemetry
    reader, :meth:`close` to end.
    """

    def __init__(self, signals: Sequence[tuple[str, str]], *, window_s: float = 5.0,
                 png_path: str | Path | None = None, backend: str | None = None,
                 png_interval_s: float = 1.0, batch_s: float = 0.05, start_timeout_s: float = 30.0):
        if not signals:
            raise PlotError("no telemetry signals selected; choose some with 'telemetry signals NAME,...'")
        self.signals = [(str(n), str(u)) for n, u in signals]
        self.png_path = str(png_path) if png_path else None
        self.batch_s = batch_s
        self.dropped_batches = 0
        self.sent_samples = 0
        self._batch: list = []
        self._batch_t = time.monotonic()
        ctx = mp.get_context("spawn")
        self._q = ctx.Queue(maxsize=64)
        self._status = ctx.Queue()
        self._proc = ctx.Process(target=_plot_main, name="picdrive-plot", daemon=True,
                                 args=(self._q, self._status, self.signals, float(window_s), self.png_path,
                                       backend, float(png_interval_s)))
        self._proc.start()
        deadline = time.monotonic() + start_timeout_s
        while True:
            try:
                kind, info = self._status.get(timeout=0.1)
                break
            except queue.Empty:
                if not self._proc.is_alive():
                    self._kill()
                    raise PlotError(f"the plot process ended at start (exit code {self._proc.exitcode})") from None
                if time.monotonic() > deadline:
                    self._kill()
                    raise PlotError(f"the plot process did not start within {start_timeout_s:.0f} s") from None
        if kind != "ready":
            self._kill()
            raise PlotError(f"cannot open a plot: {info}")
        self.backend = info
        self.total_drawn: int | None = None

    @property
    def alive(self) -> bool:
        return self._proc.is_alive()

    def feed(self, t_s: float, values: Sequence[float]) -> None:
        """Queue one sample (never blocks; drops a batch if the plot lags)."""
        self._batch.append((float(t_s), [float(v) for v in values]))
        now = time.monotonic()
        if now - self._batch_t >= self.batch_s:
            self.flush()

    def control(self, *msg) -> None:
        """Send a control message (see :func:`_plot_main`): ("signals", sigs), ("window", s),
        ("pause", bool), ("ylim", unit, lo, hi)."""
        self.flush()
        if msg[0] == "signals":
            self.signals = [(str(n), str(u)) for n, u in msg[1]]
        try:
            self._q.put(tuple(msg), timeout=1.0)
        except queue.Full:
            raise PlotError("the plot process does not keep up; 'plot off' and 'plot' again") from None

    def flush(self) -> None:
        if not self._batch:
            return
        batch, self._batch = self._batch, []
        self._batch_t = time.monotonic()
        try:
            self._q.put_nowait(batch)
            self.sent_samples += len(batch)
        except queue.Full:
            self.dropped_batches += 1

    def close(self, timeout_s: float = 5.0) -> None:
        """Flush, ask the process to end (final PNG written), wait for it."""
        if self._proc.is_alive():
            self.flush()
            try:
                self._q.put(None, timeout=1.0)
            except queue.Full:
                pass
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline:
                try:
                    kind, info = self._status.get(timeout=0.1)
                except queue.Empty:
                    if not self._proc.is_alive():
                        break
                    continue
                if kind == "done":
                    self.total_drawn = int(info)
                    break
            self._proc.join(timeout=max(0.1, deadline - time.monotonic()))
        self._kill()

    def _kill(self) -> None:
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(timeout=2.0)
        for q in (self._q, self._status):
            q.cancel_join_thread()
            q.close()


# ---------------------------------------------------------------------------
# text view
# ---------------------------------------------------------------------------

_BARS = "▁▂▃▄▅▆▇█"


def sparkline(values: Sequence[float], width: int = 24, ascii_only: bool = False) -> str:
    """A one-line sketch of ``values`` (resampled to ``width`` characters)."""
    vals = [v for v in values if v == v]
    if not vals:
        return ""
    if len(vals) > width:
        step = len(vals) / width
        vals = [vals[min(len(vals) - 1, int(i * step))] for i in range(width)]
    lo, hi = min(vals), max(vals)
    bars = "_.-=+*#@" if ascii_only else _BARS
    if hi - lo <= 1e-12 * max(1.0, abs(hi)):
        return bars[0] * len(vals)
    k = len(bars) - 1
    return "".join(bars[int(round((v - lo) / (hi - lo) * k))] for v in vals)


def _num(v: float) -> str:
    if not math.isfinite(v):
        return str(v)
    a = abs(v)
    if a >= 1000 or a == 0:
        return f"{v:.0f}"
    if a >= 10:
        return f"{v:.1f}"
    if a >= 1:
        return f"{v:.2f}"
    return f"{v:.3g}"


class TextView:
    """Compact text view of telemetry: keeps ``window_s`` of samples, renders one line."""

    def __init__(self, signals: Sequence[tuple[str, str]], window_s: float = 2.0, spark_width: int = 24,
                 ascii_only: bool | None = None):
        self.signals = [(str(n), str(u)) for n, u in signals]
        self.window_s = window_s
        self.spark_width = spark_width
        if ascii_only is None:
            enc = (getattr(sys.stdout, "encoding", "") or "").lower()
            ascii_only = "utf" not in enc
        self.ascii_only = ascii_only
        self._t: deque = deque()
        self._v: deque = deque()
        self.count = 0

    def feed(self, t_s: float, values: Sequence[float]) -> None:
        self._t.append(float(t_s))
        self._v.append([float(v) for v in values])
        self.count += 1
        while self._t and self._t[0] < self._t[-1] - self.window_s:
            self._t.popleft()
            self._v.popleft()

    def render(self) -> str:
        """One line: time, each signal latest [min..max] unit, sparkline of the first signal."""
        if not self._t:
            return "(no telemetry yet)"
        parts = [f"t {self._t[-1]:8.3f} s"]
        cols = list(zip(*self._v))
        for (name, unit), col in zip(self.signals, cols):
            u = f" {unit}" if unit and unit != "1" else ""
            parts.append(f"{name} {_num(col[-1])}{u} [{_num(min(col))}..{_num(max(col))}]")
        if cols:
            parts.append(sparkline(cols[0], self.spark_width, self.ascii_only))
        return " | ".join(parts)
