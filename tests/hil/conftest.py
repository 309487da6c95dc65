"""HIL suite fixtures (see hilbench.py for the bench and the limits).

``--target twin`` (default), ``pil`` (the processor twin: the bundled firmware's HEX,
built with picdrive.firmware.target, on the PIC18 simulator), ``pil:FILE`` (a HEX of your own on
the processor twin; needs ``--profile``) or a serial URL of a real board (root conftest);
``--profile`` names the real board's profile (required with a serial URL) or,
with the twin, selects that profile's tests (the twin runs it with firmware
generated from its committed design).  A profile the suite has no firmware
and tests for is refused, and a serial target that does not answer fails the
run instead of skipping it.
"""
from __future__ import annotations

from pathlib import Path

import pytest

from picdrive.link.client import Link
from picdrive.result import load_design

from hilbench import PROFILES, Bench, FirmwareCache, design_path, match_design, profile

_REPORT = pytest.StashKey[list]()
_PIL = pytest.StashKey[list]()


def pytest_configure(config):
    config.stash[_REPORT] = []
    config.stash[_PIL] = []


def pytest_collection_modifyitems(config, items):
    here = Path(__file__).resolve().parent
    hil = False
    for it in items:
        if here in Path(str(it.fspath)).resolve().parents:
            it.add_marker(pytest.mark.hil)
            hil = True
    if hil:
        check_options(config.getoption("--target"), config.getoption("--profile"))


def is_generated(target: str) -> bool:
    """The suite generates the firmware itself: the SIL twin, or the processor twin with its HEX."""
    return target in ("twin", "pil")


def pil_hex_file(target: str) -> str | None:
    return target[4:] if target.startswith("pil:") else None


def check_options(target: str, prof: str | None) -> None:
    """Refuse a --profile the suite cannot test, and a serial target without --profile."""
    if target.startswith("pil:"):
        f = Path(pil_hex_file(target))
        if not f.is_file():
            raise pytest.UsageError(f"--target {target}: {f} is not a file; give the processor twin a HEX "
                                    "(--target pil:firmware.hex) or 'pil' for the bundled firmware")
    if prof is not None and prof not in PROFILES:
        where = ("the twin target has no firmware for it" if is_generated(target)
                 else "the suite has no tests or design for a board of that profile")
        raise pytest.UsageError(
            f"--profile {prof}: {where}; the HIL suite generates firmware and tests only the bundled profiles "
            f"with committed designs ({', '.join(PROFILES)}).  Choose one of them (or run 'picdrive twin' with "
            "your profile and firmware and use the console)")
    if not is_generated(target) and prof is None:
        raise pytest.UsageError(f"--target {target}: name the board's profile with --profile "
                                f"({' or '.join(PROFILES)})")


@pytest.fixture(scope="session", autouse=True)
def target_answers(request):
    """A serial target must answer (and run the named profile); else the run fails, it does not skip."""
    target = request.config.getoption("--target")
    if is_generated(target) or target.startswith("pil:"):
        return
    prof = profile(request.config.getoption("--profile"))
    from picdrive.link.client import LinkError
    try:
        with Link.open(target, expect_profile_hash=prof.hash32):
            pass
    except LinkError as e:
        pytest.fail(f"--target {target}: the board under test does not answer or is not the one named: {e}",
                    pytrace=False)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    pil_rows = config.stash.get(_PIL, [])
    if pil_rows:
        # what only the processor twin measures, per firmware: the worst test of each
        tr = terminalreporter
        tr.section("processor twin (PIC18 simulator): interrupts, stack, memory")
        worst: dict = {}
        for name, tw in pil_rows:
            try:
                r = tw.processor_report()
            except Exception as e:                  # a twin that stopped on a fault says why
                tr.write_line(f"{name}: no report ({e})")
                continue
            if name not in worst or r.speed_max > worst[name].speed_max:
                worst[name] = r
        for name, r in worst.items():
            tr.write_line(f"{name}:")
            for line in r.lines():
                tr.write_line(f"  {line}")
    rows = config.stash.get(_REPORT, [])
    if not rows:
        return
    tr = terminalreporter
    tr.section("HIL step responses (measured through picdrive.link)")
    tr.write_line(f"{'case':44s} {'target':>8s} {'rise':>8s} {'settle':>8s} {'overshoot':>9s} {'ss error':>9s}")
    for r in rows:
        tr.write_line(f"{r['case']:44s} {r['target_rpm']:8.1f} {r['rise_s'] * 1e3:6.1f}ms {r['settle_s'] * 1e3:6.1f}ms "
                      f"{r['overshoot_pct']:8.3f}% {r['sse_pct']:8.4f}%")


@pytest.fixture(scope="session")
def target(request) -> str:
    return request.config.getoption("--target")


@pytest.fixture(scope="session")
def firmware_cache(tmp_path_factory) -> FirmwareCache:
    return FirmwareCache(tmp_path_factory.mktemp("hil-firmware"))


@pytest.fixture
def open_bench(request, target, firmware_cache):
    """open_bench(profile_name, method=None, perturb=None) -> Bench (closed after the test)."""
    opened: list[Bench] = []

    def _open(profile_name: str = "duy2008", method: str | None = None, perturb=None) -> Bench:
        prof = profile(profile_name)
        phash = prof.hash32
        selected = request.config.getoption("--profile")
        if is_generated(target) and selected is not None and profile_name != selected:
            pytest.skip(f"--profile {selected} selects that profile's tests")
        if is_generated(target):
            from picdrive_hil.twin import Twin
            method = method or "fuzzy-hinf"
            dp = design_path(profile_name, method)
            assert dp.exists(), f"the committed design {dp.name} is missing"
            design = load_design(dp, require_usable=True, profile=prof)
            fw_dir = firmware_cache.get(profile_name, method)
            kind = "twin"
            if target == "pil":
                tw = Twin(prof, fw_dir, perturb=perturb, hex_file=firmware_cache.hex(profile_name, method))
                kind = "pil"
                request.config.stash[_PIL].append((f"{profile_name} {method}", tw))
            else:
                tw = Twin(prof, fw_dir, perturb=perturb)
            srv = tw.serve(port=0, realtime=True)
            link = Link.open(srv.url, expect_profile_hash=phash)
            pert = ",".join(f"{k}x{v:g}" for k, v in tw.model.perturb.items())
            b = Bench(link, prof, design, method, f"{kind} {profile_name} {method}{' ' + pert if pert else ''}",
                      tw, srv, request.config.stash[_REPORT])
        elif target.startswith("pil:"):
            from picdrive_hil.twin import Twin
            board_profile = request.config.getoption("--profile")
            if profile_name != board_profile:
                pytest.skip(f"the HEX under test runs profile {board_profile!r}")
            tw = Twin(prof, perturb=perturb, hex_file=pil_hex_file(target),
                      enlarged_memory=request.config.getoption("--enlarged-memory"))
            srv = tw.serve(port=0, realtime=True)
            link = Link.open(srv.url, expect_profile_hash=phash)
            link.stop()
            try:
                m, design = match_design(link, prof)
            except BaseException:
                link.close()
                srv.stop()
                tw.close()
                raise
            if method is not None and method != m:
                link.close()
                srv.stop()
                tw.close()
                pytest.skip(f"the HEX runs the {m} design, not {method}")
            request.config.stash[_PIL].append((f"{profile_name} {m} ({pil_hex_file(target)})", tw))
            b = Bench(link, prof, design, m, f"pil {profile_name} {m}", tw, srv, request.config.stash[_REPORT])
        else:
            board_profile = request.config.getoption("--profile")
            if profile_name != board_profile:
                pytest.skip(f"the board under test runs profile {board_profile!r}")
            if perturb:
                pytest.skip("plant perturbations need the twin")
            link = Link.open(target, expect_profile_hash=phash)
            link.stop()                                    # start every test from a stopped board
            if link.status().fault != 0:
                link.fault_clear()
            m, design = match_design(link, prof)
            if method is not None and method != m:
                link.close()
                pytest.skip(f"the board runs the {m} design, not {method}")
            b = Bench(link, prof, design, m, f"board {profile_name} {m}", report=request.config.stash[_REPORT])
        opened.append(b)
        return b

    yield _open
    for b in opened:
        b.close()
