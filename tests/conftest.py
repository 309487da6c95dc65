"""Root conftest: options shared by the whole suite.

``--target`` selects what the HIL suite (tests/hil/) runs against: ``twin``
(default, the motor twin built from the bundled firmware) or a pyserial URL
of a real board (``/dev/ttyUSB0``, ``COM5``, ``socket://host:port``).
"""
import os

os.environ.setdefault("MPLBACKEND", "Agg")


def pytest_addoption(parser):
    parser.addoption("--target", default="twin",
                     help="HIL target: 'twin' (default) or a serial URL of a real board")
    parser.addoption("--profile", default="duy2008",
                     help="HIL: profile of the board under test when --target is a serial URL")
