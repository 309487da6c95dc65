"""Worst-case cycles of the firmware's interrupts and link code, measured on the PIC18 core in gpsim.

gpsim (Debian, 0.31) has no 18F4431.  Its 18F4620 runs the same PIC18 core
(instruction set and cycle counts) with 64 KB of flash and 3,968 B of RAM,
enough for today's oversized build too.  What differs, and what the timing
build does about it:

* The 18F4431's access bank splits at 0x60, the 4620's at 0x80: access-bank
  addresses 0x60-0x7F are the 4431's PCPWM/QEI/IC registers (0xF60-0xF7F)
  but GPRs on the 4620.  The same instructions (same cycles) therefore reach
  GPRs there; the timing link keeps the linker off 0x060-0x07F so nothing
  else lives in them.
* Registers whose value the hardware drives (interrupt flags, UART receive,
  ports, the ADC result, Timer5) are placed in access RAM (0x040-0x05F) in the
  timing build, so the harness can set them.  An access-RAM GPR and an SFR are both
  reached with a=0: the firmware's instructions and their cycles are the same.
  Interrupts are therefore never taken for real: the harness calls the
  interrupt entry with CALL (2 cycles, as RETFIE's 2) and adds
  ``ENTRY_CYCLES`` for the interrupt latency and the GOTO at the vector.
* The ADC is the timing processor's own: its ADCON0 has the same GO/DONE and
  ADON bits and converts AN0/AN1 for the firmware's group A/B codes, ADCON2
  has the same clock and acquisition fields, so a software start and the
  firmware's wait for GO/DONE take the simulated conversion time.  The bus
  voltage (AN1 = RA1) is a gpsim pull-up module at the middle of the
  firmware's under/overvoltage window (``FW_BUS_UV``..``FW_BUS_OV``): the
  speed loop runs without a bus fault.  The bus current is converted on the
  18F4431 by the PCPWM special event (ADCON3, SEVTCMP), which the timing
  processor does not have: the harness writes each state's current reading
  into ADRESH:ADRESL before the call, and the firmware's wait for a
  trigger-started conversion in flight at interrupt entry (at most one
  conversion, ~130 cycles on the chip) is not in the figure.

Timer1 (on both chips, Fosc/4, 1:1) is read before and after each measured
call; the harness stores the differences in RAM and gpsim's register dump is
parsed.  One gpsim run per build measures the whole corpus.
"""

from __future__ import annotations

import functools
import re
import shutil
import tempfile
import subprocess
from dataclasses import dataclass
from pathlib import Path

from ..board import FCY_HZ
from ..errors import PicdriveError
from . import p18f4431

__all__ = ["GpsimError", "measure", "measure_modes", "build_timing", "TELEMETRY_MODES", "Cycles", "ENTRY_CYCLES", "TIMING_PROCESSOR", "HARNESS_INPUTS"]

TIMING_PROCESSOR = "p18f4620"
ENTRY_CYCLES = 4             # interrupt latency to the vector (3-4 Tcy) + GOTO (2) - the harness's CALL (2)
HARNESS_INPUTS = ("INTCON", "INTCON2", "INTCON3", "PIR1", "PIR2", "PIR3", "PIE1", "PIE2", "PIE3",
                  "RCREG", "RCSTA", "TXSTA", "TXREG",
                  "PORTA", "PORTB", "PORTC", "PORTD", "PORTE", "TMR5L", "TMR5H",
                  # the speed sample's Timer2 count: set by the harness from T2_SAMPLE (free-running, it
                  # made the figures depend on the code's own timing, which decides the M/T path taken)
                  "TMR2",
                  # read in a loop until two reads agree: SDCC may read one with MOVFF (0xF6x, a GPR in
                  # bank 15 on the timing processor) and the other with a=0 (0x06x): keep them one register
                  "POSCNTL", "POSCNTH")
#: Timer2 counts (1:4 Tcy) at the speed samples, in turn: the interrupt's entry latency and the
#: code before the position read move the sample by 0..~70 counts on the chip (bench/twin.py
#: section 4), so the M/T time step is corrected by +-280 Tcy across this sequence
T2_SAMPLE = (3, 60, 10, 45, 0, 70, 20)
OVERHEAD_READS = 8           # the harness's timer-read cost: the least of these reads
INPUT_BASE = 0x040           # access RAM the inputs move to (0x040-0x05F)
RESULT_ADDR = 0xB00          # uint16 results, up to 0xEFF
MAX_RESULTS = 512
HALL_INVALID = (7, 0, 1)    # both invalid codes, then back to a valid one
TX_BYTES_PER_MS = 11         # 115200 baud, 10 bits a byte
FRAME_GAP_MS = 10         # ms of UART time before each frame of the corpus: a maximum-length telemetry
                          # frame and a maximum-length reply (2 x 47 B at 11 B/ms) have left the board


class GpsimError(PicdriveError):
    """gpsim could not measure the firmware (the message says why)."""


@functools.lru_cache(maxsize=1)
def unimplemented_sfrs() -> frozenset:
    """SFR addresses (0xF80..) gpsim's timing processor does not implement ('--' in its register dump)."""
    with tempfile.TemporaryDirectory() as t:
        (Path(t) / "d.stc").write_text("dump r\nquit\n")
        (Path(t) / "nop.hex").write_text(":020000000000FE\n:00000001FF\n")    # one NOP: gpsim needs a program
        r = subprocess.run([_gpsim(), "-i", "-S", "disable", "-p", TIMING_PROCESSOR, "-c", "d.stc", "nop.hex"], cwd=t,
                           capture_output=True, stdin=subprocess.DEVNULL, timeout=120)
    text = (r.stdout + r.stderr).decode("latin-1")
    out = set()
    for line in text.splitlines():
        m = re.match(r"^\s*(0f[89a-f]0):\s+((?:\S\S\s+){16})", line, re.I)
        if m:
            for i, tok in enumerate(m[2].split()):
                if tok == "--":
                    out.add(int(m[1], 16) + i)
    if not out:
        raise GpsimError("gpsim printed no register dump: is gpsim 0.31 installed (scripts/setup.sh)?")
    return frozenset(out)


def moved_registers() -> list[str]:
    """HARNESS_INPUTS, then the 18F4431 registers at 0xF80.. the timing processor does not implement.

    (gpsim stops on a write to an unimplemented register; those below 0xF80
    are access-bank GPRs on the timing processor, see the module docstring.)
    """
    from .p18f4431 import shim_registers
    missing = unimplemented_sfrs()
    extra = sorted((a, n) for n, a in shim_registers().items() if a in missing)
    names = list(HARNESS_INPUTS) + [n for _a, n in extra if n not in HARNESS_INPUTS]
    if len(names) > 0x60 - INPUT_BASE:
        raise GpsimError(f"{len(names)} registers to move into access RAM, room for {0x60 - INPUT_BASE}")
    return names


def timing_device() -> tuple[str, str]:
    """``xc.h`` / ``xc_sfr.c`` for the timing build: ``moved_registers()`` placed in access RAM."""
    from .p18f4431 import render_sdcc_device
    hdr, sfr = render_sdcc_device()
    from .p18f4431 import shim_registers
    regs = shim_registers()
    slots: dict[int, int] = {}
    for name in moved_registers():
        slot = slots.setdefault(regs[name], INPUT_BASE + len(slots))   # aliases share a slot
        if slot > 0x5F:
            raise GpsimError("too many registers to move into access RAM")
        new = f"__at(0x{slot:03X})"
        pat = re.compile(rf"__at\(0x[0-9A-F]+\)(\s+volatile\s+(?:uint8_t|__{name}bits_t)\s+{name}(?:bits)?;)")
        hdr, n1 = pat.subn(lambda m: new + m[1], hdr)
        sfr, n2 = pat.subn(lambda m: new + m[1], sfr)
        if n1 == 0:
            raise GpsimError(f"register {name} not in the rendered device header")
    return hdr, sfr


def timing_lkr() -> str:
    """A linker script for the timing build: 64 KB flash, access RAM below the inputs, no 0x60-0x7F."""
    return "\n".join([
        "LIBPATH .",
        "CODEPAGE   NAME=page       START=0x0               END=0xFFFF",
        "CODEPAGE   NAME=idlocs     START=0x200000          END=0x200007       PROTECTED",
        "CODEPAGE   NAME=config     START=0x300000          END=0x30000D       PROTECTED",
        "CODEPAGE   NAME=devid      START=0x3FFFFE          END=0x3FFFFF       PROTECTED",
        "CODEPAGE   NAME=eedata     START=0xF00000          END=0xF000FF       PROTECTED",
        f"ACCESSBANK NAME=accessram  START=0x0               END=0x{INPUT_BASE - 1:X}",
        f"DATABANK   NAME=inputs     START=0x{INPUT_BASE:X}  END=0x5F           PROTECTED",
        "DATABANK   NAME=shadow     START=0x60              END=0x7F           PROTECTED",
        "ACCESSBANK NAME=accesssfr  START=0xF60             END=0xFFF          PROTECTED",
        "DATABANK   NAME=gpr0       START=0x80              END=0xFF",
        *[f"DATABANK   NAME=gpr{b}       START=0x{b:X}00           END=0x{b:X}FF" for b in range(1, 0xB)],
        "DATABANK   NAME=results    START=0xB00             END=0xEFF          PROTECTED",
        ""])


@dataclass
class Cycles:
    """Worst-case cycles (interrupt entry included) and every sample, by what was measured."""

    worst: dict          # key -> cycles
    samples: dict        # key -> how many calls were measured

    def fraction(self, key: str, period_cycles: int) -> float:
        return self.worst[key] / period_cycles


def _frames(package: str = "picdrive.link") -> dict[str, list[bytes]]:
    """The link frames the corpus sends, encoded by ``<package>.codec`` (so they follow the protocol).

    ``package``: picdrive itself, or the picdrive of another revision imported
    under its own name (bench/target.py's baseline speaks that revision's framing)."""
    import importlib
    codec = importlib.import_module(f"{package}.codec")
    P = importlib.import_module(f"{package}.protocol")
    names = [s.name for s in P.SIGNALS]
    mask = sum(1 << names.index(s) for s in P.DEFAULT_TELEMETRY_SIGNALS)   # the four default signals
    big = 2 ** 31 - 1
    return {
        "set_speed_max": [codec.encode_command("set_speed", 1, {"value": 32767})],
        "set_speed_min": [codec.encode_command("set_speed", 2, {"value": -32768})],
        "set_speed_big": [codec.encode_command("set_speed", 3, {"value": big})],
        "start": [codec.encode_command("start", 4)],
        "stop": [codec.encode_command("stop", 9)],
        "fault_clear": [codec.encode_command("fault_clear", 11)],
        "telem_off": [codec.encode_command("telem_config", 10, {"mask": 0, "decimation": 0, "samples_per_frame": 0})],
        "telem4": [codec.encode_command("telem_config", 5, {"mask": mask, "decimation": 1,
                                                            "samples_per_frame": P.DEFAULT_SAMPLES_PER_FRAME})],
        "capture": [codec.encode_command("capture_arm", 6, {"mask": mask, "n_samples": 16,
                                                            "pre_trigger": 4, "decimation": 1, "trigger": 1,
                                                            "threshold": 0})],
        "max_reply": [codec.encode_command("param_get", 7, {"ids": list(range(P.PARAM_GET_MAX))})],
        # a frame of MAX_PAYLOAD bytes (no command takes that many: parsed, CRC-checked, NACKed)
        "max_frame": [codec.encode_frame(0x7F, 8, bytes((37 * i + 11) & 0xFF for i in range(P.MAX_PAYLOAD)))],
    }


OP_END, OP_RX, OP_POLL, OP_TX, OP_ADC, OP_SPEED, OP_HALL, OP_NOP, OP_PORT = range(9)


def harness_c(cases: list[tuple[str, list]], hall_codes: list[int], hall_shift: int,
              tx_vector: str = "isr_high", hall_port: str = "PORTC") -> tuple[str, list[str], dict]:
    """The timing harness: a step table and the main() that runs it.

    Returns (C text, result slot keys in order, {key: calls measured}).  The
    steps are data (a const table walked by a small loop): SDCC takes minutes
    on one long straight-line function.  Each measured step is
    ``TMR1 = 0; CALL handler; read TMR1`` and the chip keeps each key's worst.
    A hall edge puts the code on ``hall_port`` (bit ``hall_shift`` up: the firmware's
    FW_HALL_PORT / FW_HALL_SHIFT) and raises the flag of each line that changed.
    """
    if hall_port not in ("PORTA", "PORTC"):
        raise GpsimError(f"hall port {hall_port!r}: the halls are on PORTC (INT0..INT2) or PORTA (IC1..IC3)")
    keys: list[str] = []
    counts: dict[str, int] = {}
    steps: list[int] = []

    mode = [""]

    def key(k):
        if k != "overhead":
            k = mode[0] + k
        if k not in keys:
            keys.append(k)
        if len(keys) > MAX_RESULTS:
            raise GpsimError("timing corpus has too many keys")
        counts[k] = counts.get(k, 0) + 1
        return keys.index(k)

    def drain(n):
        # the UART sends a byte every ~870 cycles at 115200 baud: n transmit interrupts
        steps.extend([OP_TX, n, key("uart_tx_byte")])
        counts[mode[0] + "uart_tx_byte"] += n - 1

    # the timer read's own cost, the least of several reads (a guard: before Timer1 was stopped around
    # its writes the first read after fw_init came out 256 high, which lowered every figure by 256)
    for _ in range(OVERHEAD_READS):
        steps.extend([OP_NOP, 0, key("overhead")])
    for what, arg in cases:
        if what == "mode":
            mode[0] = arg + "|"
        elif what == "frame":
            name, data = arg
            # a host sends a command only after the reply to the previous one (docs/protocol.md), and
            # the board buffers one frame: let the UART send what is queued (telemetry, the last
            # reply) first, so that the frame's own poll dispatches it
            for _ in range(FRAME_GAP_MS):
                drain(TX_BYTES_PER_MS)
                steps.extend([OP_POLL, 0, key("link_poll")])
            for b in data:
                steps.extend([OP_RX, b, key("uart_rx_byte")])
            drain(TX_BYTES_PER_MS * 4)
            steps.extend([OP_POLL, 0, key("link_poll_frame:" + name), OP_POLL, 0, key("link_poll")])
        elif what == "speed":
            label, adc, n, step = arg
            steps.extend([OP_ADC, adc >> 8, adc & 0xFF])
            for _ in range(n):
                steps.extend([OP_SPEED, step & 0xFF, key("speed_loop_isr:" + label), OP_POLL, 0, key("link_poll")])
                drain(TX_BYTES_PER_MS)
        elif what in ("hall", "hall_invalid"):
            codes = hall_codes if what == "hall" else HALL_INVALID
            prev = hall_codes[-1]
            for c in codes:
                # one edge: the flag of each hall line that changed (INTn, or ICn in the IC wiring)
                steps.extend([OP_PORT, (c << hall_shift) & 0xFF, 0, OP_HALL, (c ^ prev) & 7, key("hall_isr")])
                prev = c
    steps.extend([OP_END, 0, 0])
    if len(keys) > 255:
        raise GpsimError("timing corpus has too many keys")
    table = ",\n".join("    " + ", ".join(f"{v}" for v in steps[i:i + 24]) for i in range(0, len(steps), 24))
    regs = ("TMR1L", "TMR1H", "T1CON", "PIR1", "PIR3", "TXSTA", "RCREG", "INTCON", "INTCON3", hall_port, "TMR2",
            "ADRESH", "ADRESL", "TMR5L", "TMR5H", "POSCNTL", "POSCNTH")
    text = f"""/* timing harness (picdrive.gpsim): GENERATED, measurement build only */
#include <stdint.h>
#include "drive.h"
/* the registers by symbol (xc_sfr.c places them): no xc.h, whose __at declarations SDCC
 * re-emits as absolute sections in a module with main() */
{chr(10).join(f"extern volatile uint8_t {r};" for r in regs)}
__at(0x{RESULT_ADDR:03X}) volatile uint16_t res[{MAX_RESULTS}];
static const uint8_t steps[] = {{
{table}
}};
static volatile uint8_t lo, hi;
/* Timer1 is stopped around every write and read: gpsim's Timer1, written while running, could still
 * carry the previous count's pending low-byte overflow into TMR1H, putting some figures exactly 256
 * cycles high depending on the code's timing (the stopped reads agree with bench/isr_profile.py's
 * instruction-by-instruction count to the cycle) */
#define T1_RESTART   T1CON = 0x80u; TMR1H = 0; TMR1L = 0; T1CON = 0x81u;
#define T1_STOP_READ T1CON = 0x80u; lo = TMR1L; hi = TMR1H;
static uint16_t t, i;
static const uint8_t t2_sample[] = {{{", ".join(str(v) for v in T2_SAMPLE)}}};
static uint8_t op, a, k, n, adc_h, adc_l, gie, t2i;
static uint16_t pos;

void harness_done(void) {{ for (;;) {{ }} }}

static void keep(void)
{{
    t = ((uint16_t)hi << 8) | lo;
    if (t > res[k]) res[k] = t;
}}

void main(void)
{{
    __asm
    extern _isr_high
    extern _isr_low
    __endasm;
    T1CON = 0x81;   /* RD16, internal Fosc/4, 1:1, on */
    TXSTA |= 0x02u; PIR1 |= 0x10u;
    fw_init();
    T1CON = 0x81;   /* again: fw_init may have configured Timer1 */
    res[0] = 0xFFFFu;   /* the overhead slot keeps the least */
    for (i = 0u; ; i += 3u) {{
        op = steps[i]; a = steps[i + 1u]; k = steps[i + 2u];
        if (op == {OP_END}u) break;
        if (op == {OP_NOP}u) {{
            gie = INTCON; INTCON = (uint8_t)(gie & 0x3Fu);   /* no interrupt inside the overhead */
            T1_RESTART
            T1_STOP_READ
            INTCON = gie;
            t = ((uint16_t)hi << 8) | lo;
            if (t < res[k]) res[k] = t;                     /* the least: see harness_c */
        }} else if (op == {OP_RX}u) {{
            RCREG = a; PIR1 |= 0x20u;
            T1_RESTART
            __asm
            CALL _isr_high
            __endasm;
            T1_STOP_READ keep();
            PIR1 &= (uint8_t)~0x20u;
        }} else if (op == {OP_POLL}u) {{
            PIR1 |= 0x10u; TXSTA |= 0x02u;
            T1_RESTART
            fw_poll();
            T1_STOP_READ keep();
        }} else if (op == {OP_TX}u) {{
            for (n = a; n != 0u; n--) {{
                PIR1 = (uint8_t)((PIR1 | 0x10u) & ~0x02u); TXSTA |= 0x02u;
                T1_RESTART
                __asm
                CALL _{tx_vector}             ; the transmit interrupt's priority (firmware_limits)
                __endasm;
                T1_STOP_READ keep();
            }}
        }} else if (op == {OP_ADC}u) {{
            adc_h = a; adc_l = k;
        }} else if (op == {OP_SPEED}u) {{
            ADRESH = adc_h; ADRESL = adc_l;      /* the bus current the special event converted */
            pos = (uint16_t)(pos + (uint16_t)(int16_t)(int8_t)a);    /* encoder counts in this sample */
            POSCNTL = (uint8_t)pos; POSCNTH = (uint8_t)(pos >> 8);
            TMR2 = t2_sample[t2i];
            t2i = (uint8_t)(t2i + 1u == {len(T2_SAMPLE)}u ? 0u : t2i + 1u);
            PIR1 |= 0x12u; TXSTA |= 0x02u;
            T1_RESTART
            __asm
            global  _harness_speed_call     ; bench/isr_profile.py breaks here (a label: no code)
_harness_speed_call:
            CALL _isr_low
            __endasm;
            T1_STOP_READ keep();
        }} else if (op == {OP_PORT}u) {{
            {hall_port} = a;
        }} else if (op == {OP_HALL}u) {{
            if ((a & 1u) != 0u) INTCON |= 0x02u;
            INTCON3 |= (uint8_t)((a >> 1) & 3u);
            PIR3 |= (uint8_t)((a & 7u) << 1);
            TMR5L = (uint8_t)(TMR5L + 0x37u); TMR5H = (uint8_t)(TMR5H + 0x13u);
            T1_RESTART
            __asm
            CALL _isr_high
            __endasm;
            T1_STOP_READ keep();
        }}
    }}
    harness_done();
}}
"""
    return text, keys, counts


TELEMETRY_MODES = ("off", "4", "4+capture")


def default_corpus(modes=TELEMETRY_MODES, *, protocol_package: str = "picdrive.link",
                   adc_trip: int = 0x3FF) -> list[tuple[str, list]]:
    """The firmware states measured, once per telemetry mode.

    States: rest, a step into the current limit (full reference, the bus
    current just under the overcurrent trip ``adc_trip``, ADC counts),
    reversal, saturation (an out-of-range reference), int16 extremes, the
    largest reply and a MAX_PAYLOAD frame, then an overcurrent (ADC at full
    scale: the fault path) and invalid hall codes.  Every state before the
    overcurrent runs the law (no fault latched).  Each state moves the
    encoder by its own count per sample (the M/T quotient; 0 after motion:
    the one-count bound's division).  ``modes``: 'off', '4' (four signals
    streaming) and/or '4+capture' (and a capture armed).
    """
    f = _frames(protocol_package)
    high = max(0, min(adc_trip, 0x400) - 1)
    cases = []
    for m in modes:
        if m not in TELEMETRY_MODES:
            raise GpsimError(f"unknown telemetry mode {m!r} (one of {', '.join(TELEMETRY_MODES)})")
        cases += [("mode", m), ("frame", ("stop", f["stop"][0])), ("frame", ("fault_clear", f["fault_clear"][0])),
                  ("frame", ("telem_off" if m == "off" else "telem4", f["telem_off" if m == "off" else "telem4"][0]))]
        if m == "4+capture":
            cases.append(("frame", ("capture", f["capture"][0])))
        cases += [("speed", ("rest", 0x000, 4, 0)), ("hall", None),
                  ("frame", ("set_speed_max", f["set_speed_max"][0])), ("frame", ("start", f["start"][0])),
                  ("speed", ("step", high, 6, 20)), ("hall", None),
                  ("speed", ("current_limit", high, 4, 40)),
                  ("frame", ("set_speed_min", f["set_speed_min"][0])), ("speed", ("reversal", 0x000, 6, -25)),
                  ("speed", ("coast", 0x000, 3, 0)),
                  ("hall", None),
                  ("frame", ("set_speed_big", f["set_speed_big"][0])), ("speed", ("saturation", high, 4, 127)),
                  ("speed", ("int16_extremes", high // 2, 4, -128)),
                  ("frame", ("max_reply", f["max_reply"][0])), ("frame", ("max_frame", f["max_frame"][0])),
                  # the fault paths last: full-scale current latches an overcurrent, the invalid
                  # codes a hall fault (cleared at the next mode's start)
                  ("speed", ("overcurrent", 0x3FF, 2, 0)),
                  ("hall_invalid", None), ("speed", ("hall_fault", 0x000, 3, 0))]
    return cases


def firmware_limits(folder) -> dict[str, int]:
    """FW_ADC_TRIP, FW_BUS_UV and FW_BUS_OV (ADC counts) of a generated folder's drive_params.h,
    ``hall_port`` and ``hall_shift`` (FW_HALL_PORT, FW_HALL_SHIFT), ``speed_loop_tcy`` (the speed
    loop's period in instruction cycles, when the folder gives it),
    and ``tx_high``: 1 when IPR1's TXIP makes the UART transmit a high-priority interrupt
    (today's firmware; c0631cc's, which bench/target.py measures beside it, had it low)."""
    text = (Path(folder) / "drive_params.h").read_text()
    m = re.search(r"#define FW_IPR1 (0x[0-9A-Fa-f]+|\d+)u?\b", text)
    out = {"tx_high": int(bool(m and int(m[1], 0) & p18f4431.reg_value("IPR1", "TXIP")))}
    for name in ("FW_ADC_TRIP", "FW_BUS_UV", "FW_BUS_OV"):
        m = re.search(rf"#define {name} (\d+)u?\b", text)
        if not m:
            raise GpsimError(f"{folder}/drive_params.h has no {name}: regenerate it with 'picdrive firmware'")
        out[name] = int(m[1])
    # the speed loop's period in Tcy: FW_LOOP_DIV Timer2 interrupts of FW_TCY_PER_TICK_MS ms + _MOD Tcy
    ms, mod, div = (re.search(rf"#define {n} (\d+)u?\b", text) for n in
                    ("FW_TCY_PER_TICK_MS", "FW_TCY_PER_TICK_MOD", "FW_LOOP_DIV"))
    if ms and mod and div:
        out["speed_loop_tcy"] = (int(ms[1]) * (FCY_HZ // 1000) + int(mod[1])) * int(div[1])
    # the hall lines' port and first bit (older firmware without them: PORTC, bit 3)
    m = re.search(r"#define FW_HALL_PORT (PORT[AC])\b", text)
    out["hall_port"] = m[1] if m else "PORTC"
    m = re.search(r"#define FW_HALL_SHIFT (\d+)u?\b", text)
    out["hall_shift"] = int(m[1]) if m else 3
    return out


def _gpsim() -> str:
    g = shutil.which("gpsim")
    if not g:
        raise GpsimError("gpsim is not installed: run scripts/setup.sh (apt-get install gpsim)")
    return g


def _dump(text: str) -> dict[int, int]:
    """gpsim 'dump r' output -> {address: byte}."""
    mem = {}
    for line in text.splitlines():
        m = re.match(r"^\s*([0-9a-fA-F]{4}):\s+((?:[0-9a-fA-F-]{2}\s+){16})", line)
        if m:
            base = int(m[1], 16)
            for i, tok in enumerate(m[2].split()):
                if tok != "--":
                    mem[base + i] = int(tok, 16)
    return mem


def measure(folder, out_dir, telemetry: str = "4+capture", **kw) -> Cycles:
    """Worst-case cycles of a firmware folder with one telemetry mode (see ``measure_modes``)."""
    return measure_modes(folder, out_dir, (telemetry,), **kw)[telemetry]


def build_timing(folder, out_dir, modes=TELEMETRY_MODES, *, max_cycles: int = 20_000_000,
                 protocol_package: str = "picdrive.link", pre_run: tuple = ()):
    """The timing build of a firmware folder and its gpsim script (``measure_modes`` runs it).

    Returns (Build, result keys, {key: calls}, script path).  ``pre_run``: more
    gpsim commands before ``run`` (bench/isr_profile.py logs the trace)."""
    from .target import build_hex
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    lim = firmware_limits(folder)
    cases = default_corpus(modes, protocol_package=protocol_package, adc_trip=lim["FW_ADC_TRIP"])
    bus_v = 5.0 * (lim["FW_BUS_UV"] + lim["FW_BUS_OV"]) / 2 / 1023
    hall_codes = [1, 3, 2, 6, 4, 5, 1, 5, 4, 6, 2, 3, 1]    # forward, then reverse; HALL_INVALID apart
    harness, keys, counts = harness_c(cases, hall_codes, lim["hall_shift"], hall_port=lim["hall_port"],
                                      tx_vector="isr_high" if lim["tx_high"] else "isr_low")
    hdr, sfr = timing_device()
    (out / "timing.lkr").write_text(timing_lkr())
    b = build_hex(folder, out, name="timing", linker_script=out / "timing.lkr",
                  sources=("drive.c", "drive_core.c", "link_fw.c"),
                  extra_c={"main_sdcc.c": _main_without_main(Path(folder) / "main_sdcc.c"), "harness.c": harness},
                  device=(hdr, sfr))
    script = out / "timing.stc"
    script.write_text("\n".join([
        # the bus voltage on AN1 (RA1): a pull-up module at the middle of the UV/OV window
        "module library libgpsim_modules", "module load pullup vbus", f"vbus.voltage = {bus_v:.4f}",
        "vbus.resistance = 100", "node nbus", "attach nbus porta1 vbus.pin",
        f"break e 0x{b.functions['_harness_done'].address:x}",
                                 f"break c {max_cycles}", *pre_run, "run", "dump r", "quit", ""]))
    return b, keys, counts, script


def measure_modes(folder, out_dir, modes=TELEMETRY_MODES, *,
                  max_cycles: int = 20_000_000, protocol_package: str = "picdrive.link") -> dict[str, Cycles]:
    """Build the timing harness around a firmware folder and run it in gpsim (one run for all modes).

    Returns {mode: Cycles}; keys of ``Cycles.worst``: ``speed_loop_isr`` (and
    ``speed_loop_isr:<state>``), ``hall_isr``, ``uart_rx_byte``, ``uart_tx_byte``,
    ``link_poll`` (idle pass), ``link_poll_max_frame`` and ``link_poll_frame:<frame>``.
    Interrupt figures include ``ENTRY_CYCLES``.  ``protocol_package``: whose
    codec frames the link commands (the firmware's own protocol revision).
    """
    b, keys, counts, script = build_timing(folder, out_dir, modes,
                                           max_cycles=max_cycles, protocol_package=protocol_package)
    out = Path(out_dir)
    r = subprocess.run([_gpsim(), "-i", "-S", "disable", "-p", TIMING_PROCESSOR, "-c", str(script),
                        str(b.hex_path.resolve())], capture_output=True, stdin=subprocess.DEVNULL, timeout=900)
    text = r.stdout.decode("latin-1") + r.stderr.decode("latin-1")
    (out / "timing.out").write_text(text)
    mem = _dump(text)
    vals = []
    for i in range(len(keys)):
        a = RESULT_ADDR + 2 * i
        if a not in mem or a + 1 not in mem:
            raise GpsimError(f"gpsim's register dump has no result at 0x{a:03X} (see {out / 'timing.out'})")
        vals.append(mem[a] | (mem[a + 1] << 8))
    if all(v == 0 for v in vals):
        raise GpsimError(f"the timing harness did not run to its end in gpsim (see {out / 'timing.out'})")
    over = vals[0]
    result: dict[str, Cycles] = {}
    for pk, v in zip(keys[1:], vals[1:]):
        if v == 0:
            raise GpsimError(f"the timing harness stopped before measuring {pk} (see {out / 'timing.out'})")
        m, k = pk.split("|", 1)
        cy = result.setdefault(m, Cycles({}, {}))
        c = v - over + (ENTRY_CYCLES if k.startswith(("speed_loop_isr", "uart_", "hall")) else 0)
        cy.worst[k] = c
        cy.samples[k] = counts[pk]
        for group, members in (("speed_loop_isr", ("speed_loop_isr:",)),
                               ("link_poll_max_frame", ("link_poll_frame:max_frame", "link_poll_frame:max_reply"))):
            if k.startswith(members):
                cy.worst[group] = max(cy.worst.get(group, 0), c)
    return result


def _main_without_main(path: Path) -> str:
    """main_sdcc.c with its main() renamed: the harness's main runs instead (vectors kept)."""
    return "#define main picdrive_firmware_main\n" + path.read_text()
