"""``picdrive robustness``: tolerance studies on Dask (a LocalCluster, and a scheduler plus a worker
started by hand on loopback), resume, a fragile design's yield drop and its driver, the worst drive
reproduced from its seed, and the bad inputs refused before any sample runs.

Studies here are tiny (a few drives, phases of 0.1 s instead of the verification's 0.6 s): the
figures of a full study are bench/robustness.py's."""
from __future__ import annotations

import csv
import json
import os
import socket
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest

from picdrive.cli import main

pytest.importorskip("distributed")

ROOT = Path(__file__).resolve().parents[1]
DESIGN = ROOT / "examples" / "duy2008.fuzzy-hinf.design.json"
HEX = ROOT / "firmware_build" / "duy2008" / "duy2008.hex"
PHASE = ["--phase-s", "0.1"]
NOMINAL = (ROOT / "examples" / "duy2008.toml").read_text(encoding="utf-8")
# every parameter nominal but R: the fragile study's R range reaches beyond the verification's +-10 %
ONLY_R = "\n[tolerances]\n" + "".join(f'{k} = {{ distribution = "none" }}\n' for k in (
    "back_emf", "inductance", "inertia", "friction", "hall_offset", "bus_voltage", "load_torque"))


def _profile(tmp: Path, name: str, extra: str) -> Path:
    p = tmp / f"{name}.toml"
    p.write_text(NOMINAL + extra, encoding="utf-8")
    return p


def _rows(out: Path) -> list[dict]:
    with open(out / "samples.csv", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run(capsys, *args) -> tuple[int, str, str]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rc = main(["robustness", "--no-progress", *map(str, args)])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


@pytest.fixture(scope="module")
def cluster():
    """A LocalCluster of two single-threaded worker processes, shared by this module's studies."""
    from distributed import LocalCluster
    import logging
    c = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                     host="127.0.0.1", silence_logs=logging.ERROR)
    yield c.scheduler_address
    c.close()


@pytest.fixture(scope="module")
def fragile(tmp_path_factory, cluster):
    """The same drives twice: R within the verification's +-10 %, then R -10 .. +90 %."""
    tmp = tmp_path_factory.mktemp("fragile")
    studies = {}
    for name, r in (("covered", (-10, 10)), ("fragile", (-10, 90))):
        prof = _profile(tmp, name, ONLY_R + f'resistance = {{ distribution = "uniform", low_pct = {r[0]}, '
                                            f'high_pct = {r[1]} }}\n')
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            rc = main(["robustness", "--no-progress", "--profile", str(prof), "--design", str(DESIGN),
                       "--samples", "8", "-o", str(tmp / name), "--scheduler", cluster, *PHASE])
        assert rc == 0
        studies[name] = tmp / name
    return studies


def test_fragile_design_shows_its_yield_drop_and_names_the_parameter(fragile):
    covered, weak = _rows(fragile["covered"]), _rows(fragile["fragile"])
    assert [r["status"] for r in covered] == ["pass"] * 8
    n_fail = sum(r["status"] != "pass" for r in weak)
    assert 2 <= n_fail <= 7, [(r["dev_resistance_pct"], r["status"]) for r in weak]
    # the failures are the drives with the highest resistance, and the report says so
    fails = [float(r["dev_resistance_pct"]) for r in weak if r["status"] != "pass"]
    passes = [float(r["dev_resistance_pct"]) for r in weak if r["status"] == "pass"]
    assert min(fails) > max(passes) > 10
    report = (fragile["fragile"] / "report.md").read_text(encoding="utf-8")
    assert "**resistance**" in report and "higher values fail more" in report
    assert f"Yield: {8 - n_fail} / 8" in report and "final error" in report
    assert "Yield: 8 / 8 = 100.0 %" in (fragile["covered"] / "report.md").read_text(encoding="utf-8")
    for f in ("plots/histograms.png", "plots/drivers.png", "study.json", ".picdrive-output"):
        assert (fragile["fragile"] / f).is_file()


def test_worst_drive_reproduces_from_its_seed(fragile, tmp_path):
    """The worst drive's profile, in the twin, gives the study's figures to the last digit."""
    from picdrive.analysis.steptest import step_figures
    from picdrive.firmware import codegen
    from picdrive.gate import twin_scenario
    from picdrive.profile import load_profile
    from picdrive.robustness.sample import METRICS
    worst = fragile["fragile"] / "worst" / "duy2008.worst-1.toml"
    text = worst.read_text(encoding="utf-8")
    assert "[as_built]" in text and "picdrive twin --profile" in text
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prof = load_profile(worst)
    row = next(r for r in _rows(fragile["fragile"]) if int(r["seed"]) == prof.as_built_seed)
    assert row["status"] == "fail"
    plan = json.loads((fragile["fragile"] / "study.json").read_text(encoding="utf-8"))["plan"]
    fw = codegen.generate(prof, str(DESIGN))           # the profile hash is the nominal one: the same firmware
    out = codegen.write_firmware(fw, tmp_path / "fw", check=False)
    fig = step_figures(twin_scenario(prof, out, fw.table, plan), plan, prof)
    for k in METRICS:
        assert row[k] == "inf" and fig[k] == float("inf") or float(row[k]) == round(float(fig[k]), 6), k
    # and 'picdrive twin' takes the profile with the nominal firmware, naming the drive
    r = subprocess.run([sys.executable, "-m", "picdrive", "twin", "--profile", str(worst), "--firmware", str(out),
                        "--duration", "0.01"], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert f"as built (seed {prof.as_built_seed})" in r.stderr and "R +" in r.stderr


def test_interrupted_study_resumes_where_it_stopped(tmp_path, capsys, cluster):
    """A study on its own LocalCluster (the default), interrupted, then resumed on another cluster."""
    import signal
    out = tmp_path / "study"
    cmd = [sys.executable, "-m", "picdrive", "robustness", "--no-progress", "--profile", "duy2008", "--design",
           str(DESIGN), "--samples", "400", "-o", str(out), "--workers", "1", *PHASE]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < 120 and p.poll() is None:
            if (out / "samples.csv").is_file() and len(_rows(out)) >= 3:
                break
            time.sleep(0.2)
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130, err
    assert "1 worker(s)" in err
    first = {int(r["sample"]): r for r in _rows(out)}
    assert 3 <= len(first) < 400
    with open(out / "samples.csv", "a", encoding="utf-8") as f:
        f.write("7,12345,pa")                       # a row cut off by the interruption
    n = len(first) + 2
    rc, so, se = _run(capsys, "--profile", "duy2008", "--design", DESIGN, "--samples", n, "-o", out,
                      "--scheduler", cluster, *PHASE)
    assert rc == 0, se
    assert f"resuming: {len(first)} done" in se and "2 worker(s)" in se
    assert "yield       " in so and "per worker" in so
    assert len(list((out / "worst").glob("*.toml"))) == 3
    again = {int(r["sample"]): r for r in _rows(out)}
    assert set(range(n)) <= set(again) and len(again) == len(set(first) | set(range(n)))
    for k, r in first.items():                     # the rows already there are kept as they were
        assert again[k] == r


def test_scheduler_and_worker_started_by_hand_run_the_processor_twin(tmp_path, capsys):
    port = _free_port()
    addr = f"tcp://127.0.0.1:{port}"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    procs = [subprocess.Popen([sys.executable, "-m", "dask", "scheduler", "--host", "127.0.0.1", "--port", str(port),
                               "--no-dashboard"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)]
    try:
        procs.append(subprocess.Popen([sys.executable, "-m", "dask", "worker", addr, "--nthreads", "1",
                                       "--no-dashboard"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                      env=env, cwd=tmp_path))
        rc, so, se = _run(capsys, "--profile", "duy2008", "--design", DESIGN, "--hex", HEX, "--samples", 3,
                          "-o", tmp_path / "pil", "--scheduler", addr, "--connect-timeout", 60, *PHASE)
        assert rc == 0, se
        assert "processor twin (duy2008.hex)" in se and "1 worker(s)" in se
        rows = _rows(tmp_path / "pil")
        assert len(rows) == 3 and all(r["status"] == "pass" for r in rows), rows
        assert len({r["worker"] for r in rows}) == 1
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()


def test_failed_simulation_is_a_failed_sample(tmp_path):
    from picdrive.analysis.steptest import sim_plan
    from picdrive.profile import load_profile
    from picdrive.firmware import codegen
    from picdrive.robustness.sample import run_sample
    prof = load_profile("duy2008")
    fw = codegen.generate(prof, str(DESIGN))
    row = run_sample(prof, tmp_path / "no-firmware", fw.table, sim_plan(prof), 0, 123)
    assert row["status"] == "error" and row["failed_limits"] == "simulation"
    assert "the simulation failed" in row["reason"] and "no-firmware" in row["reason"]


@pytest.mark.parametrize("case", ["negative-r", "distribution", "other-profile", "hex", "scheduler", "as-built"])
def test_bad_input_exits_2_before_any_sample(case, tmp_path, capsys):
    out = tmp_path / "out"
    args = ["--profile", "duy2008", "--design", DESIGN, "--samples", 2, "-o", out, *PHASE]
    if case == "negative-r":
        args[1] = _profile(tmp_path, "p", '\n[tolerances]\nresistance = { distribution = "uniform", '
                                          'low_pct = -110, high_pct = 10 }\n')
        want = ["tolerances.resistance.low_pct", "negative"]
    elif case == "distribution":
        args[1] = _profile(tmp_path, "p", '\n[tolerances]\nbus_voltage = { distribution = "gaussian", '
                                          'sigma_pct = 3 }\n')
        want = ["tolerances.bus_voltage.distribution", "'gaussian'", "'truncated-normal'"]
    elif case == "other-profile":
        args[3] = ROOT / "examples" / "duy2008_halls.fuzzy-hinf.design.json"
        want = ["was made from profile 'duy2008_halls'", "re-run 'picdrive design'"]
    elif case == "hex":
        args[3] = ROOT / "examples" / "duy2008.zn.design.json"
        args += ["--hex", HEX]
        import json
        built = json.loads((Path(HEX).parent / "board.json").read_text())["build_id"]
        want = ["does not match the design", f"build 0x{built:08X}", "picdrive firmware"]
    elif case == "scheduler":
        args += ["--scheduler", f"tcp://127.0.0.1:{_free_port()}", "--connect-timeout", "1"]
        want = ["no Dask scheduler answers", "dask scheduler"]
    else:
        args[1] = _profile(tmp_path, "p", "\n[as_built]\nseed = 5\n")
        want = ["names one drive off the line", "nominal profile"]
    t0 = time.perf_counter()
    rc, so, se = _run(capsys, *args)
    assert rc == 2 and so == ""
    for w in want:
        assert w in se, (w, se)
    assert not out.exists()
    assert time.perf_counter() - t0 < 30
