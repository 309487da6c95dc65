"""drive.c's app_signal on the PIC18 core: every signal's value and the interrupt enables after it.

app_signal is PIC18 assembly under SDCC (the host twin runs its C twin), so this builds the
bundled firmware with a small harness (picdrive.firmware.gpsim's timing device and linker
script) and runs it in gpsim: the harness sets the speed loop's state (core_s) to several
values, the drive state through the link callbacks (start, link loss), calls app_signal for
every signal index and one beyond, and stores the results; each must be what the C reads
(int16 sources, the integrator's high half, the duty signed by the direction, the state and
fault codes, 0 past the table), and GIEH/GIEL must come back as they were before the call.
"""
from __future__ import annotations

import re
import subprocess

from picdrive.firmware import gpsim, target
from picdrive.paths import firmware_build_dir

FW = firmware_build_dir() / "duy2008"

# (integ, pdc, dir, speed, r_applied, u, current, mu1)
CASES = [(0x12345678, 0x0123, 0, 1200, -300, 2500, -7, 4096),
         (-0x0ABCDEF1, 0x0100, 1, -1500, 77, -2600, 15, 0),
         (0x7FFFFFFF, 0x0000, 1, 32767, -32768, 1, -1, 1234),
         (-0x80000000, 0x07D0, 1, -32768, 32767, -1, 1023, 65535 - 65536)]
GIE = (0x00, 0xC0, 0x80)           # INTCON's GIEH/GIEL before the calls


def _define(text: str, name: str) -> int:
    m = re.search(rf"#define\s+{name}\s+\(?(-?(?:0x[0-9A-Fa-f]+|\d+))[uUlL]*\)?", text)
    assert m, name
    return int(m.group(1), 0)


def _harness(n_sig: int) -> str:
    rows = ",\n".join("    {%dL, %du, %du, %d, %d, %d, %d, %d}" % c for c in CASES)
    return f"""
#include <stdint.h>
#include "fw_port.h"
#include "drive_params.h"
#include "drive_core.h"
#include "link_fw.h"
#include "drive.h"
typedef struct {{ int32_t integ; uint16_t pdc; uint8_t dir; int16_t speed, r, u, cur, mu1; }} case_t;
static const case_t cases[] = {{
{rows}
}};
static const uint8_t gie[] = {{ {", ".join(f"0x{g:02X}u" for g in GIE)} }};
volatile int16_t __at({gpsim.RESULT_ADDR:#x}) res[{len(CASES) * 3 * len(GIE) * (n_sig + 2)}];
static uint8_t bad;
static uint16_t n;
void harness_done(void) {{ n++; }}
void main(void)
{{
    uint8_t s, c, g, i;
    n = 0u;
    for (s = 0u; s < 3u; s++) {{              /* IDLE, RUN, FAULT (link lost) */
        if (s == 1u) {{
            (void)app_command(LINK_CMD_START, 0, 0u);
        }} else if (s == 2u) {{
            app_link_lost();
        }}
        for (c = 0u; c < {len(CASES)}u; c++) {{
            core_s.law.integ = cases[c].integ;
            core_s.pdc = cases[c].pdc;
            core_s.dir = cases[c].dir;
            core_s.speed = cases[c].speed;
            core_s.r_applied = cases[c].r;
            core_s.u = cases[c].u;
            core_s.current = cases[c].cur;
            core_s.law.mu1 = cases[c].mu1;
            for (g = 0u; g < {len(GIE)}u; g++) {{
                bad = 0u;
                for (i = 0u; i <= {n_sig}u; i++) {{
                    INTCON = gie[g];
                    res[n++] = app_signal(i);
                    bad |= (uint8_t)((uint8_t)(INTCON & 0xC0u) ^ gie[g]);
                    INTCON = 0u;
                }}
                res[n++] = (int16_t)(0x100u | bad);  /* GIEH/GIEL not as they were: their bits */
            }}
        }}
    }}
    harness_done();
    for (;;) {{ }}
}}
"""


def test_app_signal_on_the_pic18_core(tmp_path):
    h = (FW / "link_fw.h").read_text()
    n_sig = _define(h, "LINK_N_SIGNALS")
    sig = {n: _define(h, f"LINK_SIG_{n.upper()}") for n in ("speed", "setpoint", "voltage", "current",
                                                              "integrator", "duty", "state", "fault", "mu1")}
    st = {n: _define(h, f"LINK_STATE_{n}") for n in ("IDLE", "RUN", "FAULT")}
    lost = _define(h, "LINK_FAULT_LINK_LOST")
    hdr, sfr = gpsim.timing_device()
    (tmp_path / "t.lkr").write_text(gpsim.timing_lkr())
    b = target.build_hex(FW, tmp_path / "b", name="sig", linker_script=tmp_path / "t.lkr",
                         sources=("drive.c", "drive_core.c", "link_fw.c"),
                         extra_c={"main_sdcc.c": gpsim._main_without_main(FW / "main_sdcc.c"),
                                  "harness.c": _harness(n_sig)}, device=(hdr, sfr))
    script = tmp_path / "s.stc"
    script.write_text("\n".join([f"break e 0x{b.functions['_harness_done'].address:x}", "break c 5000000",
                                 "run", "dump r", "quit", ""]))
    r = subprocess.run([gpsim._gpsim(), "-i", "-S", "disable", "-p", gpsim.TIMING_PROCESSOR, "-c", str(script),
                        str(b.hex_path.resolve())], capture_output=True, stdin=subprocess.DEVNULL, timeout=300)
    mem = gpsim._dump(r.stdout.decode("latin-1") + r.stderr.decode("latin-1"))
    got = []
    for k in range(len(CASES) * 3 * len(GIE) * (n_sig + 2)):
        a = gpsim.RESULT_ADDR + 2 * k
        got.append(int.from_bytes(bytes((mem[a], mem[a + 1])), "little", signed=True))
    want = []
    for s, (state, fault) in enumerate(((st["IDLE"], 0), (st["RUN"], 0), (st["FAULT"], lost))):
        for integ, pdc, d, speed, rr, u, cur, mu1 in CASES:
            v = {sig["speed"]: speed, sig["setpoint"]: rr, sig["voltage"]: u, sig["current"]: cur,
                 sig["integrator"]: integ >> 16, sig["duty"]: -pdc if d else pdc,
                 sig["state"]: state, sig["fault"]: fault, sig["mu1"]: mu1}
            for g in GIE:
                for i in range(n_sig + 1):
                    want.append(v.get(i, 0))   # hall, position: no edge, no measurement ran; 0 past the table
                want.append(0x100)
    assert got == want
