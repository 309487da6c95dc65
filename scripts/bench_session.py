#!/usr/bin/env python3
"""Capture the bench session shown in README.md and docs/bench-session.md.

Starts ``picdrive twin`` on the committed example firmware
(``firmware_build/duy2008``), drives an interactive ``picdrive console``
through a pseudo-terminal (pexpect), one command at a time as typed, and
writes what the console printed, unedited, into ``docs/bench-session.md``
(between the BEGIN/END markers) with the step plot in ``docs/img/``.

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
        return "\n".join(out).replace(url, url.rsplit(":", 1)[0] + ":5000")
    finally:
        twin.terminate()
        twin.wait(10)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument("--print", action="store_true", help="print the transcript, write nothing")
    a = ap.parse_args()
    text = capture()
    if a.print:
        print(text)
        return 0
    doc = ROOT / "docs" / "bench-session.md"
    s = doc.read_text(encoding="utf-8")
    if BEGIN not in s or END not in s:
        raise SystemExit(f"{doc} lacks the {BEGIN} / {END} markers")
    head, rest = s.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    doc.write_text(f"{head}{BEGIN}\n```\n{text}\n```\n{END}{tail}", encoding="utf-8")
    print(f"wrote {doc}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
