"""Bit-exact on the target: drive_core.c compiled by SDCC's pic16 port and run on the PIC18 core
in gpsim, against the Python model (picdrive.firmware.fixedpoint), on random vectors (10^4 per
function).  Configurations: the bundled duy2008 fuzzy-hinf build (2 rules: the assembly law), the
hall-speed mixed-pid build (1 rule), the reference feedforward, and (MORE) one synthetic build
per combination of the speed source, the derivative filter and the feedforward, 1 to 8 rules
(SDCC's C law and the assembly law on both speed sources); every combination of 1 to 8 rules
(ALL) under the slow mark.

The chip generates its own vectors (xorshift32, biased to int16/int32 extremes and saturation) and
folds every output into a checksum per function (rotate-xor and a sum, both 32-bit) and a 16-bit
checkpoint (the sum's low 16 bits) every CK vectors; Python runs the same generator through the
model and computes the same figures.  A mismatch is located by a second, short run that records one checkpoint per
vector from the first failing interval on: the report names the function, the vector index, its
inputs and the model's outputs.

Functions: core_law, core_control (limiter, ramp, law, duty, direction), core_speed_encoder (or
core_speed_hall), core_duty.  The law parameters cycle through the design's own and random sets
(tests/support/core_c.rand_params, the host comparison's generator).  The mutation tests make sure the
comparison can fail: a one-LSB change of a constant and a lost upper partial product (the M/T
product is assembly on the chip: the C form's missing 32-bit cast loses the same half).  The
"duty" checksum also folds core_premise_k (the accumulator's 16-bit quotient on the chip).

Why SDCC's C law runs on the chip too: SDCC 4.2 pic16 once miscompiled the C core_law (a
single-use temporary coalesced with the global operand it was later stored to, past an
intervening store: on the chip the law ignored its current feedback, the gcc build did not).  The
C law is what SDCC compiles for plans with more than 2 rules or the derivative filter (MORE
below); the assembly law of the other plans is held by test_a_changed_law_instruction_is_caught.

MODEL AGAINST C, FIXED: core_speed_encoder on the chip equalled the gcc build, but both differed
from fixedpoint.speed_encoder when w_avg = -32768, no count in the sample and K / t5 > 32767
(t5 < 62 ticks): the C's div_sat15 caps the one-count bound at 32767 < |-32768| and sets
w_avg = -32767, the model's unsaturated bound K // t5 left -32768 (first at vector 8020: valid 1,
pos = pos_prev = 65452, t5 = 54, t5_prev 33068, w_avg -32768).  The bound is a speed (int16): the
model now caps it at 32767 as the C does, and the speed encoder is compared too.
"""
import re
import subprocess

import numpy as np
import pytest

from picdrive.firmware import codegen, fixedpoint as fx, gpsim
from picdrive.paths import repo_root
from picdrive.profile import load_profile
from picdrive.firmware import target
from picdrive.firmware.target import build_hex
from support import core_c

N_VECTORS = 10_000          # per function
CK = 100                    # vectors per checkpoint
N_PARAM_SETS = 8
SEED = 0x2545F491
M32 = 0xFFFFFFFF
EXT16 = (-32768, -32767, -1, 0, 1, 32766, 32767, -16384)
EXT32 = (-2 ** 31, 2 ** 31 - 1, -1, 0)
FUNCS = ("law", "control", "speed", "duty")   # "duty": core_duty and core_premise_k
#: compared by the tests (all four)
CHECKED = FUNCS
N_SLOTS = (0xF00 - gpsim.RESULT_ADDR - 32) // 8      # checkpoints that fit the result area

HARNESS = r"""
/* bit-exact harness (tests/test_target_bitexact.py): GENERATED, test build only */
#include <stdint.h>
#include "drive_core.h"
#pragma config WDTEN = OFF
%(eestub)s__at(0x%(res)03X) volatile uint32_t res[8];
__at(0x%(slots)03X) volatile uint16_t slot[%(n_slots)d][4];
static const int16_t ptab[%(np)d][4 * CORE_N_RULES + 9] = { %(ptab)s };
static const int16_t ext16[8] = { -32767 - 1, -32767, -1, 0, 1, 32766, 32767, -16384 };
static const int32_t ext32[4] = { INT32_MIN, INT32_MAX, -1, 0 };
#define cp core_p
#define cs core_s
static uint32_t x, hh[4], ss[4];
static uint8_t f;

void harness_done(void) { for (;;) { } }

static uint32_t rnd(void)
{
    uint32_t t;
    t = x << 13; x ^= t;
    t = x >> 17; x ^= t;
    t = x << 5; x ^= t;
    return x;
}

static int16_t r16(void)
{
    uint32_t v = rnd();
    uint8_t m = (uint8_t)(v >> 24);
    if (m < 48u) return ext16[m & 7u];
    if (m < 128u) return (int16_t)((int16_t)(uint16_t)(v & 0x3FFu) - 512);
    return (int16_t)(uint16_t)v;
}

static int32_t r32(void)
{
    uint32_t v = rnd();
    uint8_t m = (uint8_t)v;
    if (m < 32u) return ext32[m & 3u];
    if (m < 128u) return (int32_t)(int16_t)(uint16_t)(v >> 8);
    return (int32_t)v;
}

static void fold(uint16_t v)
{
    uint32_t t = hh[f] >> 31;
    hh[f] = (hh[f] << 1) | t;
    hh[f] ^= v;
    ss[f] += v;
}

static void fold32(int32_t v)
{
    fold((uint16_t)(uint32_t)v);
    fold((uint16_t)((uint32_t)v >> 16));
}

static void law_state(core_law_t *l)
{
    l->integ = r32();
    l->d_filt = r32();
    l->y_prev = r16();
    l->primed = (uint8_t)(rnd() & 1u);
    l->mu1 = 0;
}

static void fold_law(const core_law_t *l)
{
    fold32(l->integ); fold32(l->d_filt); fold((uint16_t)l->y_prev); fold(l->primed); fold((uint16_t)l->mu1);
}

void main(void)
{
    uint16_t k, s, n = %(n)du, ck = %(ck)du, t0 = %(t0)du;
    uint8_t j, q;
    int16_t r;
    uint16_t a, pos, t5;
    uint32_t v;
    x = %(seed)sUL;
    for (k = 0u; k < n; k++) {
        __asm
        CLRWDT
        __endasm;
        q = (uint8_t)(k %% %(np)du);
        for (j = 0u; j < CORE_N_RULES; j++) {
            cp.kp[j] = ptab[q][j]; cp.kits[j] = ptab[q][CORE_N_RULES + j];
            cp.kdts[j] = ptab[q][2 * CORE_N_RULES + j]; cp.kc[j] = ptab[q][3 * CORE_N_RULES + j];
        }
        cp.premise_lo = ptab[q][4 * CORE_N_RULES]; cp.premise_hi = ptab[q][4 * CORE_N_RULES + 1];
        cp.mu_k = (uint16_t)ptab[q][4 * CORE_N_RULES + 2]; cp.b_q14 = ptab[q][4 * CORE_N_RULES + 3];
        cp.u_min = ptab[q][4 * CORE_N_RULES + 4]; cp.u_max = ptab[q][4 * CORE_N_RULES + 5];
        cp.controller = (uint8_t)ptab[q][4 * CORE_N_RULES + 6]; cp.ilim = ptab[q][4 * CORE_N_RULES + 7];
        cp.accel_step = (uint16_t)ptab[q][4 * CORE_N_RULES + 8];
        /* core_law */
        f = 0u;
        law_state(&cs.law);
        cs.r_applied = r16(); cs.speed = r16(); cs.current = r16();
#if CORE_KFF
        cs.ff = r32();
#endif
        cs.umin = cp.u_min; cs.umax = cp.u_max;
        core_law();
        fold((uint16_t)cs.u); fold_law(&cs.law);
        /* core_control */
        f = 1u;
        law_state(&cs.law);
        cs.speed_valid = (uint8_t)(rnd() & 1u);
        cs.r_applied = r16();
        v = rnd();
        cs.cap = (int16_t)(uint16_t)(v & 0x7FFFu);
        if (cs.cap > CORE_U_LIMIT) cs.cap = CORE_U_LIMIT;
        cs.speed = r16();
        cs.current = 0; cs.u = 0; cs.hold = 0; cs.pdc = 0;
        cs.dir = (uint8_t)(rnd() & 1u);
        r = r16();
        a = (uint16_t)(rnd() & 0x3FFu);
        core_control(r, a);
        fold((uint16_t)cs.u); fold_law(&cs.law);
        fold((uint16_t)cs.r_applied); fold((uint16_t)cs.cap); fold((uint16_t)cs.current); fold((uint16_t)cs.u);
        fold(cs.dir); fold(cs.hold); fold(cs.pdc);
        /* speed measurement */
        f = 2u;
        cs.speed_valid = (uint8_t)(rnd() & 1u);
        cs.w_avg = r16();
        cs.pos_prev = (uint16_t)r16();
        cs.t5_prev = (uint16_t)r16();
        cs.t2_prev = (uint8_t)rnd();
        v = rnd();
        j = (uint8_t)(v >> 24);
        if (j < 100u) pos = (uint16_t)(cs.pos_prev + (uint16_t)(int16_t)(int8_t)(uint8_t)(v >> 8));
        else if (j < 140u) pos = cs.pos_prev;
        else pos = (uint16_t)v;
        v = rnd();
        t5 = ((uint8_t)(v >> 24) < 96u) ? (uint16_t)(v & 0xFFu) : (uint16_t)v;
        j = (uint8_t)(((uint8_t)(v >> 16) & 7u) == 0u);
#if %(hall)d
        core_speed_hall(pos, t5, (uint8_t)(j ^ 1u), (uint8_t)((v >> 20) & 1u));
#else
        core_speed_encoder(pos, t5, (uint8_t)(v >> 8), j);
#endif
        fold((uint16_t)cs.speed); fold(cs.speed_valid); fold((uint16_t)cs.speed); fold((uint16_t)cs.w_avg);
        fold(cs.pos_prev); fold(cs.t5_prev); fold(cs.t2_prev);
        /* core_duty */
        f = 3u;
        fold(core_duty(r16()));
        {   /* the membership slope: the accumulator's 16-bit quotient on the chip */
            int16_t plo = r16(), phi = r16();
            fold(core_premise_k(plo, phi));
        }
        s = 0xFFFFu;
        if (k >= t0) {
            if (k - t0 < %(n_slots)du) s = k - t0;
        } else if ((uint16_t)(k + 1u) %% ck == 0u) {
            s = k / ck;
        }
        if (s < %(n_slots)du) {
            for (f = 0u; f < 4u; f++) slot[s][f] = (uint16_t)ss[f];
        }
    }
    for (f = 0u; f < 4u; f++) { res[2u * f] = hh[f]; res[2u * f + 1u] = ss[f]; }
    harness_done();
}
"""


# --- the generator and the model, as the harness runs them ------------------------------------
class Rng:
    def __init__(self, seed):
        self.x = seed

    def rnd(self):
        x = self.x
        x ^= (x << 13) & M32
        x ^= x >> 17
        x ^= (x << 5) & M32
        self.x = x
        return x

    def r16(self):
        v = self.rnd()
        m = v >> 24
        if m < 48:
            return EXT16[m & 7]
        if m < 128:
            return (v & 0x3FF) - 512
        return fx._s16(v)

    def r32(self):
        v = self.rnd()
        m = v & 0xFF
        if m < 32:
            return EXT32[m & 3]
        if m < 128:
            return fx._s16(v >> 8)
        return v - (1 << 32) if v >> 31 else v


class Sum:
    def __init__(self):
        self.h = self.s = 0

    def fold(self, v):
        v &= 0xFFFF
        self.h = (((self.h << 1) | (self.h >> 31)) & M32) ^ v
        self.s = (self.s + v) & M32

    def fold32(self, v):
        self.fold(v)
        self.fold((v & M32) >> 16)


def param_sets(plan):
    """The design's own parameters, then random ones (the host comparison's generator)."""
    rng = np.random.default_rng(7)
    sets = [fx.law_params_from_plan(plan)]
    while len(sets) < N_PARAM_SETS:
        sets.append(core_c.rand_params(plan, rng, wide=len(sets) % 3 == 0))
    return sets


def param_row(p):
    return [*p.kp, *p.kits, *p.kdts, *p.kc, p.premise_lo, p.premise_hi, fx._s16(p.mu_k), p.b_q14,
            p.u_min, p.u_max, p.controller, p.ilim, fx._s16(p.accel_step)]


def model_run(plan, n, t0, n_slots):
    """The model over the harness's vectors: (8 sums, {slot: 4 checkpoints}, inputs of each vector)."""
    g = Rng(SEED)
    sums = [Sum() for _ in FUNCS]
    sets = param_sets(plan)
    slots, inputs = {}, []

    def law_state():
        integ, d = g.r32(), g.r32()
        yp = g.r16()
        return fx.LawState(integ=integ, d_filt=d, y_prev=yp, primed=g.rnd() & 1, mu1=0)

    def fold_law(h, s):
        h.fold32(s.integ), h.fold32(s.d_filt), h.fold(s.y_prev), h.fold(s.primed), h.fold(s.mu1)

    for k in range(n):
        p = sets[k % N_PARAM_SETS]
        h = sums[0]
        ls = law_state()
        r, y, i = g.r16(), g.r16(), g.r16()
        ff = g.r32() if plan.kff else 0
        vin = {"law": (f"params set {k % N_PARAM_SETS} {p}", f"state {ls}", f"r={r} y={y} i={i} ff={ff}")}
        u = fx.law_step(plan, p, ls, r, y, i, p.u_min, p.u_max, ff)
        h.fold(u), fold_law(h, ls)
        vin["law"] += (f"-> u={u} state {ls}",)
        h = sums[1]
        st = fx.CoreState(law=law_state())
        st.speed_valid = g.rnd() & 1
        st.r_applied = g.r16()
        st.cap = min(g.rnd() & 0x7FFF, plan.u_limit)
        st.speed = g.r16()
        st.dir = g.rnd() & 1
        target = g.r16()
        adc = g.rnd() & 0x3FF
        vin["control"] = (f"params set {k % N_PARAM_SETS}", f"state {st}", f"target={target} adc={adc}")
        u = fx.core_control(plan, p, st, target, adc)
        h.fold(u), fold_law(h, st.law)
        for v in (st.r_applied, st.cap, st.current, st.u, st.dir, st.hold, st.pdc):
            h.fold(v)
        vin["control"] += (f"-> u={u} state {st}",)
        h = sums[2]
        st = fx.CoreState(speed_valid=g.rnd() & 1)
        st.w_avg = g.r16()
        st.pos_prev = g.r16() & 0xFFFF
        st.t5_prev = g.r16() & 0xFFFF
        st.t2_prev = g.rnd() & 0xFF
        v = g.rnd()
        m = v >> 24
        if m < 100:
            b = (v >> 8) & 0xFF
            pos = (st.pos_prev + (b - 256 if b & 0x80 else b)) & 0xFFFF
        elif m < 140:
            pos = st.pos_prev
        else:
            pos = v & 0xFFFF
        v = g.rnd()
        t5 = (v & 0xFF) if (v >> 24) < 96 else (v & 0xFFFF)
        j = 1 if ((v >> 16) & 7) == 0 else 0
        vin["speed"] = (f"state {st}", f"pos={pos} t5={t5} t2={(v >> 8) & 0xFF} ovf/valid={j} v={v:#x}")
        if plan.speed_source == "hall":
            w = fx.speed_hall(plan, st, pos, t5, j ^ 1, (v >> 20) & 1)
        else:
            w = fx.speed_encoder(plan, st, pos, t5, (v >> 8) & 0xFF, j)
        for x in (w, st.speed_valid, st.speed, st.w_avg, st.pos_prev, st.t5_prev, st.t2_prev):
            h.fold(x)
        vin["speed"] += (f"-> w={w} state {st}",)
        uu = g.r16()
        sums[3].fold(fx.duty_counts(plan, uu))
        plo, phi = g.r16(), g.r16()
        mk = fx.premise_k(plo, phi, plan.n_rules, plan.mu_sh)
        sums[3].fold(mk)
        vin["duty"] = (f"u={uu} -> {fx.duty_counts(plan, uu)}", f"premise_k({plo}, {phi}) -> {mk}")
        inputs.append(vin)
        s = None
        if k >= t0:
            if k - t0 < n_slots:
                s = k - t0
        elif (k + 1) % CK == 0:
            s = k // CK
        if s is not None and s < n_slots:
            slots[s] = [x.s & 0xFFFF for x in sums]
    return [v for x in sums for v in (x.h, x.s)], slots, inputs


# --- the chip -----------------------------------------------------------------------------------
def chip_run(folder, out, plan, n, t0=0xFFFF):
    """Build the harness around ``folder``'s drive_core.c, run it in gpsim: (8 sums, {slot: 4})."""
    n_slots = min(N_SLOTS, n // CK if t0 == 0xFFFF else N_SLOTS)
    sets = param_sets(plan)
    ptab = ", ".join("{" + ", ".join(str(v) for v in param_row(p)) + "}" for p in sets)
    harness = HARNESS % {"eestub": target.EEPROM_GPTR_STUBS, "res": gpsim.RESULT_ADDR, "slots": gpsim.RESULT_ADDR + 32, "n_slots": N_SLOTS,
                         "np": N_PARAM_SETS, "ptab": ptab, "n": n, "ck": CK, "t0": t0, "seed": f"0x{SEED:08X}",
                         "hall": int(plan.speed_source == "hall")}
    out.mkdir(parents=True, exist_ok=True)
    (out / "bitexact.lkr").write_text(gpsim.timing_lkr())
    b = build_hex(folder, out, name="bitexact", linker_script=out / "bitexact.lkr", sources=(),
                  extra_c={"drive_core_test.c": target.TEST_BUILD_CORE, "harness.c": harness})
    script = out / "bitexact.stc"
    script.write_text("\n".join([f"break e 0x{b.functions['_harness_done'].address:x}",
                                 "break c 2000000000", "run", "dump r", "quit", ""]))
    r = subprocess.run([gpsim._gpsim(), "-i", "-S", "disable", "-p", gpsim.TIMING_PROCESSOR, "-c", str(script),
                        str(b.hex_path.resolve())], capture_output=True, stdin=subprocess.DEVNULL, timeout=900)
    text = r.stdout.decode("latin-1") + r.stderr.decode("latin-1")
    (out / "bitexact.out").write_text(text)
    assert re.search(rf"0x0*{b.functions['_harness_done'].address:x}\b", text, re.I), \
        f"the harness did not reach harness_done (see {out / 'bitexact.out'})"
    mem = gpsim._dump(text)

    def word(a, nb):
        return sum(mem[a + i] << (8 * i) for i in range(nb))
    sums = [word(gpsim.RESULT_ADDR + 4 * i, 4) for i in range(8)]
    slots = {s: [word(gpsim.RESULT_ADDR + 32 + 8 * s + 2 * f, 2) for f in range(4)] for s in range(n_slots)}
    return sums, slots


def compare(folder, out, plan, n=N_VECTORS, funcs=CHECKED):
    """Chip against model: {function: None if equal, else a description of the first failing vector}."""
    chip, chip_slots = chip_run(folder, out / "run", plan, n)
    model, model_slots, inputs = model_run(plan, n, 0xFFFF, N_SLOTS)
    verdict = {}
    for fi, name in enumerate(FUNCS):
        if name not in funcs:
            continue
        if chip[2 * fi:2 * fi + 2] == model[2 * fi:2 * fi + 2]:
            verdict[name] = None
            continue
        bad = [s for s in sorted(model_slots) if chip_slots[s][fi] != model_slots[s][fi]]
        start = bad[0] * CK if bad else (n // CK) * CK
        start = max(0, min(start, n - 1))
        tchip, tslots = chip_run(folder, out / f"trace-{name}", plan, min(n, start + N_SLOTS), t0=start)
        _m, mslots, _i = model_run(plan, min(n, start + N_SLOTS), start, N_SLOTS)
        first = next((start + s for s in sorted(mslots) if tslots[s][fi] != mslots[s][fi]), None)
        if first is None:
            verdict[name] = f"sums differ (chip {chip[2 * fi:2 * fi + 2]}, model {model[2 * fi:2 * fi + 2]})"
        else:
            verdict[name] = f"first failing vector {first}: " + "; ".join(inputs[first][name]) + " (model)"
    return verdict


@pytest.fixture(scope="module")
def design(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bitexact")
    prof = load_profile("duy2008")
    fw = codegen.generate(prof, repo_root() / "examples" / "duy2008.fuzzy-hinf.design.json")
    out = codegen.write_firmware(fw, tmp / "fw", check=False)
    return fw.plan, out, tmp


@pytest.fixture(scope="module")
def design_halls(tmp_path_factory):
    """duy2008_halls mixed-pid: the speed from the halls (core_speed_hall on the chip, where the
    duy2008 build runs core_speed_encoder) and one rule with a derivative term."""
    tmp = tmp_path_factory.mktemp("bitexact-halls")
    prof = load_profile("duy2008_halls")
    fw = codegen.generate(prof, repo_root() / "examples" / "duy2008_halls.mixed-pid.design.json")
    out = codegen.write_firmware(fw, tmp / "fw", check=False)
    assert fw.plan.speed_source == "hall"
    return fw.plan, out, tmp


def ff_firmware(tmp):
    """duy2008 fuzzy-hinf with the reference feedforward on (control.reference_feedforward: the
    gain of picdrive.design.verify.with_reference_ff on the DC equivalent), generated into tmp."""
    import dataclasses
    from picdrive.design.verify import with_reference_ff
    from picdrive.result import load_design, save_design
    prof = load_profile("duy2008")
    res = load_design(str(repo_root() / "examples" / "duy2008.fuzzy-hinf.design.json"))
    res = dataclasses.replace(res, law=with_reference_ff(prof, res.law))
    path = save_design(res, tmp / "ff.design.json")
    fw = codegen.generate(prof, path)
    return fw, codegen.write_firmware(fw, tmp / "fw-ff", check=False)


@pytest.fixture(scope="module")
def design_ff(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bitexact-ff")
    fw, out = ff_firmware(tmp)
    return fw.plan, out, tmp


def test_generator_mirrors_are_consistent():
    # the Python mirror of the harness's xorshift32: the published sequence for seed 1
    g = Rng(1)
    assert [g.rnd() for _ in range(3)] == [270369, 67634689, 2647435461]


def test_pic18_code_matches_the_model(design):
    plan, folder, tmp = design
    verdict = compare(folder, tmp / "good", plan)
    assert verdict == {f: None for f in CHECKED}, verdict


def test_pic18_code_matches_the_model_with_the_speed_from_the_halls(design_halls):
    plan, folder, tmp = design_halls
    verdict = compare(folder, tmp / "good", plan)
    assert verdict == {f: None for f in CHECKED}, verdict


def test_pic18_code_matches_the_model_with_reference_feedforward(design_ff):
    """The reference feedforward's code (core_control's preload of each reference change, core_law's
    add before the clamp) is compiled in only when the plan has a gain: the same vectors on that
    build (the control vectors change r_applied at almost every vector, the law vectors give any
    int32 preload)."""
    plan, folder, tmp = design_ff
    assert plan.kff != 0 and "ctl_ff_store" in (folder / "drive_core.c").read_text()
    verdict = compare(folder, tmp / "good", plan)
    assert verdict == {f: None for f in CHECKED}, verdict


def test_a_changed_feedforward_constant_is_caught(design_ff):
    """KFF one LSB off in core_control's assembly must make the chip's control disagree with the model."""
    plan, folder, tmp = design_ff
    text = (folder / "drive_core.c").read_text()
    start = text.index("ctl_ramp_done:")                 # core_control_asm: the feedforward follows the ramp
    m = re.compile(r"    MOVLW   (\d+)\n    MOVWF   _core_acc \+ CORE_ACC_A, A\n").search(text, start)
    assert m and m.start() - start < 900, "the feedforward's literal was not found"
    v = int(m[1])
    lit = m[0].replace(f"MOVLW   {v}", f"MOVLW   {v + 1 if v < 255 else v - 1}")
    bad = _mutated(folder, tmp, "kff", "drive_core.c", text[start:m.end()], text[start:m.start()] + lit)
    verdict = compare(bad, tmp / "kff-run", plan, n=500, funcs=("law", "control"))
    assert verdict["control"] is not None and verdict["law"] is None, verdict


def test_a_changed_law_instruction_is_caught(design):
    """On SDCC the law is assembly (drive_core.c's core_law_asm, on the accumulator primitives):
    one changed literal in it (mu1 = 4097 - frac instead of 4096 - frac) must make the chip
    disagree with the model, so the comparison runs the assembly the HEX holds."""
    plan, folder, tmp = design
    old = ("    MOVLW   0x10\n    ADDWFC  _core_acc + CORE_ACC_X + 1, F, A\n"
           "    MOVFF   _core_acc + CORE_ACC_X, _core_s + CORE_S_LAW_MU1\n")
    bad = _mutated(folder, tmp, "asm", "drive_core.c", old, old.replace("0x10", "0x11"))
    verdict = compare(bad, tmp / "asm-run", plan, n=200, funcs=("law", "control"))
    assert verdict["law"] is not None and verdict["law"].startswith("first failing vector"), verdict
    assert verdict["control"] is not None, verdict


def _mutated(folder, tmp, name, fn, old, new):
    dst = tmp / name
    dst.mkdir()
    for p in folder.iterdir():
        if p.is_file() and p.suffix in (".c", ".h"):
            (dst / p.name).write_text(p.read_text())
    text = (dst / fn).read_text()
    assert text.count(old) == 1, (fn, old)
    (dst / fn).write_text(text.replace(old, new))
    return dst


def test_a_one_lsb_constant_change_is_caught(design):
    """The duty's constant as the chip uses it (core_duty_asm's literal, generated from CORE_KDUTY)
    one LSB off must make the chip disagree with the model."""
    plan, folder, tmp = design
    text = (folder / "drive_core.c").read_text()
    m = re.search(r"    MOVLW   (\d+)( +; CORE_KDUTY, bits 0-7\n)", text)
    v = int(m[1])
    bad = _mutated(folder, tmp, "lsb", "drive_core.c", m[0], f"    MOVLW   {v + 1 if v < 255 else v - 1}{m[2]}")
    verdict = compare(bad, tmp / "lsb-run", plan, n=2000)
    assert verdict["duty"] is not None, verdict


def test_a_lost_upper_partial_product_is_caught(design):
    """The M/T product mag x K_SPEED (K > 2^16: two 16x16 partial products) is assembly on the
    chip.  The C form's hazard, a missing 32-bit cast before `hi << 16` (int is 16 bits on the
    PIC18), loses the upper partial product; the same loss in the assembly (its add into the
    product's upper half removed) must make the chip disagree with the model."""
    plan, folder, tmp = design
    old = ("    ; x += (mag K_hi) 2^16: the upper partial product\n"
           "    MOVFF   _core_lw + CORE_LW_INC, _core_acc + CORE_ACC_T\n"
           "    MOVF    _core_acc + CORE_ACC_T, W, A\n"
           "    ADDWF   _core_acc + CORE_ACC_X + 2, F, A\n"
           "    MOVFF   _core_lw + CORE_LW_INC + 1, _core_acc + CORE_ACC_T\n"
           "    MOVF    _core_acc + CORE_ACC_T, W, A\n"
           "    ADDWFC  _core_acc + CORE_ACC_X + 3, F, A\n")
    bad = _mutated(folder, tmp, "upper", "drive_core.c", old, "")
    verdict = compare(bad, tmp / "upper-run", plan, n=2000)
    assert verdict["speed"] is not None, verdict


MAX_RULES = 8                   # protocol.build_table's limit
#: The configurations the fixtures above leave out, one build each (about 6 s apiece): every
#: combination of the speed source, the derivative filter and the reference feedforward once,
#: with rule counts from 1 to the most the protocol holds, so both laws (the assembly one: at most
#: 2 rules, no filter; SDCC's C one otherwise) run on both speed sources.  (profile, rules, filter, ff)
MORE = [("duy2008", 3, False, False), ("duy2008", 8, True, False), ("duy2008", 1, False, True),
        ("duy2008", 4, True, True), ("duy2008_halls", 2, False, False), ("duy2008_halls", 5, True, False),
        ("duy2008_halls", 1, False, True), ("duy2008_halls", 2, True, True)]
#: every configuration the generator can emit for these motors: 1 to MAX_RULES rules, with and
#: without the filter and the feedforward, both speed sources (the slow test; MORE in the suite)
ALL = [(pn, nr, d, f) for pn in ("duy2008", "duy2008_halls") for nr in range(1, MAX_RULES + 1)
       for d in (False, True) for f in (False, True)]


def _synthetic(tmp, profile: str, nr: int, dfilt: bool, ff: bool):
    from picdrive.control_law import Rule, ScheduledLaw
    from picdrive.result import DesignResult, save_design
    prof = load_profile(profile)
    rules = tuple(Rule(0.2 - 0.01 * j, 5.0 - 0.3 * j, 0.0005 if dfilt else 0.0, 10.0 - j) for j in range(nr))
    law = ScheduledLaw(rules=rules, premise_rad_s=(0.0, 2600 * 3.141592653589793 / 30), sample_time_s=1e-3,
                       u_min_v=-44.16, u_max_v=44.16, derivative_filter_hz=200.0 if dfilt else None,
                       reference_ff_v_s_per_rad=0.1 if ff else 0.0)
    path = save_design(DesignResult(method="zn", status="verified", profile_name=prof.name,
                                    profile_sha256=prof.sha256, law=law, variant="test-fixture"),
                       tmp / "synthetic.design.json")
    fw = codegen.generate(prof, path)
    return fw.plan, codegen.write_firmware(fw, tmp / "fw", check=False)


def _ids(cfgs):
    return [f"{p}-r{n}{'-dfilt' if d else ''}{'-ff' if f else ''}" for p, n, d, f in cfgs]


def _matches(tmp_path, profile, nr, dfilt, ff):
    plan, folder = _synthetic(tmp_path, profile, nr, dfilt, ff)
    assert (plan.n_rules, bool(plan.dfilt_a), bool(plan.kff)) == (nr, dfilt, ff)
    assert plan.speed_source == ("hall" if profile.endswith("halls") else "encoder")
    # which law the chip runs: the assembly one (at most 2 rules, no filter) or SDCC's C
    assert ("#define CORE_LAW_ASM 1" in (folder / "drive_core.c").read_text()) == (nr <= 2 and not dfilt)
    verdict = compare(folder, tmp_path, plan)
    assert verdict == {f: None for f in CHECKED}, verdict


@pytest.mark.parametrize("profile,nr,dfilt,ff", MORE, ids=_ids(MORE))
def test_pic18_code_matches_the_model_in_more_configurations(tmp_path, profile, nr, dfilt, ff):
    _matches(tmp_path, profile, nr, dfilt, ff)


@pytest.mark.slow
@pytest.mark.parametrize("profile,nr,dfilt,ff", [c for c in ALL if c not in MORE], ids=_ids([c for c in ALL if c not in MORE]))
def test_pic18_code_matches_the_model_in_every_configuration(tmp_path, profile, nr, dfilt, ff):
    _matches(tmp_path, profile, nr, dfilt, ff)


def _mutated_law(name):
    """core_program.LAW with one LSB changed: the setpoint weight's shift (b r / 2^14) by one, or
    the integrator's bound +-I_lim by one."""
    import dataclasses
    from picdrive.firmware import core_program as cp
    if name == "shift":
        assert cp.Asr(14) in cp.LAW.steps
        return dataclasses.replace(cp.LAW, steps=tuple(cp.Asr(15) if op == cp.Asr(14) else op for op in cp.LAW.steps))
    assert name == "bound"
    assert cp.Clamp("s.law.integ", "I_LIM") in cp.LAW.steps
    return dataclasses.replace(cp.LAW, steps=tuple(cp.Clamp("s.law.integ", "I_LIM_1") if op == cp.Clamp("s.law.integ", "I_LIM")
                                                   else op for op in cp.LAW.steps))


@pytest.mark.parametrize("profile,nr,dfilt,mutation", [("duy2008", 2, False, "shift"), ("duy2008", 2, False, "bound"),
                                                       ("duy2008", 3, False, "shift")],
                         ids=["asm-law-shift", "asm-law-bound", "c-law-shift"])
def test_a_one_lsb_change_of_the_description_is_caught(tmp_path, monkeypatch, profile, nr, dfilt, mutation):
    """The firmware generated from a description of the law one LSB off (core_program.LAW: a
    shift by one, a saturation bound by one) must make the chip disagree with the model of the
    unchanged description, on the assembly law (2 rules) and on SDCC's C law (3 rules): the
    chip's comparison sees every step the description emits."""
    from picdrive.firmware import core_program as cp
    monkeypatch.setattr(cp, "LAW", _mutated_law(mutation))
    monkeypatch.setitem(cp.CONSTS, "I_LIM_1", ("(CORE_I_LIM - 1)", "(plan.i_lim - 1)"))
    plan, folder = _synthetic(tmp_path, profile, nr, dfilt, False)
    assert ("#define CORE_LAW_ASM 1" in (folder / "drive_core.c").read_text()) == (nr <= 2 and not dfilt)
    verdict = compare(folder, tmp_path, plan, n=500, funcs=("law", "control"))
    assert verdict["law"] is not None and verdict["law"].startswith("first failing vector"), verdict
    assert verdict["control"] is not None, verdict


@pytest.mark.parametrize("profile,nr", [("duy2008", 2), ("duy2008", 3)], ids=["asm-law", "c-law"])
def test_a_law_change_is_one_edit(tmp_path, monkeypatch, profile, nr):
    """A changed law (two new saturations: the P and the D term to int16) made once, in
    core_program.LAW: the firmware generated from it and the model compiled from it agree on the
    chip, for the assembly law and for SDCC's C law."""
    import dataclasses
    from picdrive.firmware import core_program as cp
    steps = []
    for op in cp.LAW.steps:
        steps.append(op)
        if op in (cp.Shift("P"), cp.Shift("D")):
            steps.append(cp.Sat16())
    law = dataclasses.replace(cp.LAW, steps=tuple(steps))
    assert len(law.steps) == len(cp.LAW.steps) + 2
    plan, folder = _synthetic(tmp_path, profile, nr, False, False)
    before = model_run(plan, 2000, 0xFFFF, N_SLOTS)[0]            # the unchanged law's sums
    monkeypatch.setattr(cp, "LAW", law)
    model = cp.model({"sat32": fx.sat32, "shift32": fx.shift32, "shl_sat32": fx.shl_sat32,
                      "duty_counts": fx.duty_counts}, (law, cp.CONTROL))
    monkeypatch.setattr(fx, "law_step", model["law_step"])
    monkeypatch.setattr(fx, "core_control", model["core_control"])
    assert model_run(plan, 2000, 0xFFFF, N_SLOTS)[0][:4] != before[:4]   # the change changes the law
    plan, folder = _synthetic(tmp_path / "changed", profile, nr, False, False)
    assert "ACC_SAT16();\n    l_q = ACC;" in (folder / "drive_core.c").read_text()
    verdict = compare(folder, tmp_path, plan, n=2000, funcs=("law", "control"))
    assert verdict == {"law": None, "control": None}, verdict
