"""picdrive: design, fixed-point firmware, serial link and a motor twin for
BLDC speed drives on the Microchip PIC18F4431."""

__version__ = "0.1.0"
