/* The processor twin's C as one translation unit: the PIC18 core, the plant, the
 * peripheral model and the event loop (twin.c with TWIN_PIL, which includes pil.c).
 * Built with -DTWIN_PIL (build.py, pil_group). */
#include "pic18cpu.c"
#include "plant.c"
#include "pic.c"
#include "twin.c"
