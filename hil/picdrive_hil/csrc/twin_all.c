/* The twin's C as one translation unit (plant, peripheral model, event loop),
 * so that the compiler sees the whole inner loop at once: the per-step calls
 * between the three files inline and bind directly.  The firmware is compiled
 * apart with its own flags (build.py). */
#include "plant.c"
#include "pic.c"
#include "twin.c"
