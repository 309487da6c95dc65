"""``picdrive twin``: start a virtual board and serve its UART.

    picdrive twin --profile duy2008 --firmware firmware_build/duy2008/ [--port N] [--pty]
    picdrive twin --profile duy2008 --hex firmware.hex [--firmware DIR] [--enlarged-memory]

prints ``socket://127.0.0.1:<port>`` (and the pty path) and runs in real time
until Ctrl-C (or ``--duration`` simulated seconds); ``picdrive console``, ``picdrive.link`` or any pyserial
program connect to it as to a COM port.
"""
from __future__ import annotations

import argparse
import sys

from picdrive.errors import PicdriveError


def register(sub) -> None:
    from picdrive.argtypes import finite_float, nonneg_float, port, positive_float, seed
    p = sub.add_parser(
        "twin", help="start the motor twin (virtual board) on a local serial endpoint",
        description="Run the generated firmware against a PIC18F4431 peripheral model and a BLDC plant, "
                    "in real time, behind socket://127.0.0.1:<port> (and a pty with --pty).")
    p.add_argument("--profile", required=True, help="profile .toml, or a bundled profile name")
    p.add_argument("--firmware", help="generated firmware folder (picdrive firmware -o ...): its C runs "
                                      "compiled for this machine (SIL); with --hex only its board.json is read")
    p.add_argument("--hex", help="processor twin: run this Intel HEX on the PIC18 simulator instead of the C "
                                 "(board wiring from --firmware's or the HEX folder's board.json)")
    p.add_argument("--enlarged-memory", action="store_true",
                   help="with --hex: simulate 128 KB of flash and 1.5 KB of RAM (picdrive.firmware.target's enlarged "
                        "measurement memory) for a HEX that does not fit the 18F4431; reports say so")
    p.add_argument("--port", type=port, default=0, help="TCP port to listen on (default: any free port)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--pty", action="store_true", help="also offer a pseudo-terminal path")
    p.add_argument("--perturb", action="append", default=[], metavar="KEY=FACTOR",
                   help="plant perturbation (repeatable): resistance, inductance, flux, inertia, friction, "
                        "bus_voltage; e.g. --perturb resistance=1.1 for R + 10 %%, or resistance=+u / -u for "
                        "the profile's design.resistance_uncertainty")
    p.add_argument("--load-torque", type=finite_float, default=None,
                   help="constant load torque, N m (default: none; the profile's control.load_torque_n_m "
                        "is the test step, applied by tests and demos)")
    p.add_argument("--load-file", help="load torque profile: CSV rows t_s,torque_n_m (times from start)")
    p.add_argument("--load-mode", choices=("passive", "active"), default="passive",
                   help="passive: load opposes motion and holds a standing rotor (default); "
                        "active: signed torque (2016 eq 5)")
    p.add_argument("--noise-rpm", type=nonneg_float, default=None,
                   help="speed-measurement noise, rpm std (default: profile sensors.speed_noise_rpm)")
    p.add_argument("--seed", type=seed, default=None,
                   help="noise seed (default 0, or the [as_built] seed of a drive from a tolerance study)")
    p.add_argument("--speed", type=positive_float, default=1.0,
                   help="simulated seconds per wall second (default 1: real time)")
    p.add_argument("--eeprom", help="EEPROM image file (256 bytes) to start from; saved back on exit")
    p.add_argument("--duration", type=positive_float, default=None, metavar="SECONDS",
                   help="stop after this many simulated seconds, as Ctrl-C would (the processor report and "
                        "the EEPROM image follow); default: run until Ctrl-C or SIGTERM")
    p.set_defaults(func=_cmd)


def _cmd(args: argparse.Namespace) -> int:
    from pathlib import Path

    from .plant import parse_perturb
    from .twin import Twin, TwinError

    if not (args.speed > 0):
        raise PicdriveError(f"--speed {args.speed}: must be > 0 (simulated seconds per wall second)")
    if not (0 <= args.port <= 65535):
        raise PicdriveError(f"--port {args.port}: expected 0..65535 (0 = any free port)")
    if args.noise_rpm is not None and not (args.noise_rpm >= 0):
        raise PicdriveError(f"--noise-rpm {args.noise_rpm}: must be >= 0")
    if args.hex is None and args.firmware is None:
        raise PicdriveError("give --firmware DIR (the generated C) or --hex FILE (the processor twin)")
    if args.enlarged_memory and args.hex is None:
        raise PicdriveError("--enlarged-memory applies to the processor twin only: add --hex FILE")
    from picdrive.profile import load_profile
    profile = load_profile(args.profile)
    perturb = parse_perturb(args.perturb, profile)
    eeprom = None
    ee_path = None
    if args.eeprom:
        from picdrive.outputs import file_output
        p = Path(args.eeprom)
        if p.is_file() and not p.is_symlink() and p.stat().st_size != 256:
            raise PicdriveError(f"--eeprom {p}: expected a 256-byte EEPROM image, found {p.stat().st_size} bytes; "
                                "give an image the twin saved, or a new file name")
        # the image is saved back on exit: checked now, under the output rule (docs/outputs.md)
        ee_path = file_output(args.eeprom, Path("eeprom.bin"), what="EEPROM image",
                              same_kind=lambda q: q.stat().st_size == 256)
        if ee_path.is_file():
            try:
                eeprom = ee_path.read_bytes()
            except OSError as e:
                raise PicdriveError(f"--eeprom {ee_path}: cannot read it ({e.strerror})") from None
    load = None
    if args.load_file:
        from .twin import read_load_file
        load = read_load_file(args.load_file)      # a bad file is refused before the twin is built
    noise_seed = args.seed if args.seed is not None else (profile.as_built_seed or 0)
    tw = Twin(profile, args.firmware, perturb=perturb, seed=noise_seed, load_mode=args.load_mode,
              speed_noise_rpm=args.noise_rpm, eeprom=eeprom, hex_file=args.hex,
              enlarged_memory=args.enlarged_memory)
    if load is not None:
        tw.set_load_profile(*load, relative=True)
    elif args.load_torque is not None:
        tw.set_load_torque(args.load_torque)
    srv = tw.serve(port=args.port, host=args.host, realtime=True, pty=args.pty, stop_after_s=args.duration)
    srv.speed = args.speed
    srv.log = lambda msg: print(f"picdrive twin: {msg}", file=sys.stderr, flush=True)
    pert = ", ".join(f"{k} x{v:g}" for k, v in perturb.items()) or "none"
    what = (f"HEX {args.hex} on the PIC18 simulator" + (" (ENLARGED memory: does not fit the 18F4431)"
                                                          if args.enlarged_memory else "")
            if args.hex else f"firmware {args.firmware}")
    print(f"picdrive twin: profile {tw.profile.name}, {what}, perturbation {pert}", file=sys.stderr)
    if tw.as_built is not None:
        load = profile.control.load_torque_n_m * tw.as_built.load_factor
        print(f"picdrive twin: as built (seed {tw.as_built.seed}): {tw.as_built.text()}; its load step "
              f"{load:.6g} N m (--load-torque {load:.6g})", file=sys.stderr)
    print(srv.url, flush=True)
    if srv.pty_path:
        print(srv.pty_path, flush=True)

    def _term(signum, frame):                   # SIGTERM stops like Ctrl-C (the EEPROM image is saved)
        raise KeyboardInterrupt
    import signal
    # installed before the line that says so: a SIGTERM sent on reading it is handled
    signal.signal(signal.SIGTERM, _term)
    try:
        print("picdrive twin: running in real time" + (f" x{args.speed:g}" if args.speed != 1 else "")
              + (f" for {args.duration:g} s simulated" if args.duration is not None else "")
              + "; Ctrl-C stops", file=sys.stderr, flush=True)
        srv.wait()
        if args.duration is not None:
            print(f"picdrive twin: stopped at t = {tw.t:.6g} s simulated (--duration {args.duration:g})",
                  file=sys.stderr, flush=True)
    except KeyboardInterrupt:
        pass
    except TwinError:
        raise
    finally:
        srv.stop()
        if tw.processor:
            for line in tw.processor_report().lines():
                print(f"picdrive twin: {line}", file=sys.stderr, flush=True)
        if ee_path is not None:
            from picdrive.outputs import write_bytes
            write_bytes(ee_path, tw.eeprom(), what="EEPROM image")
        tw.close()
    return 0
