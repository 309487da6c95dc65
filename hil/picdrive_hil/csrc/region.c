/* The twin library's writable data: the part of its writable load segment after the RELRO range
 * (.got.plt, .data, .bss), where every variable of the twin, the PIC18 core and the firmware
 * lives.  A copy taken right after the library is loaded and written back before its next use
 * leaves it as a fresh load does (picdrive_hil.twin: one loaded copy serves the twins of a
 * process in turn).  Its own unit: dl_iterate_phdr needs _GNU_SOURCE, which the twin's C does
 * not build with. */
#define _GNU_SOURCE
#include <link.h>
#include <stdint.h>

#include "twin.h"

struct data_region { uintptr_t self, lo, hi; };

static int find_data_region(struct dl_phdr_info *info, size_t size, void *arg)
{
    (void)size;
    struct data_region *q = arg;
    int mine = 0;
    for (int k = 0; k < info->dlpi_phnum; k++) {
        const ElfW(Phdr) *ph = &info->dlpi_phdr[k];
        uintptr_t lo = info->dlpi_addr + ph->p_vaddr;
        if (ph->p_type == PT_LOAD && q->self >= lo && q->self < lo + ph->p_memsz) mine = 1;
    }
    if (!mine) return 0;                       /* another object of the process */
    uintptr_t relro_end = 0;
    for (int k = 0; k < info->dlpi_phnum; k++) {
        const ElfW(Phdr) *ph = &info->dlpi_phdr[k];
        if (ph->p_type == PT_GNU_RELRO) relro_end = info->dlpi_addr + ph->p_vaddr + ph->p_memsz;
    }
    for (int k = 0; k < info->dlpi_phnum; k++) {
        const ElfW(Phdr) *ph = &info->dlpi_phdr[k];
        if (ph->p_type != PT_LOAD || !(ph->p_flags & PF_W)) continue;
        uintptr_t lo = info->dlpi_addr + ph->p_vaddr, hi = lo + ph->p_memsz;
        if (relro_end > lo && relro_end <= hi) lo = relro_end;   /* read-only once relocated */
        if (q->hi) return -1;                  /* two writable segments: not the layout this expects */
        q->lo = lo;
        q->hi = hi;
    }
    return 1;
}

int twin_data_region(uint64_t out[2])
{
    struct data_region q = {(uintptr_t)&twin_data_region, 0, 0};
    if (dl_iterate_phdr(find_data_region, &q) != 1 || !q.hi) return -1;
    out[0] = (uint64_t)q.lo;
    out[1] = (uint64_t)(q.hi - q.lo);
    return 0;
}
