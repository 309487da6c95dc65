"""The timing harness's Timer1 figures against gpsim's own cycle counter.

``picdrive.firmware.gpsim`` measures each interrupt with Timer1 around a CALL (``measure_modes``; the
budgets of tests/test_target.py rest on it).  ``bench/isr_profile.py`` runs the same harness single-stepped
and counts every instruction's cycles.  Per state of the corpus the two must agree (the profile's worst
call plus the interrupt entry): with Timer1 written while running, gpsim put some figures exactly 256
cycles high (docs/firmware.md "Timer1 in gpsim")."""
import importlib.util
from collections import defaultdict
from pathlib import Path

from picdrive.firmware import gpsim

ROOT = Path(__file__).resolve().parents[1]


def _isr_profile():
    spec = importlib.util.spec_from_file_location("isr_profile", ROOT / "bench" / "isr_profile.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_timer1_figures_match_the_cycle_count(tmp_path):
    folder = ROOT / "firmware_build" / "duy2008"
    timer = gpsim.measure_modes(folder, tmp_path / "t1", ("off",))["off"].worst
    prof = _isr_profile()
    b, label, runs = prof.trace(folder, tmp_path / "trace", "off")
    funcs = sorted((f.address, f.size, n) for n, f in b.functions.items())
    totals = [prof.attribute(r, label, funcs)[3] for r in runs]
    # the corpus's speed samples in order: one state label per call
    labels = [arg[0] for what, arg in gpsim.default_corpus(("off",)) if what == "speed" for _ in range(arg[2])]
    assert len(labels) == len(totals) > 20
    counted = defaultdict(int)
    for lab, c in zip(labels, totals):
        counted[lab] = max(counted[lab], c + gpsim.ENTRY_CYCLES)
    for lab, c in counted.items():
        t = timer["speed_loop_isr:" + lab]
        assert abs(t - c) <= 5, f"{lab}: Timer1 {t} cycles, counted {c}"
