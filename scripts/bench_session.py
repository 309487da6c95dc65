#!/usr/bin/env python3
"""Capture the bench sessions shown in README.md and docs/bench-session.md.

Starts ``picdrive twin`` on the committed example firmware
(``firmware_build/duy2008``), drives an interactive ``picdrive console``
through a pseudo-terminal (pexpect), one command at a time as typed, and
writes what the console printed, unedited, into ``docs/bench-session.md``
(between the BEGIN/END markers) with the step plot in ``docs/img/``.

Then, on a fresh twin, it runs the scripted session ``examples/bench-session.txt``
(``--strict --run``: scope a setpoint step, expect the settled speed, save and
diff the parameters, a fault that fails the script) in a scratch folder and
writes its output and exit status between the BEGIN/END scripted markers, the
scope plot in ``docs/img/scope_setpoint_step.png``.  The same file runs in CI
(tests/test_console_bench.py).

    python3 scripts/bench_session.py            # rewrite the transcript
    python3 scripts/bench_session.py --print    # only print it
"""
from __future__ import annotations

import argparse
import re
import subprocess
import sys
import time
from pathlib import Path

import pexpect

ROOT = Path(__file__).resolve().parents[1]
PROMPT = "picdrive> "
COMMANDS = [
    "params rule1",
    "speed 1500",
    "start",
    "wait 0.5",
    "status",
    "set rule1_kp 1e9",
    "telemetry signals speed,current,voltage",
    "telemetry rate 250",
    "record out/bench-session.csv",
    "view 1",
    "record stop",
    "stop",
    "step 0 2400 --hold 0.5 --png docs/img/step_0_2400.png",
    "stop",
    "faults",
    "quit",
]
BEGIN, END = "<!-- BEGIN captured session -->", "<!-- END captured session -->"
SBEGIN, SEND = "<!-- BEGIN scripted session -->", "<!-- END scripted session -->"
SESSION = ROOT / "examples" / "bench-session.txt"
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


def screen(text: str) -> str:
    """What a terminal shows: escape codes dropped, each line's last carriage-return redraw kept."""
    out = []
    for line in ANSI.sub("", text).split("\n"):
        parts = [p for p in line.split("\r") if p.strip()]
        out.append(parts[-1] if parts else "")
    return "\n".join(out)


def start_twin() -> tuple[subprocess.Popen, str]:
    p = subprocess.Popen([sys.executable, "-m", "picdrive", "twin", "--profile", "duy2008",
                          "--firmware", "firmware_build/duy2008", "--port", "0"],
                         cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 60:
        line = p.stdout.readline()
        if not line:
            break
        m = re.search(r"socket://127\.0\.0\.1:\d+", line)
        if m:
            return p, m.group(0)
    p.kill()
    raise SystemExit("picdrive twin did not print its URL")


def capture() -> str:
    (ROOT / "out").mkdir(exist_ok=True)                  # the console creates no folders
    old = ROOT / "docs" / "img" / "step_0_2400.png"      # this script's own output, written again
    old.unlink(missing_ok=True)
    old.with_suffix(".csv").unlink(missing_ok=True)
    twin, url = start_twin()
    try:
        con = pexpect.spawn(sys.executable, ["-m", "picdrive", "console", url, "--profile", "duy2008"],
                            cwd=str(ROOT), encoding="utf-8", timeout=30, dimensions=(40, 140))
        con.expect_exact(PROMPT)
        out = [f"$ picdrive console {url.rsplit(':', 1)[0]}:5000 --profile duy2008", screen(con.before).rstrip()]
        for cmd in COMMANDS:
            con.sendline(cmd)
            if cmd == "quit":
                con.expect(pexpect.EOF)
            else:
                con.expect_exact(PROMPT)
            text = screen(con.before)
            lines = text.split("\n")
            if lines and lines[0].strip() == cmd:        # the terminal's echo of the typed line
                lines = lines[1:]
            out.append(PROMPT + cmd)
            body = "\n".join(lines).rstrip()
            if body:
                out.append(body)
        return "\n".join(out).replace(url, url.rsplit(":", 1)[0] + ":5000").replace(str(ROOT) + "/", "")
    finally:
        twin.terminate()
        twin.wait(10)


def scripted() -> tuple[str, bytes]:
    """Run examples/bench-session.txt on a fresh twin: (transcript, scope PNG bytes)."""
    import shutil
    import tempfile
    twin, url = start_twin()
    tmp = Path(tempfile.mkdtemp(prefix="picdrive-bench-"))
    try:
        shutil.copy(SESSION, tmp / SESSION.name)
        r = subprocess.run([sys.executable, "-m", "picdrive", "console", url, "--strict", "--profile", "duy2008",
                            "--run", SESSION.name], cwd=tmp, capture_output=True, text=True, timeout=120)
        png = (tmp / "scope_setpoint_step.png").read_bytes()
    finally:
        twin.terminate()
        twin.wait(10)
    short = url.rsplit(":", 1)[0] + ":5000"
    text = (f"$ picdrive console {short} --strict --profile duy2008 --run {SESSION.name}\n"
            + r.stdout + r.stderr + f"$ echo $?\n{r.returncode}")
    shutil.rmtree(tmp, ignore_errors=True)
    return text.replace(url, short).replace(str(tmp) + "/", "").rstrip(), png


def _between(s: str, begin: str, end: str, text: str, doc: Path) -> str:
    if begin not in s or end not in s:
        raise SystemExit(f"{doc} lacks the {begin} / {end} markers")
    head, rest = s.split(begin, 1)
    _, tail = rest.split(end, 1)
    return f"{head}{begin}\n```\n{text}\n```\n{end}{tail}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument("--print", action="store_true", help="print the transcript, write nothing")
    a = ap.parse_args()
    text = capture()
    stext, png = scripted()
    if a.print:
        print(text + "\n\n" + stext)
        return 0
    doc = ROOT / "docs" / "bench-session.md"
    s = doc.read_text(encoding="utf-8")
    s = _between(s, BEGIN, END, text, doc)
    s = _between(s, SBEGIN, SEND, stext, doc)
    doc.write_text(s, encoding="utf-8")
    (ROOT / "docs" / "img" / "scope_setpoint_step.png").write_bytes(png)
    print(f"wrote {doc} and docs/img/scope_setpoint_step.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
