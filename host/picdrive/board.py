"""Fixed facts of the board every layer may use (docs/architecture.md, DESIGN.md).

The PIC18F4431 runs from a 10 MHz crystal through the HSPLL (x4): the
oscillator Fosc is 40 MHz and the instruction clock Fcy = Fosc / 4 is 10 MHz
(10 MIPS).  The PWM time base, the timers, the UART baud generator, the
firmware's budgets and the twin's CPU clock all count this clock: it is
written here once.
"""
from __future__ import annotations

__all__ = ["FOSC_HZ", "FCY_HZ"]

FOSC_HZ = 40_000_000          # Hz: 10 MHz crystal x 4 (HSPLL)
FCY_HZ = FOSC_HZ // 4         # Hz: instruction cycles per second (four oscillator periods each)
