"""The firmware: the chip's registers (``p18f4431``), PWM and pins
(``pcpwm``, ``pinmap``), the fixed-point plan and bit-exact model
(``fixedpoint``), the generator (``codegen``), the SDCC build and its
budgets (``target``) and the gpsim timing harness (``gpsim``).  Depends on
the law and the profile (and the protocol it renders into C)."""
