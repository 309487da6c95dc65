"""Root conftest: options shared by the whole suite.

``--target`` selects what the HIL suite (tests/hil/) runs against: ``twin``
(default, the motor twin built from the bundled firmware) or a pyserial URL
of a real board (``/dev/ttyUSB0``, ``COM5``, ``socket://host:port``).
"""
import os
import warnings

import pytest

os.environ.setdefault("MPLBACKEND", "Agg")


@pytest.fixture(scope="session")
def profiles():
    """The bundled profiles by name (their speed-range warnings silenced)."""
    from picdrive.profile import bundled_profiles, load_profile
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return {n: load_profile(n) for n in bundled_profiles()}


def pytest_addoption(parser):
    parser.addoption("--target", default="twin",
                     help="HIL target: 'twin' (default), 'pil' (the bundled firmware's HEX on the processor "
                          "twin), 'pil:FILE' (a HEX on the processor twin; needs --profile) or a serial URL "
                          "of a real board")
    parser.addoption("--enlarged-memory", action="store_true", default=False,
                     help="HIL with --target pil:FILE: simulate 128 KB flash / 1.5 KB RAM for a HEX that does "
                          "not fit the 18F4431 (picdrive.target's enlarged measurement memory)")
    parser.addoption("--profile", default=None,
                     help="HIL: the bundled profile to test: required with a serial --target (the board's "
                          "profile); with the twin, only that profile's tests run (default: all)")


_SECTIONS = pytest.StashKey[list]()


@pytest.fixture
def report_section(request):
    """``report_section(title, text)``: a figure or table a test wants shown after the run (the
    import contract's layers, for one)."""
    def add(title: str, text: str) -> None:
        request.config.stash.setdefault(_SECTIONS, []).append((title, text))
    return add


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    for title, text in config.stash.get(_SECTIONS, []):
        terminalreporter.section(title)
        terminalreporter.write_line(text)
