"""``picdrive firmware``: the PIC18F4431 firmware of a design, whole or not at all.

``picdrive firmware --profile P --design D -o firmware_build/<name>/``

1. loads the profile and the design (a failed design, one without a law and
   one made from another profile are refused: ``load_design(...,
   require_usable=True, profile=p)``);
2. plans the chip: PWM period, dead time, duty limit and commutation table
   (:mod:`picdrive.pcpwm`), pin map (:mod:`picdrive.pinmap`), Q formats,
   coefficients, speed measurement and timers (:mod:`picdrive.fixedpoint`);
3. renders the Jinja2 templates of ``firmware_templates/`` and the protocol's
   C module (:func:`picdrive.link.protocol_c.render_c`, with the parameter scales
   and limits of the fixed-point plan);
4. build-checks the result in a temporary folder (gcc ``-std=c99 -Wall
   -Wextra -Werror -Wconversion`` against the generated register shim, and
   avr-gcc with 16-bit ``int`` when installed), then renames it into place.

Anything that cannot be done raises a :class:`~picdrive.errors.PicdriveError`
naming the problem and the fix, and leaves no output folder behind.  Output
is deterministic: the same inputs give the same bytes; the build id is the
first 4 bytes of a SHA-256 over the inputs (profile hash, design content,
generator options, templates, ``p18f4431.inc``, picdrive version).

:func:`host_build` tells the motor twin which sources and include folders
make the host build of a generated folder.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

from .. import __version__
from ..board import FCY_HZ, FOSC_HZ
from ..errors import PicdriveError
from .target import EEPROM_GPTR_STUBS
from ..commutation import hall_positions as _ident_pos
from ..profile import ProfileError, bus_guard
from .pcpwm import ident_vector_registers

__all__ = ["CodegenError", "Firmware", "generate", "write_firmware", "build_check", "host_build",
           "HOST_SOURCES", "XC8_ONLY_SOURCES", "register", "uart_brg", "bus_sense"]

HOST_SOURCES = ("drive.c", "drive_core.c", "link_fw.c")
XC8_ONLY_SOURCES = ("main_xc8.c", "config_xc8.c")
SDCC_ONLY_SOURCES = ("main_sdcc.c",)
TEMPLATES = ("drive_params.h", "drive_core.h", "drive_core.c", "drive.h", "drive.c", "fw_port.h",
             "main_xc8.c", "config_xc8.c", "main_sdcc.c")
HOST_CFLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-Wconversion")
#: the overspeed trip, x control.speed_max_rpm (the profile has no field for it)
OVERSPEED_FACTOR = 1.2
WDT_BASE_MS = 4
"""The hardware watchdog's nominal period before its postscaler (DS39616 23.2)."""
WDT_MIN_MS = 32
WDT_SAMPLES = 4


def wdt_postscale(speed_loop_hz: float) -> int:
    """The hardware watchdog's postscale (CONFIG2H WDPS): the smallest power of two giving at least
    WDT_MIN_MS and WDT_SAMPLES speed-loop periods (it is cleared after a speed-loop sample).  32 ms
    at a 1 kHz speed loop (8 x 4 ms): long against the main loop's worst pass (a few ms: at most 8
    frames a link_poll call, each checked and answered in under 1 ms with the speed loop in
    between; an EEPROM save clears it between its writes), short against a safe stop: a hung
    program keeps the bridge as it left it for at most that long before the reset turns the
    outputs off.  A slower speed loop gets a longer period (512 ms at 10 Hz)."""
    need = max(WDT_MIN_MS, WDT_SAMPLES * 1000.0 / speed_loop_hz)
    ps = 1
    while WDT_BASE_MS * ps < need and ps < 32768:
        ps *= 2
    return ps
CAPTURE_BYTES = 128
"""Capture buffer of the link module, bytes (``--capture-bytes``): 64 samples of one signal, 16 of
four.  ``bench/link_pic18.py`` prints what the link module costs with and without capture and EEPROM."""
REGENERABLE = ("build",)    # the Makefile's output folder: picdrive may replace it with the firmware


class CodegenError(PicdriveError):
    """The firmware cannot be generated (the message says why and what to do)."""


@dataclass
class Firmware:
    """A rendered firmware: file name -> text, and what was chosen."""

    name: str
    files: dict[str, str]
    build_id: int
    summary: list[str] = field(default_factory=list)
    plan: object = None
    pwm: object = None
    pinmap: object = None
    table: object = None


# ---------------------------------------------------------------------------
# Small plans that live here (no module of their own)
# ---------------------------------------------------------------------------
def uart_brg(baud: int) -> tuple[int, float]:
    """SPBRGH:SPBRG for BRG16 = 1, BRGH = 1: baud = Fosc / (4 (n + 1)).  Returns (n, achieved baud)."""
    n = round(FOSC_HZ / (4 * baud)) - 1
    if not 0 <= n <= 0xFFFF:
        raise CodegenError(f"uart.baud = {baud}: outside what the EUSART reaches at 40 MHz")
    achieved = FOSC_HZ / (4 * (n + 1))
    if abs(achieved - baud) / baud > 0.02:
        raise CodegenError(f"uart.baud = {baud}: the EUSART gives {achieved:.0f} baud at 40 MHz "
                           f"({100 * (achieved - baud) / baud:+.1f} %, more than 2 %); choose another rate")
    return n, achieved


def bus_sense(profile) -> dict:
    """Bus-voltage sense on AN1 and the guard's levels (:func:`picdrive.profile.bus_guard`) as a
    dict: divider, ``counts_per_v``, levels in V (``uv_v``, ``taper_start_v``, ``taper_end_v``,
    ``ov_v`` the trip) and in ADC counts (``uv``, ``taper_start``, ``taper_end``, ``ov``).
    Raises :class:`CodegenError` when the profile leaves no sensible guard window."""
    try:
        g = bus_guard(profile.inverter)
    except ProfileError as e:
        raise CodegenError(f"{e}: the firmware could not protect the switches from regeneration") from None
    return {"bus_sense_v_per_v": g.bus_sense_v_per_v, "source": g.source, "counts_per_v": g.counts_per_v,
            "uv_v": g.uv_v, "ov_v": g.trip_v, "taper_start_v": g.taper_start_v, "taper_end_v": g.taper_end_v,
            "uv": g.uv, "ov": g.trip, "taper_start": g.taper_start, "taper_end": g.taper_end,
            "lines": g.lines()}


# ---------------------------------------------------------------------------
# Generation
# ---------------------------------------------------------------------------
def _d(name, value, comment=""):
    return {"name": name, "value": value, "comment": comment}


def _hex8(v: int) -> str:
    return f"0x{v:02X}u"


def _reg(reg: str, *flags: str, **fields: int) -> str:
    """A register byte from its bit names in p18f4431.inc (:func:`p18f4431.reg_value`), as C."""
    from .p18f4431 import reg_value
    return _hex8(reg_value(reg, *flags, **fields))


def _inputs_hash(profile, design_bytes: bytes, options: dict) -> tuple[int, str]:
    from . import p18f4431
    from ..paths import templates_dir
    h = hashlib.sha256()
    h.update(b"picdrive.firmware/1\0")
    h.update(__version__.encode() + b"\0")
    h.update(profile.sha256.encode() + b"\0")
    h.update(hashlib.sha256(design_bytes).digest())
    h.update(json.dumps(options, sort_keys=True).encode())
    h.update(p18f4431.parse_inc().sha256.encode())
    for name in sorted(os.listdir(templates_dir())):
        if name.endswith(".j2"):
            h.update(name.encode() + b"\0" + (templates_dir() / name).read_bytes())
    digest = h.hexdigest()
    return int(digest[:8], 16), digest


def _config_bits(pm, speed_loop_hz: float) -> list[tuple[str, str, str]]:
    from . import p18f4431
    wdps = wdt_postscale(speed_loop_hz)
    cfg = [
        ("OSC", "HSPLL", "10 MHz crystal x 4 PLL: Fosc = 40 MHz"),
        ("FCMEN", "OFF", "no fail-safe clock monitor"),
        ("IESO", "OFF", "no two-speed start-up"),
        ("PWRTEN", "ON", "power-up timer"),
        ("BOREN", "ON", "brown-out reset"),
        ("BORV", "42", "at 4.2 V"),
        ("WDTEN", "ON", "watchdog timer: a hung program resets the chip (outputs off)"),
        ("WDPS", str(wdps), f"1:{wdps}: {WDT_BASE_MS * wdps} ms nominal ({WDT_BASE_MS} ms x {wdps})"),
        ("WINEN", "OFF", "no windowed watchdog (CLRWDT at any time)"),
        ("PWMPIN", "OFF", "PWM outputs off after reset until the firmware enables them"),
        ("LPOL", "HIGH", "PWM0/2/4 (low sides, IR2101 LIN) active high"),
        ("HPOL", "HIGH", "PWM1/3/5 (high sides, IR2101 HIN) active high"),
        ("T1OSCMX", "OFF", "Timer1 oscillator not used"),
        ("FLTAMX", pm.config["FLTAMX"], "FLTA (overcurrent comparator) pin"),
        ("SSPMX", pm.config["SSPMX"], "SSP (unused) off RC4/RC5/RC7"),
        ("PWM4MX", pm.config["PWM4MX"], "PWM4 (phase C low side) pin"),
        ("EXCLKMX", pm.config["EXCLKMX"], "T0CKI/T5CKI (unused) off RC3"),
        ("MCLRE", "ON", "MCLR reset pin"),
        ("STVREN", "ON", "reset on stack overflow"),
        ("LVP", pm.config["LVP"], "RB5 is PWM4, not PGM"),
        ("DEBUG", "OFF", "RB6/RB7 free of the debugger"),
    ]
    for n in ("CP0", "CP1", "CP2", "CP3", "CPB", "CPD"):
        cfg.append((n, "OFF", "no code protection"))
    known = p18f4431.config_settings()
    for k, v, _ in cfg:
        if k not in known or v not in known[k]:
            raise CodegenError(f"config setting {k} = {v} is not in p18f4431.inc")   # generator bug
    return cfg


def _sections(profile, design, plan, pwm, pm, brg, baud, bus, ident=False) -> list[dict]:
    inv, co = profile.inverter, profile.control
    t = pwm.table
    per, dt = pwm.period, pwm.dead
    S = []
    S.append({"title": "clock", "defines": [
        _d("FW_FOSC_HZ", f"{FOSC_HZ}UL", "10 MHz crystal, HSPLL (x4)"),
        _d("FW_FCY_HZ", f"{FCY_HZ}UL", "instruction clock Fosc / 4"),
        _d("FW_TCY_PER_MS", f"{FCY_HZ // 1000}u", "Tcy per millisecond"),
    ]})
    ps_code = {1: 0, 4: 1, 16: 2, 64: 3}[per.prescale]
    S.append({"title": "PCPWM (pcpwm.plan_pwm)", "defines": [
        _d("FW_PTPER", f"{per.ptper}u", f"round(Fcy / ({per.prescale} x inverter.pwm_frequency_hz = "
           f"{inv.pwm_frequency_hz:g} Hz)) - 1 -> {per.frequency_hz:.2f} Hz, duty resolution "
           f"{per.duty_full_counts} counts"),
        _d("FW_PTCON0", _reg("PTCON0", PTCKPS=ps_code), f"free-running (edge-aligned), prescaler 1:{per.prescale}, postscaler 1:1"),
        _d("FW_PTCON1", _reg("PTCON1", "PTEN"), "PTEN: time base on, counting up"),
        _d("FW_PWMCON0", _reg("PWMCON0", PWMEN=0b100, PMOD=0b0111), "PWMEN = 100 (PWM0-5), PMOD = 0111 (pairs 0-2 independent)"),
        _d("FW_PWMCON1", _reg("PWMCON1", "OSYNC"), "OSYNC: override changes at the PWM period boundary; UDIS = 0"),
        _d("FW_DTCON", _hex8(dt.dtcon), f"inverter.dead_time_ns = {dt.requested_ns:g} -> DTPS = {dt.dtps}, "
           f"DT = {dt.dt}: {dt.dead_time_ns:g} ns (acts in complementary mode only; see docs/firmware.md)"),
        _d("FW_FLTCONFIG", _reg("FLTCONFIG", "FLTAEN", "FLTCON"), "FLTAEN, FLTCON (all outputs), FLTAMOD = 0: off until FLTAS is cleared"),
        _d("FW_PDC_MAX", f"{pwm.pdc_max}u", f"duty limit {pwm.max_duty:.4f} = 1 - (inverter.bootstrap_refresh_ns "
           f"{inv.bootstrap_refresh_ns:g} + 2 x {dt.dead_time_ns:g} ns) / {per.period_ns:.0f} ns "
           f"(Profile.max_duty() = {profile.max_duty():.4f}), in PDC counts of {per.duty_full_counts}"),
        _d("FW_OVDCONS_BRAKE", _reg("OVDCONS", "POUT0", "POUT2", "POUT4"), "brake: PWM0, PWM2, PWM4 (low sides) on"),
    ]})
    S.append({"title": f"commutation (sensors.hall_spacing_deg = {t.hall_spacing_deg}, hall_offset_deg = "
                       f"{t.hall_offset_deg:g}); index = hall code (C << 2 | B << 1 | A)", "defines": [
        _d("FW_HALL_VALID_MASK", _hex8(t.valid_mask), "bit n set: hall code n is valid; "
           + ", ".join(f"{c:03b} {t.describe(c)}" for c in range(8))),
        _d("FW_COMM_OVD", ", ".join(f"{_hex8(t.ovdcons[d][c])}, {_hex8(t.ovdcond[d][c])}" for d in (0, 1) for c in range(8)),
           "OVDCONS, OVDCOND at 2 k, 2 k + 1 for k = dir << 3 | code (dir 0 forward, 1 reverse torque): "
           "OVDCOND's duty-driven pin is the high side of the source phase, OVDCONS's forced-on pin "
           "the low side of the sink phase; one table pointer reads both"),
        _d("FW_HALL_NEXT", ", ".join(str(_next_code(t, c)) for c in range(8)),
           "next code in forward rotation (hall-speed direction)"),
    ] + ([
        _d("FW_IDENT_OVD", ", ".join(f"{_hex8(cs)}, {_hex8(cd)}" for cs, cd in ident_vector_registers()),
           "identification vectors m = 0..11 (commutation.IDENT_VECTORS, current at -30 + 30 m deg): "
           "OVDCONS, OVDCOND at 2 m, 2 m + 1"),
        _d("FW_IDENT_POS", ", ".join(f"{_ident_pos(t.hall_spacing_deg).get(c, 255)}u" for c in range(8)),
           "hall code -> place in the forward sequence at offset 0 (0xFF outside it): the hall-driven "
           "identification selections (commutation.ident_hall_vector)"),
    ] if ident else [])})
    hall_int = pm.hall_input == "int"
    tr = pm.tris()
    S.append({"title": "pins (pinmap.choose_pinmap)", "defines": [
        _d("FW_HALL_INT", "1" if hall_int else "0", "halls on INT0/INT1/INT2 = RC3/RC4/RC5"),
        _d("FW_HALL_IC", "0" if hall_int else "1", "halls on IC1/IC2/IC3 = RA2/RA3/RA4 (state-change capture)"),
        _d("FW_HALL_PORT", pm.hall_port, ""),
        _d("FW_HALL_SHIFT", f"{pm.hall_shift}u", "hall A is this bit of the port, B and C the next two"),
        _d("FW_TRISA", _hex8(tr["A"]), ""), _d("FW_TRISB", _hex8(tr["B"]), "RB0-RB5: PWM0-PWM5"),
        _d("FW_TRISC", _hex8(tr["C"]), ""), _d("FW_TRISD", _hex8(tr["D"]), ""), _d("FW_TRISE", _hex8(tr["E"]), ""),
        _d("FW_ANSEL0", _reg("ANSEL0", "ANS0", "ANS1"), "AN0 bus current, AN1 bus voltage; RA2-RA4 digital (QEI/IC)"),
        _d("FW_INTCON2", _reg("INTCON2", "NOT_RBPU"), "NOT_RBPU: no PORTB pull-ups; INTEDGx set at init"),
        _d("FW_INTCON3", _reg("INTCON3", *(("INT2IP", "INT1IP", "INT2IE", "INT1IE") if hall_int else ())), "INT2IP, INT1IP high priority; INT2IE, INT1IE"),
        _d("FW_INTCON", _reg("INTCON", *(("INT0IE",) if hall_int else ())), "INT0IE (INT0 is always high priority)"),
        _d("FW_CAPXCON_HALL", _reg("CAP1CON", CAP1M=0b1000), "CAPxM = 1000: capture on every state change, no Timer5 reset"),
    ]})
    enc = plan.speed_source == "encoder"
    pdec_code = {1: 0, 4: 1, 16: 2, 64: 3}[plan.pdec]
    ps5_code = {1: 0, 2: 1, 4: 2, 8: 3}[plan.ps5]
    S.append({"title": "speed measurement (fixedpoint.plan_fixed_point)", "defines": [
        _d("FW_SPEED_ENCODER", "1" if enc else "0", "sensors.speed_source = " + plan.speed_source),
        _d("FW_QEICON", _reg("QEICON", QEIM=0b110, PDEC=pdec_code), f"VELM = 0 (velocity mode), QEIM = 110 (x4, MAXCNT reset), "
           f"PDEC 1:{plan.pdec}: a velocity event at every count"),
        _d("FW_CAP1CON", _reg("CAP1CON", "CAP1REN"), "CAP1REN: Timer5 restarts at each velocity event (every count)"),
        _d("FW_T5CON", _reg("T5CON", "NOT_RESEN", "TMR5ON", T5PS=ps5_code), f"TMR5ON, Tcy, prescaler 1:{plan.ps5}, continuous, "
           "special-event reset off"),
        _d("FW_HALL_AGE_MAX", f"{max(2, min(255, math.floor(65536 * plan.ps5 / FCY_HZ * plan.loop_hz) - 1))}u",
           "hall speed: samples after the last edge before Timer5 may have wrapped (speed reads 0)"),
    ]})
    pre_code = {1: 0, 4: 1, 16: 2}[plan.t2_pre]
    S.append({"title": "speed-loop timing (Timer2)", "defines": [
        _d("FW_PR2", f"{plan.pr2}u", ""),
        _d("FW_T2CON", _reg("T2CON", "TMR2ON", T2OUTPS=plan.t2_post - 1, T2CKPS=pre_code),
           f"postscaler 1:{plan.t2_post}, TMR2ON, prescaler 1:{plan.t2_pre}"),
        _d("FW_LOOP_DIV", f"{plan.loop_div}u", f"speed loop every {plan.loop_div} Timer2 interrupt(s): "
           f"{plan.loop_hz:.3f} Hz (control.speed_loop_hz = {co.speed_loop_hz:g})"),
        _d("FW_TCY_PER_TICK_MS", f"{plan.tcy_per_tick // (FCY_HZ // 1000)}u", f"a Timer2 interrupt is {plan.tcy_per_tick} Tcy: "
           "whole ms"),
        _d("FW_TCY_PER_TICK_MOD", f"{plan.tcy_per_tick % (FCY_HZ // 1000)}u", "and the remainder, accumulated"),
    ]})
    S.append({"title": "ADC (bus current AN0, bus voltage AN1)", "defines": [
        _d("FW_ADCON2", _reg("ADCON2", "ADFM", ACQT=0b0010, ADCS=0b010), "ADFM right-justified, ACQT = 0010 (4 TAD), ADCS = 010 (Fosc/32, TAD 0.8 us): "
           "a conversion takes 4 + 12 TAD = 12.8 us"),
        _d("FW_ADC_POLLS", "200u", "GO_DONE polls before a conversion is given up (> 12.8 us at >= 4 cycles a poll)"),
        _d("FW_EE_POLLS", "60000u", "EECON1.WR polls before an EEPROM write is given up (> 4 ms)"),
        _d("FW_WDT_MS", f"{WDT_BASE_MS * wdt_postscale(profile.control.speed_loop_hz)}u",
           f"hardware watchdog period, ms nominal (CONFIG WDPS = {wdt_postscale(profile.control.speed_loop_hz)}: "
           f"{WDT_BASE_MS} ms x the postscale, >= {WDT_MIN_MS} ms and {WDT_SAMPLES} speed-loop periods); cleared "
           "by the main loop after each speed-loop sample"),
        _d("FW_ADCON0_CUR", _reg("ADCON0", "ADON"), "ADON, single shot, single channel, group A (AN0)"),
        _d("FW_ADCON0_BUS", _reg("ADCON0", "ADON", ACMOD=0b01), "ADON, single shot, single channel, group B (AN1)"),
        _d("FW_ADC_TRIP", f"{plan.itrip}u", f"inverter.overcurrent_trip_a = {inv.overcurrent_trip_a:g} A x "
           f"{plan.counts_per_a:.2f} counts/A (current_sense_v_per_a {inv.current_sense_v_per_a:g} V/A, 5 V / 1024)"
           + (" -- beyond the ADC range: never" if plan.itrip >= 1024 else "")),
        _d("FW_BUS_UV", f"{bus['uv']}u", f"undervoltage below {bus['uv_v']:.1f} V (70 % of bus_voltage_v) x "
           f"{bus['counts_per_v']:.2f} counts/V (divider {bus['bus_sense_v_per_v']:.5f} V/V, {bus['source']})"),
        _d("FW_BUS_OV", f"{bus['ov']}u", f"overvoltage trip above {bus['ov_v']:.1f} V"),
        _d("FW_BUS_DEBOUNCE", "10u", "consecutive samples"),
    ]})
    # overspeed trip: OVERSPEED_FACTOR x speed_max_rpm in the speed format (saturated to int16)
    w_trip = OVERSPEED_FACTOR * co.speed_max_rpm * math.pi / 30.0
    trip_raw = min(plan.to_speed_raw(w_trip), 32767)
    S.append({"title": "overspeed trip", "defines": [
        _d("FW_OVERSPEED", f"{trip_raw}", f"{OVERSPEED_FACTOR:g} x control.speed_max_rpm = "
           f"{OVERSPEED_FACTOR * co.speed_max_rpm:.0f} rpm = {w_trip:.2f} rad/s x 2^{plan.qs}"
           + (" (saturated: the speed format's limit)" if trip_raw == 32767 else "")
           + "; |speed| above it for FW_OVERSPEED_SAMPLES samples latches LINK_FAULT_OVERSPEED"),
        _d("FW_OVERSPEED_SAMPLES", "2u", "consecutive speed-loop samples"),
    ]})
    S.append({"title": "EUSART and interrupts", "defines": [
        _d("FW_SPBRG", f"{brg}u", f"uart.baud = {profile.uart.baud} -> Fosc / (4 (n + 1)) = {baud:.0f} baud "
           f"({100 * (baud - profile.uart.baud) / profile.uart.baud:+.2f} %)"),
        _d("FW_BAUDCON", _reg("BAUDCON", "BRG16"), "BRG16"),
        _d("FW_TXSTA", _reg("TXSTA", "TXEN", "BRGH"), "TXEN, BRGH, asynchronous"),
        _d("FW_RCSTA", _reg("RCSTA", "SPEN", "CREN"), "SPEN, CREN"),
        _d("FW_IPR1", _reg("IPR1", "RCIP", "TXIP"), "RCIP, TXIP high (a low-priority TX waits behind the "
           "speed loop: the UART idles); TMR2IP low"),
        _d("FW_IPR3", _reg("IPR3", *(() if hall_int else ("IC1IP", "IC2QEIP", "IC3DRIP"))), "IC1IP/IC2QEIP/IC3DRIP high (halls on IC)"),
        _d("FW_PIE1", _reg("PIE1", "RCIE", "TMR2IE"), "RCIE, TMR2IE (TXIE while the TX queue holds bytes)"),
        _d("FW_PIE3", _reg("PIE3", *(() if hall_int else ("IC1IE", "IC2QEIE", "IC3DRIE"))), "IC1IE/IC2QEIE/IC3DRIE (halls on IC)"),
    ]})
    # the core
    def shift_macro(name, s):
        return (f"CORE_ASR((x), {s})" if s >= 0 else f"CORE_SHL_SAT((x), {-s})")
    S.append({"title": "fixed-point formats (fixedpoint.plan_fixed_point)", "defines": [
        _d("CORE_N_RULES", f"{plan.n_rules}u", "rules of the design"),
        _d("CORE_QS", str(plan.qs), f"speed Q{plan.qs}: {2 ** -plan.qs:.6g} rad/s per LSB"),
        _d("CORE_QU", str(plan.qu), f"voltage Q{plan.qu}: {2 ** -plan.qu:.6g} V per LSB"),
        _d("CORE_QI", str(plan.qi), "integrator Q (voltage + 16 where +-I_lim fits 32 bits)"),
        _d("CORE_TO_QI(x)", (f"CORE_SHL_SAT((x), {plan.qi - plan.qu})" if plan.qi > plan.qu else "(x)"),
           "voltage Q -> integrator Q, saturated"),
        _d("CORE_I_LIM", f"INT32_C({plan.i_lim})", f"integrator range +-I_lim in Q{plan.qi}"),
        _d("CORE_Q_KP", str(plan.q_kp), "kp format"), _d("CORE_Q_KITS", str(plan.q_kits), "ki x Ts format"),
        _d("CORE_Q_KDTS", str(plan.q_kdts), "kd / Ts format"), _d("CORE_Q_KC", str(plan.q_kc), "kc format (V/count)"),
        _d("CORE_SHIFT_P(x)", shift_macro("P", plan.shift_p), f"Q_KP + QS - QU = {plan.shift_p}"),
        _d("CORE_SHIFT_I(x)", shift_macro("I", plan.shift_i), f"Q_KITS + QS - QI = {plan.shift_i}"),
        _d("CORE_SHIFT_D(x)", shift_macro("D", plan.shift_d), f"Q_KDTS + QS - QU = {plan.shift_d}"),
        _d("CORE_SHIFT_C(x)", shift_macro("C", plan.shift_c), f"Q_KC - QU = {plan.shift_c}"),
        _d("CORE_MU_SH", f"{plan.mu_sh}u", "membership slope shift"),
        _d("CORE_MU_NUM", f"UINT32_C({(max(plan.n_rules - 1, 0)) << (12 + plan.mu_sh)})", "(r - 1) << (12 + MU_SH)"),
        _d("CORE_MU_TOP", f"UINT32_C({max(plan.n_rules - 1, 0) << 12})", "(r - 1) << 12"),
        _d("CORE_DFILT_A", f"{plan.dfilt_a}u", "derivative filter Ts/(Ts + 1/(2 pi f)), Q15; 0 = none"
           + (f" (design derivative_filter_hz = {design.law.derivative_filter_hz:g})"
              if design.law.derivative_filter_hz else " (design derivative_filter_hz = null)")),
        _d("CORE_K_SPEED", f"UINT32_C({plan.k_speed})", (
            f"speed = K x counts / ticks: 2 pi Fcy / (T5 prescale {plan.ps5} x {plan.counts_per_rev} counts/rev) x 2^QS"
            if enc else f"speed = K / period: 2 pi / ({plan.counts_per_rev} hall edges/rev) x Fcy / T5 prescale x 2^QS")),
        _d("CORE_TS_TICKS", f"{plan.ts_ticks}", "speed-loop period in Timer5 ticks"),
        _d("CORE_T2_T5_SH", str(plan.t2_t5_shift), f"Timer5 ticks per Timer2 count = 2^SH: Timer2 1:{plan.t2_pre}, "
           f"Timer5 1:{plan.ps5} of Tcy (the speed sample's TMR2: its instant after the Timer2 match)"),
        _d("CORE_T2_T5(x)", (f"((int32_t)(x) * {1 << plan.t2_t5_shift})" if plan.t2_t5_shift >= 0 else
                             f"((int32_t)(uint16_t)((uint16_t)((x) + 256) >> {-plan.t2_t5_shift}) - {256 >> -plan.t2_t5_shift})"),
           "a TMR2 change (-255..255) in Timer5 ticks, floor (fixedpoint.t2_ticks)"),
        _d("CORE_MT_DMAX", f"UINT32_C({0xFFFFFFFF // plan.k_speed})", "largest count step whose product with K fits 32 bits"),
        _d("CORE_KDUTY", f"UINT32_C({plan.kduty})", f"PDC counts per u LSB x 2^DUTY_SH: {plan.duty_full} / "
           f"bus_voltage_v {plan.bus_voltage_v:g} V x 2^-QU"),
        _d("CORE_DUTY_SH", f"{plan.duty_sh}u", ""),
        _d("CORE_PDC_MAX", f"UINT32_C({plan.pdc_max})", "= FW_PDC_MAX"),
        _d("CORE_U_LIMIT", str(plan.u_limit), f"bus x max duty = {plan.u_limit * 2 ** -plan.qu:.4g} V"),
        _d("CORE_CAP_STEP", str(plan.cap_step), "backup current limiter: |u| cap step per sample (full range in 10 ms)"),
        _d("CORE_KB", str(plan.kb), f"motor Kb = {plan.kb * 2 ** -plan.q_kb:.6g} V s/rad in Q{plan.q_kb} "
           "(current-limit window Kb w -+ R I_lim)"),
        _d("CORE_SHIFT_KB(x)", shift_macro("KB", plan.shift_kb), f"Q_KB + QS - QU = {plan.shift_kb}"),
        _d("CORE_R_CNT", str(plan.r_cnt), f"motor r_line_ohm per ADC count = {plan.r_cnt * 2 ** -plan.q_r:.6g} V "
           f"in Q{plan.q_r}"),
        _d("CORE_SHIFT_R(x)", shift_macro("R", plan.shift_r), f"Q_R - QU = {plan.shift_r}"),
        _d("CORE_KFF", str(plan.kff), (f"reference feedforward = {plan.kff * 2 ** -plan.q_kff:.6g} V s/rad in "
                                       f"Q{plan.q_kff} (integrator preload per reference change)" if plan.kff else
                                       "reference feedforward off (design reference_ff_v_s_per_rad = 0)")),
        _d("CORE_SHIFT_FF(x)", shift_macro("FF", plan.shift_ff), f"Q_KFF + QS - QI = {plan.shift_ff}"),
    ]})
    gains = []
    for c in plan.coefs:
        gains.append(_d("FW_" + c.name.upper().replace("*", "").replace("/", "_"), str(c.raw),
                        f"{c.value:.9g} {c.unit} x 2^{c.q} ({c.source}); quantisation error "
                        f"{100 * c.rel_error:.4f} %"))
    S.append({"title": "design coefficients (defaults of the parameter table; the firmware reads them from "
                       "link_params)", "defines": gains})
    return S


def _next_code(t, code: int) -> int:
    seq = list(t.sequence)
    if code not in seq:
        return code
    return seq[(seq.index(code) + 1) % len(seq)]


def _protocol_overrides(plan, profile):
    from ..link import protocol
    from .fixedpoint import param_specs, signal_specs
    ov = {}
    for name, s in {**param_specs(plan, profile), **signal_specs(plan)}.items():
        if name in ("hall", "state", "fault"):
            continue
        ov[name] = protocol.ParamOverride(scale=float(s.scale), min_raw=s.min_raw, max_raw=s.max_raw,
                                          default_raw=s.default_raw, ctype=s.ctype)
    return ov


def generate(profile, design_path, *, hall_input: str = "auto", fault_pin: str = "RC1",
             name: str | None = None, link_capture: bool = True, link_eeprom: bool = True,
             capture_bytes: int = CAPTURE_BYTES, identify: bool = False) -> Firmware:
    """Plan and render the firmware (nothing is written).

    Parameters
    ----------
    profile : picdrive.profile.Profile
        The drive; its hash goes into the build (``profile_hash``).
    design_path : str or pathlib.Path
        A usable design result (``*.design.json``) of this profile.
    hall_input : str
        Where the hall sensors enter: ``"int"`` (INT0..INT2), ``"ic"`` (IC1..IC3) or ``"auto"``
        (:func:`picdrive.firmware.pinmap.choose_pinmap`).
    fault_pin : str
        The overcurrent comparator's input pin (``"RC1"``...).
    name : str, optional
        The build's name (default: the profile's).
    link_capture, link_eeprom : bool
        Generate the link's triggered capture (commands and its ``capture_bytes`` buffer) and
        EEPROM persistence, or leave them out to save flash and RAM (a build without capture says
        0 capture words in hello and NACKs its commands UNKNOWN_COMMAND; one without EEPROM
        answers eeprom_save/eeprom_load EEPROM_ERROR and boots with the defaults).
    capture_bytes : int
        The capture buffer, B (even, 16..256).
    identify : bool
        Generate the identification build: the identification mode (``picdrive identify``: the
        ``ident`` command, state IDENT, its vector tables and hall-driven selection; about 0.8 kB
        of flash and 4 B of RAM) without the EEPROM persistence (identification saves nothing;
        0.8 kB, so that every design's identification build fits the chip).  Without it the build
        has none of the mode, NACKs ``ident`` UNKNOWN_COMMAND and says so in hello's ``features``.

    Returns
    -------
    Firmware
        The rendered files (name -> text), the build id (u32), the fixed-point plan (Q formats,
        raw limits), the PWM plan and pin map, the protocol table (scales in engineering units
        per count) and the summary lines.

    Raises
    ------
    CodegenError
        A design or option the firmware cannot hold, named with the fix.
    """
    import jinja2

    from . import core_layout, core_program, fixedpoint, p18f4431, pcpwm, pinmap
    from .. import outputs
    from ..link import protocol, protocol_c
    from ..paths import templates_dir
    from ..result import load_design

    design_path = Path(design_path)
    design = load_design(design_path, require_usable=True, profile=profile)
    try:
        design_bytes = design_path.read_bytes()
    except OSError as e:
        raise CodegenError(f"cannot read design file {design_path}: {e.strerror}") from None
    pwm = pcpwm.plan_pwm(profile)
    pm = pinmap.choose_pinmap(profile, hall_input=hall_input, fault_pin=fault_pin)
    plan = fixedpoint.plan_fixed_point(profile, design.law, pwm)
    brg, baud = uart_brg(profile.uart.baud)
    bus = bus_sense(profile)
    if isinstance(capture_bytes, bool) or not isinstance(capture_bytes, int) or capture_bytes % 2 \
            or not 16 <= capture_bytes <= 256:
        raise CodegenError(f"capture buffer of {capture_bytes!r} B: give an even number of bytes in [16, 256] "
                           "(--capture-bytes)")
    options = {"hall_input": hall_input, "fault_pin": fault_pin}
    if identify:            # the identification build leaves the EEPROM persistence out to fit (said below)
        link_eeprom = False
    # link options enter the build id only when they differ from the default (ids stay as they were)
    for k, v, d in (("link_capture", bool(link_capture), True), ("link_eeprom", bool(link_eeprom), True),
                    ("capture_bytes", capture_bytes, CAPTURE_BYTES), ("identify", bool(identify), False)):
        if v != d:
            options[k] = v
    build_id, digest = _inputs_hash(profile, design_bytes, options)
    profile_hash = profile.hash32
    name = name or profile.name

    try:
        table = protocol.build_table(plan.n_rules, _protocol_overrides(plan, profile), profile=profile)
        link = protocol_c.render_c(table, build_id, profile_hash, sample_hz=plan.loop_hz,
                                   capture_bytes=capture_bytes, capture=bool(link_capture),
                                   eeprom=bool(link_eeprom), identify=bool(identify),
                                   critical_begin="extern void fw_lock(void); fw_lock();",
                                   critical_end="extern void fw_unlock(void); fw_unlock();",
                                   sfr_bits=p18f4431.bits())
    except protocol.ProtocolError as e:
        raise CodegenError(f"the protocol table cannot hold this design's numbers: {e}") from None

    design_desc = (f"{design_path.name}: {design.method}" + (f" ({design.variant})" if design.variant else "")
                   + f", {design.law.n_rules} rule(s), status {design.status}")
    gen_note = f"profile {profile.name}, design {design_path.name}, build 0x{build_id:08X}"
    ctx = dict(gen_note=gen_note, profile_name=profile.name, profile_sha=profile.sha256, design_desc=design_desc,
               build_id=build_id, sections=_sections(profile, design, plan, pwm, pm, brg, baud, bus, bool(identify)),
               ident=bool(identify),
               config=_config_bits(pm, profile.control.speed_loop_hz), eeprom_gptr_stubs=EEPROM_GPTR_STUBS, n_rules=plan.n_rules,
               link_id={e.name: e.id for e in table.entries}, link_off=_store_offsets(table),
               signal_index={e.name: i for i, e in enumerate(table.signals)},
               bit=p18f4431.bits(),    # bit positions by name, for the assembly: {{ bit.PIR1.RCIF }}
               layout=core_layout.render_context(plan.n_rules),   # the core's structs and offsets
               core_program={"law": core_program.c_source(core_program.LAW),   # the law and control's C
                             "control": core_program.c_source(core_program.CONTROL),
                             "speed_hall": core_program.c_source(core_program.SPEED_HALL),
                             # and the law's assembly (the plans the template runs it for)
                             "law_asm": (core_program.asm_source(core_program.LAW, plan, p18f4431.bits())
                                         if plan.n_rules <= 2 and not plan.dfilt_a else ""),
                             "control_asm": (core_program.asm_source(core_program.CONTROL, plan, p18f4431.bits())
                                             if plan.n_rules <= 2 and not plan.dfilt_a
                                             and 32768 * plan.kduty < 2 ** 31 else "")},
               link_state={s.name: int(s) for s in protocol.State})   # the drive states, for the assembly
    env = jinja2.Environment(loader=jinja2.FileSystemLoader(str(templates_dir())),
                             undefined=jinja2.StrictUndefined, trim_blocks=True, lstrip_blocks=True,
                             keep_trailing_newline=True, autoescape=False)
    files = {t: env.get_template(t + ".j2").render(**ctx) for t in TEMPLATES}
    files.update(link)
    files["host/xc.h"] = p18f4431.render_host_shim()
    summary = [f"firmware    {name}: profile {profile.name} ({profile.sha256[:12]}), design {design_desc}",
               f"build id    0x{build_id:08X} (sha256 of the inputs {digest[:16]}...), table hash "
               f"0x{table.hash:08X}"]
    summary += pwm.lines() + plan.lines() + pm.lines()
    summary.append(f"uart        SPBRG = {brg}: {baud:.0f} baud")
    summary.append("bus guard   AN1 " + ("assumed " if bus["source"] == "assumed" else "")
                   + f"divider {bus['bus_sense_v_per_v']:.5f} V/V ({bus['counts_per_v']:.2f} counts/V); braking "
                   f"current full up to taper_start, linearly to 0 at taper_end; OVERVOLTAGE latches above trip")
    summary += ["            " + ln for ln in bus["lines"]]
    summary.append("link        " + (f"capture ({capture_bytes} B buffer)" if link_capture else "no capture (--no-capture)")
                   + ", " + ("EEPROM persistence" if link_eeprom else "no EEPROM persistence (--no-eeprom)"))
    summary.append("ident       " + ("identification build (--identify): the mode picdrive identify drives, and "
                                     "no EEPROM persistence to fit (the board's EEPROM is left as it is); flash "
                                     "the drive build (without --identify) back after identify" if identify
                                     else "no identification mode (--identify builds it)"))
    files["board.json"] = json.dumps(_board(profile, plan, pwm, pm, bus, build_id, table), indent=1,
                                     sort_keys=True) + "\n"
    files["Makefile"] = _makefile(name)
    files["README.md"] = _readme(name, summary)
    files[outputs.MARKER] = outputs.manifest_text("firmware", files, regenerable=REGENERABLE)
    return Firmware(name=name, files=files, build_id=build_id, summary=summary, plan=plan, pwm=pwm, pinmap=pm,
                    table=table)


def _store_offsets(table) -> dict[str, int]:
    """Byte offset of each parameter in link_fw.h's link_params_t (fields in table order, no padding on
    an 8-bit core; drive.c's assembly checks each one it uses with offsetof at compile time)."""
    off, out = 0, {}
    for e in table.params:
        out[e.name] = off
        off += e.ct.size
    return out


def _board(profile, plan, pwm, pm, bus, build_id, table) -> dict:
    """What the twin needs to wire its peripheral model to this firmware."""
    def pin(p):
        return {"port": "ABCDE".index(p[1]), "bit": int(p[2]), "name": p}
    return {
        "schema": "picdrive.board/1",
        "build_id": build_id,
        "table_hash": table.hash,
        "fosc_hz": FOSC_HZ,
        "hall_pins": [pin(pm.assign[h][0]) for h in ("hall_a", "hall_b", "hall_c")],
        "hall_input": pm.hall_input,
        "flta_pin": pin(pm.assign["fault_flta"][0]),
        "phase_pairs": [0, 1, 2],
        "analog": {"AN0": "bus_current", "AN1": "bus_voltage"},
        "current_sense_v_per_a": profile.inverter.current_sense_v_per_a,
        "current_sense_offset_v": 0.0,
        "bus_sense_v_per_v": bus["bus_sense_v_per_v"],
        "adc_vref_v": 5.0,
        "encoder": pm.encoder,
        "speed_loop_hz": plan.loop_hz,
        "pwm_frequency_hz": pwm.period.frequency_hz,
        "dead_time_ns": pwm.dead.dead_time_ns,
        "max_duty": pwm.max_duty,
        "sources": list(HOST_SOURCES),
    }


def _makefile(name: str) -> str:
    return f"""# Build the {name} firmware for the PIC18F4431 with Microchip XC8 (v2.x, C99).
# GENERATED by picdrive firmware.  `make` -> build/{name}.hex;  `make host-check`
# compiles the same sources with gcc against the register shim in host/.
XC8     ?= xc8-cc
CC      ?= gcc
SRCS     = main_xc8.c config_xc8.c drive.c drive_core.c link_fw.c
HOSTSRC  = {' '.join(HOST_SOURCES)}
HEADERS  = drive_params.h drive_core.h drive.h fw_port.h link_fw.h

all: build/{name}.hex

build/{name}.hex: $(SRCS) $(HEADERS)
\tmkdir -p build
\t$(XC8) -mcpu=18F4431 -std=c99 -O2 -Wl,-Map=build/{name}.map -o build/{name}.elf $(SRCS)

host-check: $(HOSTSRC) $(HEADERS) host/xc.h
\t$(CC) {' '.join(HOST_CFLAGS)} -Ihost -I. -fsyntax-only $(HOSTSRC)

clean:
\trm -rf build

.PHONY: all host-check clean
"""


def _readme(name: str, summary: list[str]) -> str:
    return (f"# Firmware `{name}` (generated)\n\n"
            "Generated by `picdrive firmware`; do not edit (regenerate instead).  Build with XC8: `make`, or\n"
            "open in MPLAB X as described in `firmware_build/README.md`.  The host build (gcc + `host/xc.h`)\n"
            f"compiles `{' '.join(HOST_SOURCES)}`; `main_xc8.c` and `config_xc8.c` are for XC8 only.\n\n"
            "What the generator chose:\n\n```\n" + "\n".join(summary) + "\n```\n")


# ---------------------------------------------------------------------------
# Build check and writing
# ---------------------------------------------------------------------------
def host_build(folder) -> dict:
    """How to build a generated firmware folder on the host.

    Returns ``{"sources": [...], "include_dirs": [...], "cflags": [...],
    "provide": [...]}``: compile the sources with the include folders (the
    shim ``host/xc.h`` first) and link with an object that provides the
    symbols in ``provide`` (the twin's peripheral model, or a test stub).
    """
    folder = Path(folder)
    missing = [s for s in (*HOST_SOURCES, "host/xc.h") if not (folder / s).is_file()]
    if missing:
        raise CodegenError(f"{folder} is not a generated firmware folder (missing {', '.join(missing)}): "
                           "run 'picdrive firmware' first")
    return {"sources": [str(folder / s) for s in HOST_SOURCES],
            "include_dirs": [str(folder / "host"), str(folder)],
            "cflags": list(HOST_CFLAGS),
            "provide": ["picsim_sfr", "picsim_sfr_written", "picsim_sfr_read"]}


def build_check(folder) -> list[str]:
    """Compile the host sources with gcc (and avr-gcc if installed); raise on any diagnostic."""
    hb = host_build(folder)
    done = []
    compilers = [("gcc", [])]
    if shutil.which("avr-gcc"):
        compilers.append(("avr-gcc", ["-mmcu=atmega328p"]))
    for cc, extra in compilers:
        cmd = [cc, *extra, *hb["cflags"], *[f"-I{d}" for d in hb["include_dirs"]], "-fsyntax-only",
               *hb["sources"]]
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0 or r.stderr.strip():
            raise CodegenError(f"the generated firmware does not compile cleanly with {cc} (a picdrive bug; "
                               f"please report it):\n{r.stderr.strip()}")
        done.append(cc)
    return done


def folder_budgets(folder):
    """``picdrive.firmware.target.BUDGETS`` with the speed loop's share taken of the period this
    firmware folder runs it at (``FW_LOOP_DIV`` Timer2 interrupts): 40 % of 1 ms is 4,000 cycles,
    of 0.5 ms (a 2 kHz loop) 2,000."""
    import dataclasses
    from . import gpsim, target
    tcy = gpsim.firmware_limits(folder).get("speed_loop_tcy")
    if not tcy:
        return target.BUDGETS
    return dataclasses.replace(target.BUDGETS, speed_loop_hz=target.FCY_HZ / tcy)


def target_build(folder, name: str, *, allow_over_budget: bool = False, report: list | None = None,
                 figures: dict | None = None):
    """Build ``<folder>/<name>.hex`` for the PIC18F4431 and measure it against the budgets.

    Compiles and links with picdrive.target (SDCC + gplink), times the
    interrupts in gpsim (picdrive.gpsim: the worst over telemetry off, 4
    signals, and 4 signals with a capture armed), appends the figures to ``report`` (lines) and
    ``figures`` (``flash_bytes``, ``ram_stack_bytes``, the worst cycles by interrupt:
    ``speed_loop_isr``, ``hall_isr``, ``uart_rx_byte``..., and ``over_budget``: what exceeds its
    budget, empty when the firmware fits) and raises CodegenError with them when a budget is
    exceeded (unless ``allow_over_budget``).
    Returns ``(Build, Cycles)``.
    """
    import tempfile
    from . import gpsim, target
    folder = Path(folder)
    with tempfile.TemporaryDirectory(prefix="picdrive-target-") as t:
        b = target.build_measured(folder, Path(t) / "hex", name=name)
        modes = gpsim.measure_modes(folder, Path(t) / "timing")
        # budgets hold in every telemetry mode: the worst over off / 4 signals / 4 signals + capture
        cyc = gpsim.Cycles({k: max(c.worst.get(k, 0) for c in modes.values())
                            for k in modes["4+capture"].worst}, modes["4+capture"].samples)
        if b.on_chip:          # a HEX linked beyond the chip's memory is not written
            shutil.copyfile(b.hex_path, folder / f"{name}.hex")
    budgets = folder_budgets(folder)
    lines = target.budget_lines(b, cyc.worst, budgets)
    if report is not None:
        report += lines
    bad = target.over_budget(b, cyc.worst, budgets)
    if figures is not None:
        figures.update(flash_bytes=b.flash_bytes, ram_stack_bytes=b.ram_stack_bytes, over_budget=bad,
                       **{k: v for k, v in cyc.worst.items() if ":" not in k})
    if bad and not allow_over_budget:
        raise CodegenError("the firmware does not fit the PIC18F4431's budgets (" + "; ".join(bad) + "); nothing "
                           "written.  Figures:\n  " + "\n  ".join(lines) + "\n(--allow-over-budget writes it anyway, "
                           "for measurement)")
    return b, cyc


def chip_check(profile, design_path, *, hall_input: str = "auto", fault_pin: str = "RC1") -> tuple[list[str], list[str]]:
    """The design's firmware built for the PIC18F4431 as ``picdrive firmware`` builds it, measured.

    Generates the firmware (``generate``), compiles it for the host (``build_check``) and for the
    chip (SDCC, gplink, gpsim: ``target_build``) in a temporary folder, and measures flash, static
    RAM + stack and every interrupt's worst case against ``picdrive.firmware.target.BUDGETS``.
    Returns ``(figure lines, what exceeds its budget)``; the second is empty when the firmware
    fits.  Raises TargetError when the PIC18 toolchain is missing (the message names the fix).
    """
    import tempfile
    fw = generate(profile, design_path, hall_input=hall_input, fault_pin=fault_pin)
    lines: list[str] = []
    figures: dict = {}
    with tempfile.TemporaryDirectory(prefix="picdrive-chip-check-") as t:
        write_firmware(fw, Path(t) / "fw", check=True, hex_build=True, allow_over_budget=True, report=lines,
                       figures=figures)
    return lines, figures["over_budget"]


def write_firmware(fw: Firmware, out_dir, *, check: bool = True, hex_build: bool = False,
                   allow_over_budget: bool = False, report: list | None = None, figures: dict | None = None) -> Path:
    """Write the files into ``out_dir`` whole or not at all (temp folder, build check, rename).

    ``out_dir`` follows the output rule of :mod:`picdrive.outputs`: it is
    created, or replaced only when it is a firmware folder picdrive wrote.
    ``hex_build``: also build ``<name>.hex`` with the PIC18 toolchain and refuse a
    firmware over its budgets (``target_build``).
    """
    from .. import outputs
    out = outputs.dir_output(out_dir, what="firmware folder")
    tmp = outputs.new_temp_dir(out, what="firmware folder")
    try:
        for rel, text in sorted(fw.files.items()):
            p = tmp / rel
            p.parent.mkdir(parents=True, exist_ok=True)
            with open(p, "w", encoding="utf-8", newline="\n") as f:
                f.write(text)
        if check:
            build_check(tmp)
        if hex_build:
            target_build(tmp, fw.name, allow_over_budget=allow_over_budget, report=report, figures=figures)
            hex_rel = f"{fw.name}.hex"
            if (tmp / hex_rel).is_file():
                # the marker lists the HEX too: without it, the next 'picdrive firmware' into this folder
                # took the HEX for a file of the user's and refused to replace the folder
                files = {rel: text for rel, text in fw.files.items() if rel != outputs.MARKER}
                files[hex_rel] = (tmp / hex_rel).read_bytes()
                (tmp / outputs.MARKER).write_text(outputs.manifest_text("firmware", files, regenerable=REGENERABLE),
                                                  encoding="utf-8", newline="\n")
    except OSError as e:
        shutil.rmtree(tmp, ignore_errors=True)
        raise outputs.OutputError(f"cannot write firmware folder {out}: {e.strerror or e}") from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return outputs.publish_dir(tmp, out, "firmware", regenerable=REGENERABLE, what="firmware folder")


# ---------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------
def _cmd(args) -> int:
    from ..outputs import dir_output
    from ..profile import load_profile
    profile = load_profile(args.profile)
    out = dir_output(args.output if args.output else Path("firmware_build") / profile.name,
                     what="firmware folder")
    fw = generate(profile, args.design, hall_input=args.hall_input, fault_pin=args.fault_pin,
                  link_capture=not args.no_capture, link_eeprom=not args.no_eeprom, capture_bytes=args.capture_bytes,
                  identify=args.identify)
    for line in fw.summary:
        print(line)
    report: list[str] = []
    write_firmware(fw, out, hex_build=not args.no_hex, allow_over_budget=args.allow_over_budget, report=report)
    for line in report:
        print(line)
    if report and args.allow_over_budget:
        print("built with --allow-over-budget: for measurement, not for a motor")
    print(f"wrote {out}/ ({len(fw.files) + (0 if args.no_hex else 1)} files)")
    return 0


def register(sub) -> None:
    p = sub.add_parser("firmware", help="generate the PIC18F4431 firmware of a design",
                       description="Render fixed-point C firmware for XC8 (and the host build the twin uses) "
                                   "from a drive profile and a verified design.")
    p.add_argument("--profile", required=True, help="profile .toml, or a bundled profile name")
    p.add_argument("--design", required=True, help="design result .design.json (verified, same profile)")
    p.add_argument("-o", "--output", help="output folder (default firmware_build/<profile name>/)")
    p.add_argument("--hall-input", default="auto", choices=["auto", "int", "ic"],
                   help="hall inputs: INT0..INT2 on RC3..RC5 (int, the default) or IC1..IC3 on RA2..RA4 "
                        "(ic, only without an encoder)")
    p.add_argument("--fault-pin", default="RC1", choices=["RC1", "RD4"], help="FLTA pin (FLTAMX)")
    p.add_argument("--no-capture", action="store_true",
                   help="leave the link's triggered capture out (about 1.3 kB of flash and its buffer of RAM; "
                        "hello then reports 0 capture words)")
    p.add_argument("--no-eeprom", action="store_true",
                   help="leave the EEPROM persistence of the parameters out (about 0.8 kB of flash; "
                        "eeprom_save/eeprom_load answer EEPROM_ERROR)")
    p.add_argument("--identify", action="store_true",
                   help="build the identification firmware: the mode picdrive identify drives (the ident "
                        "command; about 0.8 kB of flash), without EEPROM persistence (--no-eeprom) to fit. "
                        "Flash the build made without --identify back afterwards")
    p.add_argument("--capture-bytes", type=int, default=CAPTURE_BYTES,
                   help=f"capture buffer, bytes (even, 16..256; default {CAPTURE_BYTES})")
    p.add_argument("--allow-over-budget", action="store_true",
                   help="MEASUREMENT ONLY: write the firmware and its HEX even when flash, RAM + stack or an "
                        "interrupt's cycles exceed the PIC18F4431 budgets (the figures are printed)")
    p.add_argument("--no-hex", action="store_true",
                   help="generate the C only: skip the PIC18 HEX build (SDCC, gputils) and the budget check")
    p.set_defaults(func=_cmd)
