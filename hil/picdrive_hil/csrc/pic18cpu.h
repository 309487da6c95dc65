/* PIC18 instruction-set simulator: the PIC18F4431's core (DS39616, section 5
 * "Memory organization", 10 "Interrupts", 25 "Instruction set summary"), the
 * 75 standard instructions, extended instruction set off (the 18F4431 has none).
 *
 *   flash  16 KB (0x0000-0x3FFF), pre-decoded into one op per word
 *   data   768 B GPR (banks 0-2, 0x000-0x2FF), SFRs 0xF60-0xFFF; 0x300-0xF5F
 *          are unimplemented (read 0, writes ignored)
 *   stack  31 levels, STKPTR/STKFUL/STKUNF, STVREN from CONFIG4L
 *
 * The core owns WREG, STATUS, BSR, FSR0-2 and the INDF/POSTINC/POSTDEC/PREINC/
 * PLUSW operands, PCL/PCLATH/PCLATU, TOSU/TOSH/TOSL, STKPTR, PRODH/PRODL,
 * TBLPTRU/H/L (kept in their SFR bytes), TABLAT, and the interrupt bits it acts on (INTCON GIEH/GIEL,
 * RCON IPEN).  Every other SFR (0xF60-0xFFF) is either kept in the core's own
 * register array (no peripheral model attached: the differential tests) or
 * belongs to a peripheral model (pic18_attach): the core then calls the
 * model's read/write hook at the instruction cycle the access happens
 * (pic18_t.cycles = the count at the end of that cycle when the hook runs: an
 * instruction starting at cycle n accesses in cycle n, the hook sees n + 1; MOVFF
 * reads in its first cycle, n + 1, and writes in its second, n + 2) and takes interrupt
 * requests from the lines the model drives (pic18_set_irq).
 *
 * Time: pic18_t.cycles counts instruction cycles (Tcy = 4 Tosc) since power-on;
 * 1, 2 or 3 per instruction (datasheet Table 25-2), + the interrupt vectoring.
 * No heap, no globals: several cores live in one process. */
#ifndef PICDRIVE_PIC18CPU_H
#define PICDRIVE_PIC18CPU_H

#include <stdint.h>

#ifndef PIC18_FLASH_BYTES
#define PIC18_FLASH_BYTES  0x4000u     /* 16 KB; a build may enlarge it explicitly (-D, the twin's
                                          measurement option for a firmware that does not fit) */
#endif
#define PIC18_FLASH_WORDS  (PIC18_FLASH_BYTES / 2)
#ifndef PIC18_RAM_END
#define PIC18_RAM_END      0x300u      /* GPRs 0x000-0x2FF (enlargeable like the flash) */
#endif
#define PIC18_SFR_BASE     0xF60u      /* first SFR */
/* access bank: 0x00-0x5F are GPRs 0x000-0x05F, 0x60-0xFF the SFRs 0xF60-0xFFF on the 18F4431
 * (DS39616 Fig. 5-6).  The gpsim build compares with gpsim's p18f4520, which splits at 0x80. */
#ifndef PIC18_ACCESS_SPLIT
#ifdef PIC18_GPSIM_COMPAT
#define PIC18_ACCESS_SPLIT 0x80u
#else
#define PIC18_ACCESS_SPLIT 0x60u
#endif
#endif
#define PIC18_CONFIG_BASE  0x300000u   /* CONFIG1L .. CONFIG7H */
#define PIC18_CONFIG_N     14u
#define PIC18_IDLOC_BASE   0x200000u   /* user ID words */
#define PIC18_DEVID_BASE   0x3FFFFEu   /* DEVID1, DEVID2 */
#define PIC18_EEPROM_BASE  0xF00000u   /* data EEPROM image in a HEX */
#define PIC18_EEPROM_N     256u
#define PIC18_STACK_LEVELS 31

/* pic18_t.status: why the core stopped (0 = running / ran to the limit) */
enum {
    PIC18_OK = 0,
    PIC18_BREAK = 1,          /* PC reached the breakpoint given to pic18_run */
    PIC18_SLEEP = 2,          /* SLEEP executed, no interrupt to wake it */
    PIC18_STACK_OVERFLOW = 3, /* 31st push; with STVREN the core was reset (PC = 0) */
    PIC18_STACK_UNDERFLOW = 4,/* pop of an empty stack; with STVREN the core was reset */
    PIC18_RESET_INSN = 5,     /* RESET instruction executed (the core was reset) */
    PIC18_FAULT_PC = 16,      /* PC left the implemented flash (fatal, needs pic18_reset) */
    PIC18_FAULT_ILLEGAL = 17, /* unimplemented / illegal / extended opcode (fatal) */
};
#define PIC18_FATAL(st) ((st) >= 16)

/* interrupt-request lines the peripheral model drives (pic18_set_irq): a source
 * with its flag and enable set (and, with IPEN = 0, PEIE for peripherals) of
 * high (or compatibility-mode) / low priority.  The core gates them with
 * GIEH/GIEL and IPEN. */
#define PIC18_IRQ_HIGH 1u
#define PIC18_IRQ_LOW  2u

struct pic18;
/* the twin's C is built with -fvisibility=hidden: the API is exported explicitly */
#if defined(__GNUC__)
#define PIC18_API __attribute__((visibility("default")))
#else
#define PIC18_API
#endif
typedef uint8_t (*pic18_sfr_read_fn)(void *ctx, uint16_t addr);
typedef void (*pic18_sfr_write_fn)(void *ctx, uint16_t addr, uint8_t value);
/* interrupt bookkeeping for the twin: called after the core vectored (what = 1 high, 2 low;
 * cycles already include the vectoring) and after a RETFIE completed (what = 3) */
typedef void (*pic18_irq_hook_fn)(void *ctx, int what);
#define PIC18_HOOK_HIGH 1
#define PIC18_HOOK_LOW 2
#define PIC18_HOOK_RETFIE 3

typedef struct {
    const void *h;        /* the run loop's handler for code (set by pic18_run_bp: threaded dispatch) */
    uint32_t x;           /* target word index, second operand, branch offset */
    uint16_t f;           /* file address (access: absolute; banked: 0-255), literal, FSR index */
    uint8_t code, flags;  /* handler; a/d/bit/s fields */
} pic18_op_t;
_Static_assert(sizeof(pic18_op_t) == 16, "OP_AT indexes ops by byte address x 8");

typedef struct pic18 {
    /* --- visible state --- */
    uint32_t pc;               /* byte address of the next instruction */
    uint64_t cycles;           /* instruction cycles since power-on */
    uint64_t insns;            /* instructions executed */
    int status;                /* PIC18_* of the last stop */
    uint32_t fault_pc;         /* address of the instruction that stopped the core */
    uint16_t fault_word;       /* its first word */
    uint8_t stkptr;            /* STKFUL | STKUNF | SP<4:0> */
    uint32_t stack[32];        /* stack[1..31]; stack[0] reads 0 */
    uint8_t shadow_w, shadow_status, shadow_bsr;   /* fast register stack */
    uint8_t holding[8];        /* table-write holding registers (TBLWT) */
    uint8_t sleeping;
    uint8_t irq_lines;         /* PIC18_IRQ_* driven by the model */
    uint8_t irq_builtin;       /* 1: no model; the core evaluates INTCON/PIR/PIE/IPR itself */
    uint8_t in_high_isr;       /* bookkeeping for the twin's statistics (not architectural) */
    uint8_t stack_high;        /* stack high-water mark (levels) */
    uint8_t irq_vector_cycles; /* cycles from the interrupted boundary to the vector's first
                                  instruction: 2 (DS39616 Fig. 10-1 / DS39500 8.x: the
                                  instruction fetched is discarded, then the vector is fetched) */
    uint8_t table_cycles;      /* TBLRD/TBLWT: 2 (Table 25-2) */
    uint8_t event;             /* something outside the straight-line path needs a look */
    uint32_t pcl_target;       /* a write to PCL: where the PC goes */
    uint32_t insn_pc;          /* byte address of the instruction being executed */
    uint64_t wdt_clr;          /* cycle of the last watchdog clear: CLRWDT, SLEEP or a reset (the
                                  twin's watchdog model times out from here) */
    /* --- memories --- */
    uint8_t ram[0x1002];       /* data space; [0x1000] is the null target of INDF-through-INDF */
    uint8_t owned[256];        /* SFR 0xF00+i belongs to the model (1) */
    uint8_t config[PIC18_CONFIG_N];
    uint8_t idloc[8];
    uint8_t devid[2];
    uint8_t eeprom[PIC18_EEPROM_N];
    uint8_t flash[PIC18_FLASH_BYTES];
    pic18_op_t op[PIC18_FLASH_WORDS + 2];   /* + two fault entries past the end */
    void *const *disp_tab;     /* the run loop's handler table the ops' h point into (NULL: not yet) */
    uint8_t rd_plain[256];     /* SFR 0xF00+i reads as the core's ram[] (no side effect, no model) */
    uint8_t wr_mask[256];      /* != 0: a (non-ALU) write of SFR 0xF00+i is ram[] = v & mask, nothing else */
    /* --- peripheral model --- */
    void *ctx;
    pic18_sfr_read_fn sfr_read;
    pic18_sfr_write_fn sfr_write;
    pic18_irq_hook_fn irq_hook;
    /* INTCON kept by the model in its own byte (pic18_share_intcon): read inline, and a write
       that changes only intcon_quiet's bits (0: none) stored there without the write hook */
    volatile uint8_t *intcon_ext;
    uint8_t *intcon_mirror;
    uint8_t intcon_quiet;
    /* --- measurements (not architectural) --- */
    uint16_t fsr1_lo;          /* lowest data address reached through FSR1 (INDF1/POSTDEC1/...): 0xFFFF none */
    uint16_t fsr1_hi;          /* highest address written through POSTDEC1 (the software stack's top) */
    uint8_t ram_written[0x1000];       /* GPR bytes written since power-on, one flag a byte (PIC18_TRACK_RAM
                                          builds): 1 written, 2 only cleared (a first store of zero: the
                                          start-up clear), 0 untouched; pic18_ram_written counts the 1s */
} pic18_t;

/* All functions are safe on any input: addresses are bounded, nothing allocates. */
PIC18_API void pic18_init(pic18_t *c);                  /* erased flash (0xFFFF = NOP), default config, POR */
PIC18_API void pic18_power_on(pic18_t *c);              /* power-on reset: core registers and RAM per Table 4-4 (x -> 0) */
PIC18_API void pic18_reset(pic18_t *c);                 /* MCLR reset: u bits kept */
PIC18_API void pic18_load_flash(pic18_t *c, uint32_t addr, const uint8_t *data, uint32_t n);  /* bytes, re-decodes */
PIC18_API void pic18_set_config(pic18_t *c, const uint8_t cfg[PIC18_CONFIG_N]);
PIC18_API void pic18_flash_erase_row(pic18_t *c, uint32_t addr);   /* 64-byte row -> 0xFF */
PIC18_API void pic18_flash_write_block(pic18_t *c, uint32_t addr); /* 8 holding bytes -> flash */

/* peripheral model: owned[i] != 0 makes SFR 0xF00+i the model's (core registers stay the core's) */
PIC18_API void pic18_attach(pic18_t *c, void *ctx, pic18_sfr_read_fn rd, pic18_sfr_write_fn wr,
                  const uint8_t owned[256]);
PIC18_API void pic18_set_irq(pic18_t *c, unsigned lines);
PIC18_API void pic18_set_irq_hook(pic18_t *c, pic18_irq_hook_fn fn);
/* from a peripheral hook: return from pic18_run after the present instruction (status OK) */
PIC18_API void pic18_request_stop(pic18_t *c);
/* a model-owned INTCON that the model keeps in *reg (and a copy in *mirror): the core reads it
 * there without the read hook; a write whose changed bits are all in `quiet` (the model's word
 * that nothing it computes depends on them: with IPEN, GIEH/GIEL) goes there, and to *mirror,
 * without the write hook -- the core still looks for an interrupt when a request line is up.
 * reg NULL: every access through the hooks.  pic18_set_intcon_quiet changes the bits. */
PIC18_API void pic18_share_intcon(pic18_t *c, volatile uint8_t *reg, uint8_t *mirror);
PIC18_API void pic18_set_intcon_quiet(pic18_t *c, uint8_t quiet);
/* GPR bytes written since power-on (PIC18_TRACK_RAM builds; 0 otherwise) */
PIC18_API unsigned pic18_ram_written(const pic18_t *c);

/* Run until `max_cycles` more cycles have elapsed (the instruction that crosses
 * the limit completes), `max_insns` instructions ran, PC == break_pc (checked
 * before each instruction after the first; ~0u: none), or a stop.  Returns status. */
PIC18_API int pic18_run(pic18_t *c, uint64_t max_cycles, uint64_t max_insns, uint32_t break_pc);
/* Same, with up to n breakpoints (byte addresses). */
PIC18_API int pic18_run_bp(pic18_t *c, uint64_t max_cycles, uint64_t max_insns, const uint32_t *bps, int n);

/* data space for a debugger / the host: peek has no FSR side effects (INDF forms read 0;
 * a model-owned SFR is read through the model's hook); poke writes like MOVWF */
PIC18_API uint8_t pic18_peek(pic18_t *c, uint16_t addr);
PIC18_API void pic18_poke(pic18_t *c, uint16_t addr, uint8_t v);
PIC18_API unsigned pic18_sizeof(void);



/* accessors for ctypes (hil/picdrive_hil/pic18.py) */
PIC18_API void pic18_info(const pic18_t *c, uint64_t out[10]);
PIC18_API uint32_t pic18_stack_entry(const pic18_t *c, unsigned level);
PIC18_API void pic18_set_pc(pic18_t *c, uint32_t pc);
PIC18_API void pic18_set_timing(pic18_t *c, unsigned irq_vector_cycles, unsigned table_cycles);
PIC18_API void pic18_set_eeprom(pic18_t *c, const uint8_t *data);
PIC18_API void pic18_set_idloc(pic18_t *c, const uint8_t *data);
PIC18_API void pic18_shadow(const pic18_t *c, uint8_t out[3]);
PIC18_API void pic18_snapshot(const pic18_t *c, uint8_t out[18 + PIC18_RAM_END]);
#endif
