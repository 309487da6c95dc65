#!/usr/bin/env python3
"""Full fuzz run of the C link module under AddressSanitizer + UndefinedBehaviorSanitizer.

    python3 bench/fuzz_link.py [--bytes 2000000] [--seeds 5]

Each seed feeds --bytes bytes of garbage, intact and repeated frames and corrupted frames
(a frame inside a payload with its outer start lost, truncated frames, LEN errors with a
recomputed CRC, 1-3 bit flips, an inserted or deleted byte) through link_rx_byte + link_poll
(tests/linksupport/fuzz_main.c), which checks the accepted frames against an independent
reference decoder, that every frame sent after a delimiter is accepted, and one reply per
accepted command.  Prints, per kind of corruption, the candidates judged and the false accepts
beside the CRC-16's chance rate (candidates / 65536); exit status 1 if any seed fails.
"""
import argparse
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from linksupport import build  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument("--bytes", type=int, default=2_000_000, help="bytes per seed (>= 10^6)")
    ap.add_argument("--seeds", type=int, default=5)
    a = ap.parse_args()
    t = time.perf_counter()
    exe = build.fuzz_executable()
    print(f"harness built with {' '.join(build.SANITIZE)} in {time.perf_counter() - t:.1f} s")
    kinds = ["garbage", "nested", "truncated", "badlen", "flipped", "insdel"]
    keys = ["bytes", "accepted", "commands", "intact", "intact_accepted", "intact_lead", "intact_lead_accepted",
            "truncated_completed_by_equal_bytes", "out_badcrc_nacks", "out_telemetry", "link_lost", "seconds"] \
        + [f"candidates_{k}" for k in kinds] + [f"false_accepts_{k}" for k in kinds]
    tot: dict[str, float] = {}
    ok = True
    for seed in range(1, a.seeds + 1):
        r = subprocess.run([str(exe), "--bytes", str(a.bytes), "--seed", str(seed)], capture_output=True, text=True)
        f = dict(line.split("=", 1) for line in r.stdout.splitlines() if "=" in line)
        if r.returncode != 0 or f.get("OK") != "1":
            ok = False
            print(f"seed {seed}: FAILED (exit {r.returncode}) {f.get('FAIL', '')}\n{r.stderr[-3000:]}")
            continue
        print(f"seed {seed}: {int(f['bytes'])} bytes, {f['accepted']} frames accepted, false accepts "
              + ", ".join(f"{k} {f['false_accepts_' + k]}/{f['candidates_' + k]}" for k in kinds))
        for k in keys:
            tot[k] = tot.get(k, 0) + float(f[k])
    if tot:
        print(f"total: {tot['bytes']:.0f} bytes fuzzed in {tot['seconds']:.2f} s CPU "
              f"({tot['bytes'] / max(tot['seconds'], 1e-9) / 1e6:.1f} MB/s under ASan+UBSan)")
        print(f"  frames accepted {tot['accepted']:.0f} ({tot['commands']:.0f} host commands, each answered once); "
              f"intact frames {tot['intact']:.0f}, accepted {tot['intact_accepted']:.0f}; sent after a delimiter "
              f"{tot['intact_lead']:.0f}, accepted {tot['intact_lead_accepted']:.0f}")
        print(f"  {'corruption':<10} {'candidates':>11} {'false accepts':>14} {'chance (n/65536)':>17}")
        for k in kinds:
            n = tot[f"candidates_{k}"]
            print(f"  {k:<10} {n:>11.0f} {tot['false_accepts_' + k]:>14.0f} {n / 65536:>17.2f}")
        n = sum(tot[f"candidates_{k}"] for k in kinds)
        print(f"  {'all':<10} {n:>11.0f} {sum(tot['false_accepts_' + k] for k in kinds):>14.0f} {n / 65536:>17.2f}")
        print(f"  truncated frames completed bit for bit by following bytes equal to the lost ones (the original "
              f"frame, not a false accept): {tot['truncated_completed_by_equal_bytes']:.0f}")
        print(f"  sanitizer reports: none; reference and reply checks: {'all passed' if ok else 'FAILED'}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
