#!/usr/bin/env python3
"""Serial-link figures, measured through picdrive.link and the rendered C module.

    python3 bench/link.py [--seconds 3] [--baud 115200] [--rates 1000,1100,1120,1140,1152,1200]

1. Wire efficiency of the default telemetry frame (payload bytes / wire bytes), from the
   frames actually received.
2. Telemetry rate reachable at the baud rate against the theoretical byte limit (baud / 10
   bytes per second; 11 520 B/s at 115200): the fake board (rendered link_fw.c + fake app, a
   discrete-event UART model: 10 bit times per byte, a 16-byte firmware TX queue) runs in step
   with the wall clock behind a local socket; picdrive.link configures the default telemetry
   and counts samples, wire bytes and dropped samples (from the 16-bit sample counter) while
   the board's sample clock is swept.  Keep-alive heartbeats run as in normal use.
3. Command round trip while telemetry streams.
4. RAM of the C module from the avr-gcc build (avr-nm --size-sort -S): buffers and state, for
   the two-rule default table and the bundled example's profile table.
"""
from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from picdrive.link import protocol as P  # noqa: E402
from picdrive.firmware.p18f4431 import bits  # noqa: E402
from picdrive.link.protocol_c import render_c  # noqa: E402
from picdrive.link.client import Link  # noqa: E402
from linksupport import build  # noqa: E402
from linksupport.fakeboard import FakeBoard  # noqa: E402


def run_rate(table, baud: int, rate_hz: int, seconds: float, spf: int, txq: int) -> dict:
    b = FakeBoard(table, baud=baud, sample_hz=rate_hz, txq_bytes=txq)
    try:
        url = b.serve()
        with Link.open(url, baudrate=baud) as lk:
            lk.configure_telemetry(P.DEFAULT_TELEMETRY_SIGNALS, decimation=1, samples_per_frame=spf)
            lk.set_speed(1500)
            lk.start()
            time.sleep(0.3)                                   # settle
            lk.flush_samples()
            s0 = lk.telemetry_stats
            f0, n0, d0, rx0 = s0.frames, s0.samples, s0.dropped, lk.stats["rx_bytes"]
            board_drop0 = lk.status().telem_dropped
            t0 = time.perf_counter()
            sim0 = b.now_s
            time.sleep(seconds)
            st = lk.telemetry_stats
            rx1, t1, sim1 = lk.stats["rx_bytes"], time.perf_counter(), b.now_s
            frames, samples, dropped = st.frames - f0, st.samples - n0, st.dropped - d0
            crc_errors = lk.stats["crc_errors"]
            board_drop = lk.status().telem_dropped - board_drop0
            # round trip of a command while streaming
            rtt = []
            for _ in range(20):
                t = time.perf_counter()
                lk.get("speed")
                rtt.append(time.perf_counter() - t)
            lk.stop()
        wall = t1 - t0
        return dict(rate=rate_hz, crc_errors=crc_errors, frames=frames, samples=samples, dropped=dropped, board_dropped=board_drop,
                    wire_bps=(rx1 - rx0) / wall, samples_per_s=samples / wall, wall=wall, sim=sim1 - sim0,
                    rtt_ms=1e3 * statistics.median(rtt), rtt_max_ms=1e3 * max(rtt))
    finally:
        b.close()


def efficiency(table, baud: int) -> list[tuple[str, int, int, int]]:
    """(label, payload, sample-data bytes, wire bytes) of received telemetry frames."""
    out = []
    for spf, label in ((P.DEFAULT_SAMPLES_PER_FRAME, "default: 4 signals x 4 samples"),
                       (1, "4 signals x 1 sample"), (1, "1 signal x 1 sample")):
        sig = P.DEFAULT_TELEMETRY_SIGNALS if label.startswith("4") or label.startswith("default") else ("speed",)
        b = FakeBoard(table, baud=baud, sample_hz=200)
        try:
            with Link.open(b.serve(), baudrate=baud, keepalive=False) as lk:
                lk.configure_telemetry(sig, samples_per_frame=spf)
                payload = lk.telemetry.payload_len
                rx0, f0 = lk.stats["rx_bytes"], lk.telemetry_stats.frames
                time.sleep(0.5)
                wire = (lk.stats["rx_bytes"] - rx0) / max(1, lk.telemetry_stats.frames - f0)
        finally:
            b.close()
        out.append((label, payload, payload - P.TELEMETRY_HEADER_BYTES, wire))
    return out


def ram(table, capture_bytes: int) -> tuple[dict[str, int], int]:
    files = render_c(table, build_id=1, profile_hash=2, sample_hz=1000, capture_bytes=capture_bytes,
                     sfr_bits=bits())
    with tempfile.TemporaryDirectory() as d:
        obj = build.avr_object(files, Path(d))
        sym = build.avr_ram_bytes(obj)
        size = subprocess.run(["avr-size", str(obj)], capture_output=True, text=True, check=True).stdout
    text = int(size.splitlines()[1].split()[0])
    return sym, text


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--baud", type=int, default=115200)
    ap.add_argument("--rates", default="1000,1100,1120,1140,1152,1200",
                    help="board sample rates (Hz) to sweep with the default frame")
    ap.add_argument("--txq", type=int, default=16, help="the firmware's UART TX queue in the model, bytes")
    a = ap.parse_args()
    table = P.build_table(2)
    limit = a.baud / 10.0

    print(f"== wire efficiency (measured from received frames, {a.baud} baud)")
    for label, payload, data, wire in efficiency(table, a.baud):
        print(f"  {label:34s} payload {payload:2d} B, wire {wire:4.1f} B/frame: payload/wire = "
              f"{payload / wire:5.1%}  (sample data/wire = {data / wire:5.1%})")

    print(f"\n== telemetry rate at {a.baud} baud: byte limit {limit:.0f} B/s; default frame "
          f"({len(P.DEFAULT_TELEMETRY_SIGNALS)} signals x {P.DEFAULT_SAMPLES_PER_FRAME} samples, "
          f"{P.TELEMETRY_HEADER_BYTES + 8 * P.DEFAULT_SAMPLES_PER_FRAME + P.FRAME_OVERHEAD} B on the wire) "
          f"-> theoretical {limit / 10:.0f} samples/s; firmware TX queue {a.txq} B; {a.seconds:g} s per point")
    print(f"  {'board Hz':>8} {'samples/s':>10} {'wire B/s':>9} {'of limit':>8} {'dropped':>8} {'board drop':>10} "
          f"{'sim/wall':>8} {'host CRC err':>12} {'cmd RTT ms (med/max)':>21}")
    best = None
    for rate in [int(x) for x in a.rates.split(",")]:
        r = run_rate(table, a.baud, rate, a.seconds, P.DEFAULT_SAMPLES_PER_FRAME, a.txq)
        print(f"  {r['rate']:>8} {r['samples_per_s']:>10.1f} {r['wire_bps']:>9.0f} {r['wire_bps'] / limit:>8.1%} "
              f"{r['dropped']:>8} {r['board_dropped']:>10} {r['sim'] / r['wall']:>8.4f} {r['crc_errors']:>12} "
              f"{r['rtt_ms']:>10.2f} / {r['rtt_max_ms']:<8.2f}")
        if r["dropped"] == 0 and r["board_dropped"] == 0 and (best is None or r["wire_bps"] > best["wire_bps"]):
            best = r
    if best:
        print(f"  reachable with 0 dropped samples: {best['samples_per_s']:.0f} samples/s of 4 signals, "
              f"{best['wire_bps']:.0f} B/s = {best['wire_bps'] / limit:.1%} of the {limit:.0f} B/s limit "
              f"(target >= 90 %)")
    else:
        print("  no rate ran without drops")

    print("\n== RAM of the C module (avr-gcc -Os, avr-nm --size-sort -S: .bss/.data/common)")
    from picdrive.profile import load_profile
    for label, t, cap in (("2 rules, default table", table, P.CAPTURE_BYTES_DEFAULT),
                          ("duy2008 profile table", P.build_table(2, profile=load_profile("duy2008")),
                           P.CAPTURE_BYTES_DEFAULT),
                          ("8 rules, int32 gains", P.build_table(8, {f"rule{j}_{k}": P.ParamOverride(ctype="int32")
                                                                      for j in range(1, 9) for k in ("kp", "ki", "kd", "kc")}),
                           P.CAPTURE_BYTES_DEFAULT)):
        sym, text = ram(t, cap)
        total = sum(sym.values())
        print(f"  {label}: {total} B of RAM  ({', '.join(f'{k} {v}' for k, v in sorted(sym.items(), key=lambda x: -x[1]))})"
              f"; code + const table {text} B (on AVR; XC8 keeps the const table in flash too)")
        b = P.ram_budget(t, cap)
        print(f"    = buffers {sum(b.values())} B ({', '.join(f'{k} {v}' for k, v in b.items())}) + scalar state "
              f"{total - sum(b.values())} B; {768 - total} B of the PIC18F4431's 768 B left to the firmware")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
