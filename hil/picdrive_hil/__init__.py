"""picdrive's motor twin: the generated firmware compiled on the host, a
PIC18F4431 peripheral model and a three-phase BLDC plant, behind a pyserial
URL.  See docs/architecture.md, seam 5."""
