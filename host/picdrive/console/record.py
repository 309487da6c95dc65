"""Recording telemetry to CSV: the console's ``record <file.csv>`` / ``record stop``.

A recording is a plain CSV file preceded by ``#`` comment lines that say
what was recorded, so a file found on a disk months later still tells which
board, firmware and profile produced it and at what rate::

    # picdrive telemetry recording (picdrive.telemetry/2)
    # firmware: build 0x8cf0e6ac table 0x02670afb
    # profile: duy2008 hash 0x4b0e5fba
    # protocol: 1.0
    # rate_hz: 1000
    # signals: speed [rpm], current [A], duty [counts]
    # started: 2025-01-01T12:00:00+00:00
    t [s],speed [rpm],current [A],duty [counts]
    0.000000,0,0,0
    ...
    # stopped: 2025-01-01T12:00:03+00:00 samples 3000 dropped 0

Each column name carries its unit in brackets (``[1]``: a plain number).
``t`` is the board's sample time (sample counter / sample rate) in seconds
from the first recorded sample (a step test's CSV keeps 0 at the step:
``relative_time=False``), so gaps from dropped telemetry frames show as
missing time stamps, and the closing line counts them.

Where it may be written is :func:`picdrive.console.files.output_path`'s rule
(no folder created, no foreign file replaced).  The file is written whole or not at all: samples go to a hidden temporary
file in the destination folder, renamed to the requested name on
:meth:`Recorder.close` (``record stop``).  An aborted recording (lost link
without reconnection, console killed) leaves no half-written CSV under the
requested name.
"""
from __future__ import annotations

import datetime as _dt
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import PicdriveError
from ..fileio import current_umask

FORMAT_ID = "picdrive.telemetry/2"
FORMAT_FAMILY = "picdrive.telemetry/"

__all__ = ["RecordError", "Recorder", "Recording", "read_recording", "FORMAT_ID"]


class RecordError(PicdriveError):
    """A recording cannot be started, written or read."""


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _fmt(v: float) -> str:
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    f = float(v)
    if not math.isfinite(f):
        return "nan" if math.isnan(f) else ("inf" if f > 0 else "-inf")
    return f"{f:.7g}"


class Recorder:
    """Writes telemetry samples to ``path`` (CSV with a descriptive header).

    ``signals``: ``(name, unit)`` pairs in column order; ``rate_hz``: the
    telemetry sample rate; ``firmware``, ``profile``, ``protocol``: strings
    from the board's handshake.  Samples are given as ``(t_s, values)`` with
    ``values`` in signal order.
    """

    def __init__(self, path: str | Path, signals: Sequence[tuple[str, str]], rate_hz: float, *,
                 firmware: str = "", profile: str = "", protocol: str = "", relative_time: bool = True,
                 notes: Sequence[str] = (), what: str = "recording"):
        from .files import FileRuleError, output_path
        try:
            self.path = output_path(path, ".csv", what)
        except FileRuleError as e:
            raise RecordError(str(e)) from None
        if not signals:
            raise RecordError("no telemetry signals selected; choose some with 'telemetry signals NAME,...'")
        if not (rate_hz > 0 and math.isfinite(rate_hz)):
            raise RecordError(f"telemetry rate {rate_hz!r} Hz is not a positive number")
        folder = self.path.parent
        self.signals = [(str(n), str(u)) for n, u in signals]
        self.rate_hz = float(rate_hz)
        self.samples = 0
        self.dropped = 0
        self._t0: float | None = None if relative_time else 0.0
        self._first = True
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".partial", dir=folder)
        except OSError as e:
            raise RecordError(f"cannot write in {folder}: {e.strerror}") from None
        self._tmp = Path(tmp)
        self._f = os.fdopen(fd, "w", encoding="utf-8", newline="\n")
        sig = ", ".join(f"{n} [{u or '1'}]" for n, u in self.signals)
        head = [f"# picdrive telemetry recording ({FORMAT_ID})",
                f"# firmware: {firmware}", f"# profile: {profile}", f"# protocol: {protocol}",
                f"# rate_hz: {_fmt(self.rate_hz)}", f"# signals: {sig}"]
        head += [f"# {n}" for n in notes]
        head += [f"# started: {_now()}", ",".join(["t [s]"] + [f"{n} [{u or '1'}]" for n, u in self.signals])]
        self._f.write("\n".join(head) + "\n")

    @property
    def closed(self) -> bool:
        return self._f is None

    def write(self, t_s: float, values: Sequence[float], dropped: int = 0) -> None:
        """Append one sample.  ``dropped``: telemetry frames lost just before it."""
        if self._f is None:
            raise RecordError("recording already stopped")
        if len(values) != len(self.signals):
            raise RecordError(f"sample has {len(values)} values for {len(self.signals)} signals")
        if self._t0 is None:
            self._t0 = float(t_s)
        if self._first:
            self._first = False
        else:
            self.dropped += int(dropped)
        self._f.write(",".join([f"{float(t_s) - self._t0:.6f}"] + [_fmt(v) for v in values]) + "\n")
        self.samples += 1

    def close(self) -> Path:
        """Finish the file and move it to its name; returns the path."""
        if self._f is None:
            return self.path
        self._f.write(f"# stopped: {_now()} samples {self.samples} dropped {self.dropped}\n")
        self._f.close()
        self._f = None
        try:
            os.chmod(self._tmp, 0o666 & ~current_umask())    # mkstemp made it 0600; a CSV is an ordinary file
            os.replace(self._tmp, self.path)
        except OSError as e:
            self._tmp.unlink(missing_ok=True)
            raise RecordError(f"cannot write {self.path}: {e.strerror}") from None
        return self.path

    def abort(self) -> None:
        """Discard the recording (nothing is left under the requested name)."""
        if self._f is not None:
            self._f.close()
            self._f = None
        self._tmp.unlink(missing_ok=True)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, *exc):
        if exc_type is None:
            self.close()
        else:
            self.abort()


@dataclass
class Recording:
    """A recording read back: header fields, column names and units, data."""

    meta: dict[str, str]
    columns: list[str]
    units: list[str]
    data: np.ndarray = field(repr=False)          # shape (samples, 1 + signals); column 0 is t (s)
    samples: int = 0
    dropped: int = 0

    @property
    def rate_hz(self) -> float:
        return float(self.meta["rate_hz"])

    def column(self, name: str) -> np.ndarray:
        try:
            return self.data[:, self.columns.index(name)]
        except ValueError:
            raise RecordError(f"recording has no column {name!r}; it has {', '.join(self.columns)}") from None


def read_recording(path: str | Path) -> Recording:
    """Read a file written by :class:`Recorder`."""
    p = Path(path)
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
    except OSError as e:
        raise RecordError(f"cannot read recording {p}: {e.strerror}") from None
    if not lines or FORMAT_FAMILY not in lines[0]:
        raise RecordError(f"{p} is not a picdrive telemetry recording (first line should name {FORMAT_ID})")
    meta: dict[str, str] = {}
    rows: list[list[float]] = []
    columns: list[str] | None = None
    samples = dropped = None
    for ln in lines[1:]:
        if ln.startswith("#"):
            key, _, val = ln[1:].strip().partition(":")
            meta[key.strip()] = val.strip()
            if key.strip() == "stopped":
                parts = val.split()
                samples, dropped = int(parts[parts.index("samples") + 1]), int(parts[parts.index("dropped") + 1])
        elif columns is None:
            columns = [c.split(" [", 1)[0] for c in ln.split(",")]   # names without their units
        elif ln:
            rows.append([float(x) for x in ln.split(",")])
    if columns is None or "signals" not in meta or "rate_hz" not in meta:
        raise RecordError(f"{p}: header incomplete (needs 'signals', 'rate_hz' and a column row)")
    units = ["s"] + [s.rsplit("[", 1)[1].rstrip("]") for s in meta["signals"].split(", ")]
    if columns and columns[0] == "t":
        columns[0] = "t_s"                      # one name for the time column in both versions
    data = np.array(rows, dtype=float).reshape(len(rows), len(columns))
    return Recording(meta, columns, units, data, samples if samples is not None else len(rows),
                     dropped or 0)
