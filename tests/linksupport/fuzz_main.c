/*
 * fuzz_main.c -- fuzz the rendered link module's receiver and dispatcher (built with
 * -fsanitize=address,undefined; see build.py).
 *
 *   fuzz_link --bytes N --seed S
 *
 * Generates a stream of N bytes: garbage (biased towards SOF and plausible LEN bytes), intact
 * frames (random or well-formed commands, valid CRC), intact frames with 1..3 flipped bits
 * outside SOF/LEN, frames with a corrupted LEN, truncated frames, repeated frames (duplicate
 * SEQ) and inter-byte gaps.  The stream goes byte by byte through link_rx_byte + link_poll
 * (gaps: link_tick_ms past the frame gap), with link_sample and ticks now and then.
 *
 * Checks, any failure -> exit status 1:
 *  - the frames the module accepts are exactly those of an independent reference decoder
 *    (whole-array scan, bitwise CRC) applying the protocol's rule;
 *  - no frame with a bit flipped (outside LEN) is accepted;
 *  - every intact frame is accepted, unless a frame that passed the CRC by chance overlaps it;
 *  - resynchronisation within one frame: a frame is accepted by the time the byte at
 *    max(its end, its SOF + LINK_MAX_FRAME - 2) has arrived, or at the first gap after it;
 *  - the board's output is a clean sequence of valid frames with exactly one ACK/NACK per
 *    accepted frame, in order, echoing its SEQ.
 * Prints key=value figures.
 */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include "link_fw.h"

/* fake_app.c */
void peer_reset(uint32_t baud, uint32_t hz, uint16_t txq_bytes);
uint32_t peer_take_tx(uint8_t *out, uint32_t cap);
int peer_log_get(uint32_t i, uint8_t *type, uint8_t *seq, uint8_t *payload, uint32_t *at);
void peer_log_clear(void);
uint32_t peer_stat(int which);
void peer_erase_eeprom(void);
void peer_feed(const uint8_t *p, uint32_t n);

static uint64_t rng_s;
static uint64_t rnd(void)
{
    rng_s ^= rng_s >> 12;
    rng_s ^= rng_s << 25;
    rng_s ^= rng_s >> 27;
    return rng_s * 2685821657736338717ULL;
}
static uint32_t below(uint32_t n) { return (uint32_t)(rnd() % n); }

static uint16_t crc_bitwise(const uint8_t *p, size_t n)
{
    uint16_t crc = 0xFFFFu;
    size_t i;
    int b;
    for (i = 0; i < n; i++) {
        crc ^= (uint16_t)(p[i] << 8);
        for (b = 0; b < 8; b++)
            crc = (crc & 0x8000u) ? (uint16_t)((crc << 1) ^ 0x1021u) : (uint16_t)(crc << 1);
    }
    return crc;
}

enum { K_GARBAGE, K_INTACT, K_FLIPPED, K_BADLEN, K_TRUNC, K_REPEAT, K_GAP, K_N };
static const char *kind_name[K_N] = {"garbage", "intact", "flipped", "badlen", "truncated", "repeat", "gap"};

typedef struct { uint32_t start, end, full; uint8_t kind; } seg_t;   /* segments; full: length of the frame a truncated one was cut from */

static uint8_t *S;          /* the stream */
static uint8_t *gap_before; /* gap_before[i]: a gap precedes byte i (and gap_before[N]: at the end) */
static uint32_t N, cap;
static seg_t *segs;
static uint32_t nseg, segcap;
static uint64_t kind_count[K_N];

static void put(uint8_t b)
{
    if (N < cap) S[N++] = b;
}

static void add_seg(uint32_t start, uint8_t kind)
{
    if (nseg == segcap) {
        segcap = segcap ? 2 * segcap : 1024;
        segs = realloc(segs, segcap * sizeof *segs);
        if (!segs) { perror("realloc"); exit(2); }
    }
    segs[nseg].start = start;
    segs[nseg].end = N - 1;
    segs[nseg].kind = kind;
    segs[nseg].full = 0;
    nseg++;
}

static uint32_t make_frame(uint8_t *f)
{
    static const uint8_t cmd_len[] = {0, 1, 255, 5, 4, 0, 0, 0, 1, 5, 11, 3, 0, 0, 0, 0, 0};
    uint8_t type, len, i;
    uint16_t c;
    if (below(20) == 0) {                              /* a well-formed config command */
        uint16_t mask = (uint16_t)(1u + below((1u << LINK_N_SIGNALS) - 1u));
        uint32_t q = below(4);
        f[0] = LINK_SOF;
        f[3] = (uint8_t)below(256);
        if (q == 0) {
            f[1] = 5; f[2] = LINK_CMD_TELEM_CONFIG;
            mask = (uint16_t)(mask & 0x000Fu ? mask & 0x000Fu : 1u);
            f[4] = (uint8_t)mask; f[5] = (uint8_t)(mask >> 8);
            f[6] = (uint8_t)below(3); f[7] = 0; f[8] = (uint8_t)(1 + below(4));
        } else if (q == 1) {
            f[1] = 11; f[2] = LINK_CMD_CAPTURE_ARM;
            f[4] = (uint8_t)mask; f[5] = (uint8_t)(mask >> 8);
            f[6] = (uint8_t)(1 + below(40)); f[7] = 0;            /* n */
            f[8] = (uint8_t)below(f[6]); f[9] = 0;                 /* pre */
            f[10] = (uint8_t)(1 + below(3)); f[11] = 0;            /* decimation */
            f[12] = (uint8_t)below(4);
            if (f[12] == 0) f[8] = 0;
            f[13] = (uint8_t)below(256); f[14] = (uint8_t)below(4);
        } else if (q == 2) {
            f[1] = 3; f[2] = LINK_CMD_CAPTURE_READ;
            f[4] = (uint8_t)below(50); f[5] = 0; f[6] = (uint8_t)below(256);
        } else {
            f[1] = 5; f[2] = LINK_CMD_PARAM_SET;
            f[4] = (uint8_t)below(0x50);
            f[5] = (uint8_t)below(256); f[6] = (uint8_t)below(256); f[7] = (uint8_t)below(2); f[8] = 0;
        }
        len = f[1];
        c = crc_bitwise(&f[1], (size_t)len + 3u);
        f[4 + len] = (uint8_t)(c >> 8);
        f[5 + len] = (uint8_t)c;
        return (uint32_t)len + 6u;
    }
    if (below(10) < 7) {
        type = (uint8_t)(1 + below(0x11));
        len = cmd_len[type - 1];
        if (len == 255) len = (uint8_t)(1 + below(LINK_PARAM_GET_MAX));
        if (below(4) == 0) len = (uint8_t)below(LINK_MAX_PAYLOAD + 1);
    } else {
        type = (uint8_t)below(256);
        len = (uint8_t)below(LINK_MAX_PAYLOAD + 1);
    }
    f[0] = LINK_SOF;
    f[1] = len;
    f[2] = type;
    f[3] = (uint8_t)below(256);
    for (i = 0; i < len; i++) {
        /* plausible ids / small numbers half of the time, so handlers go deep */
        uint32_t r = below(4);
        f[4 + i] = r == 0 ? (uint8_t)below(0x50) : r == 1 ? (uint8_t)below(4) : (uint8_t)below(256);
    }
    c = crc_bitwise(&f[1], (size_t)len + 3u);
    f[4 + len] = (uint8_t)(c >> 8);
    f[5 + len] = (uint8_t)c;
    return (uint32_t)len + 6u;
}

static void generate(uint32_t nbytes)
{
    uint8_t f[LINK_MAX_FRAME], last[LINK_MAX_FRAME];
    uint32_t lastn = 0, n, i, k;
    cap = nbytes;
    S = malloc(cap + 1);
    gap_before = calloc(cap + 1, 1);
    if (!S || !gap_before) { perror("malloc"); exit(2); }
    while (N < cap) {
        uint32_t r = below(100), start = N;
        if (r < 30) {                                 /* garbage */
            k = 1 + below(64);
            for (i = 0; i < k; i++) {
                uint32_t q = below(8);
                put(q == 0 ? LINK_SOF : q == 1 ? (uint8_t)below(LINK_MAX_PAYLOAD + 6) : (uint8_t)below(256));
            }
            add_seg(start, K_GARBAGE);
            kind_count[K_GARBAGE]++;
            continue;
        }
        if (r < 37) {                                 /* gap */
            gap_before[N] = 1;
            kind_count[K_GAP]++;
            continue;
        }
        if (r < 42 && lastn) {                        /* repeat the previous intact frame */
            if (N + lastn > cap) break;
            for (i = 0; i < lastn; i++) put(last[i]);
            add_seg(start, K_INTACT);
            kind_count[K_REPEAT]++;
            continue;
        }
        n = make_frame(f);
        if (N + n > cap) break;
        if (r < 75) {
            memcpy(last, f, n);
            lastn = n;
            for (i = 0; i < n; i++) put(f[i]);
            add_seg(start, K_INTACT);
            kind_count[K_INTACT]++;
        } else if (r < 87) {
            k = 1 + below(3);                          /* flip 1..3 distinct bits in TYPE..CRC */
            {
                uint32_t bits[3], j, m, dup;
                for (j = 0; j < k;) {
                    bits[j] = 16u + below((n - 2u) * 8u);
                    for (dup = 0, m = 0; m < j; m++) dup |= bits[m] == bits[j];
                    if (!dup) j++;
                }
                for (j = 0; j < k; j++) f[bits[j] / 8u] ^= (uint8_t)(1u << (bits[j] % 8u));
            }
            for (i = 0; i < n; i++) put(f[i]);
            add_seg(start, K_FLIPPED);
            kind_count[K_FLIPPED]++;
        } else if (r < 93) {
            f[1] ^= (uint8_t)(1u << below(8));
            for (i = 0; i < n; i++) put(f[i]);
            add_seg(start, K_BADLEN);
            kind_count[K_BADLEN]++;
        } else {
            k = 1 + below(n - 1);
            for (i = 0; i < k; i++) put(f[i]);
            add_seg(start, K_TRUNC);
            segs[nseg - 1].full = n;
            kind_count[K_TRUNC]++;
        }
    }
    if (N < cap) {                                    /* fill up with garbage */
        uint32_t start = N;
        while (N < cap) put((uint8_t)below(256));
        add_seg(start, K_GARBAGE);
    }
    gap_before[N] = 1;                                /* the stream ends with a gap */
}

/* ---- reference decoder: whole-array scan ---- */
typedef struct { uint32_t start, end; } acc_t;
static acc_t *ref;
static uint32_t nref;
static uint64_t ref_crc_fail;

static int gap_inside(uint32_t a, uint32_t b)       /* a gap before any byte in (a, b] */
{
    uint32_t i;
    for (i = a + 1; i <= b; i++)
        if (gap_before[i]) return 1;
    return 0;
}

static void reference(void)
{
    uint32_t i = 0, len, need;
    ref = malloc(((size_t)N / 6u + 2u) * sizeof *ref);
    if (!ref) { perror("malloc"); exit(2); }
    while (i < N) {
        if (S[i] != LINK_SOF) { i++; continue; }
        if (i + 1 >= N || gap_before[i + 1]) { i++; continue; }
        len = S[i + 1];
        if (len > LINK_MAX_PAYLOAD) { i++; continue; }
        need = len + 6u;
        if (i + need > N || gap_inside(i, i + need - 1u)) { i++; continue; }
        if (crc_bitwise(&S[i + 1], len + 3u) != (uint16_t)((S[i + need - 2u] << 8) | S[i + need - 1u])) {
            ref_crc_fail++;
            i++;
            continue;
        }
        ref[nref].start = i;
        ref[nref].end = i + need - 1u;
        nref++;
        i += need;
    }
}

/* ---- board output checker: strictly framed ---- */
static uint8_t ob[4 * LINK_MAX_FRAME + 8192];
static uint32_t obn;
static uint64_t out_frames, out_replies, out_badcrc_nacks, out_events, out_telem;
static uint8_t *reply_seq;     /* SEQ of the i-th ACK/NACK (not BAD_CRC) */
static uint64_t nreply_seq;

static int fail(const char *what, uint64_t a, uint64_t b)
{
    printf("FAIL=%s (%llu, %llu)\n", what, (unsigned long long)a, (unsigned long long)b);
    exit(1);
}

static void take_output(void)
{
    uint32_t n = peer_take_tx(ob + obn, (uint32_t)(sizeof ob - obn)), p = 0;
    obn += n;
    while (obn - p >= 2) {
        uint32_t len = ob[p + 1], need = len + 6u;
        if (ob[p] != LINK_SOF || len > LINK_MAX_PAYLOAD) fail("board output not framed", p, ob[p]);
        if (obn - p < need) break;
        if (crc_bitwise(&ob[p + 1], len + 3u) != (uint16_t)((ob[p + need - 2] << 8) | ob[p + need - 1]))
            fail("board output CRC", out_frames, 0);
        out_frames++;
        {
            uint8_t type = ob[p + 2];
            if (type == LINK_MSG_NACK && len == 2 && ob[p + 5] == LINK_NACK_BAD_CRC) {
                out_badcrc_nacks++;
            } else if (type == LINK_MSG_NACK || (type & LINK_ACK_BIT)) {
                reply_seq[nreply_seq++] = ob[p + 3];
                out_replies++;
            } else if (type == LINK_MSG_EVENT) {
                out_events++;
            } else if (type == LINK_MSG_TELEMETRY) {
                out_telem++;
            } else {
                fail("unknown frame type from the board", type, out_frames);
            }
        }
        p += need;
    }
    memmove(ob, ob + p, obn - p);
    obn -= p;
}

int main(int argc, char **argv)
{
    uint32_t nbytes = 1000000u, seed = 1u, i, k, next_ref = 0;
    uint64_t trunc_completed = 0, accepted = 0, spurious = 0, intact = 0, intact_ok = 0, intact_lost = 0, flipped = 0;
    uint64_t max_after_end = 0;
    uint8_t type, seq, pl[LINK_MAX_PAYLOAD];
    uint32_t at;
    clock_t t0;
    for (i = 1; i + 1 < (uint32_t)argc; i += 2) {
        if (!strcmp(argv[i], "--bytes")) nbytes = (uint32_t)strtoul(argv[i + 1], 0, 10);
        else if (!strcmp(argv[i], "--seed")) seed = (uint32_t)strtoul(argv[i + 1], 0, 10);
    }
    rng_s = 0x9E3779B97F4A7C15ULL ^ ((uint64_t)seed << 17) ^ seed;
    rnd();
    generate(nbytes);
    reference();
    reply_seq = malloc((size_t)N / 6u + 16u);
    if (!reply_seq) { perror("malloc"); return 2; }

    peer_erase_eeprom();
    peer_reset(0u, 0u, 4096u);
    peer_log_clear();
    take_output();
    t0 = clock();
    for (i = 0; i <= N; i++) {
        if (gap_before[i]) {
            for (k = 0; k < LINK_FRAME_GAP_MS + 1u; k++) {
                link_tick_ms();
                link_poll();
            }
        }
        if (i < N) {
            peer_feed(&S[i], 1u);                        /* link_rx_byte + link_poll */
            if ((i & 63u) == 0u) link_sample();
            if ((i & 255u) == 0u) link_tick_ms();        /* time passes: the watchdog may fire */
            link_poll();
        }
        take_output();
        /* what was accepted at the gap before byte i (at == i) or with byte i (at == i + 1) */
        for (k = 0; peer_log_get(k, &type, &seq, pl, &at) >= 0; k++) {
            acc_t r;
            uint32_t bound, gp, pos;
            int at_gap;
            if (next_ref >= nref) fail("module accepted a frame the reference did not", i, k);
            r = ref[next_ref];
            if (S[r.start + 2] != type || S[r.start + 3] != seq || S[r.start + 1] != (uint8_t)(r.end - r.start - 5u)
                || memcmp(pl, &S[r.start + 4], r.end - r.start - 5u) != 0)
                fail("module and reference accepted different frames", r.start, i);
            if (at == i + 1u && i < N) {
                pos = i;
                at_gap = 0;
            } else if (at == i && gap_before[i]) {
                pos = i - 1u;
                at_gap = 1;
            } else {
                fail("frame accepted at an unexpected time", at, i);
                return 1;
            }
            bound = r.end > r.start + LINK_MAX_FRAME - 2u ? r.end : r.start + LINK_MAX_FRAME - 2u;
            for (gp = r.end + 1u; gp <= N && !gap_before[gp]; gp++) {}
            if (pos > bound && !(at_gap && i == gp)) fail("resync later than one frame", r.start, pos);
            if (!at_gap && pos - r.end > max_after_end) max_after_end = pos - r.end;
            next_ref++;
            accepted++;
        }
        peer_log_clear();
    }
    if (next_ref != nref) fail("reference frames not accepted by the module", nref - next_ref, nref);

    /* classify against the generated segments */
    {
        uint32_t a = 0;
        for (k = 0; k < nseg; k++) {
            while (a < nref && ref[a].start < segs[k].start) a++;
            if (segs[k].kind == K_INTACT) {
                intact++;
                if (a < nref && ref[a].start == segs[k].start && ref[a].end == segs[k].end) {
                    intact_ok++;
                } else {
                    /* lost: only allowed if a chance-CRC frame overlaps it */
                    uint32_t b2;
                    int covered = 0;
                    for (b2 = a > 0 ? a - 1 : 0; b2 < nref && ref[b2].start <= segs[k].end; b2++)
                        if (ref[b2].end >= segs[k].start && ref[b2].start != segs[k].start) covered = 1;
                    if (!covered) fail("intact frame lost without a chance-CRC frame over it", segs[k].start, 0);
                    intact_lost++;
                }
            } else if (segs[k].kind == K_FLIPPED) {
                flipped++;
                if (a < nref && ref[a].start == segs[k].start) fail("bit-flipped frame accepted", segs[k].start, 0);
            } else if (segs[k].kind == K_TRUNC && a < nref && ref[a].start == segs[k].start
                       && ref[a].end - ref[a].start + 1u == segs[k].full) {
                /* cut one byte short and completed by a following byte equal to the missing one:
                   the accepted bytes are the original frame, CRC and all */
                trunc_completed++;
            }
        }
        spurious = accepted - intact_ok - trunc_completed;
        if (getenv("FUZZ_SHOW_CHANCE")) {                /* where the chance-CRC frames came from */
            uint32_t sg = 0;
            for (a = 0; a < nref; a++) {
                while (sg + 1 < nseg && segs[sg + 1].start <= ref[a].start) sg++;
                if (segs[sg].start == ref[a].start && (segs[sg].kind == K_INTACT || segs[sg].kind == K_TRUNC))
                    continue;
                printf("chance: at %u len %u in %s+%u (seg %u..%u), next %s\n", ref[a].start,
                       ref[a].end - ref[a].start + 1u, kind_name[segs[sg].kind], ref[a].start - segs[sg].start,
                       segs[sg].start, segs[sg].end, sg + 1 < nseg ? kind_name[segs[sg + 1].kind] : "-");
            }
        }
    }
    /* one reply per accepted frame, in order, echoing its SEQ */
    if (out_replies != accepted) fail("replies != accepted frames", out_replies, accepted);
    for (k = 0; k < nref; k++)
        if (reply_seq[k] != S[ref[k].start + 3]) fail("reply SEQ differs", k, reply_seq[k]);

    {
        double secs = (double)(clock() - t0) / CLOCKS_PER_SEC;
        printf("bytes=%u\nseed=%u\n", N, seed);
        for (k = 0; k < K_N; k++) printf("gen_%s=%llu\n", kind_name[k], (unsigned long long)kind_count[k]);
        printf("accepted=%llu\nintact=%llu\nintact_accepted=%llu\nintact_lost=%llu\nflipped_rejected=%llu\n",
               (unsigned long long)accepted, (unsigned long long)intact, (unsigned long long)intact_ok,
               (unsigned long long)intact_lost, (unsigned long long)flipped);
        printf("truncated_completed_by_next_byte=%llu\n", (unsigned long long)trunc_completed);
        printf("chance_crc_frames=%llu\ncrc_failures=%llu\nchance_expected=%.2f\n", (unsigned long long)spurious,
               (unsigned long long)ref_crc_fail, (double)ref_crc_fail / 65536.0);
        printf("max_accept_bytes_after_frame_end=%llu\nresync_bound_bytes=%u\n",
               (unsigned long long)max_after_end, (unsigned)(LINK_MAX_FRAME - 2u));
        printf("out_frames=%llu\nout_replies=%llu\nout_badcrc_nacks=%llu\nout_events=%llu\nout_telemetry=%llu\n",
               (unsigned long long)out_frames, (unsigned long long)out_replies,
               (unsigned long long)out_badcrc_nacks, (unsigned long long)out_events,
               (unsigned long long)out_telem);
        printf("link_lost=%u\nseconds=%.3f\nbytes_per_s=%.0f\nOK=1\n", peer_stat(1), secs, secs > 0 ? N / secs : 0.0);
    }
    free(S);
    free(gap_before);
    free(segs);
    free(ref);
    free(reply_seq);
    return 0;
}
