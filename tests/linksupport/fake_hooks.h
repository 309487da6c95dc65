/* fake_hooks.h -- test hook of link_fw.c (compiled in with -include fake_hooks.h). */
#ifndef FAKE_HOOKS_H
#define FAKE_HOOKS_H
#include <stdint.h>
void peer_hook_frame(uint8_t type, uint8_t seq, const uint8_t *payload, uint8_t len);
#define LINK_HOOK_FRAME(type, seq, payload, len) peer_hook_frame((type), (seq), (payload), (len))
#endif
