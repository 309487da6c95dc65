"""The motor twin: firmware C + PIC18F4431 peripheral model + BLDC plant,
compiled into one shared library and driven from Python (architecture.md,
seam 5).

    from picdrive_hil.twin import Twin
    tw = Twin(profile, firmware_dir, perturb={"resistance": 1.1}, seed=0)
    tw.run(0.5)                         # simulated seconds, as fast as possible
    s = tw.state()                      # true plant state
    tw.set_load_torque(0.015)
    tw.inject("hall", code=0)
    tw.uart_write(b"...")               # host -> board at the baud rate
    tw.uart_read()                      # board -> host bytes off the wire
    srv = tw.serve(port=0, realtime=True)

The inner loop runs in C (``csrc/``); Python only sets it up and moves bytes.
Each Twin runs on a private copy of the library, so several twins (different
perturbations, different firmware) can live in one process; a closed Twin's copy
serves the next Twin of the same build, its data restored as loaded.
"""
from __future__ import annotations

import atexit
import ctypes as C
import math
import shutil
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from picdrive.board import FOSC_HZ

from . import build, cmodel, regs
from .build import TwinError
from .plant import PlantModel, plant_from_profile

PORTS = "ABCDE"
PS = 1_000_000_000_000
# the trace records' layout, as numpy reads them (built once: deriving it from the ctypes type costs ~1 ms)
_TRACE_DTYPE = np.dtype(cmodel.TraceRec)


@dataclass(frozen=True)
class BoardConfig:
    """How the board is wired: what the firmware's pin map says.

    Pins are ``(port letter, bit)``.  ``analog`` maps ADC channel numbers
    (AN0..AN8) to the signal on that pin: ``"current"`` (the current-sense
    amplifier) or ``"bus_voltage"`` (the bus divider).  ``current_signal``
    is what the current-sense amplifier shows: ``"link_on"`` (the DC-link
    current while the PWM'd high switch conducts, what a shunt in the bus
    return shows when sampled in the on-time), ``"bus_avg"`` (an RC-filtered
    shunt) or ``"peak"`` (largest phase current)."""

    hall_pins: tuple[tuple[str, int], ...] = (("C", 3), ("C", 4), ("C", 5))
    flta_pin: tuple[str, int] | None = ("C", 1)
    phase_pairs: tuple[int, int, int] = (0, 1, 2)
    analog: Mapping[int, str] = field(default_factory=dict)
    current_signal: str = "link_on"
    current_sense_offset_v: float = 0.0
    bus_sense_v_per_v: float = 0.0
    adc_vref_v: float = 5.0
    fosc_hz: float = float(FOSC_HZ)
    current_sense_v_per_a: float | None = None     # None: the profile's

    def pin(self, p) -> cmodel.Pin:
        if p is None:
            return cmodel.Pin(0xFF, 0)
        port, bit = p
        if port not in PORTS or not 0 <= bit <= 7:
            raise TwinError(f"board pin {p!r}: expected (port letter A..E, bit 0..7)")
        return cmodel.Pin(PORTS.index(port), bit)


_SIGNALS = {"current": cmodel.ASIG_CURRENT, "bus_voltage": cmodel.ASIG_BUS_VOLTAGE}
_CURSIG = {"link_on": cmodel.CURSIG_LINK_ON, "bus_avg": cmodel.CURSIG_BUS_AVG, "peak": cmodel.CURSIG_PEAK}
_INJECT = {"hall": cmodel.INJ_HALL, "overcurrent": cmodel.INJ_OVERCURRENT, "lock_rotor": cmodel.INJ_LOCK_ROTOR,
           "encoder": cmodel.INJ_ENCODER, "bus_voltage": cmodel.INJ_BUS_VOLTAGE}


def shim_dir() -> Path:
    """Folder holding the firmware generator's host ``xc.h`` (for the twin's
    test firmware; generated firmware folders carry their own in host/)."""
    d = build.cache_dir() / "shim"
    regs.write_shim(d)
    return d


def gen_dir() -> Path:
    d = build.cache_dir() / "gen"
    regs.write_header(d)
    return d


def board_from_json(path: str | Path) -> BoardConfig:
    """The board wiring a generated firmware folder declares (``board.json``,
    schema ``picdrive.board/1``, written by ``picdrive firmware``)."""
    import json
    try:
        d = json.loads(Path(path).read_text())
    except (OSError, ValueError) as e:
        raise TwinError(f"cannot read the board description {path}: {e}") from None
    if d.get("schema") != "picdrive.board/1":
        raise TwinError(f"{path}: schema {d.get('schema')!r}, this twin reads 'picdrive.board/1'")

    def pin(x):
        if x is None:
            return None
        return (PORTS[int(x["port"])], int(x["bit"]))
    analog = {}
    for k, v in (d.get("analog") or {}).items():
        ch = int(str(k).upper().removeprefix("AN"))
        sig = {"bus_current": "current", "current": "current", "bus_voltage": "bus_voltage"}.get(v)
        if sig is None:
            raise TwinError(f"{path}: analog {k} = {v!r}: the twin knows bus_current and bus_voltage")
        analog[ch] = sig
    return BoardConfig(
        hall_pins=tuple(pin(x) for x in d["hall_pins"]),
        flta_pin=pin(d.get("flta_pin")),
        phase_pairs=tuple(int(x) for x in d.get("phase_pairs", (0, 1, 2))),
        analog=analog,
        current_signal=d.get("current_signal", "link_on"),
        current_sense_offset_v=float(d.get("current_sense_offset_v", 0.0)),
        bus_sense_v_per_v=float(d.get("bus_sense_v_per_v", 0.0)),
        adc_vref_v=float(d.get("adc_vref_v", 5.0)),
        fosc_hz=float(d.get("fosc_hz", FOSC_HZ)),
        current_sense_v_per_a=d.get("current_sense_v_per_a"),
    )


def firmware_group(firmware_dir: str | Path) -> build.Group:
    """Sources, include folders and flags of a generated firmware folder
    (``picdrive.firmware.codegen.host_build``), compiled unchanged."""
    fw = Path(firmware_dir)
    if not fw.is_dir():
        what = "is a file, not a folder" if fw.exists() else "does not exist"
        raise TwinError(f"firmware folder {fw} {what}: give the folder 'picdrive firmware' wrote (generate it "
                        "with 'picdrive firmware --profile P --design D -o <folder>')")
    from picdrive.firmware import codegen
    hb = codegen.host_build(fw)
    # their flags, optimised; warnings that only optimisation reveals must not stop the twin
    flags = tuple(hb["cflags"]) + ("-O2", "-Wno-error")
    return build.Group(tuple(Path(s) for s in hb["sources"]), tuple(Path(d) for d in hb["include_dirs"]), flags)


def firmware_profile_hash(firmware_dir: str | Path) -> int | None:
    """The 32-bit profile hash the firmware was generated from (:attr:`picdrive.profile.Profile.hash32`),
    if its link_fw.h says."""
    import re
    f = Path(firmware_dir) / "link_fw.h"
    if not f.exists():
        return None
    m = re.search(r"#define\s+LINK_PROFILE_HASH\s+0x([0-9A-Fa-f]{8})", f.read_text())
    return int(m.group(1), 16) if m else None


class Twin:
    """A virtual board: firmware + peripherals + plant (see module docstring).

    Parameters
    ----------
    profile : picdrive.profile.Profile or str
        The drive (or a bundled profile's name): the plant's constants, SI units.
    firmware_dir : str or pathlib.Path, optional
        A firmware folder written by ``picdrive firmware`` (its C runs unchanged on the host).
    firmware : picdrive_hil.build.Group, optional
        Already-gathered C sources instead of a folder.
    board : BoardConfig, optional
        The board wiring (default: the folder's ``board.json``).
    perturb : mapping or sequence of str, optional
        Multiplicative plant perturbations (``{"resistance": 1.1}``) or ``"resistance=+u"``
        (the profile's ``design.resistance_uncertainty``).
    seed : int
        Seed of the twin's random numbers (the speed-sensor noise).
    load_mode : str
        ``"passive"`` (the load opposes motion, holds a standing rotor) or ``"active"`` (a
        signed torque, 2016 eq 5).
    speed_noise_rpm : float, optional
        Speed-sensor noise, rpm (default: the profile's ``sensors.speed_noise_rpm``).
    eeprom : bytes, optional
        The EEPROM's content at power-on (default: erased, or a HEX's EEPROM data).
    diode_drop_v : float
        Forward drop of the bridge's freewheeling diodes, V (0 .. 5).
    power_on : bool
        Power the board on now (else call :meth:`power_on`).
    hex_file : str or pathlib.Path, optional
        Processor-in-the-loop: run this HEX on the PIC18 core instead of the C.
    enlarged_memory : bool
        With ``hex_file``: simulate 128 KB flash / 1.5 KB RAM (a HEX that does not fit the 18F4431).
    hall_error_deg : float
        Electrical degrees added to the motor's hall placement (the firmware's table stays the
        profile's).

    A profile with an ``[as_built]`` section (one drive of a tolerance study,
    :mod:`picdrive.tolerances`) runs that drive: its deviations, drawn from its seed, multiply
    ``perturb`` and add to ``hall_error_deg`` (:attr:`as_built`).
    """

    def __init__(self, profile, firmware_dir: str | Path | None = None, *,
                 firmware: build.Group | None = None,
                 board: BoardConfig | None = None,
                 perturb: Mapping[str, float] | Sequence[str] | None = None,
                 seed: int = 0, load_mode: str = "passive",
                 speed_noise_rpm: float | None = None,
                 eeprom: bytes | None = None, diode_drop_v: float = 0.0,
                 power_on: bool = True,
                 hex_file: str | Path | None = None, enlarged_memory: bool = False,
                 hall_error_deg: float = 0.0):
        from picdrive.profile import Profile, load_profile
        self.profile = profile if isinstance(profile, Profile) else load_profile(profile)
        #: the drive off the line the profile's [as_built] section names (picdrive.tolerances.Deviation), or None
        self.as_built = None
        if self.profile.as_built_seed is not None:
            from picdrive.tolerances import draw
            from .plant import parse_perturb
            self.as_built = draw(self.profile.tolerances, self.profile.as_built_seed)
            merged = dict(parse_perturb(perturb, self.profile))
            for k, f in self.as_built.plant_perturb().items():
                merged[k] = merged.get(k, 1.0) * f
            perturb = merged
            hall_error_deg = hall_error_deg + self.as_built.hall_error_deg
        self.firmware_dir = Path(firmware_dir) if firmware_dir is not None else None
        self.hex_file = Path(hex_file) if hex_file is not None else None
        self.enlarged_memory = bool(enlarged_memory)
        self._pil_img = None
        if self.hex_file is not None:
            # processor-in-the-loop: the HEX runs on the PIC18 core (pil.py); the board wiring
            # from the firmware folder's board.json (given, or beside the HEX)
            from . import pil
            if firmware is not None:
                raise TwinError("give either hex_file (processor twin) or firmware (C sources), not both")
            self._pil_img = pil.load_image(self.hex_file, enlarged=self.enlarged_memory)
            if self.firmware_dir is not None:
                self._check_profile_hash(self.firmware_dir)
            bj = (self.firmware_dir or self.hex_file.parent) / "board.json"
            if board is None:
                if not bj.exists():
                    raise TwinError(f"no board.json {'in ' + str(self.firmware_dir) if self.firmware_dir else 'beside ' + str(self.hex_file)}: "
                                    "the processor twin needs the board's wiring (hall pins, analog channels, Fosc); "
                                    "give the generated firmware folder (--firmware DIR) or put its board.json beside the HEX")
                board = board_from_json(bj)
            self.board = board or BoardConfig()
            self.pil_notes = pil.check_config(self._pil_img, self.board, str(self.hex_file))
            lib_path = pil.library(gen_dir(), self.enlarged_memory)
        elif firmware is None:
            if self.firmware_dir is None:
                raise TwinError("give the firmware folder (generated by 'picdrive firmware')")
            firmware = firmware_group(self.firmware_dir)
            self._check_profile_hash(self.firmware_dir)
            if board is None and (self.firmware_dir / "board.json").exists():
                board = board_from_json(self.firmware_dir / "board.json")
        if self.hex_file is None:
            self.board = board or BoardConfig()
            lib_path = build.build_library([firmware, build.twin_group(gen_dir())])
        self.model: PlantModel = plant_from_profile(self.profile, perturb, load_mode=load_mode,
                                                    diode_drop_v=diode_drop_v, hall_error_deg=hall_error_deg)
        self._loaded = _acquire(lib_path, self._pil_img is not None)
        self._copy = self._loaded.copy
        self._lib = self._loaded.lib
        self._lock = threading.RLock()
        self._rx_buf = C.create_string_buffer(65536)
        noise_rpm = self.profile.sensors.speed_noise_rpm if speed_noise_rpm is None else speed_noise_rpm
        cfg = self._config(seed, noise_rpm)
        if self._lib.twin_init(C.byref(cfg)) != 0:
            raise TwinError("twin_init refused the configuration (ABI mismatch)")
        if self._pil_img is not None:
            img = self._pil_img
            if self._lib.pil_load(bytes(img.flash), len(img.flash), bytes(img.config)) != 0:
                raise TwinError(f"{self.hex_file}: {len(img.flash)} B of program memory, the processor twin "
                                f"was built with {self._lib.pil_flash_bytes()} B")
            if eeprom is None and img.eeprom != bytearray(b"\xff" * len(img.eeprom)):
                eeprom = bytes(img.eeprom)          # the HEX's EEPROM data, as a programmer writes it
        if eeprom is not None:
            self.eeprom_write_all(eeprom)
        self._load = (np.array([0.0]), np.array([0.0]))
        if power_on:
            self.power_on()

    # -- setup --------------------------------------------------------------
    def _check_profile_hash(self, folder: Path) -> None:
        fh = firmware_profile_hash(folder)
        if fh is not None and fh != self.profile.hash32:
            raise TwinError(
                f"firmware {folder} was generated from another profile (hash {fh:08x}, "
                f"profile {self.profile.name!r} is {self.profile.hash32:08x}): regenerate it with "
                f"'picdrive firmware --profile {self.profile.name} ...' or give its own profile")

    def _config(self, seed: int, noise_rpm: float) -> cmodel.TwinConfig:
        b, p = self.board, self.profile
        cfg = cmodel.TwinConfig()
        cfg.abi_version = cmodel.ABI_VERSION
        cfg.plant = self.model.to_c()
        cfg.fosc_hz = b.fosc_hz
        if len(b.hall_pins) != 3:
            raise TwinError("board.hall_pins must list three pins (hall A, B, C)")
        for k, pn in enumerate(b.hall_pins):
            cfg.hall_pin[k] = b.pin(pn)
        cfg.flta_pin = b.pin(b.flta_pin)
        for k, pair in enumerate(b.phase_pairs):
            if pair not in (0, 1, 2, 3):
                raise TwinError(f"board.phase_pairs[{k}] = {pair!r}: a PWM output pair 0..3")
            cfg.phase_pair[k] = pair
        for ch, sig in b.analog.items():
            if not 0 <= int(ch) <= 8 or sig not in _SIGNALS:
                raise TwinError(f"board.analog {ch!r}: {sig!r}: channels 0..8, signals {sorted(_SIGNALS)}")
            cfg.analog_signal[int(ch)] = _SIGNALS[sig]
        if b.current_signal not in _CURSIG:
            raise TwinError(f"board.current_signal {b.current_signal!r}: one of {sorted(_CURSIG)}")
        cfg.current_signal = _CURSIG[b.current_signal]
        cfg.current_sense_v_per_a = (p.inverter.current_sense_v_per_a if b.current_sense_v_per_a is None
                                     else float(b.current_sense_v_per_a))
        cfg.current_sense_offset_v = b.current_sense_offset_v
        cfg.bus_sense_v_per_v = b.bus_sense_v_per_v
        cfg.adc_vref_v = b.adc_vref_v
        cfg.overcurrent_trip_a = p.inverter.overcurrent_trip_a
        cfg.host_baud = float(p.uart.baud)
        cfg.max_step_s = 50e-6
        cfg.speed_noise_rad_s = noise_rpm * 2 * math.pi / 60.0
        cfg.noise_sample_s = 1.0 / p.control.speed_loop_hz
        cfg.seed = (int(seed) * 0x9E3779B97F4A7C15 + 1) & 0xFFFFFFFFFFFFFFFF
        cfg.eeprom_write_s = 4e-3
        return cfg

    def power_on(self) -> None:
        """Chip reset and ``fw_init()`` (the motor keeps turning)."""
        with self._lock:
            self._check(self._lib.twin_power_on())

    def close(self) -> None:
        """End this twin: its loaded library goes back to the process's pool, where the next twin of
        the same build takes it, its data as loaded (:func:`_acquire`); the twin's methods then
        raise TwinError."""
        ld = getattr(self, "_loaded", None)
        if ld is not None:
            self._loaded = None
            self._copy = None
            self._lib = _ClosedLibrary()
            _release(ld)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass

    # -- time ---------------------------------------------------------------
    @property
    def processor(self) -> bool:
        """True for the processor twin (the HEX on the PIC18 core)."""
        return self._pil_img is not None

    def pil_stats(self):
        """The processor twin's raw counters (pil.PilStats)."""
        from . import pil
        if not self.processor:
            raise TwinError("pil_stats(): this twin runs the firmware's C (SIL), not a HEX")
        st = pil.PilStats()
        with self._lock:
            self._lib.pil_get_stats(C.byref(st))
        return st

    def processor_report(self):
        """What only the processor twin measures (pil.Report): the speed-loop interrupt's
        duration (min/mean/max), missed periods, stack high-water marks, RAM and flash used."""
        from . import pil
        return pil.report(self.pil_stats(), self._pil_img, self.board.fosc_hz, self.enlarged_memory,
                          float(self.profile.control.speed_loop_hz))

    def patch_flash(self, addr: int, data: bytes) -> None:
        """Change the processor twin's program memory under the running program (fault injection:
        a hang at a chosen instant); the next fetch of those words runs the new instructions."""
        if not self.processor:
            raise TwinError("patch_flash(): only the processor twin runs a program from flash")
        data = bytes(data)
        with self._lock:
            if self._lib.pil_patch_flash(int(addr), data, len(data)) != 0:
                raise TwinError(f"patch_flash(): 0x{addr:X} + {len(data)} B is outside the program memory")

    def peek(self, addr: int) -> int:
        """A data-memory byte of the processor twin (GPR or SFR), without side effects."""
        if not self.processor:
            raise TwinError("peek(): only the processor twin has a data memory")
        with self._lock:
            return self._lib.pil_peek(int(addr) & 0xFFF)

    def _check(self, err: int) -> None:
        if err:
            if err & cmodel.TWIN_ERR_CPU and self.processor:
                from . import pil
                raise TwinError(pil.cpu_stop_message(self.pil_stats(), self._pil_img, str(self.hex_file)))
            msgs = [m for bit, m in cmodel.TWIN_ERRORS.items() if err & bit]
            raise TwinError("twin stopped: " + "; ".join(msgs or [f"error bits 0x{err:x}"]))

    @property
    def t(self) -> float:
        """Simulated time, s."""
        s = cmodel.TwinState()
        with self._lock:
            self._lib.twin_get_state(C.byref(s))
        return s.now_ps / PS

    def run(self, seconds: float) -> None:
        """Advance the simulation by ``seconds`` (free-running)."""
        if not (seconds >= 0 and math.isfinite(seconds)):
            raise ValueError(f"run({seconds!r}): seconds must be finite and >= 0")
        with self._lock:
            s = cmodel.TwinState()
            self._lib.twin_get_state(C.byref(s))
            self._check(self._lib.twin_run_until(s.now_ps + int(round(seconds * PS))))

    def run_until(self, t_s: float) -> None:
        with self._lock:
            self._check(self._lib.twin_run_until(int(round(t_s * PS))))

    # -- plant --------------------------------------------------------------
    def state(self) -> dict:
        """True plant and board state (SI units)."""
        s = cmodel.TwinState()
        with self._lock:
            self._lib.twin_get_state(C.byref(s))
        ps = s.plant
        return {
            "t_s": s.now_ps / PS,
            "speed_rad_s": ps.w_rad_s,
            "speed_rpm": ps.w_rad_s * 60.0 / (2 * math.pi),
            "angle_rad": ps.theta_rad,
            "i_abc_a": tuple(ps.i_a),
            "i_bus_a": ps.i_bus_a,
            "i_peak_a": ps.i_peak_a,
            "v_term_v": tuple(ps.v_term),
            "torque_e_n_m": ps.torque_e_n_m,
            "torque_load_n_m": ps.torque_load_n_m,
            "energy_j": ps.energy_j,
            "bus_voltage_v": ps.v_bus_v,
            "i_brake_a": ps.i_brake_a,
            "hall": s.hall_code,
            "hall_true": s.hall_true,
            "encoder_count": s.enc_count,
            "legs": tuple((lg.f_hi, lg.f_lo) for lg in s.leg),
            "gate_hi": tuple(s.gate_hi),
            "gate_lo": tuple(s.gate_lo),
            "outputs_active": bool(s.pwm_outputs_active),
            "outputs_off_t_s": None if s.outputs_off_ps < 0 else s.outputs_off_ps / PS,
            "flta_asserted": bool(s.flta_asserted),
            "pwm_fault_latched": bool(s.pwm_fault_latched),
            "shoot_through": s.shoot_through,
            "duty": tuple(s.duty),
            "pwm_period_s": s.pwm_period_s,
            "dead_time_s": s.dead_time_s,
            "board_baud": s.board_baud,
            "uart_rx_overruns": s.uart_rx_overruns,
            "uart_rx_framing_errors": s.uart_rx_framing,
            "isr_high_calls": s.isr_high_calls,
            "isr_low_calls": s.isr_low_calls,
            "poll_calls": s.poll_calls,
            "eeprom_writes": s.eeprom_writes,
            "eeprom_rejected": s.eeprom_rejected,
            "rotor_locked": bool(ps.locked),
        }

    def set_plant_state(self, speed_rad_s: float, angle_rad: float | None = None) -> None:
        """Put the rotor at a speed (and angle) — e.g. a load spinning it."""
        with self._lock:
            th = self.state()["angle_rad"] if angle_rad is None else angle_rad
            self._lib.twin_set_plant_state(float(speed_rad_s), float(th))

    def set_load_torque(self, torque_n_m: float) -> None:
        """A load-torque step, applied from now on.

        Parameters
        ----------
        torque_n_m : float
            The load torque, N m (:class:`Twin`'s ``load_mode`` says how it acts).
        """
        self.set_load_profile([0.0], [torque_n_m])

    def set_load_profile(self, t_s: Sequence[float], torque_n_m: Sequence[float], *,
                         relative: bool = False) -> None:
        """Piecewise-linear load torque through (t, T) points (absolute simulated
        time, or relative to now); constant before the first and after the last."""
        t = np.asarray(t_s, dtype=float).ravel()
        v = np.asarray(torque_n_m, dtype=float).ravel()
        if t.size != v.size or t.size == 0:
            raise TwinError("load profile: t and torque need the same, nonzero, number of points")
        if t.size > 1024:
            raise TwinError(f"load profile has {t.size} points; the twin takes up to 1024")
        if np.any(np.diff(t) < 0) or not np.all(np.isfinite(t)) or not np.all(np.isfinite(v)):
            raise TwinError("load profile: times must be increasing and all values finite")
        if relative:
            t = t + self.t
        elif t.size == 1:
            t = np.array([self.t])
        tc = (C.c_double * t.size)(*t)
        vc = (C.c_double * v.size)(*v)
        with self._lock:
            self._lib.twin_set_load_table(tc, vc, t.size)
        self._load = (t, v)

    def load_profile_file(self, path: str | Path, *, relative: bool = True) -> None:
        """Load torque from a CSV file of ``t_s,torque_n_m`` rows (:func:`read_load_file`)."""
        t, v = read_load_file(path)
        self.set_load_profile(t, v, relative=relative)

    # -- faults ---------------------------------------------------------------
    def inject(self, kind: str, **kw) -> None:
        """Inject a fault.

        * ``hall``: ``code=0..7`` forces the hall pins (``code=None`` releases);
          ``duration_s`` optional.
        * ``overcurrent``: the comparator asserts FLTA for ``duration_s`` (1 ms).
        * ``lock_rotor``: ``locked=True/False``.
        * ``encoder``: ``connected=False`` freezes the encoder, True reconnects.
        * ``bus_voltage``: ``volts=...``.
        """
        if kind not in _INJECT:
            raise TwinError(f"unknown injection {kind!r}; known: {', '.join(_INJECT)}")
        dur = float(kw.pop("duration_s", 0.0))
        if kind == "hall":
            code = kw.pop("code")
            value = -1.0 if code is None else float(int(code) & 7)
        elif kind == "overcurrent":
            value = 1.0
        elif kind == "lock_rotor":
            value = 1.0 if kw.pop("locked", True) else 0.0
        elif kind == "encoder":
            value = 1.0 if kw.pop("connected", False) else 0.0
        else:
            value = float(kw.pop("volts"))
        if kw:
            raise TwinError(f"inject({kind!r}): unknown argument(s) {sorted(kw)}")
        with self._lock:
            self._lib.twin_inject(_INJECT[kind], value, dur)

    # -- UART -----------------------------------------------------------------
    def uart_write(self, data: bytes) -> int:
        """Queue host -> board bytes; they arrive one frame time apart at the host's baud.
        Returns how many were queued: fewer than given when the 64 KiB queue is full (the caller
        keeps the rest and offers it again later)."""
        data = bytes(data)
        with self._lock:
            return self._lib.twin_uart_host_write(data, len(data))

    def uart_read(self, max_bytes: int = 65536) -> bytes:
        """Board -> host bytes that have left the wire."""
        with self._lock:
            # one buffer for the twin's life (the real-time server calls this every chunk)
            buf = self._rx_buf if max_bytes <= len(self._rx_buf) else C.create_string_buffer(max_bytes)
            n = self._lib.twin_uart_host_read(buf, min(max_bytes, len(buf)))
            return C.string_at(buf, n)

    def uart_flush_input(self) -> int:
        """Drop the host -> board bytes the board has not started to receive (a byte already on
        the wire completes); returns how many were dropped."""
        with self._lock:
            return self._lib.twin_uart_host_flush()

    def uart_pending(self) -> int:
        """Host bytes not yet received by the board."""
        with self._lock:
            return self._lib.twin_uart_host_pending()

    # -- EEPROM ---------------------------------------------------------------
    def eeprom(self) -> bytes:
        buf = C.create_string_buffer(256)
        with self._lock:
            self._lib.twin_eeprom_get(buf)
        return buf.raw

    def eeprom_write_all(self, data: bytes) -> None:
        data = bytes(data)
        if len(data) != 256:
            raise TwinError(f"EEPROM image must be 256 bytes, got {len(data)}")
        with self._lock:
            self._lib.twin_eeprom_set(data)

    def sfr(self, name: str) -> int:
        """Current value of an SFR by its p18f4431.inc name (for tests)."""
        r = regs.registers()
        if name not in r:
            raise TwinError(f"no SFR named {name!r} in p18f4431.inc")
        with self._lock:
            return self._lib.twin_sfr_get(r[name] - 0xF00)

    # -- traces ---------------------------------------------------------------
    def record(self, seconds: float, period_s: float = 1e-3) -> dict[str, np.ndarray]:
        """Run ``seconds`` and return the plant sampled every ``period_s``.

        Parameters
        ----------
        seconds : float
            Simulated time to run, s.
        period_s : float
            Sample period, s (exact, in simulated time).

        Returns
        -------
        dict of numpy.ndarray
            ``t_s`` (s), ``w_rad_s`` (rad/s), ``i_a``/``i_b``/``i_c``/``i_bus_a`` (A),
            ``duty_max``, ``fault``... (:data:`picdrive_hil.cmodel.TRACE_FIELDS`).
        """
        n = int(math.floor(seconds / period_s + 1e-9)) + 1
        buf = (cmodel.TraceRec * n)()
        with self._lock:
            self._lib.twin_trace_start(period_s, buf, n)
            try:
                self.run(seconds)
            finally:
                cnt = self._lib.twin_trace_count()
                self._lib.twin_trace_start(0.0, None, 0)
        arr = np.frombuffer(buf, dtype=_TRACE_DTYPE, count=cnt)
        return {name: np.array(arr[name]) for name in cmodel.TRACE_FIELDS}

    # -- endpoint -------------------------------------------------------------
    def serve(self, port: int = 0, *, realtime: bool = True, pty: bool = False,
              host: str = "127.0.0.1", stop_after_s: float | None = None):
        """Start the serial endpoint in a background thread: socket://host:port
        (and a pty path with pty=True); with ``stop_after_s`` it stops serving once that much
        simulated time (s) has run.  Returns the running TwinServer."""
        from .endpoint import TwinServer
        srv = TwinServer(self, port=port, host=host, realtime=realtime, pty=pty, stop_after_s=stop_after_s)
        srv.start()
        return srv


@dataclass
class _Loaded:
    """A private copy of a built library, loaded and bound, with its writable data as it was loaded."""

    path: str                  # the built library it is a copy of
    copy: Path                 # the copy's file (removed when the process ends)
    lib: C.CDLL
    data_at: int               # address and content of the library's writable data right after the load
    pristine: bytes


# per process: the loaded libraries no twin uses, by the built library's path.  Loading a private
# copy costs a few milliseconds and stays mapped until the process ends (ctypes never unloads):
# a process that runs thousands of twins one after another (a tolerance study's worker) loads one
# copy and restores its data for each twin instead
_POOL: dict[str, list[_Loaded]] = {}
_POOL_LOCK = threading.Lock()
#: the most idle loaded copies of one library a process keeps (more are dropped, still mapped)
POOL_KEEP = 4


class _ClosedLibrary:
    """The library of a closed twin: every call says so."""

    def __getattr__(self, name):
        raise TwinError("this twin is closed (Twin.close()); start a new Twin")


def _acquire(lib_path: Path, processor: bool) -> _Loaded:
    """A loaded copy of ``lib_path`` no other twin uses, its writable data exactly as a fresh load
    leaves it: an idle one from the pool with that data written back, or a new private copy."""
    key = str(lib_path)
    with _POOL_LOCK:
        free = _POOL.get(key)
        ld = free.pop() if free else None
    if ld is not None:
        C.memmove(ld.data_at, ld.pristine, len(ld.pristine))
        return ld
    copy = build.private_copy(lib_path)
    atexit.register(shutil.rmtree, copy.parent, True)
    lib = cmodel.bind_twin(C.CDLL(str(copy)))
    if processor:
        from . import pil
        pil.bind(lib)
        if lib.pil_sizeof() != C.sizeof(pil.PilStats):
            raise TwinError(f"ctypes mirror PilStats ({C.sizeof(pil.PilStats)} B) differs from the C struct "
                            f"({lib.pil_sizeof()} B)")
    for i, st in enumerate((cmodel.TwinConfig, cmodel.TwinState, cmodel.TraceRec,
                            cmodel.PlantParams, cmodel.PlantState, cmodel.Leg)):
        n = lib.twin_sizeof(i)
        if n != C.sizeof(st):
            raise TwinError(f"ctypes mirror {st.__name__} ({C.sizeof(st)} B) differs from the C struct ({n} B)")
    region = (C.c_uint64 * 2)()
    if lib.twin_data_region(region) != 0:
        # a layout region.c does not know: this copy serves its twin only (no restore, no reuse)
        return _Loaded(key, copy, lib, 0, b"")
    return _Loaded(key, copy, lib, int(region[0]), C.string_at(int(region[0]), int(region[1])))


def _release(ld: _Loaded) -> None:
    """A closed twin's library back to the pool (its data is restored when it is taken again)."""
    if not ld.pristine:
        return
    with _POOL_LOCK:
        free = _POOL.setdefault(ld.path, [])
        if len(free) < POOL_KEEP:
            free.append(ld)


def read_load_file(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """The (t_s, torque_n_m) points of a load-torque CSV file (UTF-8 text; a header line and
    ``#`` comments allowed).  Any other row is refused, naming its line."""
    try:
        text = Path(path).read_bytes().decode("utf-8")
    except OSError as e:
        raise TwinError(f"cannot read load profile {path}: {e.strerror or e}") from None
    except UnicodeDecodeError as e:
        raise TwinError(f"load profile {path}: byte {e.start} is not UTF-8; expected a CSV text file of "
                        "'t_s,torque_n_m' rows") from None
    rows, first = [], True
    for n, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        cells = [c.strip() for c in line.split(",")]
        try:
            if len(cells) != 2:
                raise ValueError
            rows.append((float(cells[0]), float(cells[1])))
            first = False
        except ValueError:
            if first:
                first = False
                continue                                  # the header line
            raise TwinError(f"load profile {path}: line {n} {line[:40]!r} is not a row 't_s,torque_n_m' "
                            "of two numbers") from None
    if not rows:
        raise TwinError(f"load profile {path}: expected rows of 't_s,torque_n_m'")
    data = np.array(rows, dtype=float)
    return data[:, 0], data[:, 1]
