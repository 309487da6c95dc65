"""The processor-in-the-loop twin's Python side: the HEX, the configuration words the
peripheral model depends on, the C library, and what only a processor can report.

``Twin(profile, hex_file="firmware.hex")`` (twin.py) runs the HEX on the PIC18 core
(csrc/pic18cpu.c) inside the same peripheral model and plant as the SIL twin
(csrc/pil.c has the event loop); this module is what that needs besides.

Program memory: the 18F4431's 16 KB of flash and 768 B of GPRs; a HEX that does not fit
is refused (ihex.HexError).  ``enlarged=True`` builds the core with 128 KB of flash and
1.5 KB of GPRs -- the memories of picdrive.firmware.target.enlarged_lkr, the linker script the
project measures a firmware with when it does not fit -- and every report then says so.
"""
from __future__ import annotations

import ctypes as C
from dataclasses import dataclass
from pathlib import Path

from picdrive.firmware import ihex

from . import build
from .build import TwinError


class PilError(TwinError):
    """The HEX cannot run on the processor twin as configured."""


class PilStats(C.Structure):
    """ctypes mirror of ``pil_stats_t`` (csrc/twin.h)."""

    _fields_ = [(n, C.c_uint64) for n in (
        "cycles", "insns", "cpu_status", "fault_pc", "fault_word", "insn_pc", "pc", "stkptr", "stack_high",
        "fsr1_lo", "fsr1_hi", "ram_written",
        "speed_n", "speed_min", "speed_max", "speed_sum", "speed_last", "speed_overrun", "speed_lost",
        "high_n", "high_min", "high_max", "high_sum", "low_n", "low_min", "low_max", "low_sum",
        "retfie_outside", "in_isr", "resets", "sleep_runs", "adc_starts", "rcreg_reads",
        "speed_preempted", "overrun_first_cycle", "pos_reads", "pos_delay_min", "pos_delay_max",
        "pos_read_unmasked", "pos_read_after_adc", "adc_pwm_starts", "adc_in_on_time",
        "adc_phase_min_ppm", "adc_phase_max_ppm", "missed_at_start",
        "lat_n", "lat_min", "lat_max", "lat_sum", "steps", "stops",
        "wdt_period_cycles", "wdt_resets", "wdt_reset_cycle", "wdt_wakes", "speed_entry_last", "speed_gap_max")]


def bind(lib: C.CDLL) -> C.CDLL:
    lib.pil_load.argtypes = [C.c_char_p, C.c_uint32, C.c_char_p]
    lib.pil_load.restype = C.c_int
    lib.pil_flash_bytes.argtypes = []
    lib.pil_flash_bytes.restype = C.c_uint32
    lib.pil_ram_end.argtypes = []
    lib.pil_ram_end.restype = C.c_uint32
    lib.pil_get_stats.argtypes = [C.POINTER(PilStats)]
    lib.pil_get_stats.restype = None
    lib.pil_peek.argtypes = [C.c_uint16]
    lib.pil_peek.restype = C.c_uint8
    lib.pil_patch_flash.argtypes = [C.c_uint32, C.c_char_p, C.c_uint32]
    lib.pil_patch_flash.restype = C.c_int
    lib.pil_sizeof.argtypes = []
    lib.pil_sizeof.restype = C.c_int
    return lib


def library(gen_dir: Path, enlarged: bool = False) -> Path:
    return build.build_library([build.pil_group(gen_dir, enlarged=enlarged)],
                               name="libpil-enlarged" if enlarged else "libpil")


def load_image(path, enlarged: bool = False) -> ihex.HexImage:
    """The HEX, validated for the 18F4431 (or the enlarged measurement memory).

    The parsed image of a file's content is kept (a copy is returned): a tolerance study starts
    one processor twin per drive on the same HEX, and parsing it took a quarter of each drive's
    run (74 of 274 ms)."""
    import copy
    import hashlib
    raw = None
    if Path(path).is_file():                          # a regular file (anything else: load_hex decides)
        try:
            raw = Path(path).read_bytes()
        except OSError:
            pass                                      # load_hex names the problem
    if raw is None:
        return ihex.load_hex(path, flash_bytes=build.ENLARGED_FLASH_BYTES if enlarged else ihex.FLASH_BYTES)
    key = (hashlib.sha256(raw).hexdigest(), str(path), bool(enlarged))
    img = _IMAGES.get(key)
    if img is None:
        img = ihex.load_hex(path, flash_bytes=build.ENLARGED_FLASH_BYTES if enlarged else ihex.FLASH_BYTES)
        if len(_IMAGES) >= 8:
            _IMAGES.clear()
        _IMAGES[key] = img
    return copy.deepcopy(img)


#: parsed HEX images by (content digest, path, enlarged): see load_image
_IMAGES: dict = {}


# configuration bits (DS39616 section 23; names as in gputils' p18f4431.inc)
_FOSC_NAMES = {0x0: "LP", 0x1: "XT", 0x2: "HS", 0x3: "RC2", 0x4: "EC", 0x5: "ECIO", 0x6: "HSPLL",
               0x7: "RCIO", 0x8: "IRCIO", 0x9: "IRC", 0xC: "RC", 0xD: "RC1"}
_FOSC_MAX_HZ = {"LP": 200e3, "XT": 4e6, "HS": 25e6, "HSPLL": 40e6, "EC": 40e6, "ECIO": 40e6, "RC": 4e6,
                "RC1": 4e6, "RC2": 4e6, "RCIO": 4e6, "IRCIO": 8e6, "IRC": 8e6}


def check_config(img: ihex.HexImage, board, name: str) -> list[str]:
    """Refuse configuration words the peripheral model does not follow (PilError, naming the
    word, its value and the fix); returns notes on the ones it honours."""
    cfg = img.config
    fosc = cfg[1] & 0x0F
    mode = _FOSC_NAMES.get(fosc, f"0x{fosc:X}")
    limit = _FOSC_MAX_HZ.get(mode)
    if limit is None or board.fosc_hz > limit:
        raise PilError(f"{name}: CONFIG1H (0x300001) = 0x{cfg[1]:02X} selects oscillator {mode}, which cannot run "
                       f"the board's Fosc {board.fosc_hz / 1e6:g} MHz (board.json fosc_hz); build with "
                       "OSC=HSPLL (10 MHz crystal x 4) or fix board.json")
    wdt = (f"watchdog on (CONFIG2H WDTEN), {4 << ((cfg[3] >> 1) & 0x0F)} ms (4 ms x 1:{1 << ((cfg[3] >> 1) & 0x0F)}): "
           "a time-out resets the chip, outputs off" if cfg[3] & 0x01 else
           "watchdog off (CONFIG2H WDTEN; WDTCON.SWDTEN may turn it on)")
    if not cfg[4] & 0x04:
        raise PilError(f"{name}: CONFIG3L (0x300004) = 0x{cfg[4]:02X} sets PWMPIN=ON (PWM outputs active at reset); "
                       "the twin models PWMPIN=OFF only: build with PWMPIN=OFF")
    if (cfg[4] & 0x18) != 0x18:
        raise PilError(f"{name}: CONFIG3L (0x300004) = 0x{cfg[4]:02X} makes PWM outputs active-low (LPOL/HPOL=LOW); "
                       "the twin's inverter is driven active-high: build with LPOL=HIGH, HPOL=HIGH")
    flta_rc1 = bool(cfg[5] & 0x01)
    if board.flta_pin is not None and tuple(board.flta_pin) != (("C", 1) if flta_rc1 else ("D", 4)):
        raise PilError(f"{name}: CONFIG3H (0x300005) = 0x{cfg[5]:02X} puts FLTA on {'RC1' if flta_rc1 else 'RD4'} "
                       f"but the board wires the comparator to R{board.flta_pin[0]}{board.flta_pin[1]}: "
                       "build with FLTAMX matching board.json's flta_pin")
    return [f"oscillator {mode}", wdt, f"STVREN {'on' if img.stvren else 'off'} (stack overflow/underflow "
            f"{'resets' if img.stvren else 'does not reset'} the core; the twin stops either way)"]


def mnemonic(flash: bytes, addr: int) -> str:
    """The instruction at ``addr`` in words a reader recognises: control flow by name, anything
    else by its opcode word(s) (no full disassembler: gpdasm does that).  Decoded by
    picdrive.firmware.target.decode_insn, the build's own decoder."""
    from picdrive.firmware.target import decode_insn
    if not 0 <= addr < len(flash) - 1:
        return f"(no instruction: 0x{addr:06X} is outside the flash)"
    kind, op, size, w, w2 = decode_insn(flash, addr)
    two = f"0x{w:04X} 0x{w2:04X}" if addr + 3 < len(flash) else f"0x{w:04X}"
    if kind == "goto":
        return f"GOTO 0x{op:06X} ({two})"
    if kind == "call":
        return f"CALL 0x{op:06X}{', FAST' if w & 0x100 else ''} ({two})"
    if kind in ("rcall", "bra"):
        return f"{kind.upper()} 0x{op:06X} (0x{w:04X})"
    if kind == "bcc":
        return f"{op[0]} 0x{op[1]:06X} (0x{w:04X})"
    if kind in ("return", "retfie"):
        return f"{kind.upper()}{' FAST' if op else ''} (0x{w:04X})"
    if kind in ("push", "pop", "reset", "sleep"):
        return f"{kind.upper()} (0x{w:04X})"
    if kind == "retlw":
        return f"RETLW 0x{op:02X} (0x{w:04X})"
    if kind == "movwf" and op == 0xFF9:
        return f"MOVWF PCL (0x{w:04X}, a computed jump)"
    return f"opcode 0x{w:04X}"


def cpu_stop_message(st: PilStats, img: ihex.HexImage, hex_name: str) -> str:
    """The core's stop in one line, naming the address and the instruction."""
    code, ipc, target = int(st.cpu_status), int(st.insn_pc), int(st.fault_pc)
    insn = mnemonic(bytes(img.flash), ipc)
    top = len(img.flash) - 1
    if code == 16:
        if ipc == target:
            what = f"execution ran off the end of the flash at 0x{target:06X} (0x0000-0x{top:04X})"
        else:
            what = (f"jump outside the flash: {insn} at 0x{ipc:06X} sent the PC to 0x{target:06X} "
                    f"(flash 0x0000-0x{top:04X})")
    elif code == 17:
        what = (f"illegal or unimplemented opcode 0x{int(st.fault_word):04X} at 0x{ipc:06X} (an extended-set "
                "or undefined instruction, or data executed as code)")
    elif code == 3:
        what = f"return-stack overflow (31st push) by {insn} at 0x{ipc:06X}"
    elif code == 4:
        what = f"return-stack underflow (pop of an empty stack) by {insn} at 0x{ipc:06X}"
    else:
        what = f"core stop {code} at 0x{ipc:06X} ({insn})"
    return (f"processor twin stopped running {hex_name}: {what}; PWM outputs off (peripherals reset). "
            "Fix the firmware (its .map names the function at that address) and power the twin on again")


@dataclass(frozen=True)
class Report:
    """What the processor twin measured (cycles at Fosc/4)."""

    cycles: int
    insns: int
    fosc_hz: float
    speed_n: int
    speed_min: int
    speed_mean: float
    speed_max: int
    speed_overrun: int
    speed_lost: int
    missed_at_start: int
    high_n: int
    high_max: int
    high_mean: float
    low_n: int
    low_max: int
    stack_levels: int
    soft_stack_bytes: int | None
    soft_stack_top: int | None
    ram_written: int
    flash_used: int
    flash_top: int
    enlarged: bool
    speed_loop_hz: float
    entry_min: int = 0           # Timer2 interrupt entry latency (cycles from TMR2IF to the vectoring)
    entry_mean: float = 0.0
    entry_max: int = 0
    wdt_period: int = 0          # the watchdog's period, cycles (0: off)
    wdt_resets: int = 0          # its time-outs that reset the chip
    wdt_reset_cycle: int = 0     # the last of them
    wdt_wakes: int = 0           # its time-outs in Sleep (a wake-up, no reset)
    speed_gap_max: int = 0       # longest time between two speed-loop interrupt entries, cycles
    speed_silent: int = 0        # cycles since the last speed-loop interrupt entry (0: none yet)

    @property
    def speed_stopped(self) -> bool:
        """The speed-loop interrupt stopped arriving: none for more than two of its periods."""
        return self.speed_n > 0 and self.speed_silent > 2 * self.speed_period_cycles

    @property
    def speed_period_cycles(self) -> float:
        return (1.0 / self.speed_loop_hz / self.tcy_s) if self.speed_loop_hz else 0.0

    @property
    def tcy_s(self) -> float:
        return 4.0 / self.fosc_hz

    def as_dict(self) -> dict:
        us = self.tcy_s * 1e6
        per = (1.0 / self.speed_loop_hz / self.tcy_s) if self.speed_loop_hz else 0.0
        return {
            "cycles": self.cycles, "instructions": self.insns,
            "speed_isr_periods": self.speed_n,
            "speed_isr_cycles": {"min": self.speed_min, "mean": round(self.speed_mean, 1), "max": self.speed_max},
            "speed_isr_us": {"min": round(self.speed_min * us, 2), "mean": round(self.speed_mean * us, 2),
                             "max": round(self.speed_max * us, 2)},
            "speed_isr_max_fraction": round(self.speed_max / per, 4) if per else None,
            "speed_isr_entry_latency_cycles": {"min": self.entry_min, "mean": round(self.entry_mean, 1),
                                               "max": self.entry_max},
            "speed_periods_missed": self.speed_overrun + self.speed_lost,
            "speed_periods_overrun": self.speed_overrun, "speed_periods_lost": self.speed_lost,
            "speed_periods_missed_at_start": self.missed_at_start,
            "high_isr": {"n": self.high_n, "mean_cycles": round(self.high_mean, 1), "max_cycles": self.high_max},
            "low_isr": {"n": self.low_n, "max_cycles": self.low_max},
            "return_stack_high_water": self.stack_levels,
            "software_stack_bytes": self.soft_stack_bytes,
            "ram_bytes_written": self.ram_written,
            "flash_bytes": self.flash_used, "flash_top": self.flash_top,
            "watchdog": {"period_ms": round(self.wdt_period * self.tcy_s * 1e3, 3) if self.wdt_period else None,
                         "resets": self.wdt_resets,
                         "last_reset_s": round(self.wdt_reset_cycle * self.tcy_s, 6) if self.wdt_resets else None,
                         "wakes_from_sleep": self.wdt_wakes},
            "speed_isr_longest_gap_ms": round(self.speed_gap_max * self.tcy_s * 1e3, 3),
            "speed_isr_stopped": self.speed_stopped,
            "speed_isr_silent_ms": round(self.speed_silent * self.tcy_s * 1e3, 3),
            "program_memory": "enlarged (128 KB flash, 1.5 KB RAM: does NOT fit the 18F4431)" if self.enlarged
                              else "PIC18F4431 (16 KB flash, 768 B RAM)",
        }

    def lines(self) -> list[str]:
        us = self.tcy_s * 1e6
        d = self.as_dict()
        out = [f"processor: {self.insns:,} instructions, {self.cycles:,} cycles"
               + ("  [ENLARGED program memory: this HEX does not fit the 18F4431]" if self.enlarged else "")]
        if self.speed_n:
            out.append(f"speed-loop interrupt: {self.speed_n} periods, {self.speed_min} / {self.speed_mean:.0f} / "
                       f"{self.speed_max} cycles min/mean/max ({self.speed_min * us:.1f} / {self.speed_mean * us:.1f} / "
                       f"{self.speed_max * us:.1f} us), {100 * (d['speed_isr_max_fraction'] or 0):.1f} % of its period "
                       f"at worst; periods missed {self.speed_overrun + self.speed_lost} "
                       f"(overran {self.speed_overrun}, lost {self.speed_lost}; {self.missed_at_start} of them "
                       "before the first speed-loop interrupt ended)")
            out.append(f"speed-loop interrupt entry: {self.entry_min} / {self.entry_mean:.0f} / {self.entry_max} cycles "
                       f"min/mean/max after Timer2 set its flag ({self.entry_min * us:.1f} / {self.entry_mean * us:.1f} / "
                       f"{self.entry_max * us:.1f} us): the speed sample's instant moves by that much")
            if self.speed_stopped:
                silent_ms = self.speed_silent * self.tcy_s * 1e3
                out.append(f"speed-loop interrupt: STOPPED ARRIVING: none for {silent_ms:.1f} ms "
                           f"(its period {self.speed_period_cycles * self.tcy_s * 1e3:g} ms)")
            elif self.speed_gap_max > 2 * self.speed_period_cycles:
                out.append(f"speed-loop interrupt: stopped arriving for {self.speed_gap_max * self.tcy_s * 1e3:.1f} ms "
                           "at worst (a reset, or the interrupts off), then came again")
        else:
            out.append("speed-loop interrupt: not run yet")
        if self.wdt_period:
            out.append(f"watchdog: period {self.wdt_period * self.tcy_s * 1e3:g} ms; "
                       + (f"{self.wdt_resets} time-out reset(s) of the chip (outputs off), the last at "
                          f"{self.wdt_reset_cycle * self.tcy_s:.4f} s" if self.wdt_resets else "no time-out")
                       + (f"; {self.wdt_wakes} wake-up(s) from Sleep" if self.wdt_wakes else ""))
        else:
            out.append("watchdog: off")
        if self.high_n:
            out.append(f"high-priority interrupts: {self.high_n}, mean {self.high_mean:.0f}, max {self.high_max} cycles")
        ss = f"{self.soft_stack_bytes} B below 0x{self.soft_stack_top:03X}" if self.soft_stack_bytes is not None else "unused"
        out.append(f"stack high-water: return stack {self.stack_levels} of 31 levels, software stack (FSR1) {ss}")
        out.append(f"memory: flash {self.flash_used:,} B programmed (top 0x{self.flash_top:05X}), "
                   f"RAM {self.ram_written} B written")
        return out


def report(st: PilStats, img: ihex.HexImage, fosc_hz: float, enlarged: bool, speed_loop_hz: float) -> Report:
    soft = None
    top = None
    if st.fsr1_lo != 0xFFFF and st.fsr1_hi:
        top = int(st.fsr1_hi)
        soft = max(0, int(st.fsr1_hi) - int(st.fsr1_lo) + 1)
    return Report(
        cycles=int(st.cycles), insns=int(st.insns), fosc_hz=fosc_hz,
        speed_n=int(st.speed_n), speed_min=int(st.speed_min),
        speed_mean=(st.speed_sum / st.speed_n) if st.speed_n else 0.0, speed_max=int(st.speed_max),
        speed_overrun=int(st.speed_overrun), speed_lost=int(st.speed_lost), missed_at_start=int(st.missed_at_start),
        high_n=int(st.high_n), high_max=int(st.high_max),
        high_mean=(st.high_sum / st.high_n) if st.high_n else 0.0,
        low_n=int(st.low_n), low_max=int(st.low_max),
        stack_levels=int(st.stack_high), soft_stack_bytes=soft, soft_stack_top=top,
        ram_written=int(st.ram_written), flash_used=img.flash_used, flash_top=img.flash_top,
        enlarged=enlarged, speed_loop_hz=speed_loop_hz,
        entry_min=int(st.lat_min), entry_mean=(st.lat_sum / st.lat_n) if st.lat_n else 0.0, entry_max=int(st.lat_max),
        wdt_period=int(st.wdt_period_cycles), wdt_resets=int(st.wdt_resets), wdt_reset_cycle=int(st.wdt_reset_cycle),
        wdt_wakes=int(st.wdt_wakes), speed_gap_max=int(st.speed_gap_max),
        speed_silent=int(st.cycles - st.speed_entry_last) if st.speed_n else 0)
