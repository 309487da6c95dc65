"""The HIL suite's own options (tests/hil/conftest.py): ``--profile`` selects what it is
given or is refused, and a serial target that does not answer fails the run."""
import os
import socket
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_hil(*args, timeout=600):
    env = dict(os.environ)
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-rs", *args],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
    return r.returncode, r.stdout + r.stderr


def dead_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()                                   # nothing listens there now
    return port


def test_a_serial_target_that_does_not_answer_fails_the_run():
    code, out = run_hil("tests/hil", "--target", f"socket://127.0.0.1:{dead_port()}", "--profile", "duy2008")
    assert code == 1, out
    assert "the board under test does not answer" in out and " passed" not in out
    assert " skipped" not in out.splitlines()[-1], out.splitlines()[-1]


def test_a_profile_the_suite_cannot_test_is_refused_not_skipped():
    for target in ("twin", f"socket://127.0.0.1:{dead_port()}"):
        code, out = run_hil("tests/hil", "--target", target, "--profile", "mymotor")
        assert code == 4, out                                  # pytest's usage error
        assert "--profile mymotor" in out and "duy2008" in out and "skipped" not in out
    code, out = run_hil("tests/hil", "--target", f"socket://127.0.0.1:{dead_port()}")
    assert code == 4 and "name the board's profile with --profile" in out, out


def test_profile_selects_the_twins_tests():
    test = "tests/hil/test_hil_link.py::test_handshake_identifies_the_profile_and_table"   # a duy2008 test
    code, out = run_hil(test, "--profile", "assawinchaichote2016")
    assert code == 0 and "1 skipped" in out and "--profile assawinchaichote2016 selects" in out, out
    code, out = run_hil(test, "--profile", "duy2008")
    assert code == 0 and "1 passed" in out, out
