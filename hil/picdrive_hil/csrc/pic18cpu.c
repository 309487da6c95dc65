/* PIC18 instruction-set simulator (see pic18cpu.h).  Section / table numbers
 * are DS39616 (PIC18F2331/2431/4331/4431 data sheet).  Flash is pre-decoded
 * into one pic18_op_t per word; the run loop dispatches with computed goto. */
#include <string.h>
#include "pic18cpu.h"

/* core SFR addresses (p18f4431.inc) */
enum {
    A_TOSU = 0xFFF, A_TOSH = 0xFFE, A_TOSL = 0xFFD, A_STKPTR = 0xFFC, A_PCLATU = 0xFFB,
    A_PCLATH = 0xFFA, A_PCL = 0xFF9, A_TBLPTRU = 0xFF8, A_TBLPTRH = 0xFF7, A_TBLPTRL = 0xFF6,
    A_TABLAT = 0xFF5, A_PRODH = 0xFF4, A_PRODL = 0xFF3, A_INTCON = 0xFF2, A_INTCON2 = 0xFF1,
    A_INTCON3 = 0xFF0, A_FSR0H = 0xFEA, A_FSR0L = 0xFE9, A_WREG = 0xFE8, A_FSR1H = 0xFE2,
    A_FSR1L = 0xFE1, A_BSR = 0xFE0, A_FSR2H = 0xFDA, A_FSR2L = 0xFD9, A_STATUS = 0xFD8,
    A_RCON = 0xFD0, A_PIE1 = 0xF9D, A_PIR1 = 0xF9E, A_IPR1 = 0xF9F, A_PIE2 = 0xFA0,
    A_PIR2 = 0xFA1, A_IPR2 = 0xFA2, A_PIE3 = 0xFA3, A_PIR3 = 0xFA4, A_IPR3 = 0xFA5,
    A_NULL = 0x1000,
};
enum { S_C = 1, S_DC = 2, S_Z = 4, S_OV = 8, S_N = 16 };
#define STKFUL 0x80
#define STKUNF 0x40
#define EV_PCL 1
#define EV_IRQ 2
#define EV_STOP 4
#define EV_RESET 8   /* a stack full/underflow reset is due (STVREN) */

/* handlers */
enum {
    O_ILL, O_PCFAULT, O_NOP, O_SLEEP, O_CLRWDT, O_PUSH, O_POP, O_DAW, O_TBLRD, O_TBLWT,
    O_RETFIE, O_RETURN, O_RESET, O_MOVLB, O_SUBLW, O_IORLW, O_XORLW, O_ANDLW, O_RETLW,
    O_MULLW, O_MOVLW, O_ADDLW, O_MULWF, O_DECF, O_IORWF, O_ANDWF, O_XORWF, O_COMF,
    O_ADDWFC, O_ADDWF, O_INCF, O_DECFSZ, O_RRCF, O_RLCF, O_SWAPF, O_INCFSZ, O_RRNCF,
    O_RLNCF, O_INFSNZ, O_DCFSNZ, O_MOVF, O_SUBFWB, O_SUBWFB, O_SUBWF, O_CPFSLT, O_CPFSEQ,
    O_CPFSGT, O_TSTFSZ, O_SETF, O_CLRF, O_NEGF, O_MOVWF, O_BTG, O_BSF, O_BCF, O_BTFSS,
    O_BTFSC, O_MOVFF, O_BRA, O_RCALL, O_BCOND, O_CALL, O_LFSR, O_GOTO,
    O_MOVFF_GG,          /* MOVFF from a GPR to a GPR */
    O_MOVFF_PUSH,        /* MOVFF gpr, POSTDEC1 (SDCC's push on its software stack) */
    O_MOVFF_POP,         /* MOVFF PREINC1, gpr (its pop) */
    /* the file-register instructions O_MULWF..O_BTFSC on an access-bank GPR (a = 0, f below the
       split): the address is f, no BSR, no indirect form, no SFR -- code O_G0 + (op - O_MULWF) */
    O_G0,
    O_N = O_G0 + (O_BTFSC - O_MULWF + 1)
};
#define F_BANKED 1
#define F_2WORD 2        /* the instruction's length in bytes is 2 + (flags & F_2WORD) */
#define F_DEST 0x80
#define BITNO(o) (((o)->flags >> 2) & 7)

/* ---------------------------------------------------------------- decode */

static uint16_t flash_word(const pic18_t *c, uint32_t w)
{
    if (w >= PIC18_FLASH_WORDS) return 0xFFFF;
    return (uint16_t)(c->flash[2 * w] | (c->flash[2 * w + 1] << 8));
}

static void decode(pic18_t *c, uint32_t w)
{
    pic18_op_t *o = &c->op[w];
    uint16_t iw = flash_word(c, w), w2 = flash_word(c, w + 1);
    unsigned hi = iw >> 8, lo = iw & 0xFF;
    memset(o, 0, sizeof *o);
    o->code = O_ILL;
    unsigned a = (iw >> 8) & 1, d = (iw >> 9) & 1;
    uint16_t fabs = a ? lo : (lo < PIC18_ACCESS_SPLIT ? lo : (uint16_t)(0xF00 | lo));
#define FILEOP(code_, hasd) do { o->code = (code_); o->f = fabs; \
        o->flags = (uint8_t)((a ? F_BANKED : 0) | ((hasd) && d ? F_DEST : 0)); } while (0)
    switch (iw >> 10) {  /* top six bits */
    case 0x00:
        if (hi == 0x00) {
            switch (lo) {
            case 0x00: o->code = O_NOP; break;
            case 0x03: o->code = O_SLEEP; break;
            case 0x04: o->code = O_CLRWDT; break;
            case 0x05: o->code = O_PUSH; break;
            case 0x06: o->code = O_POP; break;
            case 0x07: o->code = O_DAW; break;
            case 0x08: case 0x09: case 0x0A: case 0x0B: o->code = O_TBLRD; o->f = lo & 3; break;
            case 0x0C: case 0x0D: case 0x0E: case 0x0F: o->code = O_TBLWT; o->f = lo & 3; break;
            case 0x10: case 0x11: o->code = O_RETFIE; o->f = lo & 1; break;
            case 0x12: case 0x13: o->code = O_RETURN; o->f = lo & 1; break;
            case 0xFF: o->code = O_RESET; break;
            default: break;  /* 0x0014 CALLW (extended) and the rest: illegal */
            }
        } else if (hi == 0x01) {
            if (lo < 0x10) { o->code = O_MOVLB; o->f = lo; }
        } else {             /* 0x02, 0x03: MULWF */
            FILEOP(O_MULWF, 0);
        }
        break;
    case 0x01: FILEOP(O_DECF, 1); break;
    case 0x02: {
        static const uint8_t lit[4] = {O_SUBLW, O_IORLW, O_XORLW, O_ANDLW};
        o->code = lit[hi & 3]; o->f = lo; break;
    }
    case 0x03: {
        static const uint8_t lit[4] = {O_RETLW, O_MULLW, O_MOVLW, O_ADDLW};
        o->code = lit[hi & 3]; o->f = lo; break;
    }
    case 0x04: FILEOP(O_IORWF, 1); break;
    case 0x05: FILEOP(O_ANDWF, 1); break;
    case 0x06: FILEOP(O_XORWF, 1); break;
    case 0x07: FILEOP(O_COMF, 1); break;
    case 0x08: FILEOP(O_ADDWFC, 1); break;
    case 0x09: FILEOP(O_ADDWF, 1); break;
    case 0x0A: FILEOP(O_INCF, 1); break;
    case 0x0B: FILEOP(O_DECFSZ, 1); break;
    case 0x0C: FILEOP(O_RRCF, 1); break;
    case 0x0D: FILEOP(O_RLCF, 1); break;
    case 0x0E: FILEOP(O_SWAPF, 1); break;
    case 0x0F: FILEOP(O_INCFSZ, 1); break;
    case 0x10: FILEOP(O_RRNCF, 1); break;
    case 0x11: FILEOP(O_RLNCF, 1); break;
    case 0x12: FILEOP(O_INFSNZ, 1); break;
    case 0x13: FILEOP(O_DCFSNZ, 1); break;
    case 0x14: FILEOP(O_MOVF, 1); break;
    case 0x15: FILEOP(O_SUBFWB, 1); break;
    case 0x16: FILEOP(O_SUBWFB, 1); break;
    case 0x17: FILEOP(O_SUBWF, 1); break;
    case 0x18: FILEOP(d ? O_CPFSEQ : O_CPFSLT, 0); break;
    case 0x19: FILEOP(d ? O_TSTFSZ : O_CPFSGT, 0); break;
    case 0x1A: FILEOP(d ? O_CLRF : O_SETF, 0); break;
    case 0x1B: FILEOP(d ? O_MOVWF : O_NEGF, 0); break;
    default: {
        unsigned top4 = iw >> 12;
        if (top4 >= 0x7 && top4 <= 0xB) {
            static const uint8_t bit[5] = {O_BTG, O_BSF, O_BCF, O_BTFSS, O_BTFSC};
            o->code = bit[top4 - 7]; o->f = fabs;
            o->flags = (uint8_t)((a ? F_BANKED : 0) | (((iw >> 9) & 7) << 2));
        } else if (top4 == 0xC) {
            o->code = O_MOVFF; o->f = iw & 0xFFF; o->x = w2 & 0xFFF; o->flags = F_2WORD;
            if ((w2 >> 12) != 0xF) o->code = O_ILL;
        } else if (top4 == 0xD) {
            int n = iw & 0x7FF;
            if (n & 0x400) n -= 0x800;
            o->code = (iw & 0x800) ? O_RCALL : O_BRA; o->x = (uint32_t)n;
        } else if (top4 == 0xE) {
            unsigned sub = (iw >> 8) & 0xF;
            if (sub < 8) {
                static const uint8_t mask[8] = {S_Z, S_Z, S_C, S_C, S_OV, S_OV, S_N, S_N};
                int n = (int8_t)lo;
                o->code = O_BCOND; o->f = mask[sub]; o->flags = (sub & 1) ? 0 : 1; o->x = (uint32_t)n;
            } else if (sub == 0xC || sub == 0xD) {
                o->code = O_CALL; o->f = sub & 1; o->flags = F_2WORD;
                o->x = ((uint32_t)(w2 & 0xFFF) << 8 | lo) << 1;
                if ((w2 >> 12) != 0xF) o->code = O_ILL;
            } else if (sub == 0xE) {
                if ((lo & 0xC0) == 0 && ((lo >> 4) & 3) < 3 && (w2 >> 8) == 0xF0) {
                    o->code = O_LFSR; o->f = (lo >> 4) & 3; o->flags = F_2WORD;
                    o->x = (uint32_t)(((lo & 0xF) << 8) | (w2 & 0xFF));
                }
            } else if (sub == 0xF) {
                o->code = O_GOTO; o->flags = F_2WORD;
                o->x = ((uint32_t)(w2 & 0xFFF) << 8 | lo) << 1;
                if ((w2 >> 12) != 0xF) o->code = O_ILL;
            }  /* 0xE8-0xEB: ADDFSR/ADDULNK/SUBFSR/SUBULNK/PUSHL/MOVSF/MOVSS (extended): illegal */
        } else if (top4 == 0xF) {
            o->code = O_NOP;  /* second word of a 2-word instruction executes as NOP */
        }
        break;
    }
    }
#undef FILEOP
    if (o->code >= O_MULWF && o->code <= O_BTFSC && !(o->flags & F_BANKED) && o->f < PIC18_ACCESS_SPLIT)
        o->code = (uint8_t)(O_G0 + (o->code - O_MULWF));
    else if (o->code == O_MOVFF && o->f < PIC18_RAM_END && o->x < PIC18_RAM_END)
        o->code = O_MOVFF_GG;
    else if (o->code == O_MOVFF && o->f < PIC18_RAM_END && o->x == 0xFE5)
        o->code = O_MOVFF_PUSH;
    else if (o->code == O_MOVFF && o->f == 0xFE4 && o->x < PIC18_RAM_END)
        o->code = O_MOVFF_POP;
    o->h = c->disp_tab ? c->disp_tab[o->code] : 0;
}

static void decode_all(pic18_t *c)
{
    for (uint32_t w = 0; w < PIC18_FLASH_WORDS; w++) decode(c, w);
    memset(&c->op[PIC18_FLASH_WORDS], 0, 2 * sizeof(pic18_op_t));
    c->op[PIC18_FLASH_WORDS].code = O_PCFAULT;
    c->op[PIC18_FLASH_WORDS + 1].code = O_PCFAULT;
    for (uint32_t w = PIC18_FLASH_WORDS; w < PIC18_FLASH_WORDS + 2; w++)
        c->op[w].h = c->disp_tab ? c->disp_tab[O_PCFAULT] : 0;
}

/* ---------------------------------------------------------------- data space */

static inline unsigned sp_of(const pic18_t *c) { return c->stkptr & 0x1F; }
/* TBLPTR (22 bits) lives in its three SFR bytes: a write to them is a plain store */
static inline uint32_t tblptr_get(const pic18_t *c)
{
    return c->ram[A_TBLPTRL] | ((uint32_t)c->ram[A_TBLPTRH] << 8) | ((uint32_t)(c->ram[A_TBLPTRU] & 0x3F) << 16);
}
static inline void tblptr_set(pic18_t *c, uint32_t v)
{
    c->ram[A_TBLPTRL] = (uint8_t)v;
    c->ram[A_TBLPTRH] = (uint8_t)(v >> 8);
    c->ram[A_TBLPTRU] = (uint8_t)((v >> 16) & 0x3F);
}
static inline unsigned fsr_get(const pic18_t *c, unsigned n)
{
    static const uint16_t lo[3] = {A_FSR0L, A_FSR1L, A_FSR2L};
    return c->ram[lo[n]] | ((c->ram[lo[n] + 1] & 0x0F) << 8);
}
static inline void fsr_set(pic18_t *c, unsigned n, unsigned v)
{
    static const uint16_t lo[3] = {A_FSR0L, A_FSR1L, A_FSR2L};
    c->ram[lo[n]] = (uint8_t)v;
    c->ram[lo[n] + 1] = (uint8_t)((v >> 8) & 0x0F);
}
/* The indirect operands: 0xFDB-0xFDF (FSR2), 0xFE3-0xFE7 (FSR1), 0xFEB-0xFEF (FSR0), each block
 * PLUSWn, PREINCn, POSTDECn, POSTINCn, INDFn -- address bits 2-0 = 3..7; the block's FSRnL is at
 * (address & ~7) + 1 (0xFD9, 0xFE1, 0xFE9). */
static inline int is_indf(unsigned a)
{
    return a >= 0xFDB && a <= 0xFEF && (a & 7) >= 3;
}

/* An INDFn/POSTINCn/POSTDECn/PREINCn/PLUSWn operand -> the address it reaches (its FSR
 * side effect applied, once per operand); an indirect reach of one of those registers
 * is the null target (reads 0, writes ignored: section 5.12).  Other addresses: as is. */
static inline __attribute__((always_inline)) unsigned resolve(pic18_t *c, unsigned a)
{
    /* by form (address bits 2-0): the offset of the address reached from the FSR (PREINC +1,
       PLUSW + signed W) and the FSR's change (PREINC/POSTINC +1, POSTDEC -1): no branch on the form */
    static const uint8_t pre[8] = {0, 0, 0, 0, 1, 0, 0, 0};
    static const int8_t step[8] = {0, 0, 0, 0, 1, -1, 1, 0};
    unsigned m = a & 7, lo, fsr, ea;
    if (a < 0xFDB || a > 0xFEF || m < 3) return a;
    lo = (a & ~7u) + 1;
    fsr = c->ram[lo] | ((c->ram[lo + 1] & 0x0F) << 8);
    ea = (fsr + pre[m] + (m == 3 ? (unsigned)(int8_t)c->ram[A_WREG] : 0u)) & 0xFFF;
    if (step[m]) {
        unsigned nf = (fsr + (unsigned)(int)step[m]) & 0xFFF;
        c->ram[lo] = (uint8_t)nf;
        c->ram[lo + 1] = (uint8_t)(nf >> 8);
    }
    if (lo == A_FSR1L) {      /* the software stack's reach (SDCC: FSR1 is the stack pointer) */
        if (ea < c->fsr1_lo) c->fsr1_lo = (uint16_t)ea;
        if (m == 5 && ea > c->fsr1_hi) c->fsr1_hi = (uint16_t)ea;
    }
    return is_indf(ea) ? A_NULL : ea;
}

/* the INDFn / PLUSWn address of an indirect operand without its FSR side effect */
static unsigned resolve_nofx(pic18_t *c, unsigned a)
{
    unsigned m = a & 7, lo, ea;
    if (a < 0xFDB || a > 0xFEF || m < 3) return a;
    lo = (a & ~7u) + 1;
    ea = c->ram[lo] | ((c->ram[lo + 1] & 0x0F) << 8);
    if (m == 3) ea = (ea + (unsigned)(int8_t)c->ram[A_WREG]) & 0xFFF;
    return is_indf(ea) ? A_NULL : ea;
}

static void stack_fault(pic18_t *c, int st, uint32_t ipc);
/* an interrupt-control register was written: look at the requests at the next boundary.  With a
 * model attached and no request line up, irq_check would find nothing (the lines change only
 * through pic18_set_irq, which asks for the look itself): no look */
static void irq_recheck(pic18_t *c) { if (c->irq_builtin || c->irq_lines) c->event |= EV_IRQ; }
static int irq_related(unsigned a)
{
    return a == A_INTCON || a == A_INTCON2 || a == A_INTCON3 || a == A_RCON ||
           (a >= A_PIE1 && a <= A_IPR3);
}

static uint8_t reg_get(pic18_t *c, unsigned a)   /* interrupt-control registers, wherever they live */
{
    if (c->owned[a & 0xFF] && c->sfr_read) return c->sfr_read(c->ctx, (uint16_t)a);
    return c->ram[a];
}
static void reg_set(pic18_t *c, unsigned a, uint8_t v)
{
    if (c->owned[a & 0xFF] && c->sfr_write) c->sfr_write(c->ctx, (uint16_t)a, v);
    else c->ram[a] = v;
}

static uint8_t sfr_rd(pic18_t *c, unsigned a)
{
    if (a < PIC18_SFR_BASE || a >= 0x1000) return 0;   /* unimplemented, null */
    switch (a) {
    case A_TOSU: return (uint8_t)((c->stack[sp_of(c)] >> 16) & 0x1F);
    case A_TOSH: return (uint8_t)(c->stack[sp_of(c)] >> 8);
    case A_TOSL: return (uint8_t)c->stack[sp_of(c)];
    case A_STKPTR: return c->stkptr;
    case A_PCL:
        c->ram[A_PCLATH] = (uint8_t)(c->pc >> 8);
        c->ram[A_PCLATU] = (uint8_t)((c->pc >> 16) & 0x1F);
        return (uint8_t)c->pc;
    case A_TBLPTRU: case A_TBLPTRH: case A_TBLPTRL:
    case A_PCLATU: case A_PCLATH: case A_TABLAT: case A_PRODH: case A_PRODL:
    case A_FSR0H: case A_FSR0L: case A_WREG: case A_FSR1H: case A_FSR1L: case A_BSR:
    case A_FSR2H: case A_FSR2L: case A_STATUS:
        return c->ram[a];
    default:
        if (is_indf(a)) return 0;  /* only reached through peek */
        if (c->owned[a & 0xFF] && c->sfr_read) return c->sfr_read(c->ctx, (uint16_t)a);
        return c->ram[a];
    }
}

/* alu: the value is an instruction's result that also sets STATUS bits; written to
 * STATUS, the five flag bits keep the device logic's values (section 5.x STATUS note) */
static void sfr_wr(pic18_t *c, unsigned a, uint8_t v, int alu)
{
    if (a < PIC18_SFR_BASE || a >= 0x1000) return;
    unsigned sp = sp_of(c);
    switch (a) {
    case A_TOSU: if (sp) c->stack[sp] = (c->stack[sp] & 0x00FFFF) | ((uint32_t)(v & 0x1F) << 16); return;
    case A_TOSH: if (sp) c->stack[sp] = (c->stack[sp] & 0x1F00FF) | ((uint32_t)v << 8); return;
    case A_TOSL: if (sp) c->stack[sp] = (c->stack[sp] & 0x1FFF00) | v; return;
    case A_STKPTR: c->stkptr = (uint8_t)((c->stkptr & v & (STKFUL | STKUNF)) | (v & 0x1F)); return;
    case A_PCL:
        c->ram[A_PCL] = v;
        c->pcl_target = ((uint32_t)(c->ram[A_PCLATU] & 0x1F) << 16) | ((uint32_t)c->ram[A_PCLATH] << 8) | (v & 0xFE);
        c->event |= EV_PCL;
        return;
    case A_PCLATU: c->ram[a] = v & 0x1F; return;
    case A_TBLPTRU: c->ram[a] = v & 0x3F; return;
    case A_FSR0H: case A_FSR1H: case A_FSR2H: case A_BSR: c->ram[a] = v & 0x0F; return;
#ifdef PIC18_GPSIM_COMPAT
    /* gpsim 0.31 keeps STATUS bits 7-5 (unimplemented on the chip: read 0) and writes an
     * instruction's result to STATUS before setting the flags it affects (the chip keeps
     * all five flag bits from the result: DS39616 section 5.x) */
    case A_STATUS: (void)alu; c->ram[a] = v; return;
#else
    case A_STATUS: if (!alu) c->ram[a] = v & 0x1F; return;
#endif
    case A_PCLATH: case A_TABLAT: case A_PRODH: case A_PRODL: case A_FSR0L: case A_WREG:
    case A_FSR1L: case A_FSR2L: case A_TBLPTRH: case A_TBLPTRL:
        c->ram[a] = v; return;
    default:
        if (is_indf(a)) return;
        if (c->owned[a & 0xFF] && c->sfr_write) c->sfr_write(c->ctx, (uint16_t)a, v);
        else c->ram[a] = v;
        if (irq_related(a)) irq_recheck(c);
        return;
    }
}

/* ---------------------------------------------------------------- stack */

static void do_reset(pic18_t *c, int por);
static void fast_tables(pic18_t *c);

/* A stack fault stops the core after the instruction (EV_STOP) and, with STVREN,
 * resets it there (EV_RESET); the instruction itself completes as the datasheet says. */
static inline void push(pic18_t *c, uint32_t v, uint32_t ipc)
{
    unsigned sp = sp_of(c);
    if (sp >= PIC18_STACK_LEVELS) {          /* full: further pushes are lost */
        c->stkptr |= STKFUL;
        stack_fault(c, PIC18_STACK_OVERFLOW, ipc);
        return;
    }
    sp++;
    c->stack[sp] = v & 0x1FFFFE;
    c->stkptr = (uint8_t)((c->stkptr & 0xC0) | sp);
    if (sp > c->stack_high) c->stack_high = (uint8_t)sp;
    if (sp == PIC18_STACK_LEVELS) {          /* the 31st push sets STKFUL (section 5.1.2.4) */
        c->stkptr |= STKFUL;
        stack_fault(c, PIC18_STACK_OVERFLOW, ipc);
    }
}

static inline uint32_t pop(pic18_t *c, uint32_t ipc)
{
    unsigned sp = sp_of(c);
    if (sp == 0) {                           /* underflow: 0 to the PC, STKUNF */
        c->stkptr |= STKUNF;
        stack_fault(c, PIC18_STACK_UNDERFLOW, ipc);
        return 0;
    }
    uint32_t v = c->stack[sp];
    c->stkptr = (uint8_t)((c->stkptr & 0xC0) | (sp - 1));
    return v;
}

static int stvren(const pic18_t *c) { return c->config[6] & 1; }   /* CONFIG4L bit 0 */

static void stack_fault(pic18_t *c, int st, uint32_t ipc)
{
    c->insn_pc = ipc;
    c->status = st;
    c->fault_pc = c->insn_pc;
    c->fault_word = (uint16_t)(c->insn_pc < PIC18_FLASH_BYTES ? flash_word(c, c->insn_pc >> 1) : 0xFFFF);
    c->event |= EV_STOP;
    if (stvren(c)) c->event |= EV_RESET;     /* stack full/underflow reset; STKFUL/STKUNF stay */
}

/* ---------------------------------------------------------------- reset */

static void do_reset(pic18_t *c, int por)
{
    /* Table 4-4: values on POR / on MCLR and the other resets ("x" and POR "u" -> 0) */
    c->pc = 0;
    c->stkptr = por ? 0 : (uint8_t)(c->stkptr & 0xC0);
    memset(c->stack, 0, sizeof c->stack);
    c->ram[A_PCLATU] = c->ram[A_PCLATH] = c->ram[A_PCL] = 0;
    tblptr_set(c, 0);
    c->ram[A_TABLAT] = 0;
    c->ram[A_BSR] = 0;
    if (!c->owned[A_INTCON & 0xFF]) c->ram[A_INTCON] = por ? 0 : (c->ram[A_INTCON] & 1);
    if (!c->owned[A_INTCON2 & 0xFF]) c->ram[A_INTCON2] = 0xF5;
    if (!c->owned[A_INTCON3 & 0xFF]) c->ram[A_INTCON3] = 0xC0;
    if (!c->owned[A_RCON & 0xFF]) c->ram[A_RCON] = por ? 0x1C : (uint8_t)(c->ram[A_RCON] & 0x7F);
    for (unsigned a = A_PIE1; a <= A_IPR3; a++) if (!c->owned[a & 0xFF]) c->ram[a] = 0;
    if (!c->owned[A_IPR1 & 0xFF]) c->ram[A_IPR1] = 0xFF;
    if (!c->owned[A_IPR2 & 0xFF]) c->ram[A_IPR2] = 0xFF;   /* bits that exist read 1 */
    if (!c->owned[A_IPR3 & 0xFF]) c->ram[A_IPR3] = 0xFF;
    if (por) {
        memset(c->ram, 0, PIC18_RAM_END);
        c->ram[A_WREG] = c->ram[A_STATUS] = 0;
        c->ram[A_FSR0L] = c->ram[A_FSR0H] = c->ram[A_FSR1L] = c->ram[A_FSR1H] = 0;
        c->ram[A_FSR2L] = c->ram[A_FSR2H] = c->ram[A_PRODL] = c->ram[A_PRODH] = 0;
        c->shadow_w = c->shadow_status = c->shadow_bsr = 0;
    }
    c->sleeping = 0;
    c->in_high_isr = 0;
    c->wdt_clr = c->cycles;                  /* every reset clears the watchdog */
    c->event |= EV_IRQ;
}

void pic18_power_on(pic18_t *c)
{
    do_reset(c, 1);
    c->fsr1_lo = 0xFFFF;
    c->fsr1_hi = 0;
    memset(c->ram_written, 0, sizeof c->ram_written);
    c->cycles = 0;
    c->wdt_clr = 0;
    c->insns = 0;
    c->status = PIC18_OK;
    c->stack_high = 0;
}

void pic18_reset(pic18_t *c)
{
    do_reset(c, 0);
    c->status = PIC18_OK;
}

void pic18_init(pic18_t *c)
{
    /* erased config: DS39616 Table 23-1 default/unprogrammed values (CONFIG4L = STVREN on) */
    static const uint8_t cfg[PIC18_CONFIG_N] = {0xFF, 0xCF, 0x0F, 0x3F, 0x3C, 0x9D, 0x85, 0xFF,
                                                0x0F, 0xC0, 0x0F, 0xE0, 0x0F, 0x40};
    memset(c, 0, sizeof *c);
    memset(c->flash, 0xFF, sizeof c->flash);
    memset(c->idloc, 0xFF, sizeof c->idloc);
    memset(c->eeprom, 0xFF, sizeof c->eeprom);
    memcpy(c->config, cfg, sizeof cfg);
    c->devid[0] = 0x00; c->devid[1] = 0x05;   /* DEVID1/DEVID2 of the 18F4431: 0x05 0x0xx */
    c->irq_builtin = 1;
    c->irq_vector_cycles = 2;
    c->table_cycles = 2;
    fast_tables(c);
    decode_all(c);
    pic18_power_on(c);
}

void pic18_load_flash(pic18_t *c, uint32_t addr, const uint8_t *data, uint32_t n)
{
    for (uint32_t i = 0; i < n && addr + i < PIC18_FLASH_BYTES; i++) c->flash[addr + i] = data[i];
    decode_all(c);
}

void pic18_set_config(pic18_t *c, const uint8_t cfg[PIC18_CONFIG_N])
{
    memcpy(c->config, cfg, PIC18_CONFIG_N);
}

void pic18_flash_erase_row(pic18_t *c, uint32_t addr)
{
    addr &= ~63u;
    if (addr >= PIC18_FLASH_BYTES) return;
    memset(&c->flash[addr], 0xFF, 64);
    for (uint32_t w = addr / 2; w < addr / 2 + 32; w++) decode(c, w);
    if (addr) decode(c, addr / 2 - 1);      /* a 2-word instruction just before the row */
}

void pic18_flash_write_block(pic18_t *c, uint32_t addr)
{
    addr &= ~7u;
    if (addr >= PIC18_FLASH_BYTES) return;
    for (int i = 0; i < 8; i++) c->flash[addr + i] &= c->holding[i];   /* programming clears bits */
    memset(c->holding, 0xFF, sizeof c->holding);
    for (uint32_t w = addr / 2; w < addr / 2 + 4; w++) decode(c, w);
    if (addr) decode(c, addr / 2 - 1);
}

/* the SFR accesses the run loop does inline (what sfr_rd / sfr_wr would do: a plain byte of
 * ram[], masked on writes); everything else goes through them */
static void fast_tables(pic18_t *c)
{
    for (unsigned i = 0; i < 256; i++) {
        unsigned a = 0xF00 + i;
        int model_rd = c->owned[i] && c->sfr_read, model_wr = c->owned[i] && c->sfr_write;
        int core = 0;
        uint8_t m = 0;
        switch (a) {
        case A_PCLATU: core = 1; m = 0x1F; break;
        case A_TBLPTRU: core = 1; m = 0x3F; break;
        case A_FSR0H: case A_FSR1H: case A_FSR2H: case A_BSR: core = 1; m = 0x0F; break;
        case A_PCLATH: case A_TABLAT: case A_PRODH: case A_PRODL: case A_FSR0L: case A_WREG:
        case A_FSR1L: case A_FSR2L: case A_TBLPTRH: case A_TBLPTRL: core = 1; m = 0xFF; break;
        case A_STATUS: core = 1; m = 0; break;      /* the ALU-write rule: sfr_wr */
        default: break;
        }
        if (a < PIC18_SFR_BASE) { c->rd_plain[i] = 0; c->wr_mask[i] = 0; continue; }
        if (core) { c->rd_plain[i] = 1; c->wr_mask[i] = m; continue; }
        switch (a) {   /* side effects or state kept elsewhere */
        case A_TOSU: case A_TOSH: case A_TOSL: case A_STKPTR: case A_PCL:
            c->rd_plain[i] = 0; c->wr_mask[i] = 0; continue;
        default: break;
        }
        if (is_indf(a)) { c->rd_plain[i] = 0; c->wr_mask[i] = 0; continue; }
        c->rd_plain[i] = (uint8_t)!model_rd;
        c->wr_mask[i] = (uint8_t)((model_wr || irq_related(a)) ? 0 : 0xFF);
    }
}

void pic18_attach(pic18_t *c, void *ctx, pic18_sfr_read_fn rd, pic18_sfr_write_fn wr,
                  const uint8_t owned[256])
{
    c->ctx = ctx;
    c->sfr_read = rd;
    c->sfr_write = wr;
    for (int i = 0; i < 256; i++) c->owned[i] = owned ? (owned[i] != 0) : 0;
    c->irq_builtin = 0;
    c->intcon_ext = NULL;
    c->intcon_quiet = 0;
    c->event |= EV_IRQ;
    fast_tables(c);
}

void pic18_set_irq_hook(pic18_t *c, pic18_irq_hook_fn fn) { c->irq_hook = fn; }
void pic18_request_stop(pic18_t *c) { c->event |= EV_STOP; }
void pic18_share_intcon(pic18_t *c, volatile uint8_t *reg, uint8_t *mirror)
{
    c->intcon_ext = c->owned[A_INTCON & 0xFF] ? reg : NULL;
    c->intcon_mirror = mirror;
    c->intcon_quiet = 0;
}
void pic18_set_intcon_quiet(pic18_t *c, uint8_t quiet) { c->intcon_quiet = c->intcon_ext ? quiet : 0; }
unsigned pic18_ram_written(const pic18_t *c)
{
    unsigned n = 0;
    for (unsigned a = 0; a < PIC18_RAM_END; a++) n += c->ram_written[a] == 1;
    return n;
}

void pic18_set_irq(pic18_t *c, unsigned lines)
{
    c->irq_lines = (uint8_t)(lines & 3);
    c->event |= EV_IRQ;
}

uint8_t pic18_peek(pic18_t *c, uint16_t addr)
{
    addr &= 0xFFF;
    if (addr < PIC18_RAM_END) return c->ram[addr];
    if (addr < PIC18_SFR_BASE || is_indf(addr)) return 0;
    if (addr == A_PCL) return (uint8_t)c->pc;
    if (c->owned[addr & 0xFF]) return c->sfr_read ? c->sfr_read(c->ctx, addr) : 0;
    return sfr_rd(c, addr);
}

void pic18_poke(pic18_t *c, uint16_t addr, uint8_t v)
{
    addr &= 0xFFF;
    if (addr < PIC18_RAM_END) { c->ram[addr] = v; return; }
    if (addr == A_PCL) { c->pc = ((uint32_t)(c->ram[A_PCLATU] & 0x1F) << 16) |
                                 ((uint32_t)c->ram[A_PCLATH] << 8) | (v & 0xFE); return; }
    sfr_wr(c, addr, v, 0);
}

unsigned pic18_sizeof(void) { return (unsigned)sizeof(pic18_t); }

/* ---------------------------------------------------------------- interrupts */

/* the request lines of the built-in controller (no model): INTCON/INTCON2/INTCON3 and
 * PIRn/PIEn/IPRn as in section 10, not gated by GIEH/GIEL */
static unsigned builtin_lines(const pic18_t *c)
{
    const uint8_t *r = c->ram;
    int ipen = r[A_RCON] >> 7;
    unsigned lines = 0;
    uint8_t ic = r[A_INTCON], ic2 = r[A_INTCON2], ic3 = r[A_INTCON3];
    struct { int f, e, p; } src[5] = {
        {ic & 0x02, ic & 0x10, 1},                    /* INT0: always high */
        {ic & 0x04, ic & 0x20, ic2 & 0x04},           /* TMR0, TMR0IP */
        {ic & 0x01, ic & 0x08, ic2 & 0x01},           /* RB, RBIP */
        {ic3 & 0x01, ic3 & 0x08, ic3 & 0x40},         /* INT1, INT1IP */
        {ic3 & 0x02, ic3 & 0x10, ic3 & 0x80},         /* INT2, INT2IP */
    };
    for (int k = 0; k < 5; k++) {
        if (!(src[k].f && src[k].e)) continue;
        lines |= (!ipen || src[k].p) ? PIC18_IRQ_HIGH : PIC18_IRQ_LOW;
    }
    static const uint16_t pir[3] = {A_PIR1, A_PIR2, A_PIR3}, pie[3] = {A_PIE1, A_PIE2, A_PIE3},
                          ipr[3] = {A_IPR1, A_IPR2, A_IPR3};
    for (int k = 0; k < 3; k++) {
        uint8_t act = r[pir[k]] & r[pie[k]];
        if (!act) continue;
        if (!ipen) { if (ic & 0x40) lines |= PIC18_IRQ_HIGH; continue; }
        if (act & r[ipr[k]]) lines |= PIC18_IRQ_HIGH;
        if (act & ~r[ipr[k]]) lines |= PIC18_IRQ_LOW;
    }
    return lines;
}

/* at an instruction boundary: vector if a request is enabled.  Returns 1 when vectored. */
static int irq_check(pic18_t *c)
{
    unsigned lines = c->irq_builtin ? builtin_lines(c) : c->irq_lines;
    if (c->sleeping && lines) c->sleeping = 0;    /* any enabled source wakes the core */
    if (!lines) return 0;
    uint8_t intcon = reg_get(c, A_INTCON);
    int ipen = reg_get(c, A_RCON) >> 7;
    uint32_t vec;
    if ((lines & PIC18_IRQ_HIGH) && (intcon & 0x80)) {
        vec = 0x08; intcon &= 0x7F; c->in_high_isr = 1;
    } else if (ipen && (lines & PIC18_IRQ_LOW) && (intcon & 0xC0) == 0xC0) {
        vec = 0x18; intcon &= 0xBF;
    } else {
        return 0;
    }
    reg_set(c, A_INTCON, intcon);
    c->shadow_w = c->ram[A_WREG];
    c->shadow_status = c->ram[A_STATUS];
    c->shadow_bsr = c->ram[A_BSR];
    c->insn_pc = c->pc;
    push(c, c->pc, c->pc);
    c->pc = vec;
    c->cycles += c->irq_vector_cycles;
    if (c->irq_hook) c->irq_hook(c->ctx, vec == 0x08 ? PIC18_HOOK_HIGH : PIC18_HOOK_LOW);
    return 1;
}

/* ---------------------------------------------------------------- table reads */

static uint8_t table_byte(const pic18_t *c, uint32_t a)
{
    if (a < PIC18_FLASH_BYTES) return c->flash[a];
    if (a >= PIC18_CONFIG_BASE && a < PIC18_CONFIG_BASE + PIC18_CONFIG_N) return c->config[a - PIC18_CONFIG_BASE];
    if (a >= PIC18_IDLOC_BASE && a < PIC18_IDLOC_BASE + 8) return c->idloc[a - PIC18_IDLOC_BASE];
    if (a == PIC18_DEVID_BASE) return c->devid[0];
    if (a == PIC18_DEVID_BASE + 1) return c->devid[1];
    return 0;   /* unimplemented program memory reads 0 */
}

/* ---------------------------------------------------------------- run loop */

static inline uint8_t flags_add(unsigned a, unsigned b, unsigned cin, unsigned r9)
{
    uint8_t r = (uint8_t)r9, s = 0;
    if (r9 & 0x100) s |= S_C;
    if (((a & 0xF) + (b & 0xF) + cin) & 0x10) s |= S_DC;
    if ((a ^ r) & (b ^ r) & 0x80) s |= S_OV;
    if (!r) s |= S_Z;
    if (r & 0x80) s |= S_N;
    return s;
}
/* byte-oriented ALU ops with their STATUS bits.  GPSIM_OV(src): under PIC18_GPSIM_COMPAT
 * (the build the differential test compares with gpsim 0.31 only), OV as gpsim computes it
 * for ADDWF/ADDLW: set when the result's sign differs from the old value of the destination
 * (W or f); ADDWFC and INCF to f: from f's; INCF to W: the result's sign (measured over all
 * operands against gpsim).  Not the
 * datasheet's signed overflow, which the normal build computes; SUB*, DECF, NEGF agree. */
#ifdef PIC18_GPSIM_COMPAT
#define GPSIM_OV(s, src, r) ((s) = (uint8_t)(((s) & ~S_OV) | ((((src) ^ (r)) & 0x80) ? S_OV : 0)))
#else
#define GPSIM_OV(s, src, r) ((void)0)
#endif
#define ZN(r) ((uint8_t)(((r) ? 0 : S_Z) | ((r) & 0x80 ? S_N : 0)))

int pic18_run(pic18_t *c, uint64_t max_cycles, uint64_t max_insns, uint32_t break_pc)
{
    return pic18_run_bp(c, max_cycles, max_insns, &break_pc, break_pc == ~0u ? 0 : 1);
}

int pic18_run_bp(pic18_t *c, uint64_t max_cycles, uint64_t max_insns, const uint32_t *bps, int nbp)
{
    static void *const disp[O_N] = {
        [O_ILL] = &&L_ILL, [O_PCFAULT] = &&L_PCFAULT, [O_NOP] = &&L_NOP, [O_SLEEP] = &&L_SLEEP,
        [O_CLRWDT] = &&L_CLRWDT, [O_PUSH] = &&L_PUSH, [O_POP] = &&L_POP, [O_DAW] = &&L_DAW,
        [O_TBLRD] = &&L_TBLRD, [O_TBLWT] = &&L_TBLWT, [O_RETFIE] = &&L_RETFIE,
        [O_RETURN] = &&L_RETURN, [O_RESET] = &&L_RESET, [O_MOVLB] = &&L_MOVLB,
        [O_SUBLW] = &&L_SUBLW, [O_IORLW] = &&L_IORLW, [O_XORLW] = &&L_XORLW,
        [O_ANDLW] = &&L_ANDLW, [O_RETLW] = &&L_RETLW, [O_MULLW] = &&L_MULLW,
        [O_MOVLW] = &&L_MOVLW, [O_ADDLW] = &&L_ADDLW, [O_MULWF] = &&L_MULWF,
        [O_DECF] = &&L_DECF, [O_IORWF] = &&L_IORWF, [O_ANDWF] = &&L_ANDWF,
        [O_XORWF] = &&L_XORWF, [O_COMF] = &&L_COMF, [O_ADDWFC] = &&L_ADDWFC,
        [O_ADDWF] = &&L_ADDWF, [O_INCF] = &&L_INCF, [O_DECFSZ] = &&L_DECFSZ,
        [O_RRCF] = &&L_RRCF, [O_RLCF] = &&L_RLCF, [O_SWAPF] = &&L_SWAPF,
        [O_INCFSZ] = &&L_INCFSZ, [O_RRNCF] = &&L_RRNCF, [O_RLNCF] = &&L_RLNCF,
        [O_INFSNZ] = &&L_INFSNZ, [O_DCFSNZ] = &&L_DCFSNZ, [O_MOVF] = &&L_MOVF,
        [O_SUBFWB] = &&L_SUBFWB, [O_SUBWFB] = &&L_SUBWFB, [O_SUBWF] = &&L_SUBWF,
        [O_CPFSLT] = &&L_CPFSLT, [O_CPFSEQ] = &&L_CPFSEQ, [O_CPFSGT] = &&L_CPFSGT,
        [O_TSTFSZ] = &&L_TSTFSZ, [O_SETF] = &&L_SETF, [O_CLRF] = &&L_CLRF,
        [O_NEGF] = &&L_NEGF, [O_MOVWF] = &&L_MOVWF, [O_BTG] = &&L_BTG, [O_BSF] = &&L_BSF,
        [O_BCF] = &&L_BCF, [O_BTFSS] = &&L_BTFSS, [O_BTFSC] = &&L_BTFSC,
        [O_MOVFF] = &&L_MOVFF, [O_BRA] = &&L_BRA, [O_RCALL] = &&L_RCALL,
        [O_BCOND] = &&L_BCOND, [O_CALL] = &&L_CALL, [O_LFSR] = &&L_LFSR, [O_GOTO] = &&L_GOTO,
        [O_MOVFF_GG] = &&L_MOVFF_GG, [O_MOVFF_PUSH] = &&L_MOVFF_PUSH, [O_MOVFF_POP] = &&L_MOVFF_POP,
#define GV(X) [O_G0 + (O_##X - O_MULWF)] = &&L_##X##_G
        GV(MULWF), GV(DECF), GV(IORWF), GV(ANDWF), GV(XORWF), GV(COMF), GV(ADDWFC), GV(ADDWF),
        GV(INCF), GV(DECFSZ), GV(RRCF), GV(RLCF), GV(SWAPF), GV(INCFSZ), GV(RRNCF), GV(RLNCF),
        GV(INFSNZ), GV(DCFSNZ), GV(MOVF), GV(SUBFWB), GV(SUBWFB), GV(SUBWF), GV(CPFSLT),
        GV(CPFSEQ), GV(CPFSGT), GV(TSTFSZ), GV(SETF), GV(CLRF), GV(NEGF), GV(MOVWF), GV(BTG),
        GV(BSF), GV(BCF), GV(BTFSS), GV(BTFSC),
#undef GV
    };
    /* G_: 1 inside the access-GPR copy of a file-register handler (TWO), where EA, RESOLVE, RD
       and WR reduce to ram[f]; 0 everywhere else */
    enum { G_ = 0 };
    uint8_t *const ram = c->ram;
    const pic18_op_t *o;
    uint32_t pc;
    uint64_t cyc_end = (max_cycles > UINT64_MAX - c->cycles) ? UINT64_MAX : c->cycles + max_cycles;
    uint64_t ins_end = (max_insns > UINT64_MAX - c->insns) ? UINT64_MAX : c->insns + max_insns;
    /* the hot counters live in locals; SYNC() publishes them before anything that may read
     * them (a peripheral hook, the stack, the interrupt logic) */
    uint64_t cyc = c->cycles, ins = c->insns;
    uint32_t ipc = c->insn_pc;
    int first = 1;
    /* an instruction limit or breakpoints: every instruction through `next` (the twin runs by
       cycles without either: one test per instruction, NEXT's) */
    const int slow = nbp != 0 || ins_end != UINT64_MAX;
    /* NEXT's one test: the cycle limit, or 0 when slow (every instruction goes through next) or
       when an event is pending (EVT: events arise only inside the calls a handler makes) */
    uint64_t lim = slow ? 0 : cyc_end;

    if (PIC18_FATAL(c->status)) return c->status;
    c->status = PIC18_OK;
    c->event |= EV_IRQ;
    if (c->disp_tab != disp) {            /* first run: each op gets its handler's address */
        c->disp_tab = disp;
        for (uint32_t w = 0; w < PIC18_FLASH_WORDS + 2; w++) c->op[w].h = disp[c->op[w].code];
    }

/* EA: the operand's data address (banked through BSR); RESOLVE applies an INDF form once */
#define EA() (G_ ? (unsigned)o->f : (o->flags & F_BANKED) ? ((unsigned)(ram[A_BSR] << 8) | o->f) : o->f)
#ifdef PIC18_GPSIM_COMPAT
/* gpsim 0.31: ADDWF POSTINCn/POSTDECn/PREINCn, W reads INDFn and leaves the FSR */
#define GPSIM_ADDWF_W_NOFX (!(o->flags & F_DEST))
#else
#define GPSIM_ADDWF_W_NOFX 0
#endif
#define RESOLVE_NOFX(a) do { if (!G_ && (a) >= 0xFDB && (a) <= 0xFEF) (a) = resolve_nofx(c, (a)); } while (0)
#define RESOLVE(a) do { if (!G_ && (a) >= 0xFDB && (a) <= 0xFEF) (a) = resolve(c, (a)); } while (0)
#define SYNC() (c->pc = pc, c->cycles = cyc, c->insn_pc = ipc)
/* after a call that may have raised an event (a peripheral hook, the stack, the interrupt
   logic): the next NEXT goes through `next` */
#define EVT() do { if (__builtin_expect(c->event != 0, 0)) lim = 0; } while (0)
/* a GPR, a plain core register (rd_plain / wr_mask), or sfr_rd / sfr_wr (EA() < 0x1000; RESOLVE
 * gives A_NULL = 0x1000 for an indirect reach of INDF) */
#define SFR_FAST(a) ((a) >= 0xF00u && (a) < 0x1000u)
#define RD(a) ((G_ || (a) < PIC18_RAM_END) ? ram[a] : (SFR_FAST(a) && c->rd_plain[(a) & 0xFF]) ? ram[a] \
               : ((a) == A_INTCON && c->intcon_ext) ? *c->intcon_ext \
               : ({ uint8_t v_; SYNC(); v_ = sfr_rd(c, (a)); EVT(); v_; }))
/* a write of a shared INTCON that changes only its quiet bits (pic18_share_intcon): stored, no
 * hook; the interrupt look as sfr_wr asks for it (irq_related) */
#define INTCON_QUIET(a, v) ((a) == A_INTCON && c->intcon_quiet && \
                            !((((uint8_t)(v)) ^ *c->intcon_ext) & (uint8_t)~c->intcon_quiet))
#define INTCON_STORE(v) do { *c->intcon_ext = *c->intcon_mirror = (uint8_t)(v); irq_recheck(c); EVT(); } while (0)
#ifdef PIC18_TRACK_RAM
/* 1: written; 2: only a first store of zero so far (SDCC's crt0iz clears all RAM at reset: that
 * clear alone does not use a byte).  One branch-free store a write. */
#define NOTE_WR(a, v) (c->ram_written[a] = (uint8_t)(((v) & 0xFF) || c->ram_written[a] ? 1 : 2))
#else
#define NOTE_WR(a, v) ((void)0)
#endif
#define WR(a, v) do { if (G_ || (a) < PIC18_RAM_END) { ram[a] = (uint8_t)(v); NOTE_WR(a, v); } \
                      else if (SFR_FAST(a) && c->wr_mask[(a) & 0xFF]) ram[a] = (uint8_t)((v) & c->wr_mask[(a) & 0xFF]); \
                      else if (INTCON_QUIET(a, v)) INTCON_STORE(v); \
                      else { SYNC(); sfr_wr(c, (a), (uint8_t)(v), 0); EVT(); } } while (0)
#define WR_ALU(a, v) do { if (G_ || (a) < PIC18_RAM_END) { ram[a] = (uint8_t)(v); NOTE_WR(a, v); } \
                      else if (SFR_FAST(a) && c->wr_mask[(a) & 0xFF]) ram[a] = (uint8_t)((v) & c->wr_mask[(a) & 0xFF]); \
                      else if (INTCON_QUIET(a, v)) INTCON_STORE(v); \
                      else { SYNC(); sfr_wr(c, (a), (uint8_t)(v), 1); EVT(); } } while (0)
#define DEST_ALU(a, v) do { if (o->flags & F_DEST) WR_ALU(a, v); else ram[A_WREG] = (uint8_t)(v); } while (0)
#define DEST(a, v) do { if (o->flags & F_DEST) WR(a, v); else ram[A_WREG] = (uint8_t)(v); } while (0)
#define SETF(mask, s) (ram[A_STATUS] = (uint8_t)((ram[A_STATUS] & ~(mask)) | (s)))
#define CYC(n) (cyc += (n))
#define JUMP(t) do { pc = (t) & 0x1FFFFE; if (pc >= PIC18_FLASH_BYTES) goto pc_fault_jump; } while (0)
/* op of the word at byte address pc: an offset from c (no base pointer to keep in a register) */
#define OP_AT(pc) ((const pic18_op_t *)((const char *)c->op + (size_t)(pc) * (sizeof(pic18_op_t) / 2)))
#define SKIP() do { unsigned n2 = 2u + (OP_AT(pc)->flags & F_2WORD); pc += n2; CYC(n2 / 2); } while (0)
/* threaded dispatch: each handler ends with its own indirect jump (better predicted than one
 * shared jump), one basic block with no branch so that the compiler keeps a copy in every
 * handler; anything unusual (an event, a limit, breakpoints) goes through `next`.  A handler
 * starts with ADV(its length in bytes): the PC past it, the instruction counted. */
#define NEXT do { o = OP_AT(pc); goto *(cyc >= lim ? &&next : o->h); } while (0)
#define ADV(n) (ipc = pc, pc += (n), ins++)
/* a file-register handler in two copies: any operand, and an access-bank GPR (O_G0 + ...) */
#define TWO(label, ...) label: ADV(2); { __VA_ARGS__ } \
                        label##_G: ADV(2); { enum { G_ = 1 }; __VA_ARGS__ }

    pc = c->pc;
next:
    if (c->event) {
        SYNC();
        c->insns = ins;
        if (c->event & EV_PCL) {              /* an instruction wrote PCL: 2 cycles, PC from PCLATU:PCLATH:PCL */
            c->event &= (uint8_t)~EV_PCL;
            CYC(1);
            pc = c->pcl_target;
            if (pc >= PIC18_FLASH_BYTES) goto pc_fault_jump;
            c->pc = pc;
        }
        if (c->event & EV_STOP) {
            c->event &= (uint8_t)~EV_STOP;
            if (c->event & EV_RESET) {
                c->event &= (uint8_t)~EV_RESET;
                do_reset(c, 0);
                pc = 0;
            }
            goto out;
        }
        if (c->event & EV_IRQ) {
            c->event &= (uint8_t)~EV_IRQ;
            if (irq_check(c)) {
                pc = c->pc;
                cyc = c->cycles;
                ipc = c->insn_pc;
                goto next;
            }
            if (c->sleeping) { c->status = PIC18_SLEEP; c->event |= EV_IRQ; goto out; }
        }
    }
    if (cyc >= cyc_end || ins >= ins_end) goto out;
    if (nbp && !first) {
        for (int k = 0; k < nbp; k++)
            if (pc == bps[k]) { c->status = PIC18_BREAK; goto out; }
    }
    first = 0;
    lim = (slow || c->event) ? 0 : cyc_end;   /* an event raised by a hook called above: after this instruction */
    o = OP_AT(pc);
    goto *disp[o->code];

L_ILL: ADV(2);
    pc = ipc;
    c->status = PIC18_FAULT_ILLEGAL;
    c->fault_pc = pc;
    c->fault_word = flash_word(c, pc >> 1);
    ins--;
    goto out;
L_PCFAULT: ADV(2);
    pc = ipc;
    c->insn_pc = ipc;               /* execution ran past the end of the flash */
    ins--;
    c->status = PIC18_FAULT_PC;
    c->fault_pc = pc;
    c->fault_word = 0xFFFF;
    goto out;
pc_fault_jump:
    c->insn_pc = ipc;               /* the instruction that jumped */
    c->status = PIC18_FAULT_PC;
    c->fault_pc = pc;               /* the target outside flash */
    c->fault_word = 0xFFFF;
    goto out;

L_NOP: ADV(2); CYC(1); NEXT;
L_SLEEP: ADV(2);
    CYC(1);
    if (!c->owned[A_RCON & 0xFF]) ram[A_RCON] = (uint8_t)((ram[A_RCON] | 0x08) & ~0x04);   /* TO=1, PD=0 */
    c->wdt_clr = cyc;                        /* SLEEP clears the watchdog */
    c->sleeping = 1;
    c->event |= EV_IRQ;
    goto next;
L_CLRWDT: ADV(2);
    CYC(1);
    c->wdt_clr = cyc;
    if (!c->owned[A_RCON & 0xFF]) ram[A_RCON] |= 0x0C;
    NEXT;
L_PUSH: ADV(2); CYC(1); push(c, pc, ipc); EVT(); NEXT;
L_POP: ADV(2); CYC(1); pop(c, ipc); EVT(); NEXT;
L_DAW: ADV(2); {
    /* DS39616: low nibble +6 if > 9 or DC; high nibble +6 if > 9 or C, and then C = 1.  A carry out
     * of the low adjust (W = 0xFA-0xFF) sets C and leaves the high nibble as carried (W<7:4> is
     * then 0: no high adjust unless C was set) -- the data sheet's two steps read on the 8-bit W */
    unsigned w = ram[A_WREG], s = ram[A_STATUS], cin = s & S_C, cy = cin;
    CYC(1);
    if ((w & 0xF) > 9 || (s & S_DC)) w += 6;
    if (w > 0xFF) { cy = S_C; w &= 0xFF; }
    if ((w >> 4) > 9 || cin) { w += 0x60; cy = S_C; }
    ram[A_WREG] = (uint8_t)w;
    SETF(S_C, cy);
    NEXT;
}
L_TBLRD: ADV(2); {
    uint32_t t = tblptr_get(c);
    CYC(c->table_cycles);
    if (o->f == 3) t = (t + 1) & 0x3FFFFF;
    ram[A_TABLAT] = table_byte(c, t);
    if (o->f == 1) t = (t + 1) & 0x3FFFFF;
    else if (o->f == 2) t = (t - 1) & 0x3FFFFF;
    tblptr_set(c, t);
    NEXT;
}
L_TBLWT: ADV(2); {
    uint32_t t = tblptr_get(c);
    CYC(c->table_cycles);
    if (o->f == 3) t = (t + 1) & 0x3FFFFF;
    if (t < PIC18_FLASH_BYTES) c->holding[t & 7] = ram[A_TABLAT];
    if (o->f == 1) t = (t + 1) & 0x3FFFFF;
    else if (o->f == 2) t = (t - 1) & 0x3FFFFF;
    tblptr_set(c, t);
    NEXT;
}
L_RETFIE: ADV(2); {
    uint32_t t;
    CYC(2);
    SYNC();
    t = pop(c, ipc);
    if (o->f) { ram[A_WREG] = c->shadow_w; ram[A_STATUS] = c->shadow_status; ram[A_BSR] = c->shadow_bsr; }
    {
        /* sets GIEH, or GIEL when GIEH is already set (a low-priority return) */
        uint8_t ic = reg_get(c, A_INTCON);
        int ipen = reg_get(c, A_RCON) >> 7;
        if (!ipen || !(ic & 0x80)) { ic |= 0x80; c->in_high_isr = 0; }
        else ic |= 0x40;
        reg_set(c, A_INTCON, ic);
        c->event |= EV_IRQ;
    }
    if (c->irq_hook) c->irq_hook(c->ctx, PIC18_HOOK_RETFIE);
    JUMP(t);
    goto next;
}
L_RETURN: ADV(2); {
    uint32_t t;
    CYC(2);
    t = pop(c, ipc);
    EVT();
    if (o->f) { ram[A_WREG] = c->shadow_w; ram[A_STATUS] = c->shadow_status; ram[A_BSR] = c->shadow_bsr; }
    JUMP(t);
    NEXT;
}
L_RESET: ADV(2);
    CYC(1);
    SYNC();
    do_reset(c, 0);
    if (!c->owned[A_RCON & 0xFF]) ram[A_RCON] &= (uint8_t)~0x10;   /* RI = 0 */
    c->status = PIC18_RESET_INSN;
    c->fault_pc = ipc;
    c->fault_word = 0x00FF;
    pc = 0;
    goto out;
L_MOVLB: ADV(2); CYC(1); ram[A_BSR] = (uint8_t)o->f; NEXT;
L_SUBLW: ADV(2); {
    unsigned w = ram[A_WREG], k = o->f, r = k + (~w & 0xFF) + 1;
    CYC(1);
    ram[A_WREG] = (uint8_t)r;
    SETF(0x1F, flags_add(k, ~w & 0xFF, 1, r));
    NEXT;
}
L_IORLW: ADV(2); { uint8_t r = ram[A_WREG] | (uint8_t)o->f; CYC(1); ram[A_WREG] = r; SETF(S_Z | S_N, ZN(r)); NEXT; }
L_XORLW: ADV(2); { uint8_t r = ram[A_WREG] ^ (uint8_t)o->f; CYC(1); ram[A_WREG] = r; SETF(S_Z | S_N, ZN(r)); NEXT; }
L_ANDLW: ADV(2); { uint8_t r = ram[A_WREG] & (uint8_t)o->f; CYC(1); ram[A_WREG] = r; SETF(S_Z | S_N, ZN(r)); NEXT; }
L_RETLW: ADV(2); {
    uint32_t t;
    CYC(2);
    ram[A_WREG] = (uint8_t)o->f;
    t = pop(c, ipc);
    EVT();
    JUMP(t);
    NEXT;
}
L_MULLW: ADV(2); {
    unsigned p = ram[A_WREG] * (unsigned)o->f;
    CYC(1);
    ram[A_PRODL] = (uint8_t)p; ram[A_PRODH] = (uint8_t)(p >> 8);
    NEXT;
}
L_MOVLW: ADV(2); CYC(1); ram[A_WREG] = (uint8_t)o->f; NEXT;
L_ADDLW: ADV(2); {
    unsigned w = ram[A_WREG], k = o->f, r = w + k;
    CYC(1);
    uint8_t st_ = flags_add(w, k, 0, r);
    GPSIM_OV(st_, w, r);
    ram[A_WREG] = (uint8_t)r;
    SETF(0x1F, st_);
    NEXT;
}
TWO(L_MULWF, {
    unsigned a = EA(), p;
    CYC(1);
    RESOLVE(a);
    p = ram[A_WREG] * (unsigned)RD(a);
    ram[A_PRODL] = (uint8_t)p; ram[A_PRODH] = (uint8_t)(p >> 8);
    NEXT;
})

#define ARITH(label, expr_a, expr_b, cin, gsrc, nofx) \
TWO(label, unsigned a = EA(), f, r, x, y, ci, w0 = ram[A_WREG]; uint8_t st_; CYC(1); \
    if (nofx) { RESOLVE_NOFX(a); } else { RESOLVE(a); } f = RD(a); \
    (void)w0; \
    x = (expr_a); y = (expr_b); ci = (cin); r = x + y + ci; \
    DEST_ALU(a, r); st_ = flags_add(x, y, ci, r); \
    if ((gsrc) >= 0) { GPSIM_OV(st_, (unsigned)(gsrc), r); } SETF(0x1F, st_); NEXT;)
#define GDST ((o->flags & F_DEST) ? (int)f : (int)w0)   /* the destination's old value */
ARITH(L_ADDWF, ram[A_WREG], f, 0, GDST, GPSIM_ADDWF_W_NOFX)
ARITH(L_ADDWFC, ram[A_WREG], f, ram[A_STATUS] & S_C, (int)f, 0)
ARITH(L_INCF, f, 1, 0, ((o->flags & F_DEST) ? (int)f : 0), 0)
ARITH(L_DECF, f, 0xFF, 0, -1, 0)
ARITH(L_SUBWF, f, ~ram[A_WREG] & 0xFF, 1, -1, 0)
ARITH(L_SUBWFB, f, ~ram[A_WREG] & 0xFF, ram[A_STATUS] & S_C, -1, 0)
ARITH(L_SUBFWB, ram[A_WREG], ~f & 0xFF, ram[A_STATUS] & S_C, -1, 0)

#define LOGIC(label, expr) \
TWO(label, unsigned a = EA(), f; uint8_t r; CYC(1); RESOLVE(a); f = RD(a); r = (uint8_t)(expr); \
    DEST_ALU(a, r); SETF(S_Z | S_N, ZN(r)); NEXT;)
LOGIC(L_IORWF, ram[A_WREG] | f)
LOGIC(L_ANDWF, ram[A_WREG] & f)
LOGIC(L_XORWF, ram[A_WREG] ^ f)
LOGIC(L_COMF, ~f)
LOGIC(L_MOVF, f)
LOGIC(L_RLNCF, (f << 1) | (f >> 7))
LOGIC(L_RRNCF, (f >> 1) | (f << 7))

TWO(L_RLCF, {
    unsigned a = EA(), f; uint8_t r;
    CYC(1); RESOLVE(a); f = RD(a);
    r = (uint8_t)((f << 1) | (ram[A_STATUS] & S_C));
    DEST_ALU(a, r);
    SETF(S_C | S_Z | S_N, ZN(r) | ((f >> 7) & 1));
    NEXT;
})
TWO(L_RRCF, {
    unsigned a = EA(), f; uint8_t r;
    CYC(1); RESOLVE(a); f = RD(a);
    r = (uint8_t)((f >> 1) | ((ram[A_STATUS] & S_C) << 7));
    DEST_ALU(a, r);
    SETF(S_C | S_Z | S_N, ZN(r) | (f & 1));
    NEXT;
})
TWO(L_SWAPF, { unsigned a = EA(), f; CYC(1); RESOLVE(a); f = RD(a); DEST(a, (f << 4) | (f >> 4)); NEXT; })

#define SKIPOP(label, expr, dest) \
TWO(label, unsigned a = EA(), f; uint8_t r; CYC(1); RESOLVE(a); f = RD(a); r = (uint8_t)(expr); \
    if (dest) { DEST(a, r); } if (SKIPCOND) { SKIP(); } NEXT;)
#define SKIPCOND (r == 0)
SKIPOP(L_DECFSZ, f - 1, 1)
SKIPOP(L_INCFSZ, f + 1, 1)
SKIPOP(L_TSTFSZ, f, 0)
#undef SKIPCOND
#define SKIPCOND (r != 0)
SKIPOP(L_DCFSNZ, f - 1, 1)
SKIPOP(L_INFSNZ, f + 1, 1)
#undef SKIPCOND
#define SKIPCOND (r)
SKIPOP(L_CPFSEQ, f == ram[A_WREG], 0)
SKIPOP(L_CPFSGT, f > ram[A_WREG], 0)
SKIPOP(L_CPFSLT, f < ram[A_WREG], 0)
#undef SKIPCOND

TWO(L_SETF, { unsigned a = EA(); CYC(1); RESOLVE(a); WR(a, 0xFF); NEXT; })
TWO(L_CLRF, { unsigned a = EA(); CYC(1); RESOLVE(a); WR_ALU(a, 0); SETF(S_Z, S_Z); NEXT; })
TWO(L_MOVWF, { unsigned a = EA(); CYC(1); RESOLVE(a); WR(a, ram[A_WREG]); NEXT; })
TWO(L_NEGF, {
    unsigned a = EA(), f, r;
    CYC(1); RESOLVE(a); f = RD(a);
    r = (~f & 0xFF) + 1;
    WR_ALU(a, r);
    SETF(0x1F, flags_add(0, ~f & 0xFF, 1, r));
    NEXT;
})
TWO(L_BTG, { unsigned a = EA(), f; CYC(1); RESOLVE(a); f = RD(a); WR(a, f ^ (1u << BITNO(o))); NEXT; })
TWO(L_BSF, { unsigned a = EA(), f; CYC(1); RESOLVE(a); f = RD(a); WR(a, f | (1u << BITNO(o))); NEXT; })
TWO(L_BCF, { unsigned a = EA(), f; CYC(1); RESOLVE(a); f = RD(a); WR(a, f & ~(1u << BITNO(o))); NEXT; })
TWO(L_BTFSS, { unsigned a = EA(), f; CYC(1); RESOLVE(a); f = RD(a); if (f & (1u << BITNO(o))) SKIP(); NEXT; })
TWO(L_BTFSC, { unsigned a = EA(), f; CYC(1); RESOLVE(a); f = RD(a); if (!(f & (1u << BITNO(o)))) SKIP(); NEXT; })
L_MOVFF_GG: ADV(4); {    /* GPR to GPR (most of SDCC's): no SFR, no INDF */
    unsigned d = o->x;
    CYC(2);
    ram[d] = ram[o->f];
    NOTE_WR(d, ram[d]);
    NEXT;
}
/* MOVFF's two stack forms: what RESOLVE does for POSTDEC1 / PREINC1, written out (FSR1 and its
 * reach, resolve()); a GPR reached moves in one step, anything else as L_MOVFF does it */
L_MOVFF_PUSH: ADV(4); {
    unsigned fsr = ram[A_FSR1L] | ((ram[A_FSR1H] & 0x0F) << 8), nf = (fsr - 1) & 0xFFF;
    uint8_t v = ram[o->f];
    ram[A_FSR1L] = (uint8_t)nf;
    ram[A_FSR1H] = (uint8_t)(nf >> 8);
    if (fsr < c->fsr1_lo) c->fsr1_lo = (uint16_t)fsr;
    if (fsr > c->fsr1_hi) c->fsr1_hi = (uint16_t)fsr;
    CYC(2);
    if (fsr < PIC18_RAM_END) { ram[fsr] = v; NOTE_WR(fsr, v); NEXT; }
    fsr = is_indf(fsr) ? A_NULL : fsr;
    WR(fsr, v);
    NEXT;
}
L_MOVFF_POP: ADV(4); {
    unsigned d = o->x, ea = ((ram[A_FSR1L] | ((ram[A_FSR1H] & 0x0F) << 8)) + 1) & 0xFFF;
    uint8_t v;
    ram[A_FSR1L] = (uint8_t)ea;
    ram[A_FSR1H] = (uint8_t)(ea >> 8);
    if (ea < c->fsr1_lo) c->fsr1_lo = (uint16_t)ea;
    if (ea < PIC18_RAM_END) { CYC(2); ram[d] = ram[ea]; NOTE_WR(d, ram[d]); NEXT; }
    ea = is_indf(ea) ? A_NULL : ea;
    CYC(1);
    {
        uint32_t pc2 = pc;
        pc = ipc + 2;
        v = RD(ea);
        pc = pc2;
    }
    CYC(1);
    ram[d] = v;
    NOTE_WR(d, v);
    NEXT;
}
L_MOVFF: ADV(4); {
    unsigned s = o->f, d = o->x, v;
    RESOLVE(s);
    CYC(1);
    {   /* read in the first cycle, while the PC addresses the second word (a PCL read) */
        uint32_t pc2 = pc;
        pc = ipc + 2;
        v = RD(s);
        pc = pc2;
    }
    CYC(1);
    RESOLVE(d);
    WR(d, v);                  /* written in the second */
    NEXT;
}
L_BRA: ADV(2); CYC(2); JUMP(pc + 2 * o->x); NEXT;
L_RCALL: ADV(2); {
    uint32_t ret = pc;
    CYC(2);
    push(c, ret, ipc);
    EVT();
    JUMP(ret + 2 * o->x);
    NEXT;
}
L_BCOND: ADV(2);
    if (((ram[A_STATUS] & o->f) != 0) == o->flags) { CYC(2); JUMP(pc + 2 * o->x); }
    else CYC(1);
    NEXT;
L_CALL: ADV(4);
    CYC(2);
    if (o->f) { c->shadow_w = ram[A_WREG]; c->shadow_status = ram[A_STATUS]; c->shadow_bsr = ram[A_BSR]; }
    push(c, pc, ipc);
    EVT();
    JUMP(o->x);
    NEXT;
L_LFSR: ADV(4); CYC(2); fsr_set(c, o->f, o->x); NEXT;
L_GOTO: ADV(4); CYC(2); JUMP(o->x); NEXT;

out:
    c->pc = pc;
    c->cycles = cyc;
    c->insns = ins;
    c->insn_pc = ipc;
    return c->status;
}

/* ---------------------------------------------------------------- accessors (ctypes) */

void pic18_info(const pic18_t *c, uint64_t out[10])
{
    out[0] = c->pc; out[1] = c->cycles; out[2] = c->insns; out[3] = (uint64_t)c->status;
    out[4] = c->fault_pc; out[5] = c->fault_word; out[6] = c->stkptr; out[7] = c->stack_high;
    out[8] = tblptr_get(c); out[9] = c->sleeping;
}
uint32_t pic18_stack_entry(const pic18_t *c, unsigned level) { return level < 32 ? c->stack[level] : 0; }
void pic18_set_pc(pic18_t *c, uint32_t pc) { c->pc = pc & 0x1FFFFE; }
void pic18_set_timing(pic18_t *c, unsigned irq_vector_cycles, unsigned table_cycles)
{
    c->irq_vector_cycles = (uint8_t)irq_vector_cycles;
    c->table_cycles = (uint8_t)table_cycles;
}
void pic18_set_eeprom(pic18_t *c, const uint8_t *data) { memcpy(c->eeprom, data, PIC18_EEPROM_N); }
void pic18_set_idloc(pic18_t *c, const uint8_t *data) { memcpy(c->idloc, data, 8); }
void pic18_shadow(const pic18_t *c, uint8_t out[3]) { out[0] = c->shadow_w; out[1] = c->shadow_status; out[2] = c->shadow_bsr; }
/* core state for comparisons: WREG STATUS BSR FSR0L FSR0H FSR1L FSR1H FSR2L FSR2H PRODL PRODH
 * TABLAT TBLPTRL TBLPTRH TBLPTRU STKPTR PCLATH PCLATU, then RAM 0x000-0x2FF */
void pic18_snapshot(const pic18_t *c, uint8_t out[18 + PIC18_RAM_END])
{
    static const uint16_t a[15] = {A_WREG, A_STATUS, A_BSR, A_FSR0L, A_FSR0H, A_FSR1L, A_FSR1H,
                                   A_FSR2L, A_FSR2H, A_PRODL, A_PRODH, A_TABLAT, 0, 0, 0};
    for (int i = 0; i < 12; i++) out[i] = c->ram[a[i]];
    out[12] = c->ram[A_TBLPTRL]; out[13] = c->ram[A_TBLPTRH]; out[14] = c->ram[A_TBLPTRU];
    out[15] = c->stkptr; out[16] = c->ram[A_PCLATH]; out[17] = c->ram[A_PCLATU];
    memcpy(out + 18, c->ram, PIC18_RAM_END);
}
