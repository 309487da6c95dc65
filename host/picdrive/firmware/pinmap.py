"""Pin map of the PIC18F4431 (40/44-pin) for a drive profile.

Facts (PIC18F2331/2431/4331/4431 data sheet DS39616D, pin diagrams and
Table 1-3; ``p18f4431.inc`` CONFIG listing for the multiplexing bits):

* PWM0..PWM5 on RB0..RB3, RB5 (PWM4, or RD5 with ``PWM4MX = RD5``), RB4
  (PWM5); PWM6/PWM7 on RD6/RD7 (unused).
* The input-capture pins CAP1/CAP2/CAP3 are RA2/RA3/RA4, which are also the
  QEI's INDX/QEA/QEB; IC and QEI share the module: in velocity mode the QEI
  captures Timer5 through IC1 (VELR is CAP1BUF) and uses the IC2QEIF and
  IC3DRIF flags.  So with an encoder the hall sensors cannot use the IC
  module and go to the external interrupts INT0/INT1/INT2 on RC3/RC4/RC5.
* RB4..RB7 interrupt-on-change is not usable for halls: RB4/RB5 are PWM5/PWM4
  and RB6/RB7 are PGC/PGD (programming and debugging).
* EUSART TX/RX are fixed on RC6/RC7.  FLTA is RC1 (``FLTAMX = RC1``) or RD4.
* RC3 also carries T0CKI/T5CKI and RC4/RC5 the SSP: ``EXCLKMX = RD0`` and
  ``SSPMX = RD1`` move those (unused) functions off the hall pins.
* The bus-current sense goes to AN0/RA0.

:func:`choose_pinmap` picks a valid map for a profile (halls on INT0..INT2 by
default: valid with and without an encoder) and :func:`check_pinmap` refuses
an impossible one with a message that names the conflict and the fix.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from ..errors import PicdriveError

__all__ = ["PinMapError", "PinMap", "PINS", "choose_pinmap", "check_pinmap", "HALL_INPUTS", "FAULT_PINS"]


class PinMapError(PicdriveError, ValueError):
    """The requested pin map cannot work on the PIC18F4431."""


#: pin -> functions it can carry (40/44-pin PIC18F4431), names as in the data sheet
PINS: dict[str, tuple[str, ...]] = {
    "RA0": ("AN0",), "RA1": ("AN1",), "RA2": ("AN2", "VREF-", "CAP1", "INDX"),
    "RA3": ("AN3", "VREF+", "CAP2", "QEA"), "RA4": ("AN4", "CAP3", "QEB"), "RA5": ("AN5", "LVDIN"),
    "RA6": ("OSC2", "CLKO"), "RA7": ("OSC1", "CLKI"),
    "RB0": ("PWM0",), "RB1": ("PWM1",), "RB2": ("PWM2",), "RB3": ("PWM3",),
    "RB4": ("KBI0", "PWM5"), "RB5": ("KBI1", "PWM4", "PGM"), "RB6": ("KBI2", "PGC"), "RB7": ("KBI3", "PGD"),
    "RC0": ("T1OSO", "T1CKI"), "RC1": ("T1OSI", "CCP2", "FLTA"), "RC2": ("CCP1", "FLTB"),
    "RC3": ("T0CKI", "T5CKI", "INT0"), "RC4": ("INT1", "SDI", "SDA"), "RC5": ("INT2", "SCK", "SCL"),
    "RC6": ("TX", "CK", "SS"), "RC7": ("RX", "DT", "SDO"),
    "RD0": ("T0CKI", "T5CKI"), "RD1": ("SDO",), "RD2": ("SDI", "SDA"), "RD3": ("SCK", "SCL"),
    "RD4": ("FLTA",), "RD5": ("PWM4",), "RD6": ("PWM6",), "RD7": ("PWM7",),
    "RE0": ("AN6",), "RE1": ("AN7",), "RE2": ("AN8",), "RE3": ("MCLR", "VPP"),
}
#: pins reserved for in-circuit programming and debugging (and MCLR)
RESERVED = {"RB6": "PGC (in-circuit programming/debug)", "RB7": "PGD (in-circuit programming/debug)",
            "RE3": "MCLR/VPP", "RA6": "OSC2 (10 MHz crystal)", "RA7": "OSC1 (10 MHz crystal)"}

HALL_INPUTS = ("auto", "int", "ic")
FAULT_PINS = ("RC1", "RD4")
_HALL_PINS = {"int": (("INT0", "RC3"), ("INT1", "RC4"), ("INT2", "RC5")),
              "ic": (("CAP1", "RA2"), ("CAP2", "RA3"), ("CAP3", "RA4"))}


@dataclass(frozen=True)
class PinMap:
    """A pin assignment: function -> (pin, peripheral signal)."""

    hall_input: str                              # "int" | "ic"
    encoder: bool
    assign: dict[str, tuple[str, str]]           # function -> (pin, signal)
    config: dict[str, str] = field(default_factory=dict)   # mux config bits

    @property
    def hall_port(self) -> str:
        return "PORTC" if self.hall_input == "int" else "PORTA"

    @property
    def hall_shift(self) -> int:
        return 3 if self.hall_input == "int" else 2

    def tris(self) -> dict[str, int]:
        """TRISx values: outputs (0) for the PWM pins, inputs (1) everywhere else."""
        t = {p: 0xFF for p in "ABCDE"}
        for pin, sig in self.assign.values():
            if sig.startswith("PWM"):
                t[pin[1]] &= ~(1 << int(pin[2])) & 0xFF
        t["E"] &= 0x07
        return t

    def lines(self) -> list[str]:
        out = []
        for fn, (pin, sig) in self.assign.items():
            out.append(f"  {fn:<14} {pin:<4} {sig}")
        cfg = ", ".join(f"{k} = {v}" for k, v in self.config.items())
        return [f"pin map     halls on {'INT0..INT2' if self.hall_input == 'int' else 'IC1..IC3'}"
                f"{' (encoder on the QEI)' if self.encoder else ''}; config {cfg}"] + out


def check_pinmap(pm: PinMap) -> None:
    """Raise :class:`PinMapError` naming the conflict and the fix, or return."""
    by_pin: dict[str, list[str]] = {}
    for fn, (pin, sig) in pm.assign.items():
        if pin not in PINS:
            raise PinMapError(f"{fn}: pin {pin} does not exist on the PIC18F4431")
        if sig not in PINS[pin]:
            raise PinMapError(f"{fn}: pin {pin} cannot carry {sig} (it carries {', '.join(PINS[pin])})")
        if pin in RESERVED:
            raise PinMapError(f"{fn} on {pin}: that pin is {RESERVED[pin]}; choose another pin")
        by_pin.setdefault(pin, []).append(fn)
    uses_qei = any(sig in ("QEA", "QEB", "INDX") for _, sig in pm.assign.values())
    uses_ic = [fn for fn, (_, sig) in pm.assign.items() if sig in ("CAP1", "CAP2", "CAP3")]
    if uses_qei and uses_ic:
        raise PinMapError(
            f"{', '.join(uses_ic)} on the input-capture module and the encoder on the QEI: on the "
            "PIC18F4431 IC1..IC3 and the QEI share pins RA2..RA4, the capture buffers (VELR is CAP1BUF) "
            "and the flags IC2QEIF/IC3DRIF, so they cannot both be used; put the halls on INT0..INT2 "
            "(hall input 'int': RC3, RC4, RC5) or remove the encoder (sensors.encoder_lines = 0)")
    for pin, fns in by_pin.items():
        if len(fns) > 1:
            raise PinMapError(f"pin {pin} is assigned twice ({' and '.join(fns)}); move one of them")
    flta = pm.assign.get("fault_flta", ("RC1",))[0]
    if pm.config.get("FLTAMX", "RC1") != flta:
        raise PinMapError(f"FLTA on {flta} needs config FLTAMX = {flta}")
    pwm4 = pm.assign.get("phase_c_low", ("RB5",))[0]
    if pm.config.get("PWM4MX", "RB5") != pwm4:
        raise PinMapError(f"PWM4 on {pwm4} needs config PWM4MX = {pwm4}")
    if pwm4 == "RB5" and pm.config.get("LVP", "OFF") != "OFF":
        raise PinMapError("PWM4 on RB5 needs LVP = OFF (RB5 is PGM while low-voltage programming is on)")
    if pm.hall_input == "int":
        if pm.config.get("EXCLKMX") != "RD0":
            raise PinMapError("hall A on RC3/INT0 needs EXCLKMX = RD0 (moves T0CKI/T5CKI off RC3)")
        if pm.config.get("SSPMX") != "RD1":
            raise PinMapError("halls on RC4/RC5 need SSPMX = RD1 (moves the SSP off RC4/RC5/RC7)")


def choose_pinmap(profile, hall_input: str = "auto", fault_pin: str = "RC1") -> PinMap:
    """A valid pin map for the profile.

    ``hall_input``: ``"int"`` (RC3/RC4/RC5, INT0..INT2), ``"ic"`` (RA2..RA4,
    input capture in state-change mode; only without an encoder) or
    ``"auto"`` (= ``"int"``: valid with and without an encoder, and the same
    firmware path for both).  ``fault_pin``: ``"RC1"`` or ``"RD4"``.
    """
    if hall_input not in HALL_INPUTS:
        raise PinMapError(f"hall input {hall_input!r}: expected one of {', '.join(HALL_INPUTS)}")
    if fault_pin not in FAULT_PINS:
        raise PinMapError(f"fault pin {fault_pin!r}: FLTA can be on RC1 or RD4 only")
    hi = "int" if hall_input == "auto" else hall_input
    enc = profile.sensors.has_encoder
    assign: dict[str, tuple[str, str]] = {
        "phase_a_low": ("RB0", "PWM0"), "phase_a_high": ("RB1", "PWM1"),
        "phase_b_low": ("RB2", "PWM2"), "phase_b_high": ("RB3", "PWM3"),
        "phase_c_low": ("RB5", "PWM4"), "phase_c_high": ("RB4", "PWM5"),
        "fault_flta": (fault_pin, "FLTA"),
        "uart_tx": ("RC6", "TX"), "uart_rx": ("RC7", "RX"),
        "bus_current": ("RA0", "AN0"),
    }
    for name, (sig, pin) in zip(("hall_a", "hall_b", "hall_c"), _HALL_PINS[hi]):
        assign[name] = (pin, sig)
    if enc:
        assign["encoder_a"] = ("RA3", "QEA")
        assign["encoder_b"] = ("RA4", "QEB")
    config = {"FLTAMX": fault_pin, "PWM4MX": "RB5", "LVP": "OFF", "SSPMX": "RD1", "EXCLKMX": "RD0"}
    pm = PinMap(hall_input=hi, encoder=enc, assign=assign, config=config)
    check_pinmap(pm)
    return pm
