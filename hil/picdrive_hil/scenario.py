"""The speed step plus load-torque step on the twin: one procedure for everyone who runs it.

Two ways in, the same scenario (start the drive at its setpoint, then step the load torque):

* :func:`step_and_load` -- free-running, in simulated time: the start command goes in as a frame
  over the twin's UART and the true plant state is recorded every ``dt_s``
  (:meth:`picdrive_hil.twin.Twin.record`).  Used by the design gate's check against the twin
  (:func:`picdrive.gate.twin_run`) and bench/twin.py (SIL beside PIL).
* :func:`load_step_on_link` -- through ``picdrive.link`` on a served twin (real time): the
  telemetry before and after the load step.  Used by ``picdrive demo`` and the HIL suite's
  load-step test.

The caller configures the firmware first (setpoint, link watchdog): how differs (frames, the
link) and is not part of the scenario.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from picdrive.link import codec

__all__ = ["StepLoadRecord", "step_and_load", "load_step_on_link"]


@dataclass
class StepLoadRecord:
    """What :func:`step_and_load` recorded (twin records: ``t_s`` in s on the twin's clock,
    ``w_rad_s``, ``i_a``..., ``duty_max``...)."""

    parts: list          # the records in order: before the load step (one or two), then after it
    t_zero_s: float      # the scenario's t = 0 on the twin's clock, s (the start, or the switch-on plus offset)
    t_load_s: float      # when the load torque stepped, s on the twin's clock

    @property
    def step(self) -> dict:
        """The record before the load step (parts joined)."""
        before = self.parts[:-1]
        return before[0] if len(before) == 1 else {k: np.concatenate([p[k] for p in before]) for k in before[0]}

    @property
    def load(self) -> dict:
        """The record after the load step."""
        return self.parts[-1]


def step_and_load(tw, *, load_n_m: float, load_after_s: float, load_for_s: float, dt_s: float = 1e-4,
                  start_seq: int = 3, from_switch_on: bool = False, probe_s: float = 0.02,
                  on_offset_s: float = 0.0) -> StepLoadRecord:
    """Start the drive and record it free-running; step the load torque; record on.

    Parameters
    ----------
    tw : picdrive_hil.twin.Twin
        A twin whose firmware is configured (setpoint, watchdog) and idle.
    load_n_m : float
        The load torque applied as a step, N m.
    load_after_s : float
        When the load steps, s after t = 0: the start command, or with ``from_switch_on`` the
        bridge's first switch-on (the first record with ``duty_max > 0``) plus ``on_offset_s``.
    load_for_s : float
        How long to record after the load step, s.
    dt_s : float
        Record period, s (simulated time).
    start_seq : int
        SEQ of the start frame.
    from_switch_on, probe_s, on_offset_s
        Count t = 0 from the switch-on found in the first ``probe_s`` s of the record
        (RuntimeError when the bridge stays off), offset by ``on_offset_s`` s.

    Returns
    -------
    StepLoadRecord
        The records before and after the load step, t = 0 and the load instant (s, twin clock).
    """
    tw.uart_write(codec.encode_command("start", start_seq))
    if from_switch_on:
        parts = [tw.record(probe_s, dt_s)]
        on = np.nonzero(parts[0]["duty_max"] > 0)[0]
        if on.size == 0:
            raise RuntimeError("the firmware never switched the bridge on")
        t0 = float(parts[0]["t_s"][on[0]]) + on_offset_s
        parts.append(tw.record(t0 + load_after_s - tw.t, dt_s))
    else:
        t0 = tw.t
        parts = [tw.record(load_after_s, dt_s)]
    tw.set_load_torque(load_n_m)
    t_load = tw.t
    parts.append(tw.record(load_for_s, dt_s))
    return StepLoadRecord(parts=parts, t_zero_s=t0, t_load_s=t_load)


def load_step_on_link(tw, link, load_n_m: float, before_s: float, after_s: float, *,
                      flush: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """The load-torque step on a served twin, seen through the link's telemetry.

    Parameters
    ----------
    tw : picdrive_hil.twin.Twin
        The twin behind ``link`` (its server running), the drive running and the telemetry on.
    link : picdrive.link.client.Link
        The open link.
    load_n_m : float
        The load torque applied as a step, N m.
    before_s, after_s : float
        Telemetry read before and after the load step, s.
    flush : bool
        Drop the samples still queued after the ``before_s`` read, so that the second read
        starts at the step.

    Returns
    -------
    before, after : numpy.ndarray
        The telemetry records (``link.read_samples``) before and after the load step.
    t_load_s : float
        The twin's clock when the load stepped, s.
    """
    before = link.read_samples(seconds=before_s)
    if flush:
        link.flush_samples()
    t_load = tw.t
    tw.set_load_torque(load_n_m)
    after = link.read_samples(seconds=after_s)
    return before, after, t_load
