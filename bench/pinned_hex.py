#!/usr/bin/env python3
"""The HEX of every firmware configuration with the build id pinned: a refactoring check.

The build id hashes the templates, so any template edit changes the HEX in its four build-id
bytes.  With the id pinned (``codegen._inputs_hash`` replaced), a change that only renames or
re-comments (register names for addresses, named offsets for numbers) must give byte-identical
HEX files.  Builds: every bundled design, the halls on the input-capture pins, no capture and no
EEPROM, and synthetic designs with 1-4 rules, the derivative filter and the reference
feedforward on both speed sources (those that do not fit the 18F4431 are linked with
picdrive.firmware.target.enlarged_lkr, for comparison only).  About 2-10 s a build.

Usage:
  python3 bench/pinned_hex.py OUT                  # render and build every configuration into OUT/<name>/
  python3 bench/pinned_hex.py OUT NAME...          # only these
  python3 bench/pinned_hex.py --compare OLD NEW    # SAME/DIFF per configuration; exit 1 on a difference

Typical use: build into /tmp/before on the old tree, into /tmp/after on the new one, compare.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

PINNED_ID = 0x5EED1234
RPM = 3.141592653589793 / 30


def _synthetic(tmp: Path, profile, name: str, nr: int, dfilt: bool, ff: bool) -> Path:
    from picdrive.control_law import Rule, ScheduledLaw
    from picdrive.result import DesignResult, save_design
    rules = tuple(Rule(0.2 - 0.02 * j, 5.0 - 0.5 * j, 0.0005 if dfilt else 0.0, 10.0 - j) for j in range(nr))
    law = ScheduledLaw(rules=rules, premise_rad_s=(0.0, 2600 * RPM), sample_time_s=1e-3, u_min_v=-44.16,
                       u_max_v=44.16, derivative_filter_hz=200.0 if dfilt else None,
                       reference_ff_v_s_per_rad=0.1 if ff else 0.0)
    return save_design(DesignResult(method="zn", status="verified", profile_name=profile.name,
                                    profile_sha256=profile.sha256, law=law, variant="test-fixture"),
                       tmp / f"{name}.design.json")


def configurations():
    """(name, profile name, design maker (folder -> path), generate options)."""
    from picdrive.paths import repo_root
    from picdrive.profile import load_profile
    ex = repo_root() / "examples"
    for d in sorted(ex.glob("*.design.json")):
        yield d.name.removesuffix(".design.json"), json.loads(d.read_text())["profile"]["name"], \
            (lambda tmp, d=d: d), {}
    yield "duy2008_halls.fuzzy-hinf.ic", "duy2008_halls", \
        (lambda tmp: ex / "duy2008_halls.fuzzy-hinf.design.json"), {"hall_input": "ic"}
    yield "duy2008.fuzzy-hinf.nocap", "duy2008", (lambda tmp: ex / "duy2008.fuzzy-hinf.design.json"), \
        {"link_capture": False, "link_eeprom": False}
    for pn in ("duy2008", "duy2008_halls"):
        for nr, dfilt, ff in ((1, False, False), (2, True, False), (2, False, True), (3, False, False),
                              (4, True, True)):
            name = f"{pn}.synth-r{nr}{'-df' if dfilt else ''}{'-ff' if ff else ''}"
            yield name, pn, (lambda tmp, pn=pn, name=name, nr=nr, dfilt=dfilt, ff=ff:
                             _synthetic(tmp, load_profile(pn), name, nr, dfilt, ff)), {}


def build(out: Path, only: set[str]) -> None:
    from picdrive.firmware import codegen, target
    from picdrive.profile import load_profile
    codegen._inputs_hash = lambda *a, **k: (PINNED_ID, "0" * 64)     # the pinned build id
    out.mkdir(parents=True, exist_ok=True)
    designs = out / "_designs"
    designs.mkdir(exist_ok=True)
    for name, pn, design, opts in configurations():
        if only and name not in only:
            continue
        t0 = time.time()
        fw = codegen.generate(load_profile(pn), design(designs), **opts)
        d = out / name
        if d.exists():
            shutil.rmtree(d)
        for rel, text in fw.files.items():
            (d / rel).parent.mkdir(parents=True, exist_ok=True)
            (d / rel).write_text(text)
        b = target.build_measured(d, out / "_obj" / name, name=name)
        shutil.copyfile(b.hex_path, d / f"{name}.hex")
        print(f"{name:36} flash {b.flash_bytes:6} B{'' if b.on_chip else ' (enlarged link)'}  "
              f"{time.time() - t0:.0f} s", flush=True)


def compare(a: Path, b: Path) -> int:
    names = sorted(p.name for p in a.iterdir() if (p / f"{p.name}.hex").is_file())
    bad = 0
    for n in names:
        hb = b / n / f"{n}.hex"
        same = hb.is_file() and (a / n / f"{n}.hex").read_bytes() == hb.read_bytes()
        bad += not same
        print(f"{'SAME' if same else 'DIFF'} {n}")
    print(f"{len(names) - bad} of {len(names)} byte-identical")
    return 1 if bad else 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", nargs="?")
    ap.add_argument("names", nargs="*")
    ap.add_argument("--compare", nargs=2, metavar=("OLD", "NEW"))
    a = ap.parse_args()
    if a.compare:
        return compare(Path(a.compare[0]), Path(a.compare[1]))
    if not a.out:
        ap.error("give an output folder, or --compare OLD NEW")
    build(Path(a.out), set(a.names))
    return 0


if __name__ == "__main__":
    sys.exit(main())
