#!/usr/bin/env python3
"""The C link module on the PIC18 core: flash, RAM and cycles with SDCC 4.2.0 (pic16) and gpsim.

    python3 bench/link_pic18.py                  # the module firmware_build/duy2008 carries now
    python3 bench/link_pic18.py --rev c0631cc    # the same files at a git revision (before/after)
    python3 bench/link_pic18.py --features       # + flash without capture / EEPROM (generation options)

Compiles firmware_build/duy2008/link_fw.c for the PIC18F4431 (device header from
picdrive.firmware.p18f4431.render_sdcc_device), links it with a small harness (app_* stubs: app_signal
reads an array, the UART TX queue always has room), and runs it in gpsim's p18f4520 (the same
PIC18 core; the 18F4431 is not in gpsim).  Prints:

* flash of link_fw.o (its code and const sections) and the runtime-library routines it pulls
  in, RAM of its variables;
* cycles of one received byte in a high-priority interrupt that calls link_rx_byte() (entry,
  context save/restore and RETFIE included), of link_poll() on a maximum-length frame (40 B
  payload: decode, CRC, NACK, reply encoded into the UART queue), on param_get of 10 ids and on
  param_info, of the CRC per byte (link_crc16 over 40 B of RAM, its generic-pointer read
  included), of link_sample() with 4 telemetry signals
  and a 4-signal capture armed (worst and mean of 15 samples) and of link_tick_ms().
Figures are gpsim instruction cycles (10 MIPS at 40 MHz: 100 ns each), net of the harness's
marker calls.
"""
from __future__ import annotations

import argparse
import binascii
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "host"))
from picdrive.link import codec, protocol as P  # noqa: E402
from picdrive.firmware.p18f4431 import render_sdcc_device  # noqa: E402
from picdrive.firmware.target import EEPROM_GPTR_STUBS, SDCC_FLAGS  # noqa: E402

SDCC = Path(os.environ.get("PICDRIVE_SDCC", Path.home() / ".cache/picdrive/toolchain/sdcc-4.2.0-pic16"))
LIB = SDCC / "share/sdcc/lib/pic16"
LKR = "/usr/share/gputils/lkr/18f4520_g.lkr"   # the 4520's memory (gpsim runs it); flash is counted per object
CFLAGS = list(SDCC_FLAGS)   # the image's options (picdrive.target); --obanksel=N miscompiles this module:
                            # it drops a BANKSEL after a CALL (tests/test_link_target.py catches it)

HARNESS = r"""
#include <stdint.h>
#include <xc.h>
#include "link_fw.h"
volatile uint8_t sink, isr_byte;
uint8_t crcbuf[40];
uint8_t ee[256];
int16_t sig[16];
uint8_t app_command(uint8_t cmd, const uint8_t *arg, uint8_t n) { (void)cmd; (void)arg; (void)n; return 0; }
void app_param_changed(uint8_t id) LINK_WPARAM { (void)id; }
int16_t app_signal(uint8_t s) LINK_WPARAM { return sig[s]; }
/* signals 0..3 straight from sig[], the others through app_signal (both paths of link_sample) */
LINK_DATA int16_t * const app_signal_src[LINK_N_SIGNALS] = { &sig[0], &sig[1], &sig[2], &sig[3] };
void app_link_lost(void) {}
uint8_t app_tx_free(void) { return 255; }
void app_tx_byte(uint8_t b) LINK_WPARAM { sink = b; }
uint8_t app_eeprom_read(uint8_t a) { return ee[a]; }
void app_eeprom_write(uint8_t a, uint8_t v) { ee[a] = v; }
void fw_lock(void) {}
void fw_unlock(void) {}
void mark(void) { sink++; }
void isr_high(void) __interrupt(1)
{
    INTCONbits.INT0IF = 0;
    link_rx_byte(isr_byte);
}
%(frames)s
static void feed(const uint8_t *p, uint8_t n)
{
    while (n--) link_rx_byte(*p++);
}
void main(void)
{
    uint8_t k;
    uint16_t c = 0xFFFFu;
    link_init();
    link_poll();
    INTCONbits.INT0IE = 1;
    INTCONbits.GIEH = 1;
    mark();
    mark();                                     /* 1: the markers' own cost */
    isr_byte = 0x11;
    for (k = 0; k < 3; k++) {                   /* 2..4: one RX interrupt each */
        INTCONbits.INT0IF = 1;
        mark();
    }
    INTCONbits.GIEH = 0;
    feed(f_end, sizeof f_end);                  /* end the stray bytes */
    link_poll();
    feed(f_max, sizeof f_max);
    mark();
    link_poll();                                /* 5: maximum-length frame */
    mark();
    feed(f_get, sizeof f_get);
    mark();
    link_poll();                                /* 7: param_get of 10 ids */
    mark();
    feed(f_info, sizeof f_info);
    mark();
    link_poll();                                /* 9: param_info */
    mark();
    c = link_crc16(crcbuf, 40);                 /* 10: 40 CRC bytes */
    sink = (uint8_t)c;
    mark();
    feed(f_tel, sizeof f_tel);
    link_poll();
    feed(f_cap, sizeof f_cap);
    link_poll();
    for (k = 0; k < 16; k++) {                  /* 12..27: link_sample */
        link_sample();
        mark();
    }
    link_tick_ms();                             /* 28: link_tick_ms */
    mark();
    while (1) {
    }
}
"""

EESTUB = EEPROM_GPTR_STUBS


def _run(cmd, cwd):
    r = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(map(str, cmd))} failed:\n{r.stdout[-3000:]}{r.stderr[-3000:]}")
    return r.stdout + r.stderr


def _old_frame(type_: int, seq: int, payload: bytes) -> bytes:
    """Protocol 1.x frame (SOF 0xA5, no stuffing), for measuring an older module."""
    body = bytes((len(payload), type_, seq)) + payload
    c = binascii.crc_hqx(body, 0xFFFF)
    return b"\xa5" + body + bytes((c >> 8, c & 0xFF))


def _frames(header: str) -> str:
    old = "LINK_SOF" in header
    enc = _old_frame if old else (lambda t, s, p: codec.encode_frame(t, s, p, lead=True))
    table = P.build_table(2)
    ids = [e.id for e in table.entries][:10]
    cmd = P.COMMAND_BY_NAME
    frames = {
        "f_end": b"\x00",
        "f_max": enc(cmd["heartbeat"].code, 1, bytes(range(1, 41))),        # 40 B: MALFORMED
        "f_get": enc(cmd["param_get"].code, 2, bytes(ids)),
        "f_info": enc(cmd["param_info"].code, 3, bytes((5,))),
        "f_tel": enc(cmd["telem_config"].code, 4, codec.command_payload(
            "telem_config", {"mask": 0xF, "decimation": 1, "samples_per_frame": 4})),
        "f_cap": enc(cmd["capture_arm"].code, 5, codec.command_payload(
            "capture_arm", {"mask": 0xF, "n_samples": 16, "pre_trigger": 0, "decimation": 1, "trigger": 0,
                            "threshold": 0})),
    }
    return "\n".join(f"static const uint8_t {k}[{len(v)}] = {{ {', '.join(str(b) for b in v)} }};"
                     for k, v in frames.items())


def _sections(obj: Path) -> tuple[dict, int]:
    """({section: flash bytes}, RAM bytes) of an object: code/const sections (SDCC puts each function
    in its own, S_<file>__<function>), udata sections."""
    out = _run(["gpvo", str(obj)], obj.parent)
    secs, ram = {}, 0
    for blk in out.split("Section Header")[1:]:
        m = re.search(r"Name\s+(\S+).*?Size of Section\s+(\d+).*?Flags\s+(0x[0-9a-fA-F]+)", blk, re.S)
        if not m:
            continue
        name, size, f = m.group(1), int(m.group(2)), int(m.group(3), 16)
        if f & 0x20:
            secs[re.sub(r"^S_link_fw__", "", name)] = size
        elif name.startswith(("udata", "idata", "ustat")):   # ustat: an __at block (access RAM)
            ram += size
    return secs, ram


def _object_sizes(obj: Path) -> tuple[int, int]:
    """(flash, RAM) bytes of an object: code/const sections, udata sections."""
    secs, ram = _sections(obj)
    return sum(secs.values()), ram


def _write_sources(d: Path, c_text: str, h_text: str) -> None:
    """The module and the rendered 18F4431 device header and SFR placement, into folder ``d``."""
    xc_h, xc_sfr = render_sdcc_device()
    (d / "xc.h").write_text(xc_h)
    (d / "xc_sfr.c").write_text(xc_sfr)
    (d / "link_fw.c").write_text(c_text)
    (d / "link_fw.h").write_text(h_text)


def flash_with(c_text: str, h_text: str, defines: list[str]) -> int:
    """Flash of link_fw.o compiled with extra -D options."""
    with tempfile.TemporaryDirectory() as td:
        d = Path(td)
        _write_sources(d, c_text, h_text)
        _run([str(SDCC / "bin/sdcc"), *CFLAGS, *defines, "-I.", "-c", "link_fw.c"], d)
        return _object_sizes(d / "link_fw.o")[0]


def measure(c_text: str, h_text: str) -> dict:
    with tempfile.TemporaryDirectory() as td:
        d = Path(td)
        _write_sources(d, c_text, h_text)
        (d / "h.c").write_text(HARNESS % {"frames": _frames(h_text)})
        (d / "eestub.c").write_text(EESTUB)
        sdcc = [str(SDCC / "bin/sdcc"), *CFLAGS, "-I."]
        env_path = f"{SDCC / 'bin'}:{os.environ['PATH']}"
        for f in ("link_fw.c", "h.c", "xc_sfr.c", "eestub.c"):
            # link_crc16 (host API, not in a chip build) is timed here: compiled in for the harness
            r = subprocess.run([*sdcc, "-DLINK_WITH_HOST_API=1", "-c", f], cwd=d, capture_output=True, text=True,
                               env={**os.environ, "PATH": env_path})
            if r.returncode != 0:
                raise SystemExit(f"sdcc {f} failed:\n{r.stdout[-3000:]}{r.stderr[-3000:]}")
        _run(["gplink", "-m", "-w", "-s", LKR, "-o", "out.hex", str(LIB / "crt0i.o"), "h.o", "link_fw.o",
              "xc_sfr.o", "eestub.o", str(LIB / "libsdcc.lib")], d)
        funcs, ram = _sections(d / "link_fw.o")
        for k in ("link_crc16", "link_param_set"):    # the host API: not in a chip build
            funcs.pop(k, None)
        flash = sum(funcs.values())
        mp = (d / "out.map").read_text()
        lib = {m.group(1): int(m.group(2), 16) for m in
               re.finditer(r"^\s*S_(\w+?)___\w+\s+code\s+0x[0-9a-f]+\s+program\s+0x([0-9a-f]+)", mp, re.M)
               if not m.group(1).startswith(("h_", "link_fw", "eestub", "crt0", "xc_sfr"))}
        asm = (d / "link_fw.asm").read_text()
        helpers = sorted(set(re.findall(r"CALL\s+(__\w+)", asm)))
        (d / "s.stc").write_text("processor p18f4520\nload out.cod\nbreak e _mark\n"
                                 + "run\ncycles\n" * 29 + "quit\n")
        r = subprocess.run(["gpsim", "-i", "-S", "disable", "-c", "s.stc"], cwd=d, capture_output=True,
                           timeout=300)
        text = r.stdout.decode("latin-1") + r.stderr.decode("latin-1")
        cyc = [int(x) for x in re.findall(r"\*\*gpsim> (\d+) = 0x", text)]
        if len(cyc) < 29:
            raise SystemExit(f"gpsim stopped after {len(cyc)} markers:\n{text[-2000:]}")
    d_ = [b - a for a, b in zip(cyc, cyc[1:])]      # d_[i]: from marker i to marker i + 1
    ov = d_[0]                                      # marker to marker, nothing between
    isr = [x - ov - 4 for x in d_[2:4]]            # minus BSF INT0IF and the loop's increment and test
    samples = [x - ov - 4 for x in d_[12:27]]      # minus the loop (the first sample follows the feeds)
    if os.environ.get("LINK_BENCH_SAMPLES"):
        print("samples", samples)
    return dict(flash=flash, funcs=funcs, ram=ram, lib=lib, helpers=helpers, overhead=ov,
                rx_isr=max(isr), poll_max=d_[5] - ov, poll_get=d_[7] - ov, poll_info=d_[9] - ov,
                crc_per_byte=(d_[10] - ov) / 40.0,
                sample_max=max(samples), sample_mean=sum(samples) / len(samples), tick=d_[27] - ov)


EXCHANGE = r"""
#include <stdint.h>
#include <xc.h>
#include "link_fw.h"
#define N_IDS %(n_ids)su
#define PI16_AT %(pi16_at)s
__at(0x400) uint8_t txlog[240];
__at(0x4F0) uint8_t txn;
__at(0x4F1) uint8_t txn_hi;
__at(PI16_AT) int16_t pi16[N_IDS];              /* link_param_i16(f_ids[i]), below txlog */
__at(0x500) uint8_t ee[256];
int16_t sig[16];
uint8_t app_command(uint8_t cmd, const uint8_t *arg, uint8_t n) { (void)cmd; (void)arg; (void)n; return 0; }
void app_param_changed(uint8_t id) LINK_WPARAM { (void)id; }
int16_t app_signal(uint8_t s) LINK_WPARAM { return sig[s]; }
/* signals 0..3 straight from sig[], the others through app_signal (both paths of link_sample) */
LINK_DATA int16_t * const app_signal_src[LINK_N_SIGNALS] = { &sig[0], &sig[1], &sig[2], &sig[3] };
void app_link_lost(void) {}
static uint8_t tx_since;                        /* bytes queued since app_tx_free: never more than it said */
uint8_t app_tx_free(void) { tx_since = 0; return TX_ROOM; }
void app_tx_byte(uint8_t b) LINK_WPARAM { if (++tx_since > TX_ROOM) { txn_hi |= 4; } if (txn < sizeof txlog) { txlog[txn] = b; txn++; } else { txn_hi = 1; } }
uint8_t app_eeprom_read(uint8_t a) { return ee[a]; }
void app_eeprom_write(uint8_t a, uint8_t v) { ee[a] = v; }
void fw_lock(void) {}
void fw_unlock(void) {}
void done(void) { txn_hi |= 2; }
%(frames)s
void main(void)
{
    uint8_t i;
    uint16_t k;
    for (i = 0; i < 7; i++) {                   /* the first seven signals; state, fault... 0 */
        sig[i] = (int16_t)(0x0101 * i - 0x3000);
    }
    link_init();
    link_poll();
    for (i = 0; i < N_FRAMES; i++) {
        for (k = f_start[i]; k < f_start[i + 1]; k++) {
            link_rx_byte(f_bytes[k]);
            link_poll();
        }
        for (k = 0; k < f_samples[i]; k++) {
            link_sample();
            link_poll();
            sig[0] = (int16_t)(sig[0] + RAMP);  /* the speed moves by RAMP a sample */
        }
    }
    for (i = 0; i < N_IDS; i++) {
        pi16[i] = link_param_i16(f_ids[i]);
    }
    done();
    while (1) {
    }
}
"""


I16_IDS = [e.id for e in P.build_table(2).entries] + [0x0B, 0x7F]   # every id of a 2-rule table, 2 unknown
PI16_AT = 0x400 - 2 * len(I16_IDS)      # the results end where txlog starts
assert 0x380 <= PI16_AT


def chip_exchange(c_text: str, h_text: str, frames: list[bytes], samples: list[int] | None = None,
                  ramp: int = 0, tx_room: int = 255) -> bytes:
    """Run the link module on the PIC18 core in gpsim: link_init, link_poll, then every byte of
    ``frames`` through link_rx_byte with a link_poll after each (as tests/linksupport's direct
    mode does on the host), and after frame i ``samples[i]`` times link_sample and link_poll
    (app_signal(s) = 0x0101 s - 0x3000 for s < 7, else 0; signal 0 moves by ``ramp`` after each
    link_sample; app_tx_free() reports ``tx_room`` bytes); returns the bytes it sent to the UART (at most 240).  Afterwards
    ``chip_exchange.param_i16`` holds {id: link_param_i16(id)} for I16_IDS, ``chip_exchange.eeprom``
    the EEPROM."""
    samples = samples or [0] * len(frames)
    from picdrive.firmware.gpsim import _dump
    data = b"".join(frames)
    starts = [0]
    for f in frames:
        starts.append(starts[-1] + len(f))
    decl = (f"#define N_FRAMES {len(frames)}u\n#define RAMP ({int(ramp)})\n"
            f"static const uint8_t f_bytes[{max(1, len(data))}] = {{ {', '.join(str(b) for b in data) or '0'} }};\n"
            f"static const uint16_t f_start[{len(starts)}] = {{ {', '.join(map(str, starts))} }};\n"
            f"static const uint8_t f_samples[{len(frames)}] = {{ {', '.join(map(str, samples))} }};\n"
            f"static const uint8_t f_ids[N_IDS] = {{ {', '.join(map(str, I16_IDS))} }};")
    with tempfile.TemporaryDirectory() as td:
        d = Path(td)
        _write_sources(d, c_text, h_text)
        (d / "x.c").write_text(EXCHANGE % {"frames": decl, "n_ids": len(I16_IDS), "pi16_at": hex(PI16_AT)})
        (d / "eestub.c").write_text(EESTUB)
        for f in ("link_fw.c", "x.c", "xc_sfr.c", "eestub.c"):
            _run([str(SDCC / "bin/sdcc"), *CFLAGS, f"-DTX_ROOM={int(tx_room)}u", "-I.", "-c", f], d)
        _run(["gplink", "-m", "-w", "-s", LKR, "-o", "out.hex", str(LIB / "crt0i.o"), "x.o", "link_fw.o",
              "xc_sfr.o", "eestub.o", str(LIB / "libsdcc.lib")], d)
        (d / "s.stc").write_text("processor p18f4520\nload out.cod\nbreak e _done\nrun\ndump r\nquit\n")
        r = subprocess.run(["gpsim", "-i", "-S", "disable", "-c", "s.stc"], cwd=d, capture_output=True, timeout=300)
        mem = _dump(r.stdout.decode("latin-1") + r.stderr.decode("latin-1"))
    if 0x4F0 not in mem:
        raise SystemExit("gpsim printed no register dump")
    if mem[0x4F1] & 1:
        raise SystemExit("the exchange sent more than 240 bytes: shorten it")
    if mem[0x4F1] & 4:
        raise AssertionError("link_poll queued more bytes than app_tx_free() reported")
    chip_exchange.eeprom = bytes(mem.get(0x500 + i, 0) for i in range(256))
    chip_exchange.param_i16 = {k: ((mem.get(PI16_AT + 2 * i, 0) | mem.get(PI16_AT + 1 + 2 * i, 0) << 8) ^ 0x8000)
                               - 0x8000
                               for i, k in enumerate(I16_IDS)}
    return bytes(mem[0x400 + i] for i in range(mem[0x4F0]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument("--rev", help="git revision of firmware_build/duy2008/link_fw.[ch] (default: working tree)")
    ap.add_argument("--features", action="store_true", help="also the flash without capture, EEPROM, both")
    ap.add_argument("--folder", default="firmware_build/duy2008", help="generated firmware folder (default %(default)s)")
    a = ap.parse_args()
    if not (SDCC / "bin/sdcc").exists():
        print(f"SDCC pic16 not found in {SDCC}: run scripts/pic_toolchain.sh", file=sys.stderr)
        return 2
    if a.rev:
        get = lambda f: _run(["git", "show", f"{a.rev}:firmware_build/duy2008/{f}"], ROOT)  # noqa: E731
        c_text, h_text = get("link_fw.c"), get("link_fw.h")
    else:
        c_text = (ROOT / a.folder / "link_fw.c").read_text()
        h_text = (ROOT / a.folder / "link_fw.h").read_text()
    m = measure(c_text, h_text)
    print(f"link_fw.c ({a.rev or 'working tree'}), SDCC 4.2.0 {' '.join(CFLAGS[1:])}, gpsim p18f4520")
    print(f"  flash        {m['flash']:6d} B  (code + const of link_fw.o)")
    top = sorted(m["funcs"].items(), key=lambda kv: -kv[1])[:15]
    print("  largest sections (bytes; .code = the const tables):\n" + "\n".join(f"    {b:6d}  {n}" for n, b in top))
    print(f"  runtime lib  {sum(m['lib'].values()):6d} B  ({', '.join(f'{k} {v}' for k, v in sorted(m['lib'].items()))})")
    print(f"  helpers      {', '.join(m['helpers']) or 'none'} (called from link_fw.c)")
    print(f"  RAM          {m['ram']:6d} B  (static)")
    print(f"  RX byte      {m['rx_isr']:6d} cycles  (high-priority interrupt calling link_rx_byte, entry to RETFIE)")
    print(f"  link_poll    {m['poll_max']:6d} cycles  (maximum-length frame, 40 B payload -> NACK)")
    print(f"  link_poll    {m['poll_get']:6d} cycles  (param_get of 10 ids -> 40 B reply)")
    print(f"  link_poll    {m['poll_info']:6d} cycles  (param_info)")
    print(f"  CRC          {m['crc_per_byte']:6.1f} cycles per byte (link_crc16 over 40 B, generic-pointer read included)")
    print(f"  link_sample  {m['sample_max']:6d} cycles worst, {m['sample_mean']:.0f} mean "
          "(4 telemetry signals, 4-signal capture armed)")
    print(f"  link_tick_ms {m['tick']:6d} cycles")
    if a.features:
        for label, defs in (("without capture", ["-DLINK_WITH_CAPTURE=0"]),
                            ("without EEPROM", ["-DLINK_WITH_EEPROM=0"]),
                            ("without both", ["-DLINK_WITH_CAPTURE=0", "-DLINK_WITH_EEPROM=0"])):
            f = flash_with(c_text, h_text, defs)
            print(f"  flash {label:<16} {f:6d} B  ({m['flash'] - f} B less)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
