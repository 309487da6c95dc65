/*
 * fuzz_main.c -- fuzz the rendered link module's receiver and dispatcher (built with
 * -fsanitize=address,undefined; see build.py).
 *
 *   fuzz_link --bytes N --seed S
 *
 * Generates a stream of N bytes made of segments: garbage (rich in delimiters), intact frames
 * (random or well-formed commands; three in four preceded by a delimiter as the host sends
 * them), repeated frames (duplicate SEQ), and corrupted frames of five kinds:
 *   nested    a frame whose payload carries a whole host frame, its first 2.. bytes lost;
 *   truncated a frame with its last 1..3 bytes before the delimiter lost (and half of the time
 *             the delimiter too: it merges with the next segment);
 *   badlen    LEN one off (or any other LEN) with the CRC recomputed over the changed body;
 *   flipped   1..3 bits flipped in the encoded frame (delimiters excluded);
 *   insdel    one byte inserted into or deleted from the encoded frame.
 * The stream goes byte by byte through link_rx_byte + link_poll, with link_sample and
 * link_tick_ms now and then.
 *
 * Checks, any failure -> exit status 1:
 *  - the module accepts exactly the host commands an independent reference decoder accepts
 *    (whole-array split at the delimiters, COBS from its definition, bitwise CRC), each as its
 *    delimiter arrives;
 *  - every intact frame sent with a leading delimiter is accepted;
 *  - the board's output is a clean sequence of valid frames with exactly one ACK/NACK per
 *    accepted host command, in order, echoing its SEQ.
 * Prints key=value figures, among them per kind of corruption the candidates the receiver
 * judged and the false accepts (accepted candidates that are not an intact frame), with the
 * CRC-16's chance rate (candidates / 65536) to compare.
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

enum { K_GARBAGE, K_INTACT, K_REPEAT, K_NESTED, K_TRUNC, K_BADLEN, K_FLIPPED, K_INSDEL, K_N };
static const char *kind_name[K_N] = {"garbage", "intact", "repeat", "nested", "truncated", "badlen", "flipped",
                                     "insdel"};

typedef struct { uint32_t start, end; uint8_t kind, lead, nlost, lost[4]; } seg_t;   /* intact: start/end = its candidate;
                                                          truncated: the bytes lost before the delimiter */

static uint8_t *S;          /* the stream */
static uint8_t *kind_at;    /* kind of the segment each byte belongs to */
static uint32_t N, cap;
static seg_t *segs;
static uint32_t nseg, segcap;
static uint64_t kind_count[K_N];

static void put(uint8_t b, uint8_t kind)
{
    if (N < cap) {
        kind_at[N] = kind;
        S[N++] = b;
    }
}

static void add_seg(uint32_t start, uint32_t end, uint8_t kind, uint8_t lead)
{
    if (nseg == segcap) {
        segcap = segcap ? 2 * segcap : 1024;
        segs = realloc(segs, segcap * sizeof *segs);
        if (!segs) { perror("realloc"); exit(2); }
    }
    segs[nseg].start = start;
    segs[nseg].end = end;
    segs[nseg].kind = kind;
    segs[nseg].lead = lead;
    segs[nseg].nlost = 0;
    nseg++;
}

/* body: LEN TYPE SEQ payload CRC; returns its length */
static uint32_t seal(uint8_t *b, uint8_t len)
{
    uint16_t c;
    b[0] = len;
    c = crc_bitwise(b, (size_t)len + 3u);
    b[3 + len] = (uint8_t)(c >> 8);
    b[4 + len] = (uint8_t)c;
    return (uint32_t)len + 5u;
}

static uint32_t make_body(uint8_t *b, uint8_t max_len)
{
    static const uint8_t cmd_len[] = {0, 1, 255, 5, 4, 0, 0, 0, 1, 5, 11, 3, 0, 0, 0, 0, 0};
    uint8_t type, len, i;
    b[2] = (uint8_t)below(256);
    if (below(20) == 0 && max_len >= 11) {            /* a well-formed config command */
        uint16_t mask = (uint16_t)(1u + below((1u << LINK_N_SIGNALS) - 1u));
        uint32_t q = below(4);
        if (q == 0) {
            b[1] = LINK_CMD_TELEM_CONFIG;
            mask = (uint16_t)(mask & 0x000Fu ? mask & 0x000Fu : 1u);
            b[3] = (uint8_t)mask; b[4] = (uint8_t)(mask >> 8);
            b[5] = (uint8_t)below(3); b[6] = 0; b[7] = (uint8_t)(1 + below(4));
            return seal(b, 5);
        } else if (q == 1) {
            b[1] = LINK_CMD_CAPTURE_ARM;
            b[3] = (uint8_t)mask; b[4] = (uint8_t)(mask >> 8);
            b[5] = (uint8_t)(1 + below(40)); b[6] = 0;             /* n */
            b[7] = (uint8_t)below(b[5]); b[8] = 0;                 /* pre */
            b[9] = (uint8_t)(1 + below(3)); b[10] = 0;             /* decimation */
            b[11] = (uint8_t)below(4);
            if (b[11] == 0) b[7] = 0;
            b[12] = (uint8_t)below(256); b[13] = (uint8_t)below(4);
            return seal(b, 11);
        } else if (q == 2) {
            b[1] = LINK_CMD_CAPTURE_READ;
            b[3] = (uint8_t)below(50); b[4] = 0; b[5] = (uint8_t)below(256);
            return seal(b, 3);
        }
        b[1] = LINK_CMD_PARAM_SET;
        b[3] = (uint8_t)below(0x50);
        b[4] = (uint8_t)below(256); b[5] = (uint8_t)below(256); b[6] = (uint8_t)below(2); b[7] = 0;
        return seal(b, 5);
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
    if (len > max_len) len = max_len;
    b[1] = type;
    for (i = 0; i < len; i++) {
        /* plausible ids / small numbers / zeros, so handlers go deep and COBS has blocks */
        uint32_t r = below(5);
        b[3 + i] = r == 0 ? (uint8_t)below(0x50) : r == 1 ? (uint8_t)below(4) : r == 2 ? 0u : (uint8_t)below(256);
    }
    return seal(b, len);
}

static uint32_t cobs(const uint8_t *in, uint32_t n, uint8_t *out)   /* out: code, blocks; no delimiter */
{
    uint32_t o = 1, code_at = 0, i;
    uint8_t code = 1;
    for (i = 0; i < n; i++) {
        if (in[i] == 0) {
            out[code_at] = code;
            code_at = o++;
            code = 1;
        } else {
            out[o++] = in[i];
            code++;
        }
    }
    out[code_at] = code;
    return o;
}

static void generate(uint32_t nbytes)
{
    uint8_t body[LINK_MAX_BODY + 8], inner[LINK_MAX_BODY + 8], w[2 * LINK_MAX_FRAME + 8], last[2 * LINK_MAX_FRAME];
    uint32_t lastn = 0, n, wn, i, k, start;
    uint8_t lost[4] = {0}, nlost = 0;
    cap = nbytes;
    S = malloc(cap + 1);
    kind_at = malloc(cap + 1);
    if (!S || !kind_at) { perror("malloc"); exit(2); }
    while (N < cap) {
        uint32_t r = below(100);
        uint8_t kind, lead = 1;
        if (r < 20) {                                 /* garbage */
            start = N;
            k = 1 + below(64);
            for (i = 0; i < k; i++) {
                uint32_t q = below(8);
                put(q == 0 ? 0u : q == 1 ? (uint8_t)below(LINK_MAX_PAYLOAD + 6) : (uint8_t)below(256), K_GARBAGE);
            }
            add_seg(start, N - 1, K_GARBAGE, 0);
            kind_count[K_GARBAGE]++;
            continue;
        }
        if (r < 25 && lastn) {                        /* repeat the previous intact frame */
            if (N + lastn + 1 > cap) break;
            put(0, K_REPEAT);
            start = N;
            for (i = 0; i < lastn; i++) put(last[i], K_REPEAT);
            add_seg(start, N - 1, K_REPEAT, 1);
            kind_count[K_REPEAT]++;
            continue;
        }
        if (r < 33) {                                 /* nested: a host frame in the payload */
            n = make_body(inner, LINK_MAX_PAYLOAD - 8);
            body[1] = (uint8_t)(1 + below(0x11));
            body[2] = (uint8_t)below(256);
            body[3] = 0;
            wn = cobs(inner, n, &body[4]);
            body[4 + wn] = 0;
            n = seal(body, (uint8_t)(wn + 2));
            w[0] = 0;
            wn = 1 + cobs(body, n, &w[1]);
            w[wn++] = 0;
            k = 2 + below(wn - 3);                    /* lose the delimiter, the code byte and maybe more */
            if (N + wn > cap) break;
            start = N;
            for (i = k; i < wn; i++) put(w[i], K_NESTED);
            add_seg(start, N - 1, K_NESTED, 0);
            kind_count[K_NESTED]++;
            continue;
        }
        n = make_body(body, LINK_MAX_PAYLOAD);
        if (r < 70) {
            kind = K_INTACT;
            lead = below(4) != 0;
        } else if (r < 78) {
            kind = K_BADLEN;
            body[0] = below(2) ? (uint8_t)(body[0] + (below(2) ? 1u : 255u)) : (uint8_t)below(256);
            if (body[0] > n - 5) {                    /* a longer LEN: CRC over what is there */
                uint16_t c = crc_bitwise(body, n - 2);
                body[n - 2] = (uint8_t)(c >> 8);
                body[n - 1] = (uint8_t)c;
            } else if (body[0] < n - 5) {             /* a shorter one: the body ends where LEN says */
                n = (uint32_t)body[0] + 5u;
                {
                    uint16_t c = crc_bitwise(body, n - 2);
                    body[n - 2] = (uint8_t)(c >> 8);
                    body[n - 1] = (uint8_t)c;
                }
                /* keep one trailing byte of the old payload, as a LEN error leaves it */
                body[n] = (uint8_t)below(256);
                n++;
            } else {
                body[0] ^= 0x40u;
            }
        } else {
            kind = r < 85 ? K_FLIPPED : r < 93 ? K_INSDEL : K_TRUNC;
        }
        w[0] = 0;
        wn = 1 + cobs(body, n, &w[1]);
        w[wn++] = 0;
        if (kind == K_FLIPPED) {
            uint32_t bits[3], j, m, dup;
            k = 1 + below(3);
            for (j = 0; j < k;) {
                bits[j] = 8u + below((wn - 2u) * 8u);
                for (dup = 0, m = 0; m < j; m++) dup |= bits[m] == bits[j];
                if (!dup) j++;
            }
            for (j = 0; j < k; j++) w[bits[j] / 8u] ^= (uint8_t)(1u << (bits[j] % 8u));
        } else if (kind == K_INSDEL) {
            k = 1 + below(wn - 2);
            if (below(2)) {
                memmove(&w[k + 1], &w[k], wn - k);
                w[k] = (uint8_t)(k == 1 ? 1 + below(255) : below(256));   /* a 0x00 first would only be a delimiter */
                wn++;
            } else {
                memmove(&w[k], &w[k + 1], wn - k - 1);
                wn--;
            }
        } else if (kind == K_TRUNC) {               /* the last 1..3 bytes before the delimiter lost, and the */
            k = 1 + below(3);                         /* delimiter too half of the time */
            memcpy(lost, &w[wn - 1 - k], k);
            nlost = (uint8_t)k;
            if (below(2)) {
                wn -= k + 1;
            } else {
                memmove(&w[wn - 1 - k], &w[wn - 1], 1);
                wn -= k;
            }
        }
        if (N + wn > cap) break;
        if (lead) put(0, kind);
        start = N;
        for (i = 1; i < wn; i++) put(w[i], kind);
        if (kind == K_INTACT) {
            memcpy(last, &w[1], wn - 1);
            lastn = wn - 1;
        }
        add_seg(start, N - 1, kind, (uint8_t)lead);
        if (kind == K_TRUNC) {
            segs[nseg - 1].nlost = nlost;
            memcpy(segs[nseg - 1].lost, lost, nlost);
        }
        kind_count[kind]++;
    }
    while (N < cap) put(1, K_GARBAGE);               /* fill up */
}

/* ---- reference decoder: split at the delimiters ---- */
typedef struct { uint32_t start, end; } acc_t;       /* end: the delimiter */
static acc_t *ref;
static uint32_t nref;
static uint64_t cand_kind[K_N], false_kind[K_N], completed;

static int ref_decode(uint32_t a, uint32_t e, uint8_t *out)   /* bytes [a, e); body length or -1 */
{
    uint32_t i = a, o = 0, code, j;
    while (i < e) {
        code = S[i];
        if (i + code > e) return -1;                  /* block cut short */
        if (i != a) {
            if (o >= LINK_MAX_BODY) return -1;
            out[o++] = 0;
        }
        for (j = 1; j < code; j++) {
            if (o >= LINK_MAX_BODY) return -1;
            out[o++] = S[i + j];
        }
        i += code;
    }
    return (int)o;
}

static int is_host_command(uint8_t type)
{
    return !(type & LINK_ACK_BIT) && type != LINK_MSG_NACK && type != LINK_MSG_EVENT && type != LINK_MSG_TELEMETRY;
}

static void reference(void)
{
    uint32_t i, a = 0, sg = 0;
    uint8_t b[LINK_MAX_BODY];
    ref = malloc(((size_t)N / 2u + 2u) * sizeof *ref);
    if (!ref) { perror("malloc"); exit(2); }
    for (i = 0; i < N; i++) {
        int n;
        uint8_t k;
        if (S[i] != 0) continue;
        if (i == a) { a = i + 1; continue; }         /* empty candidate */
        k = kind_at[a];
        n = ref_decode(a, i, b);
        while (sg + 1 < nseg && segs[sg + 1].start <= a) sg++;
        if (!((k == K_INTACT || k == K_REPEAT) && segs[sg].start == a && segs[sg].end == i))
            cand_kind[k]++;                           /* a corrupted candidate, by the kind of its first byte */
        if (n >= 5 && b[0] + 5 == n && crc_bitwise(b, (size_t)n) == 0) {
            if (k == K_TRUNC && segs[sg].start == a && segs[sg].nlost != 0
                && i - a == segs[sg].end + 1u - a + segs[sg].nlost
                && memcmp(&S[segs[sg].end + 1u], segs[sg].lost, segs[sg].nlost) == 0) {
                completed++;                          /* the bytes that followed were the lost ones: the */
            } else if (!((k == K_INTACT || k == K_REPEAT) && segs[sg].start == a && segs[sg].end == i)) {
                false_kind[k]++;                      /* original frame, bit for bit (not a false accept) */
                if (getenv("FUZZ_SHOW")) {
                    uint32_t q;
                    printf("false %s at %u..%u seg %u..%u:", kind_name[k], a, i, segs[sg].start, segs[sg].end);
                    for (q = segs[sg].start; q <= i && q < segs[sg].start + 60; q++) printf(" %02x", S[q]);
                    printf("\n");
                }
            }
            ref[nref].start = a;
            ref[nref].end = i;
            nref++;
        }
        a = i + 1;
    }
}

/* ---- board output checker ---- */
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
    uint32_t n = peer_take_tx(ob + obn, (uint32_t)(sizeof ob - obn)), p = 0, e, i, o, code, j;
    uint8_t b[LINK_MAX_BODY + 300];
    obn += n;
    for (;;) {
        for (e = p; e < obn && ob[e] != 0; e++) {}
        if (e >= obn) break;
        if (e == p) fail("board output: empty frame", p, 0);
        for (i = p, o = 0; i < e; i += code) {       /* COBS */
            code = ob[i];
            if (i + code > e) fail("board output: bad COBS", out_frames, i);
            if (i != p) b[o++] = 0;
            for (j = 1; j < code; j++) b[o++] = ob[i + j];
        }
        if (o < 5 || b[0] + 5u != o || b[0] > LINK_MAX_PAYLOAD || crc_bitwise(b, o) != 0)
            fail("board output: bad frame", out_frames, o);
        out_frames++;
        {
            uint8_t type = b[1];
            if (type == LINK_MSG_NACK && b[0] == 2 && b[4] == LINK_NACK_BAD_CRC) {
                out_badcrc_nacks++;
            } else if (type == LINK_MSG_NACK || (type & LINK_ACK_BIT)) {
                reply_seq[nreply_seq++] = b[2];
                out_replies++;
            } else if (type == LINK_MSG_EVENT) {
                out_events++;
            } else if (type == LINK_MSG_TELEMETRY) {
                out_telem++;
            } else {
                fail("unknown frame type from the board", type, out_frames);
            }
        }
        p = e + 1;
    }
    memmove(ob, ob + p, obn - p);
    obn -= p;
}

int main(int argc, char **argv)
{
    uint32_t nbytes = 1000000u, seed = 1u, i, k, next_ref = 0;
    uint64_t accepted = 0, intact = 0, intact_ok = 0, intact_lead = 0, intact_lead_ok = 0, cmds = 0;
    uint8_t type, seq, pl[LINK_MAX_PAYLOAD], b[LINK_MAX_BODY];
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
    reply_seq = malloc((size_t)N / 2u + 16u);
    if (!reply_seq) { perror("malloc"); return 2; }

    peer_erase_eeprom();
    peer_reset(0u, 0u, 4096u);
    peer_log_clear();
    take_output();
    t0 = clock();
    for (i = 0; i < N; i++) {
        peer_feed(&S[i], 1u);                        /* link_rx_byte + link_poll */
        if ((i & 63u) == 0u) link_sample();
        if ((i & 255u) == 0u) link_tick_ms();        /* time passes: the watchdog may fire */
        link_poll();
        take_output();
        /* the host commands accepted with byte i: the next reference frames, in order */
        for (k = 0; peer_log_get(k, &type, &seq, pl, &at) >= 0; k++) {
            acc_t r;
            int n;
            while (next_ref < nref) {                /* board frame types: accepted by the decoder, ignored */
                n = ref_decode(ref[next_ref].start, ref[next_ref].end, b);
                if (is_host_command(b[1])) break;
                next_ref++;
            }
            if (next_ref >= nref) fail("module accepted a frame the reference did not", i, k);
            r = ref[next_ref];
            n = ref_decode(r.start, r.end, b);
            if (b[1] != type || b[2] != seq || b[0] != (uint8_t)(n - 5) || memcmp(pl, &b[3], (size_t)n - 5u) != 0)
                fail("module and reference accepted different frames", r.start, i);
            if (at != i + 1u || r.end != i) fail("frame accepted at another byte than its delimiter", at, r.end);
            next_ref++;
            cmds++;
        }
        peer_log_clear();
    }
    while (next_ref < nref) {
        ref_decode(ref[next_ref].start, ref[next_ref].end, b);
        if (is_host_command(b[1])) fail("reference frames not accepted by the module", next_ref, nref);
        next_ref++;
    }
    accepted = nref;
    {
        uint32_t a = 0;
        for (k = 0; k < nseg; k++) {
            if (segs[k].kind != K_INTACT) continue;
            intact++;
            intact_lead += segs[k].lead;
            while (a < nref && ref[a].start < segs[k].start) a++;
            if (a < nref && ref[a].start == segs[k].start && ref[a].end == segs[k].end) {
                intact_ok++;
                intact_lead_ok += segs[k].lead;
            } else if (segs[k].lead) {
                fail("intact frame after a delimiter not accepted", segs[k].start, 0);
            }
        }
    }
    /* one reply per accepted host command, in order, echoing its SEQ */
    if (out_replies != cmds) fail("replies != accepted commands", out_replies, cmds);
    for (k = 0, i = 0; k < nref; k++) {
        ref_decode(ref[k].start, ref[k].end, b);
        if (!is_host_command(b[1])) continue;
        if (reply_seq[i] != b[2]) fail("reply SEQ differs", k, reply_seq[i]);
        i++;
    }
    {
        double secs = (double)(clock() - t0) / CLOCKS_PER_SEC;
        uint64_t cands = 0, falses = 0;
        printf("bytes=%u\nseed=%u\n", N, seed);
        for (k = 0; k < K_N; k++) printf("gen_%s=%llu\n", kind_name[k], (unsigned long long)kind_count[k]);
        for (k = 0; k < K_N; k++) {
            if (k == K_INTACT || k == K_REPEAT) continue;
            printf("candidates_%s=%llu\nfalse_accepts_%s=%llu\n", kind_name[k], (unsigned long long)cand_kind[k],
                   kind_name[k], (unsigned long long)false_kind[k]);
        }
        for (k = 0; k < K_N; k++) {
            cands += cand_kind[k];
            falses += false_kind[k];
        }
        printf("candidates=%llu\nfalse_accepts=%llu\nchance_expected=%.3f\n", (unsigned long long)cands,
               (unsigned long long)falses, (double)cands / 65536.0);
        printf("truncated_completed_by_equal_bytes=%llu\n", (unsigned long long)completed);
        printf("accepted=%llu\ncommands=%llu\nintact=%llu\nintact_accepted=%llu\nintact_lead=%llu\n"
               "intact_lead_accepted=%llu\n", (unsigned long long)accepted, (unsigned long long)cmds,
               (unsigned long long)intact, (unsigned long long)intact_ok, (unsigned long long)intact_lead,
               (unsigned long long)intact_lead_ok);
        printf("out_frames=%llu\nout_replies=%llu\nout_badcrc_nacks=%llu\nout_events=%llu\nout_telemetry=%llu\n",
               (unsigned long long)out_frames, (unsigned long long)out_replies,
               (unsigned long long)out_badcrc_nacks, (unsigned long long)out_events,
               (unsigned long long)out_telem);
        printf("link_lost=%u\nseconds=%.3f\nbytes_per_s=%.0f\nOK=1\n", peer_stat(1), secs, secs > 0 ? N / secs : 0.0);
    }
    free(S);
    free(kind_at);
    free(segs);
    free(ref);
    free(reply_seq);
    return 0;
}
