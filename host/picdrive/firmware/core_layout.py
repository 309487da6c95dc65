"""The speed-loop core's data layout, described once.

The structs the speed loop's arithmetic works on -- ``core_params_t``, ``core_law_t``,
``core_state_t`` and ``core_in_t`` of ``drive_core.h``, and the SDCC build's scratch structs
``core_acc_t`` (the 32-bit accumulator) and ``core_lw_t`` (the assembly law's intermediates), and
drive.c's hall edge record ``hall_speed_t`` -- are listed here field by field: name, C type, element count and comment.  From this one
description come:

* the C typedefs (:meth:`Struct.c_typedef`, rendered into ``drive_core.h`` / ``drive_core.c``);
* the byte offsets the PIC18 assembly addresses the fields by, as ``#define`` names
  (:meth:`Struct.c_offsets`: ``_core_s + CORE_S_SPEED``), and the compile-time check of every
  one against ``offsetof`` on SDCC (:meth:`Struct.c_offset_check`);
* the Python model's records (:func:`model_class`: ``fixedpoint.LawParams``, ``LawState``,
  ``CoreState``) and the ctypes mirrors of the host build (:func:`ctypes_struct`).

Offsets: SDCC's pic16 port packs structs (no padding on an 8-bit core), so a field's offset is
the sum of the sizes before it; the ``offsetof`` check holds the compiler to that.  The host
build (gcc) aligns its fields, which the ctypes mirrors follow (ctypes' default alignment is the
host C compiler's).
"""
from __future__ import annotations

import dataclasses
import textwrap
from dataclasses import dataclass

__all__ = ["Field", "Struct", "CTYPE_BYTES", "CORE_PARAMS", "CORE_LAW", "CORE_STATE", "CORE_IN", "CORE_ACC",
           "CORE_LW", "HALL_SPEED", "STRUCTS", "model_class", "ctypes_struct", "offsets", "render_context"]

CTYPE_BYTES = {"int8_t": 1, "uint8_t": 1, "int16_t": 2, "uint16_t": 2, "int32_t": 4, "uint32_t": 4}
REQUIRED = object()
"""A model field with no default (the record's constructor needs it)."""


@dataclass(frozen=True)
class Field:
    """One member: ``ctype`` a stdint type name or a :class:`Struct`; ``rules``: an array of
    one element per rule (``CORE_N_RULES``); ``when``: the C preprocessor condition it exists
    under (``"CORE_KFF"``: only with the reference feedforward); ``default``: the Python model's
    initial value (``REQUIRED``: none); ``comment``: the C comment (what it is, its format)."""

    name: str
    ctype: object
    comment: str = ""
    rules: bool = False
    when: str | None = None
    default: object = 0


@dataclass(frozen=True)
class Struct:
    """A C struct: its typedef name, the prefix of its offset names and its fields in order."""

    c_name: str
    prefix: str
    fields: tuple
    doc: str = ""

    def size(self, n_rules: int) -> int:
        return sum(_bytes(f, n_rules) for f in self.fields)

    def offsets(self, n_rules: int) -> dict[str, int]:
        """{member path ("law.integ" for a nested member): byte offset} on SDCC (packed)."""
        out, off = {}, 0
        for f in self.fields:
            out[f.name] = off
            if isinstance(f.ctype, Struct):
                for k, v in f.ctype.offsets(n_rules).items():
                    out[f"{f.name}.{k}"] = off + v
            off += _bytes(f, n_rules)
        return out

    def offset_name(self, path: str) -> str:
        return self.prefix + path.replace(".", "_").upper()

    def _conds(self, path: str) -> list[str]:
        conds, s = [], self
        for part in path.split("."):
            f = next(x for x in s.fields if x.name == part)
            if f.when:
                conds.append(f.when)
            s = f.ctype
        return conds

    def c_typedef(self, indent: int = 31) -> str:
        """``typedef struct { ... } <c_name>;`` with each field's comment."""
        lines = ["typedef struct {"]
        for f in self.fields:
            t = f.ctype.c_name if isinstance(f.ctype, Struct) else f.ctype
            decl = f"    {t} {f.name}{'[CORE_N_RULES]' if f.rules else ''};"
            if f.when:
                lines.append(f"#if {f.when}")
            if f.comment:
                first, *rest = textwrap.wrap(f.comment + " */", 100 - indent - 5)
                lines.append(f"{decl:<{indent}}  /* {first}")
                lines += [" " * (indent + 5) + r for r in rest]
            else:
                lines.append(decl)
            if f.when:
                lines.append("#endif")
        lines.append(f"}} {self.c_name};")
        return "\n".join(lines)

    def c_offsets(self, n_rules: int) -> str:
        """``#define <PREFIX><FIELD> <offset>`` for every member (nested ones too), for the assembly."""
        return "\n".join(f"#define {self.offset_name(p)} {o}" for p, o in self.offsets(n_rules).items())

    def c_offset_check(self, n_rules: int) -> str:
        """A typedef whose array size is negative (a compile error) unless every offset name
        equals ``offsetof`` of its member; members under a condition are checked under it."""
        plain = [p for p in self.offsets(n_rules) if not self._conds(p)]
        terms = "\n    && ".join(f"offsetof({self.c_name}, {p}) == {self.offset_name(p)}" for p in plain)
        out = [f"typedef char {self.c_name[:-2]}_layout[({terms}\n    && sizeof({self.c_name}) == "
               f"{self.size(n_rules) if not any(f.when for f in self.fields) else self._size_expr(n_rules)}) "
               "? 1 : -1];"]
        for p in self.offsets(n_rules):
            c = self._conds(p)
            if c:
                out.append(f"#if {' && '.join(c)}\ntypedef char {self.c_name[:-2]}_{p.replace('.', '_')}_layout["
                           f"(offsetof({self.c_name}, {p}) == {self.offset_name(p)}) ? 1 : -1];\n#endif")
        return "\n".join(out)

    def _size_expr(self, n_rules: int) -> str:
        base = sum(_bytes(f, n_rules) for f in self.fields if not f.when)
        extra = " + ".join(f"(({f.when}) ? {_bytes(f, n_rules)}u : 0u)" for f in self.fields if f.when)
        return f"{base}u + {extra}"


def _bytes(f: Field, n_rules: int) -> int:
    one = f.ctype.size(n_rules) if isinstance(f.ctype, Struct) else CTYPE_BYTES[f.ctype]
    return one * (n_rules if f.rules else 1)


MU_ONE = 4096
"""Membership 1.0 in Q12 (law.mu1's value with one rule)."""

CORE_PARAMS = Struct("core_params_t", "CORE_P_", (
    Field("kp", "int16_t", "Q CORE_Q_KP, V/(rad/s)", rules=True, default=REQUIRED),
    Field("kits", "int16_t", "ki x Ts, Q CORE_Q_KITS, V/(rad/s)", rules=True, default=REQUIRED),
    Field("kdts", "int16_t", "kd / Ts, Q CORE_Q_KDTS, V/(rad/s)", rules=True, default=REQUIRED),
    Field("kc", "int16_t", "Q CORE_Q_KC, V per ADC count", rules=True, default=REQUIRED),
    Field("premise_lo", "int16_t", "speed format", default=REQUIRED),
    Field("premise_hi", "int16_t", default=REQUIRED),
    Field("mu_k", "uint16_t", "membership slope, from core_premise_k()", default=REQUIRED),
    Field("b_q14", "int16_t", "setpoint weight, Q14", default=REQUIRED),
    Field("u_min", "int16_t", "Q CORE_QU, V", default=REQUIRED),
    Field("u_max", "int16_t", default=REQUIRED),
    Field("controller", "uint8_t", "0: rule 1 only (PID), 1: memberships blend the rules", default=1),
    Field("ilim", "int16_t", "current limit, ADC counts", default=1023),
    Field("accel_step", "uint16_t", "setpoint ramp, speed LSB per sample; 0 = none"),
), "The law's parameters (raw values, copied from the parameter store).")

CORE_LAW = Struct("core_law_t", "CORE_LAW_", (
    Field("integ", "int32_t", "Q CORE_QI, V"),
    Field("d_filt", "int32_t", "Q CORE_QU, V"),
    Field("y_prev", "int16_t"),
    Field("primed", "uint8_t"),
    Field("mu1", "int16_t", "membership of rule 1, Q12", default=MU_ONE),
), "The law's memory.")

CORE_STATE = Struct("core_state_t", "CORE_S_", (
    Field("law", CORE_LAW, default=None),
    Field("speed_valid", "uint8_t"),
    Field("pos_prev", "uint16_t", "encoder: POSCNT at the last sample"),
    Field("t5_prev", "uint16_t", "encoder: Timer5 ticks since the last count edge, at the last sample"),
    Field("w_avg", "int16_t", "encoder: M/T average speed of the last sample"),
    Field("r_applied", "int16_t", "setpoint after the ramp (core_law's r)"),
    Field("cap", "int16_t", "current limiter: |u| cap, Q CORE_QU"),
    Field("speed", "int16_t", "measured speed, Q CORE_QS rad/s (core_law's y)"),
    Field("current", "int16_t", "ADC counts, signed by the direction (core_law's i)"),
    Field("u", "int16_t", "law output, Q CORE_QU V"),
    Field("dir", "uint8_t", "applied table: 0 forward, 1 reverse"),
    Field("hold", "uint8_t", "1: outputs off this sample (direction change)"),
    Field("pdc", "uint16_t", "duty, PDC counts"),
    Field("umin", "int16_t", "core_law's output limits this sample, Q CORE_QU V"),
    Field("umax", "int16_t"),
    Field("t2_prev", "uint8_t", "encoder: TMR2 read with the last sample (its instant)"),
    Field("ff", "int32_t", "reference feedforward of this sample, Q CORE_QI V (core_control sets it, "
          "core_law adds it to the integrator)", when="CORE_KFF"),
), "The speed loop's state.")

CORE_IN = Struct("core_in_t", "CORE_IN_", (
    Field("target", "int16_t", "core_control's setpoint, speed format"),
    Field("adc", "uint16_t", "core_control's bus current, ADC counts"),
    Field("pos_l", "uint8_t", "encoder: POSCNT"),
    Field("pos_h", "uint8_t"),
    Field("t5_l", "uint8_t", "encoder: Timer5 ticks since the last count edge"),
    Field("t5_h", "uint8_t"),
    Field("ovf", "uint8_t", "encoder: Timer5 overflowed"),
    Field("t2", "uint8_t", "TMR2 read with them (the sample's instant)"),
), "The speed loop's inputs (the caller writes them, the functions take no arguments).")

CORE_ACC = Struct("core_acc_t", "CORE_ACC_", (
    Field("x", "int32_t", "the accumulator"),
    Field("y", "int32_t", "second operand of sums, divisor"),
    Field("a", "int16_t", "product operand; quotient"),
    Field("b", "int16_t", "product operand"),
    Field("n", "uint8_t", "shift count"),
    Field("t", "uint8_t", "scratch"),
), "The 32-bit accumulator of the SDCC build (access RAM).")

CORE_LW = Struct("core_lw_t", "CORE_LW_", (
    Field("q", "int32_t", "everything but the integral (the speed assembly's scratch before the law)"),
    Field("inc", "int32_t", "integrator increment (the speed assembly's scratch before the law)"),
    Field("nw", "int32_t", "the current term, then the new integral"),
    Field("tmp", "int32_t", "blend's first product"),
    Field("e", "int16_t", "r - y, saturated"),
    Field("kp", "int16_t", "this sample's gains"),
    Field("ki", "int16_t"),
    Field("kd", "int16_t"),
    Field("kc", "int16_t"),
    Field("g0", "int16_t", "blend operands"),
    Field("g1", "int16_t"),
    Field("frac", "int16_t", "weight of rule 2, Q12"),
), "The assembly law's intermediates (banked RAM).")

HALL_SPEED = Struct("hall_speed_t", "HS_", (
    Field("last", "uint16_t", "Timer5 at the last edge"),
    Field("period", "uint16_t", "Timer5 counts between the last two edges"),
    Field("from", "uint8_t", "the hall code before the last edge"),
    Field("seen", "uint8_t", "edges as a run of ones, (seen << 1) | 1 each: bit 1 set = a period measured"),
    Field("age", "uint8_t", "speed-loop samples since the last edge (0xFF: none)"),
), "drive.c's hall edge record (speed from the halls): the hall interrupt's assembly writes it.")

STRUCTS = {s.c_name: s for s in (CORE_PARAMS, CORE_LAW, CORE_STATE, CORE_IN, CORE_ACC, CORE_LW, HALL_SPEED)}


def offsets(c_name: str, n_rules: int) -> dict[str, int]:
    """Byte offsets of ``c_name``'s members in the chip's (SDCC's) layout."""
    return STRUCTS[c_name].offsets(n_rules)


def model_class(s: Struct, name: str, doc: str, nested: dict | None = None):
    """A dataclass with ``s``'s fields (the Python model's record of the C struct): an int per
    scalar, a list per rule array, a ``nested[type]`` record per nested struct."""
    nested = nested or {}
    fields = []
    for f in s.fields:
        if isinstance(f.ctype, Struct):
            fields.append((f.name, object, dataclasses.field(default_factory=nested[f.ctype.c_name])))
        elif f.default is REQUIRED:
            fields.append((f.name, list if f.rules else int))
        else:
            fields.append((f.name, int, dataclasses.field(default=f.default)))
    # required fields first (a dataclass needs them before the defaulted ones): stable otherwise
    fields.sort(key=lambda x: len(x) == 3)
    cls = dataclasses.make_dataclass(name, fields)
    cls.__doc__ = doc
    cls.__module__ = "picdrive.firmware.fixedpoint"     # where the model's records live
    return cls


_CTYPES = {"int8_t": "c_int8", "uint8_t": "c_uint8", "int16_t": "c_int16", "uint16_t": "c_uint16",
           "int32_t": "c_int32", "uint32_t": "c_uint32"}


def ctypes_struct(s: Struct, n_rules: int, defined: set[str] = frozenset(), _made: dict | None = None):
    """The ctypes mirror of ``s`` for the host build (``defined``: the preprocessor conditions
    that hold, e.g. ``{"CORE_KFF"}``)."""
    import ctypes
    made = {} if _made is None else _made
    fields = []
    for f in s.fields:
        if f.when and f.when not in defined:
            continue
        if isinstance(f.ctype, Struct):
            t = made.get(f.ctype.c_name) or ctypes_struct(f.ctype, n_rules, defined, made)
        else:
            t = getattr(ctypes, _CTYPES[f.ctype])
        fields.append((f.name, t * n_rules if f.rules else t))
    cls = type(s.c_name, (ctypes.Structure,), {"_fields_": fields})
    made[s.c_name] = cls
    return cls


def render_context(n_rules: int) -> dict:
    """What the templates use: ``layout.<c_name>`` with ``typedef``, ``offsets`` (#defines) and
    ``check`` (the offsetof assertion) rendered for this plan's rule count."""
    class _R:
        def __init__(self, s):
            self.typedef = s.c_typedef()
            self.offsets = s.c_offsets(n_rules)
            self.check = s.c_offset_check(n_rules)
            self.off = s.offsets(n_rules)
            self.name = {p: s.offset_name(p) for p in self.off}
    return {k[:-2]: _R(s) for k, s in STRUCTS.items()}
