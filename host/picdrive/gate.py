"""``picdrive design``: a design method, then the gate a design passes before it is saved as usable.

A design method (:mod:`picdrive.design`) designs on the models and verifies
its law with :func:`picdrive.design.verify.verify_design`.  Two of the checks
need the drive as built, which the design layer does not import: the
firmware's speed measurement (the hall-edge period in the Timer5 ticks of the
firmware's own fixed-point plan) and the torque the bridge delivers in the
twin's three-phase plant (commutation transfers included).  This module, the
layer above design, firmware and the twin, supplies them (:class:`BuiltDrive`),
so a design is called verified only after it holds its step target in the
twin's plant and passes the simulation with the firmware's measurement.
:func:`twin_run` runs the verification's step and load step on the twin
itself (the firmware generated from the design, in the loop), for the tests
and bench/motors.py that check the model against it.

The command only dispatches, prints the summary and writes the file:

* a verified design goes to ``<profile-stem>.<method>.design.json`` next to
  the profile, or to ``-o``;
* a failed design is never written there: it goes to
  ``<...>.design.failed.json`` for inspection, an existing good design is left
  untouched, and the command exits 1.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from .analysis.steptest import RPM, sim_plan
from .design.dispatch import METHOD_MODULES
from .errors import PicdriveError
from .result import SCHEMA_ID, DesignResult, default_design_path, save_design

__all__ = ["BuiltDrive", "speed_measurement", "bridge_hold_torque", "three_phase_plant", "twin_run", "twin_scenario", "run_design", "output_path",
           "summary_lines", "register"]


class BuiltDrive:
    """The drive as built, for :func:`picdrive.design.verify.verify_design`: the firmware's speed
    measurement (:func:`speed_measurement`) and the bridge's torque in the twin's plant
    (:func:`bridge_hold_torque`)."""

    def speed_measurement(self, profile, law) -> dict:
        return speed_measurement(profile, law)

    def hold_torque(self, profile, rpm: float, *, r_factor: float = 1.0) -> tuple[float, float]:
        return bridge_hold_torque(profile, rpm, r_factor=r_factor)

    def three_phase_plant(self, profile, r_factor: float = 1.0):
        return three_phase_plant(profile, r_factor)


def three_phase_plant(profile, r_factor: float = 1.0):
    """The motor twin's three-phase plant of a profile (``picdrive_hil.plant.CPlant``), at rest, R x
    ``r_factor``, the load applied as a signed torque (:func:`picdrive.models.simulate.simulate_six_step`
    applies the passive rule): the verification simulates the winding the twin and the motor have,
    with the current transfer at every commutation, not only its DC equivalent."""
    from picdrive_hil.plant import CPlant, plant_from_profile
    return CPlant(plant_from_profile(profile, {"resistance": r_factor} if r_factor != 1.0 else None,
                                     load_mode="active"))


def speed_measurement(profile, law) -> dict:
    """The firmware's speed measurement as :func:`picdrive.models.simulate.simulate_six_step` takes it:
    ``{"measurement": "firmware"}`` (encoder M/T) or ``{"measurement": "hall", "hall": meter}``
    (hall-edge period, :func:`picdrive.models.simulate.hall_speed_meter` of the firmware's own
    fixed-point plan).  Raises the plan's :class:`picdrive.errors.PicdriveError` when no firmware
    can be built for the law."""
    if profile.sensors.speed_source != "hall":
        return {"measurement": "firmware"}
    from .firmware.fixedpoint import plan_fixed_point
    from .firmware.pcpwm import plan_pwm
    from .models.simulate import hall_speed_meter
    return {"measurement": "hall", "hall": hall_speed_meter(profile, plan_fixed_point(profile, law, plan_pwm(profile)))}


def bridge_hold_torque(profile, rpm: float, *, r_factor: float = 1.0) -> tuple[float, float]:
    """Mean electromagnetic torque the bridge delivers at a held speed, and the torque the load and
    friction take there, N m: ``(delivered, needed)``.

    The three-phase plant of the motor twin (``picdrive_hil.plant.CPlant``: per-phase currents,
    the floating phase and its diode, the commutation transfers the DC equivalent does not have)
    at ``rpm`` held constant, driven by the firmware's hall table (high-side PWM, low side on) at
    the largest duty the firmware applies there: bus x max duty, or less where the current window
    ``Kb w + R_line I_lim`` is lower; R x ``r_factor``.  Averaged over whole hall sectors after the
    currents have settled.  A drive whose sector is short against L/R loses torque at each
    commutation; if ``delivered < needed`` the target cannot be held under the load, whatever the
    law."""
    from picdrive_hil.plant import CPlant, plant_from_profile

    from .commutation import hall_table
    m, inv, se = profile.motor, profile.inverter, profile.sensors
    w = rpm * RPM
    cp = CPlant(plant_from_profile(profile))
    cp.params.inertia_kg_m2 = 1e9 * max(m.inertia_kg_m2, 1e-9)     # the speed is held
    cp.params.r_phase_ohm *= r_factor
    cp.state.w_rad_s = w
    u = min(inv.bus_voltage_v * profile.max_duty(), m.kb_v_s_per_rad * w + m.r_line_ohm * inv.current_limit_a)
    d = max(0.0, min(1.0, u / inv.bus_voltage_v))
    tab = hall_table(se.hall_spacing_deg, se.hall_offset_deg, m.back_emf_shape).forward
    h = 1.0 / inv.pwm_frequency_hz
    sector = math.pi / 3 / (m.pole_pairs * max(w, 1e-9))
    tau = m.l_line_h / (m.r_line_ohm * r_factor)
    t_warm = max(10 * tau, 2 * sector)
    n_sect = max(12, math.ceil(0.02 / sector))
    legs_off = [(0.0, 0.0)] * 3

    def legs_for(code):
        st = tab[code]
        if st is None:
            return legs_off
        lg = [(0.0, 0.0)] * 3
        lg[st[0]] = (d, 0.0)
        lg[st[1]] = (0.0, 1.0)
        return lg
    t = 0.0
    while t < t_warm:
        cp.step(legs_for(cp.hall_code()), 0.0, h)
        t += h
    t_end = t + n_sect * sector
    acc = tt = 0.0
    while tt < t_end - t:
        hh = min(h, t_end - t - tt)
        cp.step(legs_for(cp.hall_code()), 0.0, hh)
        acc += cp.state.torque_e_n_m * hh
        tt += hh
    need = m.viscous_friction_n_m_s * w + profile.control.load_torque_n_m
    return acc / tt, need


def twin_run(profile, design_path, plan=None, *, workdir=None, perturb=None, seed: int = 0,
             figures: dict | None = None):
    """The verification's step and load step on the motor twin (``picdrive_hil``), free-running.

    The firmware is generated from the design file (``picdrive firmware``'s
    codegen) into ``workdir`` (a temporary folder by default), built as
    ``picdrive firmware`` builds it (the chip's HEX within every budget: a
    firmware over one raises CodegenError and nothing runs; its figures go to
    ``figures``, see ``codegen.target_build``) and run unchanged in the twin
    (:func:`twin_scenario`).  Returns what :func:`twin_scenario` returns."""
    import tempfile
    from pathlib import Path

    from .firmware import codegen
    fw = codegen.generate(profile, str(design_path))
    with tempfile.TemporaryDirectory(prefix="picdrive-twin-run-") as tmp:
        # built as 'picdrive firmware' builds it: the host compile check and the chip's HEX within
        # every budget (CodegenError, a PicdriveError, when it does not fit: nothing runs)
        out = codegen.write_firmware(fw, Path(workdir or tmp) / "fw", check=True, hex_build=True, figures=figures)
        return twin_scenario(profile, out, fw.table, plan, perturb=perturb, seed=seed)


#: simulated time the processor twin runs before the scenario's first frame, s: the HEX's C start-up
#: (RAM clear, initialised data, fw_init) must have enabled the EUSART, or the frames are lost
PROCESSOR_BOOT_S = 0.02


def twin_scenario(profile, firmware_dir, table, plan=None, *, hex_file=None, perturb=None, seed: int | None = None,
                  load_factor: float | None = None):
    """The verification's step and load step on a built firmware in the motor twin, free-running.

    Parameters
    ----------
    profile : picdrive.profile.Profile
        The drive; with an ``[as_built]`` section, that drive off the line (the twin applies its
        deviations, :class:`picdrive_hil.twin.Twin`; its load-torque factor scales the load step
        and its seed is the noise seed unless ``seed`` is given).
    firmware_dir : str or pathlib.Path or None
        The generated firmware folder (its C runs on this machine); with ``hex_file`` only its
        ``board.json`` is read (None: the one beside the HEX).
    table : picdrive.link.protocol.Table
        The firmware's parameter table (``codegen.generate(...).table``): the ids and scales of the
        frames the scenario sends.
    plan : dict, optional
        :func:`picdrive.analysis.steptest.sim_plan` (default: the profile's).
    hex_file : str or pathlib.Path, optional
        The processor twin: this HEX on the PIC18 simulator.
    perturb : mapping, optional
        Plant perturbations (``picdrive_hil.plant.PERTURB_KEYS``), factors.
    seed : int, optional
        The twin's noise seed.
    load_factor : float, optional
        Factor on the plan's load step (default: the as-built drive's, else 1).

    Returns
    -------
    types.SimpleNamespace
        What :func:`picdrive.analysis.steptest.step_figures` reads (``t``, ``rpm``, ``omega``,
        ``omega_fine``, ``i_fine``: the true rotor speed at the law's sample instants and every
        100 us, the largest phase current) and ``faults``, the board's faults at the end (a
        latched overcurrent trip, the bridge switched off), each a phrase.

    Commands go in as frames over the twin's UART (``link_timeout`` to its maximum, the speed
    setpoint, start); t = 0 is the firmware's first sample in RUN (one PWM period before its
    first duty); the load-torque step is applied at ``plan["t_load_s"]`` on that clock.
    """
    from types import SimpleNamespace

    from picdrive_hil.scenario import step_and_load
    from picdrive_hil.twin import Twin

    from .link import codec
    plan = plan or sim_plan(profile)
    table = {e.name: e for e in table.entries}
    e_sp, e_to = table["speed_setpoint"], table["link_timeout"]
    ts = 1.0 / profile.control.speed_loop_hz
    if seed is None:
        seed = profile.as_built_seed or 0
    tw = Twin(profile, firmware_dir, perturb=perturb, seed=seed, hex_file=hex_file)
    try:
        if load_factor is None:
            load_factor = tw.as_built.load_factor if tw.as_built is not None else 1.0
        if tw.processor:
            # the HEX's C start-up (RAM clear, initialised data) runs before the UART listens
            tw.run(PROCESSOR_BOOT_S)
        seq = iter(range(1, 200))

        def send(cmd, args=None):
            tw.uart_write(codec.encode_command(cmd, next(seq), args))
        send("param_set", {"id": e_to.id, "value": e_to.max_raw})
        send("set_speed", {"value": int(round(plan["target_rpm"] / e_sp.scale))})
        tw.run(0.005)
        # t = 0: one PWM period before the first duty (the firmware's first sample in RUN)
        run = step_and_load(tw, load_n_m=plan["load_n_m"] * load_factor, load_after_s=plan["t_load_s"],
                            load_for_s=plan["t_end_s"] - plan["t_load_s"] + ts, dt_s=1e-4,
                            start_seq=next(seq), from_switch_on=True,
                            on_offset_s=-1.0 / profile.inverter.pwm_frequency_hz)
        parts, t0 = run.parts, run.t_zero_s
        st = tw.state()
        faults = []
        if st["pwm_fault_latched"]:
            faults.append("overcurrent trip latched (FLTA)")
        if not st["outputs_active"]:
            faults.append(f"the firmware switched the bridge off (at t = {st['outputs_off_t_s'] - t0:.4g} s)"
                          if st["outputs_off_t_s"] is not None else "the firmware switched the bridge off")
    finally:
        tw.close()
    t = np.concatenate([p["t_s"] for p in parts]) - t0
    w = np.concatenate([p["w_rad_s"] for p in parts])
    i = np.concatenate([np.max(np.abs(np.stack([p["i_a"], p["i_b"], p["i_c"]])), axis=0) for p in parts])
    order = np.argsort(t, kind="stable")
    t, w, i = t[order], w[order], i[order]
    keep = np.concatenate([[True], np.diff(t) > 1e-12])
    t, w, i = t[keep], w[keep], i[keep]
    tk = np.arange(int(round(plan["t_end_s"] / ts)) + 1) * ts
    wk = np.interp(tk, t, w)
    sel = t >= 0
    return SimpleNamespace(t=tk, omega=wk, rpm=wk * 60 / (2 * math.pi), omega_fine=w[sel], i_fine=i[sel],
                           t_fine=t[sel], faults=faults, load_n_m=plan["load_n_m"] * load_factor)


def run_design(profile, method: str, *, progress: bool = True, **options: Any) -> DesignResult:
    """Design and verify against the built drive; returns the result (does not write anything).

    A profile whose numbers the firmware's arithmetic cannot hold is refused before the work
    (:func:`picdrive.firmware.fixedpoint.check_profile_arithmetic`)."""
    from .design.dispatch import design
    from .firmware.fixedpoint import check_profile_arithmetic
    if method not in METHOD_MODULES:
        raise PicdriveError(f"unknown design method {method!r}; choose one of {', '.join(METHOD_MODULES)}")
    check_profile_arithmetic(profile)
    return design(profile, method, drive=BuiltDrive(), progress=progress, **options)


def check_chip(profile, result: DesignResult) -> list[str]:
    """Judge a verified design with its firmware built for the chip (``codegen.chip_check``).

    Adds the check ``firmware_fits_chip`` to ``result.verification`` and, when the firmware
    exceeds a budget, fails the design with a reason that names each figure and its budget
    (``picdrive firmware`` would refuse it).  Returns the build's figure lines.  Raises
    PicdriveError naming the fix when the PIC18 toolchain is missing."""
    import tempfile
    from .firmware import codegen
    from .firmware.target import BUDGETS, TargetError
    with tempfile.TemporaryDirectory(prefix="picdrive-design-chip-") as tmp:
        path = Path(tmp) / f"{profile.name}.{result.method}.design.json"
        save_design(result, path)
        try:
            lines, bad = codegen.chip_check(profile, path)
        except TargetError as e:
            raise PicdriveError(f"cannot build this design's firmware for the PIC18F4431 to check it against the "
                                f"chip's budgets: {e}; or design with --no-chip-check (the design file then records "
                                "that the chip build was not checked)") from None
    limit = (f"flash <= {BUDGETS.flash_bytes} B, RAM + stack <= {BUDGETS.ram_stack_bytes} B, speed loop <= "
             f"{BUDGETS.speed_loop_fraction:.0%} of its period, hall interrupt <= {BUDGETS.hall_isr_cycles} cycles, "
             f"UART receive <= {BUDGETS.uart_rx_cycles} cycles a byte")
    result.verification["firmware_fits_chip"] = {"value": "; ".join(bad) if bad else "fits", "limit": limit,
                                                 "ok": not bad}
    if bad:
        # the blocking reason first: no other check matters if the firmware cannot be flashed
        result.status = "failed"
        result.reasons.insert(0, "the firmware for this design does not fit the PIC18F4431 (" + "; ".join(bad)
                              + "); 'picdrive firmware' would refuse it")
    return lines


def _is_design_file(path: Path) -> bool:
    """A design file picdrive wrote (a design may replace it; anything else is the user's)."""
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(d, dict) and d.get("schema") == SCHEMA_ID


def output_path(profile, method: str, out: str | None, ok: bool) -> Path:
    """Where the design goes (checked by :func:`picdrive.outputs.file_output`): ``-o`` (a file, or a
    folder: an existing one or a path ending in '/'), else next to the profile."""
    from .outputs import file_output
    if profile.path is not None:
        default = default_design_path(profile.path, method)
    else:
        default = Path(f"{profile.name}.{method}.design.json")
    if not ok:
        default = default.with_name(default.name.replace(".design.json", "") + ".design.failed.json")
    if out and not ok and not (out.endswith(("/", os.sep)) or Path(out).is_dir()):
        p = Path(out)
        out = str(p.with_name(p.name.replace(".design.json", "") + ".design.failed.json"))
    return file_output(out, default, what="design file", same_kind=_is_design_file)


def _parse_option(text: str) -> tuple[str, Any]:
    if "=" not in text:
        raise PicdriveError(f"--option {text!r}: expected KEY=VALUE (for example --option gamma=0.5)")
    k, v = text.split("=", 1)
    k = k.strip().replace("-", "_")
    if not k:
        raise PicdriveError(f"--option {text!r}: the KEY is empty; expected KEY=VALUE (for example --option rules=3)")
    try:
        val = json.loads(v)
    except json.JSONDecodeError:
        val = v
    if isinstance(val, float) and not math.isfinite(val):
        raise PicdriveError(f"--option {text!r}: {k} must be a finite number")
    return k, val


def summary_lines(r: DesignResult) -> list[str]:
    out = [f"method      {r.method}" + (f" ({r.variant})" if r.variant else ""),
           f"profile     {r.profile_name} ({r.profile_sha256[:12]})",
           f"status      {r.status.upper()}"]
    cert = r.certificate or {}
    if cert.get("model"):
        out.append(f"model       {cert['model']}" + (f" (plant_model {r.options['plant_model']!r})"
                                                      if r.options.get("plant_model") else ""))
    if cert.get("plant_model_fallback"):
        out.append(f"  note      {cert['plant_model_fallback']}")
    if cert.get("time_domain_fallback"):
        out.append(f"  note      {cert['time_domain_fallback']}")
    for reason in r.reasons:
        out.append(f"  reason    {reason}")
    if r.law is not None:
        out.append(f"law         {r.law.n_rules} rule(s), b = {r.law.setpoint_weight:g}, "
                   f"u in [{r.law.u_min_v:.3g}, {r.law.u_max_v:.3g}] V, Ts = {r.law.sample_time_s * 1e3:g} ms")
        for j, g in enumerate(r.law.rules, 1):
            out.append(f"  rule {j}    kp={g.kp:.6g} V/(rad/s)  ki={g.ki:.6g} V/rad  kd={g.kd:.6g} V s^2/rad  kc={g.kc:.6g} V/A")
    else:
        out.append("law         none: not realisable on a six-step drive")
    for k, v in r.verification.items():
        if isinstance(v, dict) and "value" in v:
            lim = f" (limit {v['limit']})" if "limit" in v else ""
            ok = "" if v.get("ok", True) else "  FAILED"
            out.append(f"  check     {k}: {v['value']}{lim}{ok}")
    for k, v in r.timings_s.items():
        out.append(f"  time      {k}: {v:.3f} s")
    return out


def _cmd(args) -> int:
    from .profile import load_profile
    profile = load_profile(args.profile)
    opts = dict(_parse_option(o) for o in args.option)
    for name in ("variant", "gamma", "seed", "optimizer", "preset"):
        v = getattr(args, name)
        if v is not None:
            opts[name] = v
    # both destinations are checked before the work, so a refusal costs nothing
    output_path(profile, args.method, args.output, True)
    output_path(profile, args.method, args.output, False)
    r = run_design(profile, args.method, progress=not args.no_progress, **opts)
    chip = []
    if r.ok and args.no_chip_check:
        r.verification["firmware_fits_chip"] = {"value": "not checked (--no-chip-check)", "ok": True}
    elif r.ok:
        chip = check_chip(profile, r)
    for line in summary_lines(r):
        print(line)
    for line in chip:
        print(f"  chip      {line}")
    path = output_path(profile, args.method, args.output, r.ok)
    save_design(r, path)
    if r.ok:
        print(f"wrote {path}")
        return 0
    print(f"design FAILED its verification; wrote it for inspection only to {path}")
    return 1


def register(sub) -> None:
    from .argtypes import positive_float, seed
    p = sub.add_parser("design", help="design a speed controller from a drive profile",
                       description="Design, verify and save a speed controller.")
    p.add_argument("--profile", required=True, help="profile .toml, or a bundled profile name (duy2008, assawinchaichote2016)")
    p.add_argument("--method", required=True, choices=list(METHOD_MODULES))
    p.add_argument("-o", "--output", help="output file, or folder (existing, or ending in '/': created) "
                   "(default: next to the profile); an existing file is replaced only if it is a design file")
    p.add_argument("--variant", help="method variant (fuzzy-hinf: six-step | tracking | paper)")
    p.add_argument("--gamma", type=positive_float, help="fuzzy-hinf: prescribed H-inf level (default: minimise)")
    p.add_argument("--seed", type=seed, help="mixed-pid: GA seed (default: profile design.ga_seed)")
    p.add_argument("--optimizer", help="mixed-pid: ga | de (scipy differential evolution)")
    p.add_argument("--preset", help="zn: paper2016 for the 2016 paper's Kp=0.43, Ki=2.30, Kd=0.28")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="any other method option (repeatable), e.g. --option rules=3")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--no-chip-check", action="store_true",
                   help="do not build the verified design's firmware for the PIC18F4431 to check its flash, RAM "
                        "and interrupt budgets (needs the PIC18 toolchain; 'picdrive firmware' checks them anyway)")
    p.set_defaults(func=_cmd)
