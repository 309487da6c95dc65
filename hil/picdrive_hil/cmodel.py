"""ctypes mirrors of the C structs in ``csrc/twin.h`` (keep the two in step;
``tests/test_plant.py`` checks the sizes against the compiled library)."""
from __future__ import annotations

import ctypes as C

ABI_VERSION = 3

EMF_TRAPEZOIDAL, EMF_SINUSOIDAL = 0, 1
LOAD_ACTIVE, LOAD_PASSIVE = 0, 1
ASIG_NONE, ASIG_CURRENT, ASIG_BUS_VOLTAGE = 0, 1, 2
CURSIG_LINK_ON, CURSIG_BUS_AVG, CURSIG_PEAK = 0, 1, 2
INJ_HALL, INJ_OVERCURRENT, INJ_LOCK_ROTOR, INJ_ENCODER, INJ_BUS_VOLTAGE = 1, 2, 3, 4, 5

TWIN_ERRORS = {
    1 << 0: "interrupt storm: an interrupt flag stayed set after its handler ran 1000 times in a row",
    1 << 1: "the firmware configured an ADC mode the twin does not model (see docs/twin.md)",
    1 << 2: "the board's EUSART baud rate differs from the host's by more than 2.5 %: bytes arrive garbled",
    1 << 3: "twin not initialised",
    1 << 4: "the processor stopped (fault)",
}
TWIN_ERR_CPU = 1 << 4


class PlantParams(C.Structure):
    _fields_ = [
        ("r_phase_ohm", C.c_double),
        ("l_phase_h", C.c_double),
        ("lambda_m_v_s", C.c_double),
        ("pole_pairs", C.c_int32),
        ("emf_shape", C.c_int32),
        ("inertia_kg_m2", C.c_double),
        ("friction_n_m_s", C.c_double),
        ("bus_voltage_v", C.c_double),
        ("diode_drop_v", C.c_double),
        ("hall_offset_rad", C.c_double),
        ("hall_spacing_rad", C.c_double),
        ("encoder_lines", C.c_int32),
        ("load_mode", C.c_int32),
        ("bus_capacitance_f", C.c_double),
        ("supply_sink_a", C.c_double),
        ("brake_resistor_ohm", C.c_double),
        ("brake_chopper_v", C.c_double),
    ]


class Leg(C.Structure):
    _fields_ = [("f_hi", C.c_double), ("f_lo", C.c_double)]


class PlantState(C.Structure):
    _fields_ = [
        ("t_s", C.c_double),
        ("i_a", C.c_double * 3),
        ("w_rad_s", C.c_double),
        ("theta_rad", C.c_double),
        ("v_term", C.c_double * 3),
        ("v_neutral", C.c_double),
        ("e_v", C.c_double * 3),
        ("torque_e_n_m", C.c_double),
        ("torque_load_n_m", C.c_double),
        ("i_bus_a", C.c_double),
        ("i_link_on_a", C.c_double),
        ("i_peak_a", C.c_double),
        ("energy_j", C.c_double),
        ("locked", C.c_int32),
        ("te_valid", C.c_int32),
        ("v_bus_v", C.c_double),
        ("i_brake_a", C.c_double),
    ]


class Pin(C.Structure):
    _fields_ = [("port", C.c_uint8), ("bit", C.c_uint8)]


class TwinConfig(C.Structure):
    _fields_ = [
        ("abi_version", C.c_int32),
        ("plant", PlantParams),
        ("fosc_hz", C.c_double),
        ("hall_pin", Pin * 3),
        ("flta_pin", Pin),
        ("phase_pair", C.c_uint8 * 3),
        ("analog_signal", C.c_uint8 * 9),
        ("current_signal", C.c_uint8),
        ("pad0", C.c_uint8 * 3),
        ("current_sense_v_per_a", C.c_double),
        ("current_sense_offset_v", C.c_double),
        ("bus_sense_v_per_v", C.c_double),
        ("adc_vref_v", C.c_double),
        ("overcurrent_trip_a", C.c_double),
        ("host_baud", C.c_double),
        ("max_step_s", C.c_double),
        ("speed_noise_rad_s", C.c_double),
        ("noise_sample_s", C.c_double),
        ("seed", C.c_uint64),
        ("eeprom_write_s", C.c_double),
    ]


class TwinState(C.Structure):
    _fields_ = [
        ("plant", PlantState),
        ("now_ps", C.c_int64),
        ("hall_code", C.c_uint8),
        ("hall_true", C.c_uint8),
        ("flta_asserted", C.c_uint8),
        ("pwm_outputs_active", C.c_uint8),
        ("enc_count", C.c_int32),
        ("leg", Leg * 3),
        ("gate_hi", C.c_uint8 * 3),
        ("gate_lo", C.c_uint8 * 3),
        ("pwm_fault_latched", C.c_uint8),
        ("pad1", C.c_uint8),
        ("shoot_through", C.c_uint32),
        ("uart_rx_overruns", C.c_uint32),
        ("uart_rx_framing", C.c_uint32),
        ("isr_high_calls", C.c_uint32),
        ("isr_low_calls", C.c_uint32),
        ("poll_calls", C.c_uint32),
        ("eeprom_writes", C.c_uint32),
        ("eeprom_rejected", C.c_uint32),
        ("errors", C.c_uint32),
        ("duty", C.c_double * 4),
        ("pwm_period_s", C.c_double),
        ("board_baud", C.c_double),
        ("dead_time_s", C.c_double),
        ("outputs_off_ps", C.c_int64),
    ]


TRACE_FIELDS = ("t_s", "w_rad_s", "theta_rad", "i_a", "i_b", "i_c", "i_bus_a", "torque_e_n_m",
                "torque_load_n_m", "v_a", "v_b", "v_c", "duty_max", "hall", "fault", "v_bus_v")


class TraceRec(C.Structure):
    _fields_ = [(n, C.c_double) for n in TRACE_FIELDS]


def bind_plant(lib: C.CDLL) -> C.CDLL:
    lib.plant_sizeof.argtypes = [C.c_int]
    lib.plant_sizeof.restype = C.c_int
    lib.plant_reset.argtypes = [C.POINTER(PlantState)]
    lib.plant_reset.restype = None
    lib.plant_step.argtypes = [C.POINTER(PlantParams), C.POINTER(PlantState), C.POINTER(Leg),
                               C.c_double, C.c_double]
    lib.plant_step.restype = None
    lib.plant_emf_shape.argtypes = [C.POINTER(PlantParams), C.c_double]
    lib.plant_emf_shape.restype = C.c_double
    lib.plant_hall_code.argtypes = [C.POINTER(PlantParams), C.c_double]
    lib.plant_hall_code.restype = C.c_int
    lib.plant_sin_cos_probe.argtypes = [C.c_double, C.c_double, C.POINTER(C.c_double)]
    lib.plant_sin_cos_probe.restype = None
    return lib


def bind_twin(lib: C.CDLL) -> C.CDLL:
    bind_plant(lib)
    lib.twin_init.argtypes = [C.POINTER(TwinConfig)]
    lib.twin_init.restype = C.c_int
    lib.twin_power_on.argtypes = []
    lib.twin_power_on.restype = C.c_int
    lib.twin_run_until.argtypes = [C.c_int64]
    lib.twin_run_until.restype = C.c_int
    lib.twin_get_state.argtypes = [C.POINTER(TwinState)]
    lib.twin_get_state.restype = None
    lib.twin_set_load_table.argtypes = [C.POINTER(C.c_double), C.POINTER(C.c_double), C.c_int32]
    lib.twin_set_load_table.restype = None
    lib.twin_uart_host_write.argtypes = [C.c_char_p, C.c_int32]
    lib.twin_uart_host_write.restype = C.c_int
    lib.twin_uart_host_read.argtypes = [C.c_char_p, C.c_int32]
    lib.twin_uart_host_read.restype = C.c_int
    lib.twin_uart_host_pending.argtypes = []
    lib.twin_uart_host_pending.restype = C.c_int
    lib.twin_uart_host_flush.argtypes = []
    lib.twin_uart_host_flush.restype = C.c_int
    lib.twin_inject.argtypes = [C.c_int32, C.c_double, C.c_double]
    lib.twin_inject.restype = None
    lib.twin_eeprom_get.argtypes = [C.c_char_p]
    lib.twin_eeprom_get.restype = None
    lib.twin_eeprom_set.argtypes = [C.c_char_p]
    lib.twin_eeprom_set.restype = None
    lib.twin_trace_start.argtypes = [C.c_double, C.POINTER(TraceRec), C.c_int32]
    lib.twin_trace_start.restype = None
    lib.twin_trace_count.argtypes = []
    lib.twin_trace_count.restype = C.c_int
    lib.twin_sfr_get.argtypes = [C.c_uint16]
    lib.twin_sfr_get.restype = C.c_uint8
    lib.twin_set_plant_state.argtypes = [C.c_double, C.c_double]
    lib.twin_set_plant_state.restype = None
    lib.twin_sizeof.argtypes = [C.c_int]
    lib.twin_sizeof.restype = C.c_int
    lib.twin_data_region.argtypes = [C.POINTER(C.c_uint64)]
    lib.twin_data_region.restype = C.c_int
    return lib
