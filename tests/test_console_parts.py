"""The console's parts that need no board: recorder, step analysis and plot, views."""
import math
import os
import time

import numpy as np
import pytest

from picdrive.console.plot import LivePlot, PlotError, TextView, sparkline
from picdrive.console.record import Recorder, RecordError, read_recording
from picdrive.errors import PicdriveError
from picdrive.console.files import written_by_picdrive
from picdrive.console.step import StepError, StepRecord, analyse_step, parse_step_args, save_step_plot
from picdrive.analysis.metrics import step_metrics

SIGS = [("speed_rpm", "rpm"), ("current_a", "A")]


# --------------------------------------------------------------------------- recorder

def test_recorder_header_data_and_drops(tmp_path):
    p = tmp_path / "run.csv"
    rec = Recorder(p, SIGS, 500.0, firmware="duy2008-abc", profile="duy2008 hash 01020304", protocol="1")
    rec.write(10.000, [0, 0.1])
    rec.write(10.002, [12.5, 0.2])
    rec.write(10.008, [30.25, 0.3], dropped=2)
    assert not p.exists(), "the CSV appears only when the recording is stopped"
    assert rec.close() == p
    r = read_recording(p)
    assert r.meta["firmware"] == "duy2008-abc"
    assert r.meta["profile"] == "duy2008 hash 01020304"
    assert r.rate_hz == 500.0
    assert r.columns == ["t_s", "speed_rpm", "current_a"]
    assert r.units == ["s", "rpm", "A"]
    assert r.samples == 3 and r.dropped == 2
    assert r.column("t_s") == pytest.approx([0.0, 0.002, 0.008])
    assert r.column("speed_rpm") == pytest.approx([0, 12.5, 30.25])
    with pytest.raises(RecordError, match="no column 'duty'"):
        r.column("duty")
    assert [q.name for q in tmp_path.iterdir()] == ["run.csv"], "no temporary file left behind"
    mask = os.umask(0o022)
    os.umask(mask)
    assert p.stat().st_mode & 0o777 == 0o666 & ~mask, "permissions of an ordinary file, not mkstemp's 0600"


def test_recorder_abort_leaves_nothing(tmp_path):
    p = tmp_path / "run.csv"
    with pytest.raises(RuntimeError):
        with Recorder(p, SIGS, 100.0) as rec:
            rec.write(0.0, [1, 2])
            raise RuntimeError("link lost")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("path, sigs, rate, msg", [
    ("run.txt", SIGS, 100.0, "must end in .csv"),
    ("run.csv", [], 100.0, "no telemetry signals"),
    ("run.csv", SIGS, 0.0, "not a positive number"),
    ("afile/run.csv", SIGS, 100.0, "is a file, not a folder"),
])
def test_recorder_rejects_bad_requests(tmp_path, path, sigs, rate, msg):
    (tmp_path / "afile").write_text("x")
    with pytest.raises(RecordError, match=msg):
        Recorder(tmp_path / path, sigs, rate)


def test_recorder_wrong_width_and_after_close(tmp_path):
    rec = Recorder(tmp_path / "a.csv", SIGS, 100.0)
    with pytest.raises(RecordError, match="2 signals"):
        rec.write(0.0, [1.0])
    rec.close()
    with pytest.raises(RecordError, match="already stopped"):
        rec.write(0.0, [1.0, 2.0])


def test_read_recording_rejects_foreign_csv(tmp_path):
    p = tmp_path / "x.csv"
    p.write_text("a,b\n1,2\n")
    with pytest.raises(RecordError, match="not a picdrive telemetry recording"):
        read_recording(p)


# --------------------------------------------------------------------------- step

def test_parse_step_args():
    assert parse_step_args(["0", "2400", "--hold", "1.0"]) == (0.0, 2400.0, 1.0, None)
    assert parse_step_args(["2400", "1200", "--hold=0.5", "--png", "s.png"]) == (2400.0, 1200.0, 0.5, "s.png")
    assert parse_step_args(["0", "100"])[2] == 1.0
    for bad, msg in [(["0"], "usage"), (["0", "x"], "not a number"), (["5", "5"], "no step"),
                     (["0", "1", "--hold"], "needs a value"), (["0", "1", "--hold", "100"], "outside"),
                     (["0", "1", "--fast"], "unknown option"), (["0", "1", "--png", "a.jpg"], "must end in .png"),
                     (["0", "nan"], "finite")]:
        with pytest.raises(StepError, match=msg):
            parse_step_args(bad)


def _second_order(fs=1000.0, hold=1.0, y0=0.0, y1=2400.0, zeta=0.6, wn=40.0):
    t = np.arange(0, hold, 1 / fs)
    wd = wn * math.sqrt(1 - zeta**2)
    x = 1 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta / math.sqrt(1 - zeta**2) * np.sin(wd * t))
    return t, y0 + (y1 - y0) * x


def test_analyse_step_matches_metrics_module_and_theory():
    t, y = _second_order()
    rec = StepRecord(0.0, 2400.0, 1.0, t, y, 1e-3)
    m = analyse_step(rec)
    assert m == step_metrics(t, y, 2400.0, y0=0.0, t_step=0.0)
    zeta = 0.6
    assert m.overshoot_pct == pytest.approx(100 * math.exp(-math.pi * zeta / math.sqrt(1 - zeta**2)), rel=1e-3)
    assert "overshoot 9.48 %" in rec.summary()


def test_analyse_step_y0_from_pre_step_samples():
    t, y = _second_order(y0=1000.0, y1=2000.0)
    rec = StepRecord(1000.0, 2000.0, 1.0, t, y + 5.0 * (t < 0), 1e-3)
    m = analyse_step(rec, pre_speed_rpm=np.full(50, 990.0))
    assert m == step_metrics(t, y, 2000.0, y0=990.0, t_step=0.0)
    with pytest.raises(StepError, match="samples after the step"):
        analyse_step(StepRecord(0, 1, 1, np.array([-1.0, 0.0]), np.array([0.0, 0.0]), 1e-3))


def test_save_step_plot(tmp_path):
    t, y = _second_order()
    t = np.concatenate([np.arange(-0.05, 0, 1e-3), t])
    y = np.concatenate([np.zeros(50), y])
    rec = StepRecord(0.0, 2400.0, 1.0, t, y, 1e-3, signals={"current_a": np.ones_like(t)},
                     units={"current_a": "A"}, firmware="fw", profile="duy2008")
    analyse_step(rec)
    # picdrive's one output rule (docs/outputs.md): a missing folder is created, a parent that is a file refused
    (tmp_path / "afile").write_text("x")
    with pytest.raises(PicdriveError, match=f"{tmp_path / 'afile'} is a file, not a folder"):
        save_step_plot(rec, tmp_path / "afile" / "step.png")
    assert (tmp_path / "afile").read_text() == "x"
    assert save_step_plot(rec, tmp_path / "out" / "step.png").is_file()
    p = save_step_plot(rec, tmp_path / "step.png")
    data = p.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    assert written_by_picdrive(p)
    p2 = save_step_plot(rec, tmp_path / "step.png")          # picdrive's own file: replaced
    assert p2 == p and p.is_absolute()
    foreign = tmp_path / "photo.png"
    foreign.write_bytes(b"\x89PNG\r\n\x1a\nnot picdrive's")
    with pytest.raises(PicdriveError, match="is not a file picdrive wrote"):
        save_step_plot(rec, foreign)
    assert foreign.read_bytes() == b"\x89PNG\r\n\x1a\nnot picdrive's"
    with pytest.raises(StepError, match="must end in .png"):
        save_step_plot(rec, tmp_path / "step.jpg")


def test_faulted_step_plot_marks_the_fault_instead_of_metrics(tmp_path):
    t, y = _second_order()
    rec = StepRecord(0.0, 2400.0, 1.0, t, y, 1e-3, fault="stall", firmware="fw")
    p = save_step_plot(rec, tmp_path / "fault.png")
    fig_text = p.read_bytes()
    assert fig_text[:4] == b"\x89PNG" and rec.metrics is None
    # the same record analysed draws the metrics box; the faulted one draws the fault box (differs)
    ok = StepRecord(0.0, 2400.0, 1.0, t, y, 1e-3, firmware="fw")
    analyse_step(ok)
    assert save_step_plot(ok, tmp_path / "ok.png").read_bytes() != fig_text


# --------------------------------------------------------------------------- views

def test_sparkline_and_text_view():
    assert sparkline([0, 1, 2, 3, 4, 5, 6, 7]) == "▁▂▃▄▅▆▇█"
    assert sparkline([1, 1, 1]) == "▁▁▁"
    assert sparkline(range(100), width=10, ascii_only=True) == "_.--=+**#@"   # round(v/90*7) for v = 0, 10, ..., 90
    assert len(sparkline(range(1000), width=24)) == 24
    tv = TextView(SIGS, window_s=1.0, ascii_only=True)
    assert tv.render() == "(no telemetry yet)"
    for k in range(3000):
        tv.feed(k / 1000, [float(k), 0.5])
    line = tv.render()
    assert line.startswith("t    2.999 s | speed_rpm 2999 rpm [1999..2999] | current_a 0.5 A [0.5..0.5] | ")


def test_live_plot_process_renders_png(tmp_path):
    png = tmp_path / "live.png"
    lp = LivePlot(SIGS, png_path=png, backend="Agg", png_interval_s=0.2)
    try:
        assert lp.alive and lp.backend == "agg"
        t0 = time.monotonic()
        for k in range(2000):
            lp.feed(k / 1000, [math.sin(k / 100), 0.1])
        assert time.monotonic() - t0 < 1.0, "feeding must never block the caller"
    finally:
        lp.close()
    assert not lp.alive
    assert lp.total_drawn == lp.sent_samples == 2000 and lp.dropped_batches == 0
    assert png.read_bytes()[:4] == b"\x89PNG"
    assert [q.name for q in tmp_path.iterdir()] == ["live.png"]


def test_live_plot_without_window_or_png_is_refused():
    with pytest.raises(PlotError, match="cannot open a window"):
        LivePlot(SIGS, backend="Agg")
    with pytest.raises(PlotError, match="no telemetry signals"):
        LivePlot([], backend="Agg")


# --------------------------------------------------------------------------- live plot

def test_plot_buffer_segments_windows_and_envelopes():
    from picdrive.console.plot import PlotBuffer, unit_axes
    b = PlotBuffer(2, window_s=1.0)
    for k in range(3000):                       # 3 s at 1 kHz: only the last second is kept
        b.feed(k / 1000, [float(k), 0.0])
    assert len(b.t) == 1001 and b.t[0] == pytest.approx(1.999) and b.segments == 1
    # the telemetry reconfigured (a step, a new rate): time restarts; a new segment, no line back in time
    b.feed(0.0, [1.0, 1.0])
    assert list(b.t) == [0.0] and b.segments == 2 and b.total == 3001
    # dense data: a min/max envelope with the mean, never wider than the samples
    b = PlotBuffer(1, window_s=10.0)
    for k in range(9000):
        b.feed(k / 1000, [(-1.0) ** k])          # a +-1 square wave at the sample rate: a "solid band"
    t, [(mean, lo, hi)] = b.traces(points=1000)
    assert len(t) == 1000 and np.all(lo == -1.0) and np.all(hi == 1.0) and np.allclose(mean, 0.0, atol=0.2)
    sparse = PlotBuffer(1, window_s=10.0)
    for k in range(500):
        sparse.feed(k / 1000, [float(k)])
    t, [(y, lo, hi)] = sparse.traces(points=1000)
    assert lo is None and hi is None and len(y) == 500       # few samples: the line itself
    assert unit_axes([("speed", "rpm"), ("current", "A"), ("setpoint", "rpm")]) == ([0, 1, 0], ["rpm", "A"])


def test_live_plot_png_follows_reconfiguration(tmp_path):
    png = tmp_path / "live.png"
    lp = LivePlot([("speed", "rpm"), ("setpoint", "rpm")], png_path=png, backend="Agg", png_interval_s=0.0)
    try:
        for k in range(3000):
            lp.feed(k / 1000, [float(k % 50), 10.0])
        lp.control("window", 2.0)
        lp.control("pause", False)
        lp.control("ylim", "rpm", -5.0, 60.0)
        lp.control("signals", [("current", "A")])
        for k in range(100):
            lp.feed(k / 1000, [0.5])
    finally:
        lp.close()
    assert lp.total_drawn == 100                # the reconfiguration started a new buffer
    assert written_by_picdrive(png)
