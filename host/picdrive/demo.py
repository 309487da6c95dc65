"""``picdrive demo``: the whole chain on a bundled profile, end to end.

1. design: the three methods (fuzzy-hinf, mixed-pid, zn), each re-run with the
   options recorded in the committed design of ``examples/`` (default options
   where there is none) and verified; the recomputed gains are compared with
   the committed ones;
2. firmware: ``picdrive firmware`` for each verified design (rendered,
   build-checked with gcc and avr-gcc, written whole);
3. twin: each firmware runs in the motor twin behind a socket, driven only
   through ``picdrive.link``: a speed step from rest to
   :meth:`Profile.speed_step_rpm` and, once settled, a load-torque step
   (``control.load_torque_n_m``), recorded by the board's own telemetry;
4. report: ``report.md`` with the tables and PNG plots.

Everything is produced in a temporary folder and moved to ``-o`` (default
``out/demo``) only when the whole chain succeeded.
"""
from __future__ import annotations

import json
import math
import shutil
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import PicdriveError
from .analysis.metrics import step_metrics

METHODS = ("fuzzy-hinf", "mixed-pid", "zn")
TELEMETRY = ("speed", "setpoint", "voltage", "current")
RPM = 60.0 / (2.0 * math.pi)


@dataclass
class TwinRun:
    """What one firmware did in the twin (telemetry arrays, SI/rpm units as the board reports)."""

    method: str
    t: np.ndarray
    speed_rpm: np.ndarray
    setpoint_rpm: np.ndarray
    voltage_v: np.ndarray
    current_a: np.ndarray
    t_load_s: float
    target_rpm: float
    dropped: int
    true_final_rpm: float
    metrics: dict = field(default_factory=dict)


def _say(msg: str) -> None:
    print(msg, flush=True)


def redesign(profile, method: str, progress: bool):
    """Design with the options of the committed design (if any); returns (result, committed or None)."""
    from .gate import run_design
    from .result import DesignError, load_design

    committed = None
    opts: dict = {}
    if profile.path is not None:
        p = profile.path.with_name(f"{profile.path.stem}.{method}.design.json")
        if p.exists():
            try:
                committed = load_design(p)
                opts = dict(committed.options)
            except DesignError as e:
                _say(f"  note: committed design {p.name} unreadable ({e}); default options")
    r = run_design(profile, method, progress=progress, **opts)
    return r, committed


def gain_difference(a, b) -> float:
    """Largest relative difference between two laws' rule gains (0 = identical)."""
    if a is None or b is None or a.n_rules != b.n_rules:
        return math.inf
    worst = 0.0
    for ra, rb in zip(a.rules, b.rules):
        for k in ("kp", "ki", "kd", "kc"):
            x, y = getattr(ra, k), getattr(rb, k)
            scale = max(abs(x), abs(y))
            if scale > 0:
                worst = max(worst, abs(x - y) / scale)
    return worst


def run_in_twin(profile, firmware_dir: Path, method: str, *, step_s: float, load_s: float) -> TwinRun:
    """Speed step then load step on the twin, commanded and recorded through picdrive.link."""
    from picdrive_hil.scenario import load_step_on_link
    from picdrive_hil.twin import Twin

    from .link.client import Link

    target = profile.speed_step_rpm()
    load = profile.control.load_torque_n_m
    tw = Twin(profile, firmware_dir)
    srv = tw.serve(realtime=True)
    try:
        with Link.open(srv.url) as ln:
            ln.start_keepalive()
            ln.configure_telemetry(TELEMETRY, decimation=1)
            ln.flush_samples()
            ln.set_speed(target)
            ln.start()
            first, second, _ = load_step_on_link(tw, ln, load, step_s, load_s)
            true_final = tw.state()["speed_rad_s"] * RPM
            dropped = ln.telemetry_stats.dropped
            ln.stop()
    finally:
        srv.stop()
        tw.close()
    rec = np.concatenate([first, second])
    if rec.size < 10:
        raise PicdriveError(f"the twin sent only {rec.size} telemetry samples for {method}; "
                            "the link or the firmware did not stream")
    t = rec["t"] - rec["t"][0]
    t_load = float(t[len(first)]) if len(first) < len(rec) else float(t[-1])
    return TwinRun(method, t, rec["speed"].astype(float), rec["setpoint"].astype(float),
                   rec["voltage"].astype(float), rec["current"].astype(float), t_load, target, int(dropped),
                   float(true_final))


def twin_metrics(profile, run: TwinRun) -> dict:
    """Step metrics of the speed step, load-step dip and recovery, and the physical-limit ratio."""
    m = profile.motor
    sel = run.t < run.t_load_s
    sm = step_metrics(run.t[sel], run.speed_rpm[sel], run.target_rpm, y0=0.0, t_step=0.0)
    after = ~sel
    dip = float(run.target_rpm - np.min(run.speed_rpm[after])) if after.any() else math.nan
    band = 0.02 * run.target_rpm
    rec_s = math.nan
    if after.any():
        ta, ya = run.t[after], run.speed_rpm[after]
        outside = np.nonzero(np.abs(ya - run.target_rpm) > band)[0]
        rec_s = 0.0 if outside.size == 0 else (math.inf if outside[-1] == ya.size - 1
                                                else float(ta[outside[-1] + 1] - run.t_load_s))
    tail = run.speed_rpm[run.t > run.t[-1] - 0.1 * (run.t[-1] - run.t_load_s)]
    sse_load = float(run.target_rpm - np.mean(tail)) if tail.size else math.nan
    # fastest possible rise from rest at the current limit against the load:
    # t_min = J w / (Kt Imax - T_load)  (the 10-90 % rise is compared with 0.8 of it)
    w = run.target_rpm / RPM
    torque = m.kt_n_m_per_a * profile.inverter.current_limit_a
    t_min = m.inertia_kg_m2 * w / torque
    t90 = sm.rise_time_s + _first_time(run.t[sel], run.speed_rpm[sel], 0.1 * run.target_rpm)
    return {
        "rise_ms": sm.rise_time_s * 1e3, "settling_ms": sm.settling_time_s * 1e3,
        "overshoot_pct": sm.overshoot_pct, "sse_pct": sm.steady_state_error_pct,
        "load_dip_rpm": dip, "load_recovery_ms": rec_s * 1e3, "sse_under_load_pct": 100 * abs(sse_load) / run.target_rpm,
        "peak_current_a": float(np.max(np.abs(run.current_a))), "peak_voltage_v": float(np.max(np.abs(run.voltage_v))),
        "t_min_ms": t_min * 1e3, "t90_over_tmin": t90 / t_min if t_min > 0 else math.nan,
        "dropped_samples": run.dropped, "true_final_rpm": run.true_final_rpm,
    }


def _first_time(t, y, level) -> float:
    idx = np.nonzero(y >= level)[0]
    return float(t[idx[0]]) if idx.size else math.inf


def plot_runs(profile, runs: list[TwinRun], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(3, 1, figsize=(9, 9), sharex=True)
    for r in runs:
        ax[0].plot(r.t, r.speed_rpm, label=r.method, lw=1.2)
        ax[1].plot(r.t, r.voltage_v, label=r.method, lw=1.0)
        ax[2].plot(r.t, r.current_a, label=r.method, lw=1.0)
    if runs:
        ax[0].plot(runs[0].t, runs[0].setpoint_rpm, "k--", lw=0.8, label="setpoint")
        for a in ax:
            a.axvline(runs[0].t_load_s, color="0.6", lw=0.8, ls=":")
    ax[0].set_ylabel("speed (rpm)")
    ax[1].set_ylabel("law output u (V)")
    ax[2].set_ylabel("bus current (A)")
    ax[2].set_xlabel("time (s)")
    ax[0].set_title(f"{profile.name}: firmware in the twin, speed step then "
                    f"{profile.control.load_torque_n_m:g} N m load step (dotted line)")
    ax[0].legend(loc="lower right")
    for a in ax:
        a.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_zoom(profile, runs: list[TwinRun], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    for r in runs:
        s = r.t < min(r.t_load_s, 0.3)
        ax[0].plot(r.t[s] * 1e3, r.speed_rpm[s], label=r.method)
        a = (r.t >= r.t_load_s - 0.02) & (r.t <= r.t_load_s + 0.25)
        ax[1].plot((r.t[a] - r.t_load_s) * 1e3, r.speed_rpm[a], label=r.method)
    tgt = runs[0].target_rpm if runs else 0
    for a in ax:
        a.axhline(tgt, color="k", ls="--", lw=0.8)
        a.grid(True, alpha=0.3)
        a.set_xlabel("time (ms)")
    ax[0].set_ylabel("speed (rpm)")
    ax[0].set_title("speed step (first 300 ms)")
    ax[1].set_title("load step")
    ax[1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _fmt(x, nd=2) -> str:
    if isinstance(x, float) and not math.isfinite(x):
        return "never" if x > 0 else "—"
    return f"{x:.{nd}f}" if isinstance(x, float) else str(x)


def write_report(out: Path, profile, designs: dict, committed: dict, firmwares: dict, runs: dict,
                 timings: dict, failed: dict) -> Path:
    L = [f"# picdrive demo: {profile.name}", "",
         f"{profile.description}  ", f"Profile hash `{profile.sha256[:12]}`; bus {profile.inverter.bus_voltage_v:g} V, "
         f"current limit {profile.inverter.current_limit_a:g} A, PWM {profile.inverter.pwm_frequency_hz / 1e3:g} kHz, "
         f"speed loop {profile.control.speed_loop_hz:g} Hz; step target {profile.speed_step_rpm():.0f} rpm "
         f"(reference {profile.control.reference_rpm:g} rpm), load step {profile.control.load_torque_n_m:g} N m.", ""]
    L += ["## 1. Designs", "",
          "Each method re-run with the options of its committed design and verified "
          "(`picdrive.design.verify`); *vs committed* is the largest relative difference of any rule gain.", "",
          "| method | variant | status | rules | kp (V/(rad/s)) | ki (V/rad) | kd (V s²/rad) | kc (V/A) | vs committed | time (s) |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for meth, r in designs.items():
        law = r.law
        g = law.rules[0] if law is not None else None
        cm = committed.get(meth)
        diff = gain_difference(law, cm.law if cm is not None else None)
        dtxt = "—" if cm is None else (f"{diff:.1e}" if math.isfinite(diff) else "different")
        L.append(f"| {meth} | {r.variant} | {r.status} | {law.n_rules if law else 0} | "
                 f"{g.kp:.4g} | {g.ki:.4g} | {g.kd:.3g} | {g.kc:.4g} | {dtxt} | {timings[meth]['design']:.1f} |"
                 if g else f"| {meth} | {r.variant} | {r.status} | — | — | — | — | — | {dtxt} | {timings[meth]['design']:.1f} |")
    for meth, reasons in failed.items():
        L.append(f"\n**{meth} failed verification**: " + "; ".join(reasons))
    L += ["", "(gains of rule 1 shown; the design files in `designs/` hold every rule, the certificate and "
          "the verification figures)", ""]
    L += ["## 2. Firmware", ""]
    for meth, fw in firmwares.items():
        L += [f"### {meth}", "", "```"] + fw.summary + ["```", ""]
    L += ["## 3. The firmware in the twin", "",
          "Commanded and recorded only through `picdrive.link` (the board's telemetry at the speed-loop rate). "
          "t_min = J w / (Kt I_max) is the fastest rise from rest at the current limit; "
          "*t90 / t_min* compares the time to 90 % with it.", "",
          "| method | rise (ms) | settling 2 % (ms) | overshoot (%) | steady error (%) | load dip (rpm) | "
          "load recovery 2 % (ms) | error under load (%) | peak current (A) | t90 / t_min | dropped samples |",
          "|---|---|---|---|---|---|---|---|---|---|---|"]
    for meth, run in runs.items():
        m = run.metrics
        L.append(f"| {meth} | {_fmt(m['rise_ms'])} | {_fmt(m['settling_ms'])} | {_fmt(m['overshoot_pct'])} | "
                 f"{_fmt(m['sse_pct'], 3)} | {_fmt(m['load_dip_rpm'], 1)} | {_fmt(m['load_recovery_ms'])} | "
                 f"{_fmt(m['sse_under_load_pct'], 3)} | {_fmt(m['peak_current_a'])} | {_fmt(m['t90_over_tmin'])} | "
                 f"{m['dropped_samples']} |")
    L += ["", "![speed, voltage and current](twin_runs.png)", "", "![step and load step, zoomed](twin_zoom.png)", ""]
    L += ["## Files", "", "- `designs/`: the design results (JSON)", "- `firmware/<method>/`: the generated firmware "
          "(open in MPLAB X / build with XC8: see its README.md)", "- `twin/<method>.csv`: the recorded telemetry", ""]
    path = out / "report.md"
    path.write_text("\n".join(L) + "\n", encoding="utf-8")
    return path


def run_demo(profile_ref: str = "duy2008", out_dir: str | Path = "out/demo", *, methods=METHODS,
             step_s: float = 1.0, load_s: float = 1.0, progress: bool = True) -> Path:
    from .firmware import codegen
    from . import outputs
    from .profile import ProfileWarning, load_profile
    from .result import save_design

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ProfileWarning)
        profile = load_profile(profile_ref)
    for w in caught:
        _say(f"picdrive: warning: {w.message}")
    out = outputs.dir_output(out_dir, what="demo folder")
    for t in (step_s, load_s):
        if not (math.isfinite(t) and 0.05 <= t <= 60.0):
            raise PicdriveError(f"--step-s/--load-s {t!r}: expected seconds in [0.05, 60]")
    tmp = outputs.new_temp_dir(out, what="demo folder")
    try:
        (tmp / "designs").mkdir()
        (tmp / "twin").mkdir()
        designs, committed, firmwares, runs, timings, failed = {}, {}, {}, {}, {}, {}
        for meth in methods:
            timings[meth] = {}
            _say(f"[design]   {profile.name}: {meth} ...")
            t0 = time.perf_counter()
            r, c = redesign(profile, meth, progress)
            timings[meth]["design"] = time.perf_counter() - t0
            designs[meth] = r
            if c is not None:
                committed[meth] = c
            dpath = save_design(r, tmp / "designs" / f"{profile.name}.{meth}.design.json")
            _say(f"           {r.status}" + (f": {'; '.join(r.reasons)}" if r.reasons else "")
                 + f" ({timings[meth]['design']:.1f} s)")
            if not r.ok or r.law is None:
                failed[meth] = r.reasons or ["no firmware law"]
                continue
            _say(f"[firmware] {meth}: rendering, build-checking (gcc, avr-gcc) and the chip's HEX (SDCC, gpsim) ...")
            t0 = time.perf_counter()
            fw = codegen.generate(profile, dpath, name=f"{profile.name}-{meth}")
            chip: dict = {}
            fdir = codegen.write_firmware(fw, tmp / "firmware" / meth, check=True, hex_build=True, figures=chip)
            timings[meth]["firmware"] = time.perf_counter() - t0
            _say(f"           flash {chip['flash_bytes']:,} B, RAM + stack {chip['ram_stack_bytes']} B, speed loop "
                 f"{chip['speed_loop_isr']:,} / hall {chip['hall_isr']} / UART receive {chip['uart_rx_byte']} cycles: "
                 "within every budget")
            firmwares[meth] = fw
            _say(f"[twin]     {meth}: step to {profile.speed_step_rpm():.0f} rpm, then "
                 f"{profile.control.load_torque_n_m:g} N m load ...")
            t0 = time.perf_counter()
            run = run_in_twin(profile, fdir, meth, step_s=step_s, load_s=load_s)
            timings[meth]["twin"] = time.perf_counter() - t0
            run.metrics = twin_metrics(profile, run)
            runs[meth] = run
            m = run.metrics
            _say(f"           rise {m['rise_ms']:.1f} ms, settling {_fmt(m['settling_ms'], 1)} ms, overshoot "
                 f"{m['overshoot_pct']:.2f} %, load dip {m['load_dip_rpm']:.1f} rpm, "
                 f"error under load {m['sse_under_load_pct']:.3f} %")
            np.savetxt(tmp / "twin" / f"{meth}.csv",
                       np.column_stack([run.t, run.setpoint_rpm, run.speed_rpm, run.voltage_v, run.current_a]),
                       delimiter=",", header="t_s,setpoint_rpm,speed_rpm,voltage_v,current_a", comments="",
                       fmt="%.6g")
        if not runs:
            raise PicdriveError("no design passed its verification, so nothing ran in the twin: "
                                + "; ".join(f"{k}: {', '.join(v)}" for k, v in failed.items()))
        plot_runs(profile, list(runs.values()), tmp / "twin_runs.png")
        plot_zoom(profile, list(runs.values()), tmp / "twin_zoom.png")
        (tmp / "summary.json").write_text(json.dumps(
            {"profile": profile.name, "profile_sha256": profile.sha256,
             "twin": {k: v.metrics for k, v in runs.items()},
             "designs": {k: {"status": v.status, "reasons": v.reasons} for k, v in designs.items()},
             "timings_s": timings}, indent=1, sort_keys=True, default=float) + "\n")
        write_report(tmp, profile, designs, committed, firmwares, runs, timings, failed)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    outputs.publish_dir(tmp, out, "demo", what="demo folder",
                        regenerable=[f"firmware/{m}/{r}" for m in methods for r in codegen.REGENERABLE])
    return out / "report.md"


def _cmd(args) -> int:
    from .outputs import dir_output
    dir_output(args.output, what="demo folder")      # refused before the work, not after
    methods = tuple(args.method) if args.method else METHODS
    report = run_demo(args.profile, args.output, methods=methods, step_s=args.step_s, load_s=args.load_s,
                      progress=not args.no_progress)
    _say(f"wrote {report} (plots and data beside it)")
    return 0


def register(sub) -> None:
    p = sub.add_parser("demo", help="the whole chain on a bundled profile: design, firmware, twin, report",
                       description="Design the bundled example with the three methods, generate the firmware, "
                                   "run it in the motor twin through a speed step and a load step, and write "
                                   "the report with its plots.")
    p.add_argument("--profile", default="duy2008", help="profile name or .toml (default: duy2008)")
    p.add_argument("-o", "--output", default="out/demo", help="output folder (default: out/demo)")
    p.add_argument("--method", action="append", choices=METHODS,
                   help="run only this method (repeatable; default: all three)")
    p.add_argument("--step-s", type=float, default=1.0, help="seconds recorded after the speed step (default 1)")
    p.add_argument("--load-s", type=float, default=1.0, help="seconds recorded after the load step (default 1)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=_cmd)
