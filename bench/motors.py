#!/usr/bin/env python3
"""The corpus of real motors (tests/motors/*.toml): design -> firmware -> twin, and the table of docs/motors.md.

For each profile and each design method (fuzzy-hinf, mixed-pid, zn) this runs what a user would:
load the profile, ``picdrive design`` (design + verification), and for a verified design
``picdrive firmware``'s codegen and the motor twin through the verification's own step and load
step (:func:`picdrive.gate.twin_run`), beside the verification's six-step model of the same run
(:func:`picdrive.analysis.steptest.run_sim`, no disturbances); both judged by
:func:`picdrive.analysis.steptest.step_figures`.  Every outcome is one of

* ``verified`` -- with the twin's and the model's rise, overshoot and final error;
* ``refused`` -- at a stage (profile, design, firmware) with the reason picdrive gave.

:func:`judge` states the tolerances a verified design must meet in the twin
(tests/test_motors_corpus.py asserts them); nothing is cached between runs except the twin's
compiled library, which is keyed by the hash of its sources.

    python3 bench/motors.py [--jobs N] [--only NAME ...] [--write]     # prints the table; --write regenerates docs/motors.md
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CORPUS = ROOT / "tests" / "motors"
DOC = ROOT / "docs" / "motors.md"
METHODS = ("fuzzy-hinf", "mixed-pid", "zn")

# tolerances of a verified design in the twin against its verification (the same as
# tests/test_verify_twin.py's, stated there): the twin must also pass the verification's limits
RISE_REL = 0.25          # rise time within 25 % of the twin's (+ one speed-loop sample)
OVERSHOOT_PP = 1.0       # overshoot within 1 percentage point
FINAL_REL = 0.001        # final speed under the load within 0.1 % of the target


#: the chip build's figures a verified case records (picdrive.firmware.codegen.target_build's ``figures``)
FIRMWARE_KEYS = ("flash_bytes", "ram_stack_bytes", "speed_loop_isr", "hall_isr", "uart_rx_byte", "over_budget")


def profiles() -> list[Path]:
    return sorted(CORPUS.glob("*.toml"))


def _short(text: str, n: int = 260) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= n else text[: n - 3] + "..."


def run_case(profile_path: str, method: str) -> dict:
    """One profile x method through the chain; a plain dict (picklable)."""
    from picdrive.gate import run_design
    from picdrive.errors import PicdriveError
    from picdrive.profile import load_profile
    from picdrive.result import save_design
    from picdrive.analysis.steptest import run_sim, sim_plan, step_figures
    from picdrive.gate import speed_measurement, three_phase_plant, twin_run

    warnings.simplefilter("ignore")
    import tomllib
    with open(profile_path, "rb") as fh:
        src = tomllib.load(fh).get("drive", {}).get("source", "")
    out = {"profile": Path(profile_path).stem, "method": method, "source": src}
    t0 = time.perf_counter()
    try:
        prof = load_profile(profile_path)
    except PicdriveError as e:          # the message names the file: keep it machine-independent
        return {**out, "outcome": "refused", "stage": "profile",
                "reason": str(e).replace(str(profile_path), Path(profile_path).name)}
    try:
        res = run_design(prof, method, progress=False)
    except PicdriveError as e:
        return {**out, "outcome": "refused", "stage": "design", "reason": str(e), "wall_s": time.perf_counter() - t0}
    if method == "fuzzy-hinf":      # the model the gains were designed on, and why when not the default's
        out["plant_model"] = (res.certificate or {}).get("model")
        out["plant_model_fallback"] = (res.certificate or {}).get("plant_model_fallback")
    if not res.ok:
        return {**out, "outcome": "refused", "stage": "design", "reason": "; ".join(res.reasons),
                "wall_s": time.perf_counter() - t0}
    plan = sim_plan(prof)
    with tempfile.TemporaryDirectory(prefix="picdrive-corpus-") as tmp:
        path = Path(tmp) / f"{prof.name}.{method}.design.json"
        save_design(res, path)
        fw: dict = {}
        try:           # the firmware as 'picdrive firmware' builds it: the HEX within every chip budget
            tw = twin_run(prof, path, plan, workdir=tmp, figures=fw)
        except PicdriveError as e:
            return {**out, "outcome": "refused", "stage": "firmware", "reason": str(e),
                    "wall_s": time.perf_counter() - t0}
    twin = step_figures(tw, plan, prof)
    model = step_figures(run_sim(prof, res.law, plan, measurement=speed_measurement(prof, res.law), disturbances=False,
                               three_phase=three_phase_plant), plan, prof)
    keys = ("rise_s", "settling_s", "overshoot_pct", "final_error_rpm", "load_recovery_s", "load_dip_rpm",
            "peak_current_a", "t_reach_s")
    return {**out, "outcome": "verified", "target_rpm": plan["target_rpm"], "t_load_s": plan["t_load_s"],
            "t_end_s": plan["t_end_s"], "trip_a": prof.inverter.overcurrent_trip_a,
            "ts_s": 1.0 / prof.control.speed_loop_hz,
            "twin": {k: float(twin[k]) for k in keys}, "model": {k: float(model[k]) for k in keys},
            "firmware": {k: fw[k] for k in FIRMWARE_KEYS}, "wall_s": time.perf_counter() - t0}


def judge(case: dict) -> list[str]:
    """What a case breaks (empty: fine).  A refusal must name a reason; a verified design must be
    flashable (its chip build within every budget) and behave in the twin within the tolerances
    above of its verification and pass its limits."""
    if case["outcome"] == "error":
        return [f"raised instead of refusing: {case['reason']}"]
    if case["outcome"] == "refused":
        return [] if case.get("reason", "").strip() else ["refused without a reason"]
    tw, mo, tgt = case["twin"], case["model"], case["target_rpm"]
    bad = []
    fw = case.get("firmware") or {}
    if fw.get("over_budget") != []:
        bad.append(f"firmware not within the chip's budgets ({fw.get('over_budget', 'not measured')}): not flashable")
    if not abs(mo["rise_s"] - tw["rise_s"]) <= RISE_REL * tw["rise_s"] + case["ts_s"]:
        bad.append(f"rise {1e3 * tw['rise_s']:.3g} ms in the twin vs {1e3 * mo['rise_s']:.3g} ms verified")
    if not abs(mo["overshoot_pct"] - tw["overshoot_pct"]) <= OVERSHOOT_PP:
        bad.append(f"overshoot {tw['overshoot_pct']:.3g} % in the twin vs {mo['overshoot_pct']:.3g} % verified")
    if not abs(mo["final_error_rpm"] - tw["final_error_rpm"]) <= FINAL_REL * tgt:
        bad.append(f"final error {tw['final_error_rpm']:.4g} rpm in the twin vs {mo['final_error_rpm']:.4g} rpm verified")
    band = 0.02
    if not tw["settling_s"] < 0.8 * case["t_load_s"]:
        bad.append(f"the twin does not settle ({tw['settling_s']:.3g} s)")
    if not tw["overshoot_pct"] <= 100 * band:
        bad.append(f"the twin overshoots {tw['overshoot_pct']:.3g} %")
    if not tw["load_recovery_s"] < 0.8 * (case["t_end_s"] - case["t_load_s"]):
        bad.append(f"the twin does not recover from the load step ({tw['load_recovery_s']:.3g} s)")
    if not abs(tw["final_error_rpm"]) <= band * tgt:
        bad.append(f"the twin's final error {tw['final_error_rpm']:.4g} rpm")
    if not tw["peak_current_a"] < case["trip_a"]:
        bad.append(f"the twin's peak current {tw['peak_current_a']:.3g} A reaches the trip")
    if not math.isfinite(tw["t_reach_s"]):
        bad.append("the twin never reaches the target")
    return bad


def checked_case(profile_path: str, method: str) -> dict:
    """:func:`run_case`, with an exception picdrive raised where it should have refused recorded as the
    case's outcome ``error`` (a bug: :func:`judge` fails it), so one crash does not lose the other cases."""
    import traceback
    try:
        return run_case(profile_path, method)
    except Exception as e:          # noqa: BLE001 -- recorded and judged as a failure, never hidden
        where = traceback.extract_tb(e.__traceback__)[-1]
        return {"profile": Path(profile_path).stem, "method": method, "source": "", "outcome": "error",
                "stage": "design", "reason": f"{type(e).__name__}: {e} (at {Path(where.filename).name}:{where.lineno})"}


def run_all(names=None, jobs: int | None = None) -> list[dict]:
    """Every case; each one's outcome printed to stderr as it ends (a full run is about an hour)."""
    paths = [p for p in profiles() if not names or p.stem in names]
    cases = [(str(p), m) for p in paths for m in METHODS]
    jobs = jobs or min(2, os.cpu_count() or 1)
    out = []

    def seen(c):
        out.append(c)
        print(f"[{len(out)}/{len(cases)}] {c['profile']} {c['method']}: {c['outcome']}"
              f"{' (' + c['stage'] + ')' if c['outcome'] != 'verified' else ''}", file=sys.stderr, flush=True)
        return c
    if jobs <= 1:
        return [seen(checked_case(*c)) for c in cases]
    with ProcessPoolExecutor(max_workers=jobs) as ex:
        return [seen(c) for c in ex.map(checked_case, *zip(*cases))]


def cell(case: dict) -> str:
    if case["outcome"] == "refused":
        return f"refused ({case['stage']}): {_short(case['reason']).replace('|', '/')}"
    if case["outcome"] == "error":
        return f"ERROR ({case['stage']}): {_short(case['reason']).replace('|', '/')}"
    tw, mo = case["twin"], case["model"]
    plant = {"six-step-averaged": "averaged model; ", "six-step": "DC equivalent; "}.get(case.get("plant_model"), "")
    if case.get("plant_model_fallback"):
        plant = "DC equivalent (fallback: the averaged-model design failed its verification); "
    return (f"verified; {plant}twin / verification: rise {1e3 * tw['rise_s']:.1f} / {1e3 * mo['rise_s']:.1f} ms, "
            f"overshoot {tw['overshoot_pct']:.2f} / {mo['overshoot_pct']:.2f} %, final error "
            f"{tw['final_error_rpm']:.2f} / {mo['final_error_rpm']:.2f} rpm at {case['target_rpm']:.0f} rpm"
            + ("" if not judge(case) else " -- OUT OF TOLERANCE: " + "; ".join(judge(case))))


def firmware_cell(cases: list[dict]) -> str:
    """The verified designs' chip figures of one profile: flash, speed loop, hall interrupt, UART receive."""
    fw = [c["firmware"] for c in cases if c["outcome"] == "verified"]
    if not fw:
        return "no verified design"

    def span(key, unit):
        lo, hi = min(f[key] for f in fw), max(f[key] for f in fw)
        return f"{lo:,}{'' if lo == hi else f' .. {hi:,}'}{unit}"
    return (f"flash {span('flash_bytes', ' B')}, RAM + stack {span('ram_stack_bytes', ' B')}, speed loop "
            f"{span('speed_loop_isr', '')}, hall {span('hall_isr', '')}, UART receive {span('uart_rx_byte', '')} "
            "cycles")


def table(cases: list[dict]) -> str:
    by = {(c["profile"], c["method"]): c for c in cases}
    names = sorted({c["profile"] for c in cases})
    lines = ["| profile | source | " + " | ".join(METHODS) + " | firmware (verified designs) |",
             "|---" * (3 + len(METHODS)) + "|"]
    for n in names:
        src = next((by[(n, m)].get("source", "") for m in METHODS if (n, m) in by), "")
        lines.append(f"| `{n}` | {_short(src, 140).replace('|', '/')} | "
                     + " | ".join(cell(by[(n, m)]) if (n, m) in by else "" for m in METHODS)
                     + f" | {firmware_cell([by[(n, m)] for m in METHODS if (n, m) in by])} |")
    return "\n".join(lines)


DOC_HEAD = """# Motors picdrive has never seen: the corpus

<!-- generated by `python3 bench/motors.py --write`; do not edit by hand -->

Profiles of real motors written from datasheets (`tests/motors/*.toml`; none is bundled; each
names its source and marks what it assumes in its comments) go through what a user does: load
the profile, `picdrive design` with each method (design and verification), `picdrive firmware`
and the motor twin through the verification's own step from rest to `Profile.speed_step_rpm()`
and load step (`picdrive.gate.twin_run`).  The firmware is built as `picdrive firmware` builds it:
the chip's HEX within every budget (flash, RAM + stack, the speed-loop, hall and UART-receive
interrupts' worst cases), so a design over one is refused at the firmware stage, and the last
column gives the verified designs' figures (budgets: {b.flash_bytes:,} B, {b.ram_stack_bytes} B, {b.speed_loop_cycles:,},
{b.hall_isr_cycles} and {b.uart_rx_cycles} cycles).  A verified design must behave in the twin within
25 % (+ one sample) of its verification's rise time, 1 percentage point of its overshoot and
0.1 % of the target in final error, and pass the verification's own limits there
(`bench/motors.py` `judge`, asserted by `tests/test_motors_corpus.py`); a refusal names its stage
and reason.  Figures: twin / verification, on the speed averaged over one hall sector.  A verified
fuzzy-hinf design names the plant model its gains were designed on: the averaged model (the default,
docs/scheduling.md), or the DC equivalent where the averaged-model design failed its verification and
the design fell back (recorded in the design's `certificate.plant_model_fallback`).  Each row is
from the last run that included its profile: `bench/motors.py --write` runs them all, `--update NAME ...`
those profiles (a full run costs about an hour of CPU).
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=None, help="worker processes (default: min(2, CPUs))")
    ap.add_argument("--only", nargs="*", help="profile names (file stems) to run")
    ap.add_argument("--write", action="store_true", help="regenerate docs/motors.md from this run")
    ap.add_argument("--update", nargs="+", metavar="NAME",
                    help="run these profiles and replace (or add) their rows of docs/motors.md, keeping the rest")
    args = ap.parse_args(argv)
    if args.update and (args.only or args.write):
        print("--update names the profiles itself: without --only or --write", file=sys.stderr)
        return 2
    unknown = sorted(set(args.update or ()) - {p.stem for p in profiles()})
    if unknown:
        print(f"--update: no profile {', '.join(unknown)} in {CORPUS}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    cases = run_all(args.update or args.only, args.jobs)
    wall = time.perf_counter() - t0
    from picdrive.firmware.target import BUDGETS
    text = DOC_HEAD.format(b=BUDGETS) + "\n" + table(cases) + "\n"
    print(text)
    n_ver = sum(c["outcome"] == "verified" for c in cases)
    n_bad = sum(bool(judge(c)) for c in cases)
    print(f"{len(cases)} cases: {n_ver} verified, {len(cases) - n_ver} refused, {n_bad} out of tolerance; "
          f"{wall:.0f} s wall")
    if args.update:
        rows = {ln.split(" | ")[0]: ln for ln in table(cases).splitlines()[2:]}
        old = DOC.read_text().splitlines()
        head_end = next(i for i, ln in enumerate(old) if ln.startswith("| profile | source |"))
        kept = {ln.split(" | ")[0]: ln for ln in old[head_end + 2:] if ln.startswith("| `")}
        kept.update(rows)
        body = [kept[k] for k in sorted(kept)]
        DOC.write_text(DOC_HEAD.format(b=BUDGETS) + "\n" + "\n".join(table([]).splitlines()[:2] + body) + "\n")
        print(f"updated {len(rows)} rows of {DOC}")
    if args.write:
        if args.only:
            print("--write needs the whole corpus (no --only)", file=sys.stderr)
            return 2
        DOC.write_text(text)
        print(f"wrote {DOC}")
    return 1 if n_bad else 0


if __name__ == "__main__":
    sys.exit(main())
