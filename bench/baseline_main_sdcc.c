/* main_sdcc.c for the baseline firmware (bench/target.py): the vectors a new user writes
 * for SDCC's pic16 port, with the compiler's own interrupt prologue (no table-pointer save).
 * The EEPROM pointer symbols of SDCC's non-free device library are stubbed as in
 * firmware_templates/main_sdcc.c.j2.
 */
#include <xc.h>
#include "drive.h"

void isr_high(void) __interrupt(1) { fw_isr_high(); }
void isr_low(void) __interrupt(2) { fw_isr_low(); }

void eeprom_gptr_unused(void) __naked
{
    __asm
    global ___eeprom_gptrget1
    global ___eeprom_gptrget2
    global ___eeprom_gptrget3
    global ___eeprom_gptrget4
    global ___eeprom_gptrput1
    global ___eeprom_gptrput2
    global ___eeprom_gptrput3
    global ___eeprom_gptrput4
___eeprom_gptrget1:
___eeprom_gptrget2:
___eeprom_gptrget3:
___eeprom_gptrget4:
___eeprom_gptrput1:
___eeprom_gptrput2:
___eeprom_gptrput3:
___eeprom_gptrput4:
    reset
    __endasm;
}

void main(void)
{
    fw_init();
    for (;;) {
        fw_poll();
    }
}
