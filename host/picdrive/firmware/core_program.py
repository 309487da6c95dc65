"""The speed-loop core's law and control, described once as programs of accumulator operations.

The integer law (``core_law``) and the sample's control around it (``core_control``: current
limits, setpoint ramp, reference feedforward, the law, direction and duty) are lists of typed
operations (:class:`Op` subclasses) over the fields of :mod:`picdrive.firmware.core_layout`'s
structs, a few function locals and one 32-bit accumulator ``x`` (the C's ``core_acc.x``).  From
these two programs come:

* the bit-exact Python model: :func:`python_source` renders a program as a Python function,
  compiled once (:func:`model`); ``fixedpoint.law_step`` and ``fixedpoint.core_control``
  are those functions;
* the C of ``drive_core.c`` (:func:`c_source`, rendered into the template as ``core_program.law``
  and ``core_program.control``): the host build, XC8, and SDCC for plans whose law or control is
  not in assembly;
* the rules around the law that the averaged six-step simulation
  (:func:`picdrive.models.simulate.simulate_six_step`) runs on volts: the cap walk-down
  (:class:`WalkCap`) and the direction hold (:class:`DirectionHold`) call
  :func:`picdrive.control_law.walk_cap` and :func:`~picdrive.control_law.direction_hold` in the
  model, and the simulation calls the same functions.

Operands (strings): ``s.<field>`` a member of ``core_s`` (``core_state_t``; ``s.law.integ`` a
nested one), ``p.<field>`` of ``core_p`` (``core_params_t``), ``l.<name>`` a 32-bit static of the
core (``l_q``), ``g.<name>`` a gain of this sample (``g_kp``), ``v.<name>`` a local of the
function, ``K.<name>`` a generation-time constant (:data:`CONSTS`: its C macro and the plan's
value), ``x`` the accumulator, or an int.

Each operation states its overflow contract (:attr:`Op.contract`); the arithmetic rules are the
firmware's: 16x16 products in 32 bits, floor right shifts, saturating left shifts, saturating
32-bit sums and 16-bit results.  The PIC18 assembly of the plans the bundled designs use
(``core_law_asm``, ``core_control_asm`` in ``drive_core.c.j2``) runs the same steps by hand; the
chip's bit-exact test (tests/test_target_bitexact.py) holds it to the model generated here.

To change the law: edit :data:`LAW` (or :data:`CONTROL`); the model, the C and the tests follow.
The float law (:mod:`picdrive.control_law`) stays the specification.
"""
from __future__ import annotations

from dataclasses import dataclass

from ..control_law import direction_hold, walk_cap

__all__ = ["Op", "Note", "Load", "LoadSel", "LoadDiff", "MulS", "Shift", "Asr", "ToQi", "MulQ15", "Add", "Sub",
           "Sat16", "Store", "Set", "Move", "If", "When", "MaxInto", "MinInto", "Pick", "Clamp", "ClampStore",
           "Schedule", "Headroom", "Current", "WalkCap", "Window", "Ramp", "CallLaw", "DirectionHold", "Duty",
           "Let", "Div15", "Neg", "Function", "CONSTS", "SHIFTS", "CONDS", "ASM_HOME", "LAW", "CONTROL", "SPEED_HALL", "c_source", "asm_source",
           "python_source", "model", "asr_asm", "shift_asm"]

#: generation-time constants: name -> (C macro of drive_params.h, the Python model's expression on ``plan``)
CONSTS = {
    "I_LIM": ("CORE_I_LIM", "plan.i_lim"),
    "DI": ("CORE_QI - CORE_QU", "(plan.qi - plan.qu)"),
    "DFILT_A": ("CORE_DFILT_A", "plan.dfilt_a"),
    "CAP_STEP": ("CORE_CAP_STEP", "plan.cap_step"),
    "U_LIMIT": ("CORE_U_LIMIT", "plan.u_limit"),
    "R_CNT": ("CORE_R_CNT", "plan.r_cnt"),
    "KB": ("CORE_KB", "plan.kb"),
    "KFF": ("CORE_KFF", "plan.kff"),
    "K_SPEED": ("CORE_K_SPEED", "plan.k_speed"),
}
#: the plan's shifts (x 2^-s: floor right for s >= 0, saturating left otherwise): name -> plan attribute
SHIFTS = {"P": "shift_p", "I": "shift_i", "D": "shift_d", "C": "shift_c", "KB": "shift_kb", "R": "shift_r",
          "FF": "shift_ff"}
#: C preprocessor conditions of :class:`When` -> the plan's expression
CONDS = {"CORE_DFILT_A": "plan.dfilt_a", "CORE_KFF": "plan.kff"}


# ---------------------------------------------------------------------------
# operand rendering
# ---------------------------------------------------------------------------
def _c(v, ctx) -> str:
    if isinstance(v, int):
        return str(v)
    if v == "x":
        return "ACC"
    if v == "acc.a":
        return "core_acc.a"
    k, _, rest = v.partition(".")
    if k == "s":
        return "core_s." + rest
    if k == "p":
        return "core_p." + rest
    if k == "l":
        return "l_" + rest
    if k == "g":
        return "g_" + rest
    if k == "v":
        return rest
    if k == "K":
        return CONSTS[rest][0]
    raise ValueError(f"operand {v!r}")


def _py(v, ctx) -> str:
    if isinstance(v, int):
        return str(v)
    if v == "x":
        return "x"
    if v == "acc.a":
        return "acc_a"
    if v in ctx.bind:
        return ctx.bind[v]
    for pre, to in ctx.prefix:
        if v.startswith(pre):
            return to + v[len(pre):]
    k, _, rest = v.partition(".")
    if k == "s":
        return "st." + rest
    if k == "p":
        return "p." + rest
    if k in ("l", "g", "v"):
        return f"{k}_{rest}"
    if k == "K":
        return CONSTS[rest][1]
    raise ValueError(f"operand {v!r}")


class _Ctx:
    """Rendering context: ``bind`` maps operands to the Python function's names (arguments)."""

    def __init__(self, bind=(), prefix=()):
        self.bind = dict(bind)
        self.prefix = tuple(prefix)


def _block(ops, ctx, lang: str, ind: int) -> list[str]:
    out = []
    for op in ops:
        out += getattr(op, lang)(ctx, ind)
    if lang == "py" and not out:
        out = [" " * ind + "pass"]
    return out



# ---------------------------------------------------------------------------
# PIC18 assembly (SDCC's gpasm syntax): operands by the layout's offset names, never numbers
# ---------------------------------------------------------------------------
#: where the locals and statics live on the chip (``s.`` and ``p.`` fields: their layout offsets).
#: ``None``: kept in the accumulator (a value used once, by the next product); "A": in its operand a.
ASM_HOME = {
    "v.y": "_core_s + CORE_S_SPEED", "v.e": "_core_lw + CORE_LW_E", "v.ey": None, "v.dy": "A",
    "g.kp": "_core_lw + CORE_LW_KP", "g.kits": "_core_lw + CORE_LW_KI", "g.kdts": "_core_lw + CORE_LW_KD",
    "g.kc": "_core_lw + CORE_LW_KC", "l.q": "_core_lw + CORE_LW_Q", "l.inc": "_core_lw + CORE_LW_INC",
    "l.new": "_core_lw + CORE_LW_NW", "v.target": "_core_in + CORE_IN_TARGET",
}
ACC_X, ACC_Y, ACC_A, ACC_B = ("_core_acc + CORE_ACC_X", "_core_acc + CORE_ACC_Y", "_core_acc + CORE_ACC_A",
                              "_core_acc + CORE_ACC_B")
ACC_N, ACC_T = "_core_acc + CORE_ACC_N", "_core_acc + CORE_ACC_T"


def _home(v):
    """(symbol, bytes) of an operand on the chip; symbol None: in x (the value just computed)."""
    from .core_layout import CORE_STATE, CORE_PARAMS, CTYPE_BYTES
    if v in ASM_HOME:
        h = ASM_HOME[v]
        if h is None:
            return None, 2
        if h == "A":
            return ACC_A, 2
        nb = 4 if v.startswith("l.") else 2
        return h, nb
    k, _, rest = v.partition(".")
    struct, sym = (CORE_STATE, "_core_s") if k == "s" else (CORE_PARAMS, "_core_p")
    path = rest.split("[")[0]
    f, t = None, struct
    for part in path.split("."):
        f = next(x for x in t.fields if x.name == part)
        t = f.ctype
    return f"{sym} + {struct.offset_name(path)}", CTYPE_BYTES[f.ctype]


def mov(src, dst, nb):
    return [f"    MOVFF   {src}{f' + {i}' if i else ''}, {dst}{f' + {i}' if i else ''}" for i in range(nb)]


def lit(v, dst, nb):
    u = v % (1 << (8 * nb))
    out = []
    for i in range(nb):
        out += [f"    MOVLW   {(u >> (8 * i)) & 0xFF}", f"    MOVWF   {dst}{f' + {i}' if i else ''}, A"]
    return out


def asr_asm(n: int) -> list[str]:
    """x = floor(x / 2^n), n a generation-time constant: k whole bytes then r bits right
    (_core_acc_asr_b<k>), or for r >= 5 8 - r bits left through a fifth byte then k + 1 bytes
    right (_core_acc_asrl<k+1>: fewer bit steps); 4 and 12: their own entries; 0: nothing."""
    if n <= 0:
        return []
    k, r = divmod(n, 8)
    if n in (4, 12):
        return [f"    CALL    _core_acc_asr{n}"]
    if r >= 5 and k < 3:
        return [f"    MOVLW   {8 - r}", f"    MOVWF   {ACC_N}, A", f"    CALL    _core_acc_asrl{k + 1}"]
    return [f"    MOVLW   {r}", f"    MOVWF   {ACC_N}, A", f"    CALL    _core_acc_asr_b{k}"]


def shift_asm(s: int) -> list[str]:
    """x 2^-s: floor right shift (s >= 0) or saturating left shift."""
    if s >= 0:
        return asr_asm(s)
    return [f"    MOVLW   {-s}", f"    MOVWF   {ACC_N}, A", "    CALL    _core_acc_shlsat"]


class _Asm:
    """Assembly rendering state: the plan, the bit names, what x holds, a pending 16-bit load,
    a label to place after the next step, and the subroutines the steps call (emitted after the
    function's body, once each)."""

    def __init__(self, plan, bit):
        self.plan, self.bit = plan, bit
        self.x_holds = None          # the operand x equals (None: unknown)
        self.pending = None          # a 16-bit operand to sign-extend into x before the next sum
        self.after_next = None       # a label to emit after the next step
        self.trailers = {}           # name -> lines
        self.returned = False
        self.used = {}               # label -> times used
        self.last = None             # the function's last step

    def label(self, name: str) -> str:
        """A label of this function: ``name`` the first time, ``name_2``, ``name_3``... after."""
        n = self.used[name] = self.used.get(name, 0) + 1
        return name if n == 1 else f"{name}_{n}"


def _flat(ops, plan):
    """The steps with the generation-time conditions decided (When bodies in line or dropped)."""
    out = []
    for op in ops:
        if isinstance(op, When):
            if eval(CONDS[op.cond], {"plan": plan}):
                out += _flat(op.body, plan)
        else:
            out.append(op)
    return out


def _sum_asm(a, v, call):
    """x = x +- v, saturated; a pending 16-bit load enters with v through core_acc_sext_ab."""
    out = []
    hv, nb = _home(v)
    if a.pending is not None:
        out += mov(_home(a.pending)[0], ACC_A, 2)
    if nb == 2:
        out += mov(hv, ACC_B, 2) + ["    CALL    _core_acc_sext_ab" if a.pending is not None else
                                    "    CALL    _core_acc_sext_b"]
    else:
        out += (["    CALL    _core_acc_sext_ab"] if a.pending is not None else []) + mov(hv, ACC_Y, 4)
    a.pending = a.x_holds = None
    return out + [f"    CALL    {call}"]


#: carry clear iff x < y (signed 32-bit): x and y with their sign bits flipped, compared unsigned
LAW_CMP = ["law_cmp:"] + [f"    MOVF    {ACC_Y}{f' + {i}' if i else ''}, W, A\n    "
                          f"{'SUBWF ' if i == 0 else 'SUBWFB'}  {ACC_X}{f' + {i}' if i else ''}, W, A"
                          for i in range(3)] + [
    f"    MOVF    {ACC_Y} + 3, W, A", "    XORLW   0x80", f"    MOVWF   {ACC_T}, A", f"    MOVF    {ACC_X} + 3, W, A",
    "    XORLW   0x80", f"    SUBFWB  {ACC_T}, W, A", "    RETURN"]


#: carry clear iff a < b (signed 16-bit); a = min(a, b), a = max(a, b)
CTL_CMP16 = ["    ; carry clear iff a < b (signed 16-bit)", "ctl_cmp16:", f"    MOVF    {ACC_B}, W, A",
             f"    SUBWF   {ACC_A}, W, A", f"    MOVF    {ACC_B} + 1, W, A", "    XORLW   0x80",
             f"    MOVWF   {ACC_T}, A", f"    MOVF    {ACC_A} + 1, W, A", "    XORLW   0x80",
             f"    SUBFWB  {ACC_T}, W, A", "    RETURN", "    ; a = min(a, b), a = max(a, b) (signed 16-bit)",
             "ctl_min16:", "    RCALL   ctl_cmp16", "    BNC     ctl_keep", "    BRA     ctl_take", "ctl_max16:",
             "    RCALL   ctl_cmp16", "    BC      ctl_keep", "ctl_take:"] + [
    f"    MOVFF   {ACC_B}, {ACC_A}", f"    MOVFF   {ACC_B} + 1, {ACC_A} + 1", "ctl_keep:", "    RETURN"]


def _asm_block(ops, a: "_Asm") -> list[str]:
    ops = _flat(ops, a.plan)
    out = []
    for k, op in enumerate(ops):
        nxt = ops[k + 1] if k + 1 < len(ops) else None
        if isinstance(op, Store) and isinstance(nxt, Clamp) and nxt.dst == op.dst:
            a.x_holds = op.dst                # the clamp stores it: this store is dead
            continue
        if a.pending is not None and not isinstance(op, (Add, Sub, Note)):
            if isinstance(op, Load):
                a.pending = None              # replaced before it was used
            else:                             # x = sext(the pending 16-bit operand) now
                out += mov(_home(a.pending)[0], ACC_A, 2) + ["    CALL    _core_acc_sext_ab"]
                a.pending = None
                a.x_holds = None
        label, a.after_next = a.after_next, None
        out += op.asm(a)
        if label:
            out.append(f"{label}:")
    return out


# ---------------------------------------------------------------------------
# the operations
# ---------------------------------------------------------------------------
class Op:
    """One step.  ``c(ctx, indent)`` and ``py(ctx, indent)`` give its lines; ``contract`` its
    overflow behaviour."""

    contract = ""

    def c(self, ctx, ind):
        raise NotImplementedError

    def py(self, ctx, ind):
        raise NotImplementedError

    def asm(self, a):
        raise NotImplementedError(f"{type(self).__name__} has no assembly form (only inside a composite)")


def _i(n):
    return " " * n


@dataclass(frozen=True)
class Note(Op):
    """A comment in the C (why the next steps are there)."""
    text: str
    contract = "no arithmetic"

    def c(self, ctx, ind):
        return [f"{_i(ind)}/* {self.text} */"]

    def py(self, ctx, ind):
        return []

    def asm(self, a):
        # a quote in a comment of the assembly is an unterminated character constant to the C
        # preprocessor of every other compiler (the assembly sits in #if __SDCC)
        if "'" in self.text or '"' in self.text:
            raise ValueError(f"no quotes in a note: {self.text!r}")
        return [f"    ; {self.text}"]


@dataclass(frozen=True)
class Load(Op):
    """x = src (sign-extended to 32 bits; ``cast``: the C's explicit cast)."""
    src: object
    cast: str = ""
    contract = "exact"

    def c(self, ctx, ind):
        return [f"{_i(ind)}ACC = {self.cast}{_c(self.src, ctx)};"]

    def py(self, ctx, ind):
        return [f"{_i(ind)}x = {_py(self.src, ctx)}"]

    def asm(self, a):
        if a.x_holds == self.src:
            return []
        h, nb = _home(self.src)
        a.x_holds = None
        if nb == 2:
            a.pending = self.src              # sign-extended by the next sum (core_acc_sext_ab)
            return []
        a.x_holds = self.src
        return mov(h, ACC_X, 4)


@dataclass(frozen=True)
class MulS(Op):
    """x = a b, both int16: the product in 32 bits.  ``zero_skip`` (assembly labels (product,
    after the next step)): on the chip, b = 0 gives x = 0 without the product and the shift that
    follows it (a PI rule's kd: cycles saved, same result)."""
    a: object
    b: object
    zero_skip: tuple = ()
    contract = "exact: |a b| <= 2^30"

    def c(self, ctx, ind):
        return [f"{_i(ind)}ACC_MULS({_c(self.a, ctx)}, {_c(self.b, ctx)});"]

    def py(self, ctx, ind):
        return [f"{_i(ind)}x = {_py(self.a, ctx)} * {_py(self.b, ctx)}"]

    def asm(self, a):
        def load(v, dst):
            if isinstance(v, str) and v.startswith("K."):
                return lit(eval(CONSTS[v[2:]][1], {"plan": a.plan}), dst, 2)
            return mov(_home(v)[0], dst, 2)
        ops = (self.a, self.b)
        if "x" in ops:                        # the value just computed (16 bits) into b
            out = mov(ACC_X, ACC_B, 2) + load(self.b if self.a == "x" else self.a, ACC_A)
            a.x_holds = a.pending = None
            return out + ["    CALL    _core_acc_muls"]
        held = next((v for v in ops if v == a.x_holds and _home(v)[0] is None), None)
        in_a = next((v for v in ops if isinstance(v, str) and v in ASM_HOME and ASM_HOME[v] == "A"), None)
        if held is not None:
            out = mov(ACC_X, ACC_A, 2) + load(self.b if held == self.a else self.a, ACC_B)
        elif in_a is not None:
            out = load(self.b if in_a == self.a else self.a, ACC_B)
        else:
            out = load(self.a, ACC_A) + load(self.b, ACC_B)
        if self.zero_skip:
            mul, done = (a.label(x) for x in self.zero_skip)
            out += ["    ; b = 0 (a PI rule): 0 without the product and its shift (both give 0)",
                    f"    MOVF    {ACC_B}, W, A", f"    IORWF   {ACC_B} + 1, W, A", f"    BNZ     {mul}"]
            out += [f"    CLRF    {ACC_X}{f' + {i}' if i else ''}, A" for i in range(4)]
            out += [f"    BRA     {done}", f"{mul}:"]
            a.after_next = done
        a.x_holds = a.pending = None
        return out + ["    CALL    _core_acc_muls"]


@dataclass(frozen=True)
class Shift(Op):
    """x = x 2^-s, s the plan's shift ``name`` (:data:`SHIFTS`)."""
    name: str
    contract = "right: floor, exact in range; left: saturates at the int32 limits"

    def c(self, ctx, ind):
        return [f"{_i(ind)}(void)CORE_SHIFT_{self.name}(ACC);"]

    def py(self, ctx, ind):
        return [f"{_i(ind)}x = shift32(x, plan.{SHIFTS[self.name]})"]

    def asm(self, a):
        a.x_holds = None
        return shift_asm(getattr(a.plan, SHIFTS[self.name]))


@dataclass(frozen=True)
class Asr(Op):
    """x = floor(x / 2^n), n an int or a :data:`CONSTS` name."""
    n: object
    contract = "floor, never overflows"

    def c(self, ctx, ind):
        n = self.n if isinstance(self.n, int) else CONSTS[self.n][0]
        return [f"{_i(ind)}ACC_ASR({n});"]

    def py(self, ctx, ind):
        n = self.n if isinstance(self.n, int) else CONSTS[self.n][1]
        return [f"{_i(ind)}x = x >> {n}"]

    def asm(self, a):
        a.x_holds = None
        return asr_asm(self.n if isinstance(self.n, int) else eval(CONSTS[self.n][1], {"plan": a.plan}))


@dataclass(frozen=True)
class ToQi(Op):
    """x = x 2^(QI - QU): a voltage in the integrator's format."""
    contract = "saturates at the int32 limits"

    def c(self, ctx, ind):
        return [f"{_i(ind)}(void)CORE_TO_QI(ACC);"]

    def py(self, ctx, ind):
        return [f"{_i(ind)}x = shl_sat32(x, plan.qi - plan.qu)"]

    def asm(self, a):
        a.x_holds = None
        di = a.plan.qi - a.plan.qu
        return [f"    MOVLW   {di}", f"    MOVWF   {ACC_N}, A", "    CALL    _core_acc_shlsat"] if di > 0 else []


@dataclass(frozen=True)
class MulQ15(Op):
    """x = floor(x a / 2^15), a a :data:`CONSTS` name, 0 <= a <= 2^15."""
    a: str
    contract = "exact: |x a / 2^15| <= |x|"

    def c(self, ctx, ind):
        return [f"{_i(ind)}acc_mul_q15({CONSTS[self.a][0]});"]

    def py(self, ctx, ind):
        return [f"{_i(ind)}x = (x * {CONSTS[self.a][1]}) >> 15"]


@dataclass(frozen=True)
class Add(Op):
    """x = sat32(x + v)."""
    v: object
    contract = "saturates at the int32 limits"

    def c(self, ctx, ind):
        return [f"{_i(ind)}ACC_ADD({_c(self.v, ctx)});"]

    def py(self, ctx, ind):
        return [f"{_i(ind)}x = sat32(x + {_py(self.v, ctx)})"]

    def asm(self, a):
        return _sum_asm(a, self.v, "_core_acc_add")


@dataclass(frozen=True)
class Sub(Op):
    """x = sat32(x - v)."""
    v: object
    contract = "saturates at the int32 limits"

    def c(self, ctx, ind):
        return [f"{_i(ind)}ACC_SUB({_c(self.v, ctx)});"]

    def py(self, ctx, ind):
        return [f"{_i(ind)}x = sat32(x - {_py(self.v, ctx)})"]

    def asm(self, a):
        return _sum_asm(a, self.v, "_core_acc_sub")


@dataclass(frozen=True)
class Sat16(Op):
    """x = sat16(x)."""
    contract = "saturates at the int16 limits"

    def c(self, ctx, ind):
        return [f"{_i(ind)}ACC_SAT16();"]

    def py(self, ctx, ind):
        return [f"{_i(ind)}x = -32768 if x < -32768 else 32767 if x > 32767 else x"]

    def asm(self, a):
        a.x_holds = None
        return ["    CALL    _core_acc_sat16"]


@dataclass(frozen=True)
class Store(Op):
    """dst = x (``cast``: the C's conversion, e.g. ``(int16_t)`` after :class:`Sat16`)."""
    dst: str
    cast: str = ""
    contract = "exact: x fits dst (the steps before bound it)"

    def c(self, ctx, ind):
        return [f"{_i(ind)}{_c(self.dst, ctx)} = {self.cast}ACC;"]

    def py(self, ctx, ind):
        return [f"{_i(ind)}{_py(self.dst, ctx)} = x"]

    def asm(self, a):
        h, nb = _home(self.dst)
        a.x_holds = self.dst
        return [] if h is None else mov(ACC_X, h, nb)


@dataclass(frozen=True)
class Set(Op):
    """dst = a literal (``c``: its C spelling)."""
    dst: str
    value: int
    c_value: str = ""
    contract = "exact"

    def c(self, ctx, ind):
        return [f"{_i(ind)}{_c(self.dst, ctx)} = {self.c_value or self.value};"]

    def py(self, ctx, ind):
        return [f"{_i(ind)}{_py(self.dst, ctx)} = {self.value}"]

    def asm(self, a):
        h, nb = _home(self.dst)
        if h == ACC_A and self.value == 0:
            return [f"    CLRF    {ACC_A}, A", f"    CLRF    {ACC_A} + 1, A"]
        if nb == 1:                           # through t: MOVFF reaches banked RAM without the BSR
            return [f"    MOVLW   {self.value}", f"    MOVWF   {ACC_T}, A", f"    MOVFF   {ACC_T}, {h}"]
        raise NotImplementedError(f"Set {self.dst} in assembly")


@dataclass(frozen=True)
class If(Op):
    """if (a rel b) then else orelse; ``b_c``: b's C spelling when it differs (``0u``)."""
    a: object
    rel: str
    b: object
    then: tuple
    orelse: tuple = ()
    b_c: str = ""
    labels: tuple = ()
    and_: tuple = ()
    contract = "a comparison: exact"

    def _cond(self, ctx, lang):
        """``a rel b``, and with ``and_`` = (a2, rel2, b2, b2's C spelling) ``... && a2 rel2 b2``."""
        if lang == "c":
            out = f"{_c(self.a, ctx)} {self.rel} {self.b_c or _c(self.b, ctx)}"
            if self.and_:
                a2, r2, b2, b2c = self.and_
                out += f" && {_c(a2, ctx)} {r2} {b2c or _c(b2, ctx)}"
            return out
        out = f"{_py(self.a, ctx)} {self.rel} {_py(self.b, ctx)}"
        if self.and_:
            a2, r2, b2, _ = self.and_
            out += f" and {_py(a2, ctx)} {r2} {_py(b2, ctx)}"
        return out

    def c(self, ctx, ind):
        out = [f"{_i(ind)}if ({self._cond(ctx, 'c')}) {{"] + _block(self.then, ctx, "c", ind + 4)
        if self.orelse:
            out += [f"{_i(ind)}}} else {{"] + _block(self.orelse, ctx, "c", ind + 4)
        return out + [f"{_i(ind)}}}"]

    def py(self, ctx, ind):
        out = [f"{_i(ind)}if {self._cond(ctx, 'py')}:"] + _block(self.then, ctx, "py", ind + 4)
        if self.orelse:
            out += [f"{_i(ind)}else:"] + _block(self.orelse, ctx, "py", ind + 4)
        return out

    def asm(self, a):
        if self.a == "x" and self.rel == "!=" and self.b == 0 and not self.orelse and len(self.labels) == 1:
            # x after Sat16 (or any 16-bit value): its low 16 bits decide
            end = a.label(self.labels[0])
            out = [f"    MOVF    {ACC_X}, W, A", f"    IORWF   {ACC_X} + 1, W, A", f"    BZ      {end}"]
            out += _asm_block(self.then, a) + [f"{end}:"]
            a.x_holds = a.pending = None
            return out
        h, nb = _home(self.a)
        if not (nb == 1 and self.rel == "!=" and self.b == 0 and self.labels and not self.and_):
            raise NotImplementedError("If in assembly: a uint8 field != 0, with labels")
        then, end = (a.label(x) for x in self.labels)
        out = [f"    MOVFF   {h}, {ACC_T}", f"    MOVF    {ACC_T}, F, A", f"    BNZ     {then}"]
        a.x_holds = a.pending = None
        out += _asm_block(self.orelse, a) + [f"    BRA     {end}", f"{then}:"]
        a.x_holds = a.pending = None
        out += _asm_block(self.then, a) + [f"{end}:"]
        a.x_holds = a.pending = None
        return out


@dataclass(frozen=True)
class When(Op):
    """Steps that exist only when a generation-time condition holds (C ``#if``)."""
    cond: str
    body: tuple
    contract = "no arithmetic"

    def c(self, ctx, ind):
        return [f"#if {self.cond}"] + _block(self.body, ctx, "c", ind) + ["#endif"]

    def py(self, ctx, ind):
        return [f"{_i(ind)}if {CONDS[self.cond]}:"] + _block(self.body, ctx, "py", ind + 4)

    def asm(self, a):
        return _asm_block(self.body, a) if eval(CONDS[self.cond], {"plan": a.plan}) else []


@dataclass(frozen=True)
class MaxInto(Op):
    """dst = max(dst, src) (dst, src int32)."""
    dst: str
    src: str
    contract = "exact"

    def c(self, ctx, ind):
        d, s = _c(self.dst, ctx), _c(self.src, ctx)
        return [f"{_i(ind)}if ({s} > {d}) {{", f"{_i(ind + 4)}{d} = {s};", f"{_i(ind)}}}"]

    def py(self, ctx, ind):
        d, s = _py(self.dst, ctx), _py(self.src, ctx)
        return [f"{_i(ind)}if {s} > {d}:", f"{_i(ind + 4)}{d} = {s}"]


@dataclass(frozen=True)
class MinInto(Op):
    """dst = min(dst, src) (dst, src int32)."""
    dst: str
    src: str
    contract = "exact"

    def c(self, ctx, ind):
        d, s = _c(self.dst, ctx), _c(self.src, ctx)
        return [f"{_i(ind)}if ({s} < {d}) {{", f"{_i(ind + 4)}{d} = {s};", f"{_i(ind)}}}"]

    def py(self, ctx, ind):
        d, s = _py(self.dst, ctx), _py(self.src, ctx)
        return [f"{_i(ind)}if {s} < {d}:", f"{_i(ind + 4)}{d} = {s}"]


@dataclass(frozen=True)
class LoadSel(Op):
    """x = (a rel b) ? t : f, t and f int16 fields sign-extended."""
    a: str
    rel: str
    b: int
    t: str
    f: str
    contract = "exact"

    def c(self, ctx, ind):
        return [f"{_i(ind)}ACC = ({_c(self.a, ctx)} {self.rel} {self.b}) ? (int32_t){_c(self.t, ctx)} : "
                f"(int32_t){_c(self.f, ctx)};"]

    def py(self, ctx, ind):
        return [f"{_i(ind)}x = {_py(self.t, ctx)} if {_py(self.a, ctx)} {self.rel} {self.b} else {_py(self.f, ctx)}"]


@dataclass(frozen=True)
class LoadDiff(Op):
    """x = a - b, both int16, in 32 bits."""
    a: str
    b: str
    contract = "exact: |a - b| < 2^16"

    def c(self, ctx, ind):
        return [f"{_i(ind)}ACC = (int32_t){_c(self.a, ctx)} - (int32_t){_c(self.b, ctx)};"]

    def py(self, ctx, ind):
        return [f"{_i(ind)}x = {_py(self.a, ctx)} - {_py(self.b, ctx)}"]

    def asm(self, a):
        a.pending = self.a
        return _sum_asm(a, self.b, "_core_acc_sub")


@dataclass(frozen=True)
class Move(Op):
    """dst = src (same type)."""
    dst: str
    src: str
    contract = "exact"

    def c(self, ctx, ind):
        return [f"{_i(ind)}{_c(self.dst, ctx)} = {_c(self.src, ctx)};"]

    def py(self, ctx, ind):
        return [f"{_i(ind)}{_py(self.dst, ctx)} = {_py(self.src, ctx)}"]

    def asm(self, a):
        hs, nb = _home(self.src)
        return mov(hs, _home(self.dst)[0], nb)


@dataclass(frozen=True)
class Pick(Op):
    """dst = min(a, b) (``rel`` "<") or max(a, b) (">"), as one conditional expression."""
    dst: str
    a: str
    rel: str
    b: str
    contract = "exact"

    def c(self, ctx, ind):
        a, b = _c(self.a, ctx), _c(self.b, ctx)
        return [f"{_i(ind)}{_c(self.dst, ctx)} = ({a} {self.rel} {b}) ? {a} : {b};"]

    def py(self, ctx, ind):
        a, b = _py(self.a, ctx), _py(self.b, ctx)
        return [f"{_i(ind)}{_py(self.dst, ctx)} = {a} if {a} {self.rel} {b} else {b}"]


@dataclass(frozen=True)
class Clamp(Op):
    """dst = dst clamped to [-lim, lim], lim a :data:`CONSTS` name (lim < 2^31)."""
    dst: str
    lim: str
    contract = "exact"

    def c(self, ctx, ind):
        d, k = _c(self.dst, ctx), CONSTS[self.lim][0]
        return [f"{_i(ind)}if ({d} > {k}) {{", f"{_i(ind + 4)}{d} = {k};", f"{_i(ind)}}} else if ({d} < -{k}) {{",
                f"{_i(ind + 4)}{d} = -{k};", f"{_i(ind)}}}"]

    def py(self, ctx, ind):
        d, k = _py(self.dst, ctx), CONSTS[self.lim][1]
        return [f"{_i(ind)}if {d} > {k}:", f"{_i(ind + 4)}{d} = {k}", f"{_i(ind)}elif {d} < -{k}:",
                f"{_i(ind + 4)}{d} = -{k}"]

    def asm(self, a):
        h, _ = _home(self.dst)
        lim = eval(CONSTS[self.lim][1], {"plan": a.plan})
        not_hi, done = a.label("law_not_hi"), a.label("law_lim_done")
        out = [] if a.x_holds == self.dst else mov(h, ACC_X, 4)
        out += lit(lim, ACC_Y, 4) + ["    CALL    law_cmp", f"    BNC     {not_hi}"] + mov(ACC_Y, ACC_X, 4)
        out += [f"    BRA     {done}", f"{not_hi}:"] + lit(-lim, ACC_Y, 4)
        out += ["    CALL    law_cmp", f"    BC      {done}"] + mov(ACC_Y, ACC_X, 4) + [f"{done}:"]
        a.trailers.setdefault("law_cmp", LAW_CMP)
        a.x_holds = self.dst
        return out + mov(ACC_X, h, 4)


@dataclass(frozen=True)
class ClampStore(Op):
    """dst = x clamped to [lo, hi] (int16 bounds, lo <= hi)."""
    dst: str
    lo: str
    hi: str
    contract = "exact: the result lies in [lo, hi]"

    def c(self, ctx, ind):
        d, lo, hi = _c(self.dst, ctx), _c(self.lo, ctx), _c(self.hi, ctx)
        return [f"{_i(ind)}if (ACC < (int32_t){lo}) {{", f"{_i(ind + 4)}{d} = {lo};",
                f"{_i(ind)}}} else if (ACC > (int32_t){hi}) {{", f"{_i(ind + 4)}{d} = {hi};",
                f"{_i(ind)}}} else {{", f"{_i(ind + 4)}{d} = (int16_t)ACC;", f"{_i(ind)}}}"]

    def py(self, ctx, ind):
        d, lo, hi = _py(self.dst, ctx), _py(self.lo, ctx), _py(self.hi, ctx)
        return [f"{_i(ind)}{d} = {lo} if x < {lo} else {hi} if x > {hi} else x"]

    def asm(self, a):
        d, lo, hi = _home(self.dst)[0], _home(self.lo)[0], _home(self.hi)[0]
        not_min, take_x, done = a.label("law_not_min"), a.label("law_u_x"), a.label("law_u_done")
        # the function's last step returns from each branch; elsewhere the branches meet after it
        last = self is a.last
        leave = ["    RETURN"] if last else [f"    BRA     {done}"]
        out = mov(lo, ACC_B, 2) + ["    CALL    _core_acc_sext_b", "    CALL    law_cmp", f"    BC      {not_min}"]
        out += mov(lo, d, 2) + leave + [f"{not_min}:"] + mov(hi, ACC_B, 2)
        out += ["    CALL    _core_acc_sext_b", "    CALL    law_cmp", f"    BNC     {take_x}"] + mov(hi, d, 2)
        out += leave + [f"{take_x}:"] + mov(ACC_X, d, 2) + (["    RETURN"] if last else [f"{done}:"])
        a.trailers.setdefault("law_cmp", LAW_CMP)
        a.returned = last
        a.x_holds = a.pending = None
        return out


_SCHEDULE_C = """\
#if CORE_N_RULES > 1
    if (core_p.controller == 0u) {
#endif
        g_kp = core_p.kp[0];
        g_kits = core_p.kits[0];
        g_kdts = core_p.kdts[0];
        g_kc = core_p.kc[0];
        core_s.law.mu1 = 4096;
#if CORE_N_RULES > 1
    } else {
        uint16_t s = (y < 0) ? (uint16_t)(-(int32_t)y) : (uint16_t)y;
        uint16_t lo = (uint16_t)core_p.premise_lo;
        uint16_t pos;
        uint8_t j;
        if (s > (uint16_t)core_p.premise_hi) {
            s = (uint16_t)core_p.premise_hi;
        }
        if (s < lo) {
            s = lo;
        }
        ACC_MULU((uint16_t)(s - lo), core_p.mu_k);     /* < 2^31: the floor shift is the unsigned one */
        ACC_ASR(CORE_MU_SH);
        pos = ((uint32_t)ACC > CORE_MU_TOP) ? (uint16_t)CORE_MU_TOP : (uint16_t)(uint32_t)ACC;
#if CORE_N_RULES == 2
        j = 0u;
        frac = pos;                                    /* pos <= 4096: rule 2's weight */
#else
        j = (uint8_t)(pos >> 12);
        if (j >= (uint8_t)(CORE_N_RULES - 1u)) {
            j = (uint8_t)(CORE_N_RULES - 2u);
            frac = 4096u;
        } else {
            frac = (uint16_t)(pos & 4095u);
        }
#endif
        bg0 = core_p.kp[j];
        bg1 = core_p.kp[j + 1u];
        g_kp = blend();
        bg0 = core_p.kits[j];
        bg1 = core_p.kits[j + 1u];
        g_kits = blend();
        bg0 = core_p.kdts[j];
        bg1 = core_p.kdts[j + 1u];
        g_kdts = blend();
        bg0 = core_p.kc[j];
        bg1 = core_p.kc[j + 1u];
        g_kc = blend();
        core_s.law.mu1 = (j == 0u) ? (int16_t)(4096u - frac) : 0;
    }
#endif"""

_SCHEDULE_PY = """\
if plan.n_rules == 1 or p.controller == 0:
    g_kp, g_kits, g_kdts, g_kc = p.kp[0], p.kits[0], p.kdts[0], p.kc[0]
    st.mu1 = 4096
else:
    nr = plan.n_rules
    s = -{y} if {y} < 0 else {y}
    lo, hi = p.premise_lo, p.premise_hi
    if s > hi:
        s = hi
    if s < lo:
        s = lo
    pos = ((s - lo) * p.mu_k) >> plan.mu_sh
    top = (nr - 1) << 12
    if pos > top:
        pos = top
    j = pos >> 12
    if j >= nr - 1:
        j, frac = nr - 2, 4096
    else:
        frac = pos & 4095
    w0 = 4096 - frac
    g_kp = (p.kp[j] * w0 + p.kp[j + 1] * frac) >> 12
    g_kits = (p.kits[j] * w0 + p.kits[j + 1] * frac) >> 12
    g_kdts = (p.kdts[j] * w0 + p.kdts[j + 1] * frac) >> 12
    g_kc = (p.kc[j] * w0 + p.kc[j + 1] * frac) >> 12
    st.mu1 = w0 if j == 0 else 0"""


@dataclass(frozen=True)
class Schedule(Op):
    """The gains of this sample, ``g.kp``, ``g.kits``, ``g.kdts``, ``g.kc``, and the membership
    of rule 1, ``s.law.mu1`` (Q12): rule 1's gains when ``p.controller`` is 0 or the plan has one
    rule; otherwise the speed |y| clamped to the premise, its position
    ``(|y| - lo) mu_k / 2^MU_SH`` (at most ``(r - 1) 4096``) selects rules j, j + 1 and the weight
    frac of rule j + 1 (Q12), and each gain is ``floor((g_j (4096 - frac) + g_j+1 frac) / 4096)``
    (the C's blend(): one product when g_j+1 - g_j fits 16 bits)."""
    y: str
    contract = "exact: the blend lies between the two rules' gains (int16)"

    def c(self, ctx, ind):
        return _SCHEDULE_C.splitlines()

    def py(self, ctx, ind):
        return [_i(ind) + ln for ln in _SCHEDULE_PY.format(y=_py(self.y, ctx)).splitlines()]

    def asm(self, a):
        A, B, X = ACC_A, ACC_B, ACC_X
        lw, sp = "_core_lw + CORE_LW_", "_core_p + CORE_P_"
        out = []
        if a.plan.n_rules == 2:
            out += [f"    MOVFF   {sp}CONTROLLER, {ACC_T}", f"    MOVF    {ACC_T}, F, A",
                    f"    BTFSC   _STATUS, {a.bit['STATUS']['Z']}, A", "    BRA     law_rule1",
                    "    ; s = |y| clamped to [premise_lo, premise_hi] (unsigned)"]
            out += mov(_home(self.y)[0], A, 2)
            out += [f"    BTFSS   {A} + 1, 7, A", "    BRA     law_abs", f"    COMF    {A}, F, A",
                    f"    COMF    {A} + 1, F, A", f"    INCF    {A}, F, A", "    MOVLW   0",
                    f"    ADDWFC  {A} + 1, F, A", "law_abs:"] + mov(sp + "PREMISE_HI", B, 2)
            out += [f"    MOVF    {A}, W, A", f"    SUBWF   {B}, W, A", f"    MOVF    {A} + 1, W, A",
                    f"    SUBWFB  {B} + 1, W, A", "    BC      law_below_hi"] + mov(B, A, 2)
            out += ["law_below_hi:"] + mov(sp + "PREMISE_LO", B, 2)
            out += [f"    MOVF    {B}, W, A", f"    SUBWF   {A}, W, A", f"    MOVF    {B} + 1, W, A",
                    f"    SUBWFB  {A} + 1, W, A", "    BC      law_above_lo"] + mov(B, A, 2)
            out += ["law_above_lo:", "    ; pos = min((s - lo) mu_k >> MU_SH, 4096) = frac",
                    f"    MOVF    {B}, W, A", f"    SUBWF   {A}, F, A", f"    MOVF    {B} + 1, W, A",
                    f"    SUBWFB  {A} + 1, F, A"] + mov(sp + "MU_K", B, 2) + ["    CALL    _core_acc_mulu"]
            out += asr_asm(a.plan.mu_sh)
            out += [f"    MOVF    {X} + 3, W, A", f"    IORWF   {X} + 2, W, A", "    BNZ     law_pos_top",
                    "    MOVLW   0", f"    SUBWF   {X}, W, A", "    MOVLW   0x10", f"    SUBWFB  {X} + 1, W, A",
                    "    BNC     law_pos_ok", "law_pos_top:", f"    CLRF    {X}, A", "    MOVLW   0x10",
                    f"    MOVWF   {X} + 1, A", "law_pos_ok:"] + mov(X, lw + "FRAC", 2)
            out += ["    ; mu1 = 4096 - frac", f"    COMF    {X}, F, A", f"    COMF    {X} + 1, F, A",
                    f"    INCF    {X}, F, A", "    MOVLW   0x10", f"    ADDWFC  {X} + 1, F, A"]
            out += mov(X, "_core_s + CORE_S_LAW_MU1", 2) + ["    ; the four gains, blended"]
            for g, home in (("KP", "KP"), ("KITS", "KI"), ("KDTS", "KD"), ("KC", "KC")):
                out += mov(sp + g, lw + "G0", 2) + mov(sp + g + " + 2", lw + "G1", 2)
                out += ["    CALL    _core_blend_asm"] + mov(X, lw + home, 2)
            out += ["    BRA     law_gains", "law_rule1:"]
        elif a.plan.n_rules != 1:
            raise NotImplementedError("the assembly law holds at most 2 rules")
        for g, home in (("KP", "KP"), ("KITS", "KI"), ("KDTS", "KD"), ("KC", "KC")):
            out += mov(sp + g, lw + home, 2)
        out += [f"    CLRF    {X}, A", "    MOVLW   0x10", f"    MOVWF   {X} + 1, A"]
        out += mov(X, "_core_s + CORE_S_LAW_MU1", 2) + ["law_gains:"]
        a.x_holds = a.pending = None
        return out


@dataclass(frozen=True)
class Headroom(Op):
    """The integrator, integrated only into the output headroom: with the increment ``l.inc``
    and the new integral ``l.new = sat32(integ + inc)``, the headroom
    ``head = (umax or umin) - l.q`` in the integrator's format (saturated), and
    ``integ = min(new, max(integ, head))`` for inc > 0, ``max(new, min(integ, head))`` for
    inc < 0: the integral moves toward the headroom and never past it, and is not pulled back
    when it is already beyond (anti-windup without discharge)."""
    contract = "exact: integ stays between its old value and new"

    STEPS = (If("l.inc", "!=", 0, (
        LoadSel("l.inc", ">", 0, "s.umax", "s.umin"), Sub("l.q"), ToQi(),
        If("l.inc", ">", 0, (MaxInto("x", "s.law.integ"), Pick("s.law.integ", "l.new", "<", "x")),
           (MinInto("x", "s.law.integ"), Pick("s.law.integ", "l.new", ">", "x"))),
    )),)

    def c(self, ctx, ind):
        return _block(self.STEPS, ctx, "c", ind)

    def py(self, ctx, ind):
        return _block(self.STEPS, ctx, "py", ind)

    def asm(self, a):
        Y, X, A = ACC_Y, ACC_X, ACC_A
        q, nw, integ = "_core_lw + CORE_LW_Q", "_core_lw + CORE_LW_NW", "_core_s + CORE_S_LAW_INTEG"
        out = mov("_core_lw + CORE_LW_INC", Y, 4)
        out += [f"    MOVF    {Y}, W, A", f"    IORWF   {Y} + 1, W, A", f"    IORWF   {Y} + 2, W, A",
                f"    IORWF   {Y} + 3, W, A", "    BZ      law_clamp", f"    BTFSC   {Y} + 3, 7, A",
                "    BRA     law_inc_neg"] + mov("_core_s + CORE_S_UMAX", A, 2) + ["    CALL    law_head"]
        out += ["    ; cap = max(integ, head); integ = min(new, cap)", "    CALL    law_cmp",
                "    BC      law_pos_cap"] + mov(Y, X, 4) + ["law_pos_cap:"] + mov(nw, Y, 4)
        out += ["    CALL    law_cmp", "    BNC     law_store_x", "    BRA     law_store_y", "law_inc_neg:"]
        out += mov("_core_s + CORE_S_UMIN", A, 2) + ["    CALL    law_head"]
        out += ["    ; cap = min(integ, head); integ = max(new, cap)", "    CALL    law_cmp",
                "    BNC     law_neg_cap"] + mov(Y, X, 4) + ["law_neg_cap:"] + mov(nw, Y, 4)
        out += ["    CALL    law_cmp", "    BNC     law_store_y", "law_store_x:"] + mov(X, integ, 4)
        out += ["    BRA     law_clamp", "law_store_y:"] + mov(Y, integ, 4) + ["law_clamp:"]
        head = ["    ; x = the headroom sat(sext(a) - q) in the integrator format; y = integ", "law_head:",
                "    CALL    _core_acc_sext_ab"] + mov(q, Y, 4) + ["    CALL    _core_acc_sub"]
        head += ToQi().asm(a) + mov(integ, Y, 4) + ["    RETURN"]
        a.trailers.setdefault("law_head", head)
        a.trailers.setdefault("law_cmp", LAW_CMP)
        a.x_holds = a.pending = None
        return out


@dataclass(frozen=True)
class CallLaw(Op):
    """core_law on core_s (its contract: :data:`LAW`)."""
    contract = "core_law's"

    def c(self, ctx, ind):
        return [f"{_i(ind)}core_law();"]

    def py(self, ctx, ind):
        return [f"{_i(ind)}st.u = law_step(plan, p, st.law, st.r_applied, st.speed, st.current, st.umin, st.umax, "
                f"st.ff if plan.kff else 0)"]

    def asm(self, a):
        a.x_holds = a.pending = None
        return ["    CALL    _core_law_asm"]


@dataclass(frozen=True)
class WalkCap(Op):
    """s.cap walks down by CAP_STEP (to 0) while adc > p.ilim, up (to U_LIMIT) otherwise
    (:func:`picdrive.control_law.walk_cap`)."""
    contract = "exact: 0 <= cap <= U_LIMIT"

    def c(self, ctx, ind):
        return [f"{_i(ind)}if ((int16_t)adc > core_p.ilim) {{",
                f"{_i(ind + 4)}core_s.cap = (core_s.cap > CORE_CAP_STEP) ? (int16_t)(core_s.cap - CORE_CAP_STEP) : 0;",
                f"{_i(ind)}}} else {{",
                f"{_i(ind + 4)}core_s.cap = (core_s.cap < CORE_U_LIMIT - CORE_CAP_STEP) ? "
                "(int16_t)(core_s.cap + CORE_CAP_STEP)",
                f"{_i(ind + 4)}                                                        : CORE_U_LIMIT;",
                f"{_i(ind)}}}"]

    def py(self, ctx, ind):
        return [f"{_i(ind)}st.cap = walk_cap(st.cap, adc > p.ilim, plan.cap_step, plan.u_limit)"]

    def asm(self, a):
        A, B = ACC_A, ACC_B
        cap, step, top = "_core_s + CORE_S_CAP", a.plan.cap_step, a.plan.u_limit
        out = mov("_core_p + CORE_P_ILIM", A, 2) + mov("_core_in + CORE_IN_ADC", B, 2)
        out += ["    CALL    ctl_cmp16", "    BC      ctl_cap_up", "    ; cap > STEP: cap - STEP, else 0"]
        out += lit(step, A, 2) + mov(cap, B, 2) + ["    CALL    ctl_cmp16", "    BC      ctl_cap_zero"]
        out += mov(cap, A, 2) + lit(step, B, 2)
        out += [f"    MOVF    {B}, W, A", f"    SUBWF   {A}, F, A", f"    MOVF    {B} + 1, W, A",
                f"    SUBWFB  {A} + 1, F, A", "    BRA     ctl_cap_store", "ctl_cap_zero:", f"    CLRF    {A}, A",
                f"    CLRF    {A} + 1, A", "    BRA     ctl_cap_store", "ctl_cap_up:",
                "    ; cap < U_LIMIT - STEP: cap + STEP, else U_LIMIT"]
        out += mov(cap, A, 2) + lit(top - step, B, 2) + ["    CALL    ctl_cmp16", "    BC      ctl_cap_top"]
        out += lit(step, B, 2) + [f"    MOVF    {B}, W, A", f"    ADDWF   {A}, F, A", f"    MOVF    {B} + 1, W, A",
                                  f"    ADDWFC  {A} + 1, F, A", "    BRA     ctl_cap_store", "ctl_cap_top:"]
        out += lit(top, A, 2) + ["ctl_cap_store:"] + mov(A, cap, 2)
        a.trailers.setdefault("ctl_cmp16", CTL_CMP16)
        a.x_holds = a.pending = None
        return out


@dataclass(frozen=True)
class Window(Op):
    """The output limits of this sample: the back-EMF window ``hi = sat16(l.q + l.new)``,
    ``lo = sat16(l.q - l.new)`` (l.q = Kb y, l.new = R_line I_lim, shifted), then
    ``umax = min(u_max, cap, max(hi, u_min))``, ``umin = max(u_min, -cap, min(lo, u_max))`` and
    umin at most umax."""
    contract = "exact: sums saturate at the int32 limits, hi and lo at the int16 limits"

    STEPS = (Add("l.new"), Sat16(), Store("v.hi", "(int16_t)"),
             Load("l.q"), Sub("l.new"), Sat16(), Store("v.lo", "(int16_t)"))

    def c(self, ctx, ind):
        t = _i(ind)
        return _block(self.STEPS, ctx, "c", ind) + [
            f"{t}if (hi < core_p.u_min) {{", f"{t}    hi = core_p.u_min;", f"{t}}}",
            f"{t}if (lo > core_p.u_max) {{", f"{t}    lo = core_p.u_max;", f"{t}}}",
            f"{t}core_s.umax = core_p.u_max;",
            f"{t}if (core_s.cap < core_s.umax) {{", f"{t}    core_s.umax = core_s.cap;", f"{t}}}",
            f"{t}if (hi < core_s.umax) {{", f"{t}    core_s.umax = hi;", f"{t}}}",
            f"{t}core_s.umin = core_p.u_min;",
            f"{t}if ((int16_t)-core_s.cap > core_s.umin) {{", f"{t}    core_s.umin = (int16_t)-core_s.cap;",
            f"{t}}}",
            f"{t}if (lo > core_s.umin) {{", f"{t}    core_s.umin = lo;", f"{t}}}",
            f"{t}if (core_s.umin > core_s.umax) {{", f"{t}    core_s.umin = core_s.umax;", f"{t}}}"]

    def py(self, ctx, ind):
        t = _i(ind)
        return _block(self.STEPS, ctx, "py", ind) + [
            f"{t}umax = min(p.u_max, st.cap, max(v_hi, p.u_min))",
            f"{t}umin = max(p.u_min, -st.cap, min(v_lo, p.u_max))",
            f"{t}st.umax = umax",
            f"{t}st.umin = umax if umin > umax else umin"]

    def asm(self, a):
        X, Y, A, B = ACC_X, ACC_Y, ACC_A, ACC_B
        lw, sp, ss = "_core_lw + CORE_LW_", "_core_p + CORE_P_", "_core_s + CORE_S_"
        out = mov(lw + "NW", Y, 4) + ["    CALL    _core_acc_add", "    CALL    _core_acc_sat16",
                                      "    ; hi = max(sat16(q + nw), u_min) -> lw.g0"]
        out += mov(X, A, 2) + mov(sp + "U_MIN", B, 2) + ["    CALL    ctl_max16"] + mov(A, lw + "G0", 2)
        out += ["    ; lo = min(sat16(q - nw), u_max) -> lw.g1"] + mov(lw + "Q", X, 4) + mov(lw + "NW", Y, 4)
        out += ["    CALL    _core_acc_sub", "    CALL    _core_acc_sat16"] + mov(X, A, 2) + mov(sp + "U_MAX", B, 2)
        out += ["    CALL    ctl_min16"] + mov(A, lw + "G1", 2) + ["    ; umax = min(u_max, cap, hi)"]
        out += mov(sp + "U_MAX", A, 2) + mov(ss + "CAP", B, 2) + ["    CALL    ctl_min16"] + mov(lw + "G0", B, 2)
        out += ["    CALL    ctl_min16"] + mov(A, ss + "UMAX", 2) + ["    ; umin = max(u_min, -cap, lo), then at most umax"]
        out += mov(ss + "CAP", B, 2) + [f"    COMF    {B}, F, A", f"    COMF    {B} + 1, F, A", f"    INCF    {B}, F, A",
                                        "    MOVLW   0", f"    ADDWFC  {B} + 1, F, A"]
        out += mov(sp + "U_MIN", A, 2) + ["    CALL    ctl_max16"] + mov(lw + "G1", B, 2) + ["    CALL    ctl_max16"]
        out += mov(ss + "UMAX", B, 2) + ["    CALL    ctl_min16"] + mov(A, ss + "UMIN", 2)
        a.trailers.setdefault("ctl_cmp16", CTL_CMP16)
        a.x_holds = a.pending = None
        return out


@dataclass(frozen=True)
class Ramp(Op):
    """target moves at most p.accel_step from s.r_applied (p.accel_step 0: no ramp)."""
    contract = "exact: |target - r_applied| <= 32767 + 65535 in 32 bits; the result is an int16"

    def c(self, ctx, ind):
        t = _i(ind)
        return [f"{t}if (core_p.accel_step > 0u) {{",
                f"{t}    int32_t d = (int32_t)target - (int32_t)core_s.r_applied;",
                f"{t}    if (d > (int32_t)core_p.accel_step) {{",
                f"{t}        target = (int16_t)((int32_t)core_s.r_applied + (int32_t)core_p.accel_step);",
                f"{t}    }} else if (d < -(int32_t)core_p.accel_step) {{",
                f"{t}        target = (int16_t)((int32_t)core_s.r_applied - (int32_t)core_p.accel_step);",
                f"{t}    }}", f"{t}}}"]

    def py(self, ctx, ind):
        t = _i(ind)
        return [f"{t}if p.accel_step > 0:", f"{t}    d = target - st.r_applied",
                f"{t}    if d > p.accel_step:", f"{t}        target = st.r_applied + p.accel_step",
                f"{t}    elif d < -p.accel_step:", f"{t}        target = st.r_applied - p.accel_step"]

    def asm(self, a):
        X, Y, A, B = ACC_X, ACC_Y, ACC_A, ACC_B
        step, r, tgt, tmp = ("_core_p + CORE_P_ACCEL_STEP", "_core_s + CORE_S_R_APPLIED", "_core_in + CORE_IN_TARGET",
                             "_core_lw + CORE_LW_TMP")
        out = mov(step, Y, 2) + [f"    MOVF    {Y}, W, A", f"    IORWF   {Y} + 1, W, A", "    BZ      ctl_ramp_done"]
        out += mov(tgt, A, 2) + mov(r, B, 2) + ["    CALL    _core_acc_sext_ab", "    CALL    _core_acc_sub"]
        out += mov(X, tmp, 4) + ["    ; step - d < 0: d > step"] + mov(step, X, 2)
        out += [f"    CLRF    {X} + 2, A", f"    CLRF    {X} + 3, A"] + mov(tmp, Y, 4) + ["    CALL    _core_acc_sub"]
        out += mov(step, B, 2) + [f"    BTFSC   {X} + 3, 7, A", "    BRA     ctl_ramp_add",
                                  "    ; step + d < 0: d < -step"] + mov(B, X, 2)
        out += [f"    CLRF    {X} + 2, A", f"    CLRF    {X} + 3, A", "    CALL    _core_acc_add",
                f"    BTFSS   {X} + 3, 7, A", "    BRA     ctl_ramp_done", "    ; r - step: r + (-step)",
                f"    COMF    {B}, F, A", f"    COMF    {B} + 1, F, A", f"    INFSNZ  {B}, F, A",
                f"    INCF    {B} + 1, F, A", "ctl_ramp_add:", "    ; r + step (the step negated for d < -step)"]
        out += mov(r, A, 2) + [f"    MOVF    {B}, W, A", f"    ADDWF   {A}, F, A", f"    MOVF    {B} + 1, W, A",
                               f"    ADDWFC  {A} + 1, F, A"] + mov(A, tgt, 2) + ["ctl_ramp_done:"]
        a.x_holds = a.pending = None
        return out


@dataclass(frozen=True)
class DirectionHold(Op):
    """s.hold, s.dir after s.u (:func:`picdrive.control_law.direction_hold`)."""
    contract = "exact"

    def c(self, ctx, ind):
        t = _i(ind)
        return [f"{t}core_s.hold = 0u;", f"{t}if (core_s.u != 0) {{",
                f"{t}    uint8_t newdir = (core_s.u < 0) ? 1u : 0u;", f"{t}    if (newdir != core_s.dir) {{",
                f"{t}        core_s.dir = newdir;", f"{t}        core_s.hold = 1u;", f"{t}    }}", f"{t}}}"]

    def py(self, ctx, ind):
        return [f"{_i(ind)}st.dir, hold = direction_hold(st.u, st.dir)", f"{_i(ind)}st.hold = 1 if hold else 0"]

    def asm(self, a):
        A, T, N = ACC_A, ACC_T, ACC_N
        hold, d = "_core_s + CORE_S_HOLD", "_core_s + CORE_S_DIR"
        out = [f"    CLRF    {T}, A", f"    MOVFF   {T}, {hold}"] + mov("_core_s + CORE_S_U", A, 2)
        out += [f"    MOVF    {A}, W, A", f"    IORWF   {A} + 1, W, A", "    BZ      ctl_duty", "    MOVLW   0",
                f"    BTFSC   {A} + 1, 7, A", "    MOVLW   1", f"    MOVWF   {N}, A", f"    MOVFF   {d}, {T}",
                f"    XORWF   {T}, W, A", "    BZ      ctl_duty", f"    MOVFF   {N}, {d}", "    MOVLW   1",
                f"    MOVWF   {T}, A", f"    MOVFF   {T}, {hold}", "ctl_duty:"]
        a.x_holds = a.pending = None
        return out


@dataclass(frozen=True)
class Duty(Op):
    """s.pdc = min(floor(|s.u| KDUTY / 2^DUTY_SH), PDC_MAX) (core_duty)."""
    contract = "|u| KDUTY < 2^32 (the plan's check); saturates at PDC_MAX"

    def c(self, ctx, ind):
        return [f"{_i(ind)}core_s.pdc = core_duty(core_s.u);"]

    def py(self, ctx, ind):
        return [f"{_i(ind)}st.pdc = duty_counts(plan, st.u)"]

    def asm(self, a):
        a.x_holds = a.pending = None
        return ["    CALL    _core_duty_asm"] + mov(ACC_X, "_core_s + CORE_S_PDC", 2)


@dataclass(frozen=True)
class Current(Op):
    """s.current = adc signed by the applied direction."""
    contract = "exact: adc <= 1023"

    def c(self, ctx, ind):
        return [f"{_i(ind)}core_s.current = (core_s.dir != 0u) ? (int16_t)-(int16_t)adc : (int16_t)adc;"]

    def py(self, ctx, ind):
        return [f"{_i(ind)}st.current = -adc if st.dir else adc"]

    def asm(self, a):
        A = ACC_A
        out = mov("_core_in + CORE_IN_ADC", A, 2) + [f"    MOVFF   _core_s + CORE_S_DIR, {ACC_T}",
                                                   f"    MOVF    {ACC_T}, F, A", "    BZ      ctl_cur"]
        out += [f"    COMF    {A}, F, A", f"    COMF    {A} + 1, F, A", f"    INCF    {A}, F, A", "    MOVLW   0",
                f"    ADDWFC  {A} + 1, F, A", "ctl_cur:"] + mov(A, "_core_s + CORE_S_CURRENT", 2)
        a.x_holds = a.pending = None
        return out


@dataclass(frozen=True)
class Let(Op):
    """A local declared with its value: ``ctype name = value;`` or, with ``pick`` = (a, rel, b),
    ``name = (a rel b) ? a : b`` (the larger or smaller of two)."""
    ctype: str
    name: str
    value: object = 0
    pick: tuple = ()
    contract = "exact"

    def c(self, ctx, ind):
        if self.pick:
            a, rel, b = (_c(v, ctx) if v not in ("<", ">") else v for v in self.pick)
            return [f"{_i(ind)}{self.ctype} {self.name} = ({a} {rel} {b}) ? {a} : {b};"]
        return [f"{_i(ind)}{self.ctype} {self.name} = {_c(self.value, ctx)};"]

    def py(self, ctx, ind):
        dst = _py("v." + self.name, ctx)
        if self.pick:
            a, rel, b = (_py(v, ctx) if v not in ("<", ">") else v for v in self.pick)
            return [f"{_i(ind)}{dst} = {a} if {a} {rel} {b} else {b}"]
        return [f"{_i(ind)}{dst} = {_py(self.value, ctx)}"]


@dataclass(frozen=True)
class Div15(Op):
    """acc.a = min(floor(K / d), 32767), K a 32-bit :data:`CONSTS` constant, 1 <= d < 2^17 (the
    accumulator's long division, ACC_DIV15)."""
    k: str
    d: str
    contract = "saturates at 32767; d >= 1 (the caller tests it)"

    def c(self, ctx, ind):
        return [f"{_i(ind)}ACC_DIV15({CONSTS[self.k][0]}, {_c(self.d, ctx)});"]

    def py(self, ctx, ind):
        q = f"{CONSTS[self.k][1]} // {_py(self.d, ctx)}"
        return [f"{_i(ind)}acc_a = {q}", f"{_i(ind)}if acc_a > 32767:", f"{_i(ind)}    acc_a = 32767"]


@dataclass(frozen=True)
class Neg(Op):
    """dst = -dst (int16, |dst| <= 32767 here)."""
    dst: str
    contract = "exact: dst > -32768"

    def c(self, ctx, ind):
        d = _c(self.dst, ctx)
        return [f"{_i(ind)}{d} = (int16_t)-{d};"]

    def py(self, ctx, ind):
        d = _py(self.dst, ctx)
        return [f"{_i(ind)}{d} = -{d}"]


@dataclass(frozen=True)
class Function:
    """A program: C signature, locals (``(C declaration, Python initialisation)``), steps, and the
    Python model's signature, bindings and return."""
    name: str
    c_signature: str
    c_locals: tuple
    steps: tuple
    py_signature: str
    py_bind: tuple = ()
    py_prefix: tuple = ()
    py_prologue: tuple = ()
    py_return: str = ""


# ---------------------------------------------------------------------------
# The law: core_law (drive_core.h's contract)
# ---------------------------------------------------------------------------
LAW = Function(
    "core_law", "void core_law(void)", ("int16_t y = core_s.speed;", "int16_t ey, e, dy;"),
    (
        Schedule("v.y"),
        Note("e = r - y, saturated"),
        Load("s.r_applied"), Sub("v.y"), Sat16(), Store("v.e", "(int16_t)"),
        Note("P on b r - y"),
        MulS("p.b_q14", "s.r_applied"), Asr(14), Sub("v.y"), Sat16(), Store("v.ey", "(int16_t)"),
        MulS("g.kp", "v.ey"), Shift("P"), Store("l.q"),
        Note("D on the measurement"),
        If("s.law.primed", "!=", 0, (Load("s.law.y_prev"), Sub("v.y"), Sat16(), Store("v.dy", "(int16_t)")),
           (Set("v.dy", 0), Set("s.law.primed", 1, "1u")), b_c="0u", labels=("law_primed", "law_dy")),
        MulS("g.kdts", "v.dy", zero_skip=("law_dmul", "law_dstore")), Shift("D"),
        When("CORE_DFILT_A", (Sub("s.law.d_filt"), MulQ15("DFILT_A"), Add("s.law.d_filt"))),
        Store("s.law.d_filt"),
        Note("current feedback: q = (P + D) - C, everything but the integral"),
        MulS("g.kc", "s.current"), Shift("C"), Store("l.new"),
        Load("l.q"), Add("s.law.d_filt"), Sub("l.new"), Store("l.q"),
        Note("I, integrated only into the output headroom"),
        MulS("g.kits", "v.e"), Shift("I"), Store("l.inc"),
        Add("s.law.integ"), Store("l.new"),
        Headroom(),
        When("CORE_KFF", (
            Note("reference feedforward: the preload core_control set for the change of r of this sample"),
            Load("s.law.integ"), Add("s.ff"), Store("s.law.integ"))),
        Clamp("s.law.integ", "I_LIM"),
        Move("s.law.y_prev", "v.y"),
        Load("s.law.integ"), Asr("DI"), Add("l.q"),
        ClampStore("s.u", "s.umin", "s.umax"),
    ),
    "def law_step(plan, p, st, r, y, i, umin, umax, ff=0):",
    py_bind=(("v.y", "y"), ("s.r_applied", "r"), ("s.speed", "y"), ("s.current", "i"), ("s.umin", "umin"),
             ("s.umax", "umax"), ("s.ff", "ff"), ("s.u", "u")),
    py_prefix=(("s.law.", "st."),),
    py_return="u",
)

# ---------------------------------------------------------------------------
# The control around it: core_control (drive_core.h's contract)
# ---------------------------------------------------------------------------
CONTROL = Function(
    "core_control", "void core_control(int16_t target, uint16_t adc)", ("int16_t hi, lo;",),
    (
        Current(),
        Note("backup current limiter: walk the |u| cap down while the bus current exceeds the limit"),
        WalkCap(),
        Note("the window that keeps |i| <= I_lim at the present speed: Kb y -+ R_line I_lim"),
        MulS("K.R_CNT", "p.ilim"), Shift("R"), Store("l.new"),
        MulS("K.KB", "s.speed"), Shift("KB"), Store("l.q"),
        Window(),
        Note("setpoint ramp"),
        Ramp(),
        When("CORE_KFF", (
            Note("reference feedforward: the integrator preload of the change of r (the multiply only then)"),
            LoadDiff("v.target", "s.r_applied"), Sat16(),
            If("x", "!=", 0, (MulS("K.KFF", "x"), Shift("FF")), labels=("ctl_ff_store",)),
            Store("s.ff"))),
        Move("s.r_applied", "v.target"),
        CallLaw(),
        DirectionHold(),
        Duty(),
    ),
    "def core_control(plan, p, st, target, adc):",
    py_bind=(("v.target", "target"),),
    py_return="st.u",
)


# ---------------------------------------------------------------------------
# The speed from the halls: core_speed_hall (drive_core.h's contract)
# ---------------------------------------------------------------------------
SPEED_HALL = Function(
    "core_speed_hall", "void core_speed_hall(uint16_t period, uint16_t elapsed, uint8_t valid, uint8_t forward)", (),
    (
        Let("uint16_t", "p", pick=("v.period", ">", "v.elapsed")),
        Let("int16_t", "w", 0),
        If("v.valid", "!=", 0, (
            Div15("K_SPEED", "v.p"), Move("v.w", "acc.a"),
            If("v.forward", "==", 0, (Neg("v.w"),), b_c="0u"),
        ), b_c="0u", and_=("v.p", "!=", 0, "0u")),
        Move("s.speed", "v.w"),
    ),
    "def speed_hall(plan, st, period, elapsed, valid, forward):",
    py_bind=(("v.period", "period"), ("v.elapsed", "elapsed"), ("v.valid", "valid"), ("v.forward", "forward")),
    py_return="st.speed",
)


def c_source(fn: Function) -> str:
    """The C function of a program (drive_core.c)."""
    ctx = _Ctx()
    body = [f"    {d}" for d in fn.c_locals] + _block(fn.steps, ctx, "c", 4)
    return "\n".join([fn.c_signature, "{"] + body + ["}"])


def asm_source(fn: Function, plan, bit: dict) -> str:
    """The PIC18 assembly of a program for ``plan`` (the body of a ``__naked`` function):
    ``bit``: p18f4431.inc's bit positions by register (:func:`picdrive.firmware.p18f4431.bits`)."""
    a = _Asm(plan, bit)
    a.last = _flat(fn.steps, plan)[-1]
    body = _asm_block(fn.steps, a)
    if not a.returned:
        body.append("    RETURN")
    for lines in a.trailers.values():
        body += [""] + lines
    return "\n".join(body)


def python_source(fn: Function) -> str:
    """The Python model's function of a program."""
    ctx = _Ctx(fn.py_bind, fn.py_prefix)
    body = [f"    {ln}" for ln in fn.py_prologue] + _block(fn.steps, ctx, "py", 4)
    if fn.py_return:
        body.append(f"    return {fn.py_return}")
    return "\n".join([fn.py_signature] + body)


def model(prims: dict, fns=(LAW, CONTROL, SPEED_HALL)) -> dict:
    """The Python model's functions of the programs ``fns``, by name (``law_step``,
    ``core_control``), compiled from :func:`python_source`; ``prims``: the integer primitives the
    source calls (``sat32``, ``shift32``, ``shl_sat32``, ``duty_counts``: fixedpoint's)."""
    ns = dict(prims, walk_cap=walk_cap, direction_hold=direction_hold)
    out = {}
    for fn in fns:
        exec(compile(python_source(fn), f"<core_program {fn.name}>", "exec"), ns)
        out[fn.py_signature.split()[1].split("(")[0]] = ns[fn.py_signature.split()[1].split("(")[0]]
    return out
