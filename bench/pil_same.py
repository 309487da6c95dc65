"""The processor twin of this tree against the one of another git revision: the bundled HEX
over the same scenario, statistics and state compared at every checkpoint.

A change meant to make the processor twin faster (hil/picdrive_hil/csrc: the PIC18 core, pil.c,
the plant's stepping) must not change what it does.  This runs the bundled firmware's HEX
(firmware_build/duy2008, picdrive.firmware.target.build_measured) on both builds -- each in its
own process, the other revision's hil/ exported with ``git archive`` -- through one scenario in
simulated time: power-on, the link watchdog and the profile's step setpoint over the UART,
``start``, 0.5 s to speed, the profile's load torque as a step, then ``--checkpoints`` checkpoints
``--every`` s apart; at each one ``pil_stats()`` (cycles, instructions, interrupt durations,
stack, hazard counters; not the event loop's
``steps`` and ``stops``), ``state()`` (plant and board) and the whole data
memory (``peek``) are recorded, and the two runs must agree exactly.

Usage: python3 bench/pil_same.py [--against REV] [--checkpoints 800] [--every 5e-4]
       python3 bench/pil_same.py --run-only [--checkpoints N]   (this tree alone: for callgrind)
Prints the first difference (and exits 1) or "identical at every checkpoint".
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# pil_stats fields that count how the event loop cut the run (steps, runs cut short), not what
# the processor or the plant did: compared only by being printed
LOOP_COUNTERS = ("steps", "stops")


def scenario(hex_path: str, on_chip: bool, checkpoints: int, every_s: float, record: bool = True) -> list:
    """The scenario on the importable picdrive_hil; one record per checkpoint (``record`` False:
    only the last's statistics, nothing read between: the run for callgrind)."""
    import re
    import warnings
    from picdrive.link import codec
    from picdrive.paths import firmware_build_dir
    from picdrive.profile import ProfileWarning
    from picdrive_hil.twin import Twin
    fw = firmware_build_dir() / "duy2008"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ProfileWarning)
        tw = Twin("duy2008", fw, hex_file=hex_path, enlarged_memory=not on_chip, seed=0)
    h = (fw / "link_fw.h").read_text()

    def link_id(name):
        m = re.search(rf"#define\s+LINK_ID_{name.upper()}\s+0x([0-9A-Fa-f]+)u\s+/\*[^*]*?scale ([-+0-9.eE]+)", h)
        return int(m.group(1), 16), float(m.group(2))

    def command(name, seq, args=None):
        tw.uart_write(codec.encode_command(name, seq, args))
        tw.run(0.01)
        tw.uart_read()

    lt_id, _ = link_id("link_timeout")
    sp_id, sp_scale = link_id("speed_setpoint")
    prof = tw.profile
    tw.run(0.01)
    command("param_set", 1, {"id": lt_id, "value": 60000})
    command("set_speed", 2, {"value": int(round(prof.speed_step_rpm() / sp_scale))})
    command("start", 3)
    tw.run(0.5)
    tw.set_load_torque(prof.control.load_torque_n_m)
    out = []
    for k in range(checkpoints):
        tw.run(every_s)
        if not record and k < checkpoints - 1:
            continue
        st = tw.pil_stats()
        s = tw.state()
        ram = bytes(tw.peek(a) for a in range(0, 0x300))
        out.append({"k": k, "stats": {n: getattr(st, n) for n, _ in st._fields_},
                    "state": {n: (list(v) if isinstance(v, tuple) else v) for n, v in s.items()},
                    "ram": ram.hex(), "uart": tw.uart_read().hex()})
    tw.close()
    return out


def run_child(hil_dir: Path, hex_path: str, on_chip: bool, args, out: Path) -> None:
    env = dict(os.environ, PYTHONPATH=f"{hil_dir}{os.pathsep}{ROOT / 'host'}")
    cmd = [sys.executable, __file__, "--child", str(out), "--hex", hex_path, "--on-chip", str(int(on_chip)),
           "--checkpoints", str(args.checkpoints), "--every", repr(args.every)]
    subprocess.run(cmd, env=env, check=True)


def first_difference(a: list, b: list) -> str | None:
    if len(a) != len(b):
        return f"{len(a)} checkpoints against {len(b)}"
    for x, y in zip(a, b):
        for part in ("stats", "state", "ram", "uart"):
            xp, yp = x[part], y[part]
            if part == "stats":   # how the event loop cut the time is the speed work's to change
                xp = {n: v for n, v in xp.items() if n not in LOOP_COUNTERS}
                yp = {n: v for n, v in yp.items() if n not in LOOP_COUNTERS}
            if xp != yp:
                if isinstance(xp, dict):
                    keys = [n for n in xp if xp[n] != yp.get(n)]
                    return (f"checkpoint {x['k']}: {part} differs in {', '.join(keys[:8])} "
                            f"({[(n, xp[n], yp.get(n)) for n in keys[:3]]})")
                return f"checkpoint {x['k']}: {part} differs"
    return None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", default="HEAD", help="git revision whose hil/ is compared (default HEAD)")
    ap.add_argument("--checkpoints", type=int, default=800)
    ap.add_argument("--every", type=float, default=5e-4, help="s between checkpoints (simulated)")
    ap.add_argument("--run-only", action="store_true", help="run this tree's twin only (for callgrind)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--hex", help=argparse.SUPPRESS)
    ap.add_argument("--on-chip", type=int, default=1, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        Path(args.child).write_text(json.dumps(scenario(args.hex, bool(args.on_chip), args.checkpoints, args.every)))
        return 0
    from picdrive.firmware import target
    from picdrive.paths import firmware_build_dir
    with tempfile.TemporaryDirectory(prefix="pil-same-") as tmpd:
        tmp = Path(tmpd)
        b = target.build_measured(firmware_build_dir() / "duy2008", tmp / "hex")
        if args.run_only:
            recs = scenario(str(b.hex_path), b.on_chip, args.checkpoints, args.every, record=False)
            last = recs[-1]["stats"]
            print(f"ran {args.checkpoints} checkpoints: {last['cycles']} cycles, {last['insns']} instructions, "
                  f"{last['steps']} event-loop steps")
            return 0
        old = tmp / "old"
        old.mkdir()
        arch = subprocess.run(["git", "-C", str(ROOT), "archive", args.against, "hil"], check=True,
                              capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(old)], input=arch, check=True)
        run_child(old / "hil", str(b.hex_path), b.on_chip, args, tmp / "old.json")
        run_child(ROOT / "hil", str(b.hex_path), b.on_chip, args, tmp / "new.json")
        a = json.loads((tmp / "old.json").read_text())
        n = json.loads((tmp / "new.json").read_text())
        diff = first_difference(a, n)
        last = n[-1]["stats"]
        print(f"{len(n)} checkpoints {args.every * 1e3:g} ms apart after start, setpoint and load "
              f"({last['insns']:,} simulated instructions, {last['steps']:,} event-loop steps in this tree, "
              f"{a[-1]['stats']['steps']:,} in {args.against})")
        if diff:
            print(f"DIFFERENT from {args.against}: {diff}")
            return 1
        print(f"identical at every checkpoint to {args.against} (pil_stats, state, data memory, UART output)")
        return 0


if __name__ == "__main__":
    sys.exit(main())
