/* snail native garbling kernel: a whole engine program (or a contiguous range of its ops)
 * garbled or evaluated in one call, half-gates or three-halves, one run or L lanes.
 *
 * The math is that of snail_common/gc/halfgates.py, threehalves.py and lane_kernel.py
 * (their docstrings derive it); this file is the same computation gate by gate, with the
 * fixed-key hash H(x, t) = AES_k(sigma(x) ^ (0, t)) ^ sigma(x) on the CPU's AES
 * instructions. Its tables, labels and outputs are bit for bit the numpy engine's
 * (tests/test_gc_native.py).
 *
 * The program (built and bounds-checked in Python, snail_common/gc/native/program.py) is
 * a list of ops, OP_WORDS int64 each, over a table of row descriptors:
 *   op:   kind, n, first, rows, dst, aux
 *   AND:      gates first .. first+n-1 (n <= one stream block); rows -> out, a, b
 *   XOR:      out[i] = XOR of `first` columns; rows -> out, column 0, column 1, ...
 *   RAGGED:   out[i] = XOR of slots terms[starts[i] .. starts[i+1]) (last: .. aux);
 *             rows -> out, terms, starts
 *   PUBLISH:  out rows = scratch rows dst .. dst+n-1 (a step whose results wait)
 *   dst = -1 writes an op's results to its out rows, else to scratch rows dst .. dst+n-1.
 *   row descriptor: kind, a, b: SLICE (slot a + i*b; b = 0 repeats one slot), I32 or I64
 *   (an index list at address a).
 * Nothing here checks an index: the caller has checked every one against the slot
 * array, the scratch and the tables before the call.
 */
#include <cpuid.h>
#include <immintrin.h>
#include <limits.h>
#include <linux/futex.h>
#include <pthread.h>
#include <sched.h>
#include <stdatomic.h>
#include <stdint.h>
#include <string.h>
#include <sys/syscall.h>
#include <unistd.h>

#define TGT __attribute__((target("aes,sse4.1,ssse3")))
/* the wide path: VAES hashes two blocks per instruction in 256-bit registers */
#define TGTV __attribute__((target("aes,sse4.1,ssse3,avx,avx2,vaes")))
#define INLINE static inline __attribute__((always_inline))

enum { OP_AND = 0, OP_XOR = 1, OP_RAGGED = 2, OP_PUBLISH = 3 };
enum { OP_KIND = 0xff, OP_PARALLEL = 0x100 }; /* kind word: the kind | may be cut by rows */
enum { R_SLICE = 0, R_I32 = 1, R_I64 = 2 };
enum { OP_WORDS = 6 };
enum { MODE_GARBLE = 0, MODE_EVALUATE = 1 };
enum { SCHEME_HALF_GATES = 1, SCHEME_THREE_HALVES = 2 };
enum { MAX_LANES = 256 };
enum { MAX_THREADS = 2 };
/* gates per AES batch: 8 independent AES blocks fill the pipeline (4 cycles latency, 2 per
 * cycle) and still fit the 16 vector registers */
#define HG_GARBLE_BATCH 2
#define HG_EVAL_BATCH 4
#define TH_GARBLE_BATCH 2
#define TH_EVAL_BATCH 2
#define BATCH 4 /* the largest */
/* VAES: 8 independent 256-bit AES blocks (16 hashes) in flight per batch */
#define HG_GARBLE_BATCH_V 4
#define HG_EVAL_BATCH_V 8
#define BATCH_V 8

typedef struct {
    int64_t kind, a, b;
} rows_t;

/* 1 when the CPU has what this file uses (AES-NI, SSSE3, SSE4.1). */
int snail_cpu_ok(void) {
    unsigned a, b, c, d;
    if (!__get_cpuid(1, &a, &b, &c, &d)) return 0;
    return (c & bit_AES) && (c & bit_SSE4_1) && (c & bit_SSSE3);
}

/* 1 when the CPU has VAES and AVX2 and the OS saves the 256-bit registers. */
static int cpu_vaes(void) {
    unsigned a, b, c, d;
    if (!__get_cpuid(1, &a, &b, &c, &d) || !(c & bit_OSXSAVE) || !(c & bit_AVX)) return 0;
    unsigned lo, hi;
    __asm__("xgetbv" : "=a"(lo), "=d"(hi) : "c"(0));
    if ((lo & 6) != 6 || __get_cpuid_max(0, 0) < 7) return 0;
    __cpuid_count(7, 0, a, b, c, d);
    return (b & bit_AVX2) && (c & (1u << 9)); /* leaf 7 ecx bit 9: VAES */
}

static int use_vaes = -1; /* -1: not decided yet (the CPU's answer on first use) */

/* The instruction set the AND ops use: ask with want < 0; want 0 forces AES-NI alone
 * (tests compare both paths), want 1 VAES where the CPU has it. Returns 1 for VAES. */
int snail_isa(int want) {
    if (want >= 0) use_vaes = want && cpu_vaes();
    else if (use_vaes < 0) use_vaes = cpu_vaes();
    return use_vaes;
}

INLINE int64_t row_at(const rows_t *r, int64_t i) {
    switch (r->kind) {
    case R_SLICE: return r->a + i * r->b;
    case R_I32: return ((const int32_t *)(intptr_t)r->a)[i];
    default: return ((const int64_t *)(intptr_t)r->a)[i];
    }
}

/* ---------------------------------------------------------------- AES-128 (AES-NI) */

typedef struct {
    __m128i rk[11];
} aes_key;

TGT INLINE __m128i expand_step(__m128i k, __m128i t) {
    t = _mm_shuffle_epi32(t, 0xff);
    k = _mm_xor_si128(k, _mm_slli_si128(k, 4));
    k = _mm_xor_si128(k, _mm_slli_si128(k, 4));
    k = _mm_xor_si128(k, _mm_slli_si128(k, 4));
    return _mm_xor_si128(k, t);
}

#define EXPAND(i, rcon) \
    ks->rk[i] = expand_step(ks->rk[i - 1], _mm_aeskeygenassist_si128(ks->rk[i - 1], rcon))

TGT static void aes_expand(aes_key *ks, const uint8_t *key) {
    ks->rk[0] = _mm_loadu_si128((const __m128i *)key);
    EXPAND(1, 0x01); EXPAND(2, 0x02); EXPAND(3, 0x04); EXPAND(4, 0x08); EXPAND(5, 0x10);
    EXPAND(6, 0x20); EXPAND(7, 0x40); EXPAND(8, 0x80); EXPAND(9, 0x1b); EXPAND(10, 0x36);
}

/* n blocks at once (n a constant after inlining: unrolled, the blocks in registers) */
TGT INLINE void aes_n(const aes_key *ks, __m128i *x, int n) {
#pragma GCC unroll 16
    for (int i = 0; i < n; i++) x[i] = _mm_xor_si128(x[i], ks->rk[0]);
#pragma GCC unroll 9
    for (int r = 1; r < 10; r++) {
        __m128i k = ks->rk[r];
#pragma GCC unroll 16
        for (int i = 0; i < n; i++) x[i] = _mm_aesenc_si128(x[i], k);
    }
#pragma GCC unroll 16
    for (int i = 0; i < n; i++) x[i] = _mm_aesenclast_si128(x[i], ks->rk[10]);
}

/* sigma(x0, x1) = (x0 ^ x1, x0), word 0 the low one */
TGT INLINE __m128i sigma(__m128i x) {
    return _mm_xor_si128(_mm_shuffle_epi32(x, 0x4e), _mm_move_epi64(x));
}

/* all ones in each 64-bit word whose value is 1 (the words are 0 or 1) */
TGT INLINE __m128i all_of(__m128i v) { return _mm_sub_epi64(_mm_setzero_si128(), v); }

/* all ones where lsb(word 0) is 1, both words */
TGT INLINE __m128i lsb_mask(__m128i x) {
    __m128i bit = _mm_and_si128(x, _mm_set_epi64x(0, 1));
    return _mm_shuffle_epi32(all_of(bit), 0x44);
}

TGT INLINE __m128i tweak(uint64_t t) { return _mm_set_epi64x((long long)t, 0); }

INLINE uint64_t load64(const uint64_t *p) {
    uint64_t v;
    memcpy(&v, p, 8);
    return v;
}

INLINE void store64(uint64_t *p, uint64_t v) { memcpy(p, &v, 8); }

/* ---------------------------------------------------------------- one AND op */

#define CHUNK 64 /* rows whose slot addresses are resolved at once */

typedef struct {
    int mode, scheme;
    int64_t width; /* words per slot row: 2 per lane */
    int64_t lanes;
    uint64_t *values, *scratch;
    uint64_t *tables;   /* the current op's tables, lane 0 */
    int64_t lane_words; /* distance between two lanes' tables */
    aes_key keys[MAX_LANES];
    __m128i delta[MAX_LANES];
    aes_key rand_key; /* three-halves garbling: the garbler's random bits */
    int64_t rand_block;
    __m128i rand_bits;
    int vaes; /* the AND ops' instruction set (snail_isa) */
} ctx_t;

/* addresses of rows i0 .. i0+m-1 of `r` in `values` (the descriptor's kind decided once) */
INLINE void row_ptrs(const rows_t *r, int64_t i0, int64_t m, uint64_t *values, int64_t width,
                     uint64_t **out) {
    switch (r->kind) {
    case R_SLICE: { /* pointer steps, not products: vectorized, a product is 3 multiplies */
        uintptr_t p = (uintptr_t)(values + (r->a + i0 * r->b) * width);
        uintptr_t step = (uintptr_t)(r->b * width) * sizeof(uint64_t);
        for (int64_t k = 0; k < m; k++, p += step) out[k] = (uint64_t *)p;
        break;
    }
    case R_I32: { /* one lane (width 2) apart: a shift, not a product */
        const int32_t *q = (const int32_t *)(intptr_t)r->a + i0;
        if (width == 2)
            for (int64_t k = 0; k < m; k++) out[k] = values + 2 * (int64_t)q[k];
        else
            for (int64_t k = 0; k < m; k++) out[k] = values + (int64_t)q[k] * width;
        break;
    }
    default: {
        const int64_t *q = (const int64_t *)(intptr_t)r->a + i0;
        if (width == 2)
            for (int64_t k = 0; k < m; k++) out[k] = values + 2 * q[k];
        else
            for (int64_t k = 0; k < m; k++) out[k] = values + q[k] * width;
    }
    }
}

/* where rows i0 .. i0+m-1 of an op's results go: its out rows, or scratch rows dst + i */
INLINE void out_ptrs(ctx_t *c, const rows_t *out, int64_t dst, int64_t i0, int64_t m,
                     uint64_t **p) {
    if (dst < 0) {
        row_ptrs(out, i0, m, c->values, c->width, p);
        return;
    }
    uintptr_t q = (uintptr_t)(c->scratch + (dst + i0) * c->width);
    uintptr_t step = (uintptr_t)c->width * sizeof(uint64_t);
    for (int64_t k = 0; k < m; k++, q += step) p[k] = (uint64_t *)q;
}

typedef struct {
    uint64_t *a[CHUNK], *b[CHUNK], *o[CHUNK];
} chunk_t;

#define LD(p) _mm_loadu_si128((const __m128i *)(p))
#define ST(p, v) _mm_storeu_si128((__m128i *)(p), v)

/* half-gates garbling of gates i .. i+g-1 (chunk rows j ..) of an op of n gates */
TGT INLINE void hg_garble(ctx_t *c, const chunk_t *ch, int64_t n, uint64_t first, int64_t i,
                          int j, int g, int64_t lane) {
    __m128i a0[BATCH], b0[BATCH], x[4 * BATCH], y[4 * BATCH];
    __m128i d = c->delta[lane], sd = sigma(d);
    int64_t w = 2 * lane;
    _Pragma("GCC unroll 4") for (int k = 0; k < g; k++) {
        uint64_t gate = first + (uint64_t)(i + k);
        a0[k] = LD(ch->a[j + k] + w);
        b0[k] = LD(ch->b[j + k] + w);
        x[k] = _mm_xor_si128(sigma(a0[k]), tweak(2 * gate));
        x[g + k] = _mm_xor_si128(sigma(b0[k]), tweak(2 * gate + 1));
        x[2 * g + k] = _mm_xor_si128(x[k], sd);
        x[3 * g + k] = _mm_xor_si128(x[g + k], sd);
    }
    _Pragma("GCC unroll 16") for (int k = 0; k < 4 * g; k++) y[k] = x[k];
    aes_n(&c->keys[lane], y, 4 * g);
    __m128i *t = (__m128i *)(c->tables + lane * c->lane_words);
    _Pragma("GCC unroll 4") for (int k = 0; k < g; k++) {
        __m128i ta = _mm_xor_si128(_mm_xor_si128(y[k], y[2 * g + k]), sd);
        __m128i tb = _mm_xor_si128(_mm_xor_si128(y[g + k], y[3 * g + k]), sd);
        __m128i pa = lsb_mask(a0[k]), pb = lsb_mask(b0[k]);
        __m128i tg = _mm_xor_si128(ta, _mm_and_si128(pb, d));
        __m128i ya = _mm_xor_si128(_mm_xor_si128(y[k], x[k]), _mm_and_si128(pa, tg));
        __m128i yb = _mm_xor_si128(_mm_xor_si128(y[g + k], x[g + k]), _mm_and_si128(pb, tb));
        ST(t + i + k, tg);
        ST(t + n + i + k, _mm_xor_si128(tb, a0[k]));
        ST(ch->o[j + k] + w, _mm_xor_si128(_mm_xor_si128(ya, yb), _mm_set_epi64x(1, 0)));
    }
}

/* half-gates evaluation of gates i .. i+g-1 */
TGT INLINE void hg_evaluate(ctx_t *c, const chunk_t *ch, int64_t n, uint64_t first, int64_t i,
                            int j, int g, int64_t lane) {
    __m128i a[BATCH], b[BATCH], x[2 * BATCH], y[2 * BATCH];
    int64_t w = 2 * lane;
    _Pragma("GCC unroll 4") for (int k = 0; k < g; k++) {
        uint64_t gate = first + (uint64_t)(i + k);
        a[k] = LD(ch->a[j + k] + w);
        b[k] = LD(ch->b[j + k] + w);
        y[k] = x[k] = _mm_xor_si128(sigma(a[k]), tweak(2 * gate));
        y[g + k] = x[g + k] = _mm_xor_si128(sigma(b[k]), tweak(2 * gate + 1));
    }
    aes_n(&c->keys[lane], y, 2 * g);
    const __m128i *t = (const __m128i *)(c->tables + lane * c->lane_words);
    _Pragma("GCC unroll 4") for (int k = 0; k < g; k++) {
        __m128i sa = lsb_mask(a[k]), sb = lsb_mask(b[k]);
        __m128i tg = LD(t + i + k), te = LD(t + n + i + k);
        __m128i ya = _mm_xor_si128(_mm_xor_si128(y[k], x[k]), _mm_and_si128(sa, tg));
        __m128i yb = _mm_xor_si128(_mm_xor_si128(y[g + k], x[g + k]), _mm_and_si128(sb, te));
        __m128i o = _mm_xor_si128(_mm_xor_si128(ya, yb), _mm_and_si128(sb, a[k]));
        ST(ch->o[j + k] + w, _mm_xor_si128(o, _mm_set_epi64x(1, 0)));
    }
}

/* two 128-bit blocks as one 256-bit register, `lo` in the low half */
TGTV INLINE __m256i pair(__m128i lo, __m128i hi) {
    return _mm256_inserti128_si256(_mm256_castsi128_si256(lo), hi, 1);
}

TGTV INLINE __m128i high(__m256i v) { return _mm256_extracti128_si256(v, 1); }

/* aes_n on n 256-bit registers (2n blocks), the round keys broadcast to both halves */
TGTV INLINE void aes_v(const aes_key *ks, __m256i *x, int n) {
    __m256i k = _mm256_broadcastsi128_si256(ks->rk[0]);
#pragma GCC unroll 16
    for (int i = 0; i < n; i++) x[i] = _mm256_xor_si256(x[i], k);
#pragma GCC unroll 9
    for (int r = 1; r < 10; r++) {
        k = _mm256_broadcastsi128_si256(ks->rk[r]);
#pragma GCC unroll 16
        for (int i = 0; i < n; i++) x[i] = _mm256_aesenc_epi128(x[i], k);
    }
    k = _mm256_broadcastsi128_si256(ks->rk[10]);
#pragma GCC unroll 16
    for (int i = 0; i < n; i++) x[i] = _mm256_aesenclast_epi128(x[i], k);
}

/* 256-bit forms of sigma, lsb_mask and tweak: two gates side by side, gate k in the low
 * half, gate k+1 in the high one (every step stays within its 128-bit half) */
TGTV INLINE __m256i sigma2(__m256i x) {
    return _mm256_xor_si256(_mm256_shuffle_epi32(x, 0x4e),
                            _mm256_blend_epi32(_mm256_setzero_si256(), x, 0x33));
}

TGTV INLINE __m256i lsb_mask2(__m256i x) {
    __m256i bit = _mm256_and_si256(x, _mm256_set_epi64x(0, 1, 0, 1));
    return _mm256_shuffle_epi32(_mm256_sub_epi64(_mm256_setzero_si256(), bit), 0x44);
}

/* (0, 2g) | (0, 2g + 2): the tweaks of A for gates g and g + 1 (B's: one more) */
TGTV INLINE __m256i tweak2(uint64_t g) {
    return _mm256_set_epi64x((long long)(2 * g + 2), 0, (long long)(2 * g), 0);
}

TGTV INLINE __m256i rows2(const uint64_t *lo, const uint64_t *hi) { return pair(LD(lo), LD(hi)); }

TGTV INLINE void store2(uint64_t *lo, uint64_t *hi, __m256i v) {
    ST(lo, _mm256_castsi256_si128(v));
    ST(hi, high(v));
}

#define ONE_HI2 _mm256_set_epi64x(1, 0, 1, 0) /* (0, 1) in both halves */

/* the labels A, B of chunk rows q, q+1 (lane at word w) and their hashes' inputs
 * sigma(A) ^ tweak(2 gate), sigma(B) ^ tweak(2 gate + 1), `gate` the first's number */
TGTV INLINE void pair_inputs(const chunk_t *ch, int q, int64_t w, uint64_t gate, __m256i *a,
                             __m256i *b, __m256i *xa, __m256i *xb) {
    *a = rows2(ch->a[q] + w, ch->a[q + 1] + w);
    *b = rows2(ch->b[q] + w, ch->b[q + 1] + w);
    __m256i t = tweak2(gate);
    *xa = _mm256_xor_si256(sigma2(*a), t);
    *xb = _mm256_xor_si256(sigma2(*b), _mm256_add_epi64(t, ONE_HI2));
}

/* half-gates garbling with VAES of gates i .. i+g-1 (g even), two gates per register from
 * loading their labels to storing their tables and outputs; the math is hg_garble's */
TGTV INLINE void hg_garble_v(ctx_t *c, const chunk_t *ch, int64_t n, uint64_t first,
                             int64_t i, int j, int g, int64_t lane) {
    __m256i a0[BATCH_V / 2], b0[BATCH_V / 2], xa[BATCH_V / 2], xb[BATCH_V / 2];
    __m256i y[2 * BATCH_V];
    __m128i d1 = c->delta[lane];
    __m256i d = pair(d1, d1), sd = sigma2(d);
    int64_t w = 2 * lane;
    int pairs = g / 2;
    _Pragma("GCC unroll 4") for (int k = 0; k < pairs; k++) {
        pair_inputs(ch, j + 2 * k, w, first + (uint64_t)(i + 2 * k), &a0[k], &b0[k], &xa[k],
                    &xb[k]);
        y[4 * k] = xa[k];
        y[4 * k + 1] = _mm256_xor_si256(xa[k], sd);
        y[4 * k + 2] = xb[k];
        y[4 * k + 3] = _mm256_xor_si256(xb[k], sd);
    }
    aes_v(&c->keys[lane], y, 2 * g);
    uint64_t *t = c->tables + lane * c->lane_words;
    _Pragma("GCC unroll 4") for (int k = 0; k < pairs; k++) {
        int q = j + 2 * k;
        __m256i ta = _mm256_xor_si256(_mm256_xor_si256(y[4 * k], y[4 * k + 1]), sd);
        __m256i tb = _mm256_xor_si256(_mm256_xor_si256(y[4 * k + 2], y[4 * k + 3]), sd);
        __m256i pa = lsb_mask2(a0[k]), pb = lsb_mask2(b0[k]);
        __m256i tg = _mm256_xor_si256(ta, _mm256_and_si256(pb, d));
        __m256i ya = _mm256_xor_si256(_mm256_xor_si256(y[4 * k], xa[k]), _mm256_and_si256(pa, tg));
        __m256i yb = _mm256_xor_si256(_mm256_xor_si256(y[4 * k + 2], xb[k]),
                                      _mm256_and_si256(pb, tb));
        _mm256_storeu_si256((__m256i *)(t + 2 * (i + 2 * k)), tg);
        _mm256_storeu_si256((__m256i *)(t + 2 * (n + i + 2 * k)), _mm256_xor_si256(tb, a0[k]));
        store2(ch->o[q] + w, ch->o[q + 1] + w,
               _mm256_xor_si256(_mm256_xor_si256(ya, yb), ONE_HI2));
    }
}

/* half-gates evaluation with VAES of gates i .. i+g-1 (g even), two gates per register */
TGTV INLINE void hg_evaluate_v(ctx_t *c, const chunk_t *ch, int64_t n, uint64_t first,
                               int64_t i, int j, int g, int64_t lane) {
    __m256i a[BATCH_V / 2], b[BATCH_V / 2], y[BATCH_V];
    int64_t w = 2 * lane;
    int pairs = g / 2;
    _Pragma("GCC unroll 4") for (int k = 0; k < pairs; k++) {
        pair_inputs(ch, j + 2 * k, w, first + (uint64_t)(i + 2 * k), &a[k], &b[k], &y[2 * k],
                    &y[2 * k + 1]);
    }
    __m256i x[BATCH_V];
    _Pragma("GCC unroll 8") for (int k = 0; k < 2 * pairs; k++) x[k] = y[k];
    aes_v(&c->keys[lane], y, g);
    const uint64_t *t = c->tables + lane * c->lane_words;
    _Pragma("GCC unroll 4") for (int k = 0; k < pairs; k++) {
        int q = j + 2 * k;
        __m256i sa = lsb_mask2(a[k]), sb = lsb_mask2(b[k]);
        __m256i tg = _mm256_loadu_si256((const __m256i *)(t + 2 * (i + 2 * k)));
        __m256i te = _mm256_loadu_si256((const __m256i *)(t + 2 * (n + i + 2 * k)));
        __m256i ya = _mm256_xor_si256(_mm256_xor_si256(y[2 * k], x[2 * k]),
                                      _mm256_and_si256(sa, tg));
        __m256i yb = _mm256_xor_si256(_mm256_xor_si256(y[2 * k + 1], x[2 * k + 1]),
                                      _mm256_and_si256(sb, _mm256_xor_si256(te, a[k])));
        store2(ch->o[q] + w, ch->o[q + 1] + w,
               _mm256_xor_si256(_mm256_xor_si256(ya, yb), ONE_HI2));
    }
}

INLINE uint64_t lo64(__m128i v) { return (uint64_t)_mm_cvtsi128_si64(v); }

TGT INLINE uint64_t hi64(__m128i v) { return (uint64_t)_mm_extract_epi64(v, 1); }

/* the garbler's random bits r0, r1 of gate g: bits 2g, 2g+1 of AES-CTR under its key,
 * counter block j = (j, 0), 64 gates per block (threehalves._RandomBits) */
TGT INLINE void rand_bits(ctx_t *c, uint64_t g, uint64_t *r0, uint64_t *r1) {
    int64_t j = (int64_t)(g / 64);
    if (j != c->rand_block) {
        __m128i v = _mm_set_epi64x(0, (long long)j);
        aes_n(&c->rand_key, &v, 1);
        c->rand_bits = v;
        c->rand_block = j;
    }
    unsigned pos = 2 * (unsigned)(g % 64);
    uint64_t w = pos < 64 ? lo64(c->rand_bits) : hi64(c->rand_bits);
    *r0 = (w >> (pos % 64)) & 1;
    *r1 = (w >> (pos % 64 + 1)) & 1;
}

INLINE uint64_t get_bit(const uint64_t *ctl, int64_t bit) {
    return (load64(ctl + bit / 64) >> (bit % 64)) & 1;
}

/* OR the bits of v into ctl from bit `bit` on (v's set bits stay inside the array) */
INLINE void set_bits(uint64_t *ctl, int64_t bit, uint64_t v) {
    int64_t w = bit / 64;
    unsigned s = (unsigned)(bit % 64);
    store64(ctl + w, load64(ctl + w) | (v << s));
    if (s && (v >> (64 - s))) store64(ctl + w + 1, load64(ctl + w + 1) | (v >> (64 - s)));
}

/* the two 0/1 words of v as bits 0 and 1 */
TGT INLINE uint64_t two_bits(__m128i v) {
    return (uint64_t)_mm_movemask_pd(_mm_castsi128_pd(_mm_slli_epi64(v, 63)));
}

#define X2(a, b) _mm_xor_si128(a, b)
#define A2(a, b) _mm_and_si128(a, b)

/* a pair of three-halves gates side by side, gate 0 in the low 64-bit word of each
 * register and gate 1 in the high one: the hashes' words h[e] and bits hb[e] of
 * y ^ sigma(lab) (K blocks a gate) and the sums of the labels A (block 0) and B (block
 * b_at) the formulas use */
typedef struct {
    __m128i h[6], hb[6], al, ar, bl, br, s0, s1, s2;
} th_pair_t;

TGT INLINE void th_pair(const __m128i *lab, const __m128i *y, int K, int b_at, th_pair_t *p) {
    __m128i one = _mm_set1_epi64x(1);
    for (int e = 0; e < K; e++) {
        __m128i v0 = X2(y[e], sigma(lab[e])), v1 = X2(y[K + e], sigma(lab[K + e]));
        p->h[e] = _mm_unpacklo_epi64(v0, v1);
        p->hb[e] = A2(_mm_unpackhi_epi64(v0, v1), one);
    }
    p->al = _mm_unpacklo_epi64(lab[0], lab[K]);
    p->ar = _mm_unpackhi_epi64(lab[0], lab[K]);
    p->bl = _mm_unpacklo_epi64(lab[b_at], lab[K + b_at]);
    p->br = _mm_unpackhi_epi64(lab[b_at], lab[K + b_at]);
    p->s0 = X2(X2(p->al, p->ar), p->bl);
    p->s1 = X2(p->al, p->br);
    p->s2 = X2(X2(p->ar, p->bl), p->br);
}

/* th_garble's tables, control bits and output labels for gates i, i+1 (chunk rows j,
 * j+1) from their colour-0 labels `lab` and hashes `y`: the scalar formulas below, with
 * both gates side by side in the two 64-bit words of each register */
TGT INLINE void th_finish2(ctx_t *c, const chunk_t *ch, int64_t n, uint64_t first,
                           int64_t i, int j, const __m128i *lab, const __m128i *y,
                           const uint64_t *alpha, const uint64_t *beta) {
    th_pair_t p;
    th_pair(lab, y, 6, 2, &p);
    __m128i *h = p.h, *hb = p.hb, ar = p.ar, bl = p.bl, s0 = p.s0, s1 = p.s1, s2 = p.s2,
            one = _mm_set1_epi64x(1);
    uint64_t r0a, r1a, r0b, r1b;
    rand_bits(c, first + (uint64_t)i, &r0a, &r1a);
    rand_bits(c, first + (uint64_t)i + 1, &r0b, &r1b);
    __m128i r0 = _mm_set_epi64x((long long)r0b, (long long)r0a);
    __m128i r1 = _mm_set_epi64x((long long)r1b, (long long)r1a);
    __m128i alp = _mm_set_epi64x((long long)alpha[1], (long long)alpha[0]);
    __m128i bet = _mm_set_epi64x((long long)beta[1], (long long)beta[0]);
    __m128i a_ = X2(alp, one), b_ = X2(bet, one);
    __m128i m0 = all_of(r0), m1 = all_of(r1), m2 = all_of(X2(r0, a_)),
            m3 = all_of(X2(r1, b_)), m4 = all_of(X2(X2(r0, a_), b_)), m5 = all_of(X2(r1, a_)),
            m6 = all_of(A2(alp, bet)), m7 = all_of(A2(a_, b_)), m8 = all_of(A2(alp, b_));
    __m128i dl = _mm_set1_epi64x((long long)lo64(c->delta[0]));
    __m128i dr = _mm_set1_epi64x((long long)hi64(c->delta[0]));
    __m128i dlr = X2(dl, dr);
    __m128i k00l = X2(X2(X2(h[0], h[4]), X2(A2(m0, s0), A2(m1, s1))), X2(bl, A2(m6, dl)));
    __m128i k00r = X2(X2(X2(h[2], h[4]), X2(A2(m0, s1), A2(m1, s2))), X2(ar, A2(m6, dr)));
    __m128i k11l = X2(X2(X2(h[1], h[4]), A2(m2, X2(s0, dr))),
                      X2(A2(m3, X2(s1, dlr)), A2(m7, dl)));
    __m128i k11r = X2(X2(X2(h[3], h[4]), A2(m2, X2(s1, dlr))),
                      X2(A2(m3, X2(s2, dl)), A2(m7, dr)));
    __m128i k01 = X2(X2(X2(h[0], h[5]), X2(A2(m4, X2(s0, dl)), A2(m5, X2(s1, dr)))),
                     X2(X2(bl, A2(m8, dl)), dl));
    uint64_t *tab = c->tables, *ctl = c->tables + 3 * n;
    ST(tab + i, X2(k00l, k11l)); /* gates i and i+1 are adjacent in each table */
    ST(tab + n + i, X2(k00r, k11r));
    ST(tab + 2 * n + i, X2(k00l, k01));
    set_bits(ctl, i, two_bits(X2(X2(r0, hb[0]), hb[4])));
    set_bits(ctl, n + i, two_bits(X2(X2(r1, hb[2]), hb[4])));
    set_bits(ctl, 2 * n + i, two_bits(X2(X2(a_, hb[0]), hb[1])));
    set_bits(ctl, 3 * n + i, two_bits(X2(X2(b_, hb[2]), hb[3])));
    set_bits(ctl, 4 * n + i, two_bits(X2(X2(X2(a_, b_), hb[4]), hb[5])));
    ST(ch->o[j], _mm_unpacklo_epi64(k00l, k00r));
    ST(ch->o[j + 1], _mm_unpackhi_epi64(k00l, k00r));
}

/* three-halves garbling of gates i .. i+g-1 (threehalves.py, ThreeHalves.garble) */
TGT INLINE void th_garble(ctx_t *c, const chunk_t *ch, int64_t n, uint64_t first, int64_t i,
                          int j, int g) {
    __m128i lab[6 * BATCH], y[6 * BATCH];
    uint64_t alpha[BATCH], beta[BATCH];
    __m128i d = c->delta[0];
    _Pragma("GCC unroll 4") for (int k = 0; k < g; k++) {
        uint64_t gate = first + (uint64_t)(i + k);
        __m128i a0 = LD(ch->a[j + k]), b0 = LD(ch->b[j + k]);
        alpha[k] = lo64(a0) & 1;
        beta[k] = lo64(b0) & 1;
        __m128i *l = lab + 6 * k; /* colour-0 labels: A, A^D, B, B^D, A^B, A^B^D */
        l[0] = _mm_xor_si128(a0, _mm_and_si128(lsb_mask(a0), d));
        l[1] = _mm_xor_si128(l[0], d);
        l[2] = _mm_xor_si128(b0, _mm_and_si128(lsb_mask(b0), d));
        l[3] = _mm_xor_si128(l[2], d);
        l[4] = _mm_xor_si128(l[0], l[2]);
        l[5] = _mm_xor_si128(l[4], d);
        _Pragma("GCC unroll 6") for (int h = 0; h < 6; h++)
            y[6 * k + h] = _mm_xor_si128(sigma(l[h]), tweak(3 * gate + (uint64_t)(h / 2)));
    }
    aes_n(&c->keys[0], y, 6 * g);
    if (g == 2) {
        th_finish2(c, ch, n, first, i, j, lab, y, alpha, beta);
        return;
    }
    uint64_t *tab = c->tables, *ctl = c->tables + 3 * n;
    uint64_t dl = lo64(d), dr = hi64(d);
    _Pragma("GCC unroll 4") for (int k = 0; k < g; k++) {
        int64_t q = i + k;
        uint64_t h[6], hb[6];
        _Pragma("GCC unroll 6") for (int e = 0; e < 6; e++) {
            __m128i hv = _mm_xor_si128(y[6 * k + e], sigma(lab[6 * k + e]));
            h[e] = lo64(hv);
            hb[e] = hi64(hv) & 1;
        }
        uint64_t al = lo64(lab[6 * k]), ar = hi64(lab[6 * k]);
        uint64_t bl = lo64(lab[6 * k + 2]), br = hi64(lab[6 * k + 2]);
        uint64_t s0 = al ^ ar ^ bl, s1 = al ^ br, s2 = ar ^ bl ^ br;
        uint64_t r0, r1, a_ = alpha[k] ^ 1, b_ = beta[k] ^ 1;
        rand_bits(c, first + (uint64_t)q, &r0, &r1);
        uint64_t m0 = -r0, m1 = -r1, m2 = -(r0 ^ a_), m3 = -(r1 ^ b_), m4 = -(r0 ^ a_ ^ b_),
                 m5 = -(r1 ^ a_), m6 = -(alpha[k] & beta[k]), m7 = -(a_ & b_),
                 m8 = -(alpha[k] & b_);
        uint64_t k00l = h[0] ^ h[4] ^ (m0 & s0) ^ (m1 & s1) ^ bl ^ (m6 & dl);
        uint64_t k00r = h[2] ^ h[4] ^ (m0 & s1) ^ (m1 & s2) ^ ar ^ (m6 & dr);
        uint64_t k11l = h[1] ^ h[4] ^ (m2 & (s0 ^ dr)) ^ (m3 & (s1 ^ dl ^ dr)) ^ (m7 & dl);
        uint64_t k11r = h[3] ^ h[4] ^ (m2 & (s1 ^ dl ^ dr)) ^ (m3 & (s2 ^ dl)) ^ (m7 & dr);
        uint64_t k01 = h[0] ^ h[5] ^ (m4 & (s0 ^ dl)) ^ (m5 & (s1 ^ dr)) ^ bl ^ (m8 & dl) ^ dl;
        store64(tab + q, k00l ^ k11l);
        store64(tab + n + q, k00r ^ k11r);
        store64(tab + 2 * n + q, k00l ^ k01);
        set_bits(ctl, q, r0 ^ hb[0] ^ hb[4]);
        set_bits(ctl, n + q, r1 ^ hb[2] ^ hb[4]);
        set_bits(ctl, 2 * n + q, a_ ^ hb[0] ^ hb[1]);
        set_bits(ctl, 3 * n + q, b_ ^ hb[2] ^ hb[3]);
        set_bits(ctl, 4 * n + q, a_ ^ b_ ^ hb[4] ^ hb[5]);
        ST(ch->o[j + k], _mm_set_epi64x((long long)k00r, (long long)k00l));
    }
}

/* bits `bit` and `bit` + 1 of ctl as bits 0 and 1 */
INLINE uint64_t get_bits2(const uint64_t *ctl, int64_t bit) {
    int64_t w = bit / 64;
    unsigned s = (unsigned)(bit % 64);
    uint64_t v = load64(ctl + w) >> s;
    if (s == 63) v |= load64(ctl + w + 1) << 1;
    return v & 3;
}

/* bits 0 and 1 of v as the two 0/1 words of a register */
TGT INLINE __m128i words_of(uint64_t v) {
    return _mm_set_epi64x((long long)(v >> 1), (long long)(v & 1));
}

/* th_evaluate's output labels for gates i, i+1 (chunk rows j, j+1) from their labels
 * `lab` (a, b, a^b of each) and hashes `y`: the scalar formulas below, both gates side by
 * side in the two 64-bit words of each register */
TGT INLINE void th_eval_finish2(ctx_t *c, const chunk_t *ch, int64_t n, int64_t i, int j,
                                const __m128i *lab, const __m128i *y) {
    th_pair_t p;
    th_pair(lab, y, 3, 1, &p);
    __m128i *h = p.h, *hb = p.hb, al = p.al, ar = p.ar, bl = p.bl, s0 = p.s0, s1 = p.s1,
            s2 = p.s2, one = _mm_set1_epi64x(1);
    __m128i ci = A2(al, one), cj = A2(bl, one), x = X2(ci, cj);
    const uint64_t *tab = c->tables, *ctl = c->tables + 3 * n;
    __m128i z[5];
    for (int e = 0; e < 5; e++) z[e] = words_of(get_bits2(ctl, e * n + i));
    __m128i r1 = X2(X2(X2(z[0], A2(ci, z[2])), A2(x, z[4])), X2(hb[0], hb[2]));
    __m128i r2 = X2(X2(X2(z[1], A2(cj, z[3])), A2(x, z[4])), X2(hb[1], hb[2]));
    __m128i g0 = LD(tab + i), g1 = LD(tab + n + i), g2 = LD(tab + 2 * n + i);
    __m128i mx = all_of(x), mi = all_of(ci), mj = all_of(cj), mr1 = all_of(r1),
            mr2 = all_of(r2);
    __m128i cl = X2(X2(X2(h[0], h[2]), X2(A2(mx, g2), A2(mi, g0))),
                    X2(X2(A2(mr1, s0), A2(mr2, s1)), _mm_andnot_si128(mi, bl)));
    __m128i cr = X2(X2(X2(h[1], h[2]), X2(A2(mx, g2), A2(mj, g1))),
                    X2(X2(A2(mr1, s1), A2(mr2, s2)), _mm_andnot_si128(mj, ar)));
    ST(ch->o[j], _mm_unpacklo_epi64(cl, cr));
    ST(ch->o[j + 1], _mm_unpackhi_epi64(cl, cr));
}

/* three-halves evaluation of gates i .. i+g-1 (ThreeHalves.evaluate) */
TGT INLINE void th_evaluate(ctx_t *c, const chunk_t *ch, int64_t n, uint64_t first, int64_t i,
                            int j, int g) {
    __m128i lab[3 * BATCH], y[3 * BATCH];
    _Pragma("GCC unroll 4") for (int k = 0; k < g; k++) {
        uint64_t gate = first + (uint64_t)(i + k);
        __m128i *l = lab + 3 * k;
        l[0] = LD(ch->a[j + k]);
        l[1] = LD(ch->b[j + k]);
        l[2] = _mm_xor_si128(l[0], l[1]);
        _Pragma("GCC unroll 3") for (int h = 0; h < 3; h++)
            y[3 * k + h] = _mm_xor_si128(sigma(l[h]), tweak(3 * gate + (uint64_t)h));
    }
    aes_n(&c->keys[0], y, 3 * g);
    if (g == 2) {
        th_eval_finish2(c, ch, n, i, j, lab, y);
        return;
    }
    const uint64_t *tab = c->tables, *ctl = c->tables + 3 * n;
    _Pragma("GCC unroll 4") for (int k = 0; k < g; k++) {
        int64_t q = i + k;
        uint64_t h[3], hb[3];
        _Pragma("GCC unroll 3") for (int e = 0; e < 3; e++) {
            __m128i hv = _mm_xor_si128(y[3 * k + e], sigma(lab[3 * k + e]));
            h[e] = lo64(hv);
            hb[e] = hi64(hv) & 1;
        }
        uint64_t al = lo64(lab[3 * k]), ar = hi64(lab[3 * k]);
        uint64_t bl = lo64(lab[3 * k + 1]), br = hi64(lab[3 * k + 1]);
        uint64_t s0 = al ^ ar ^ bl, s1 = al ^ br, s2 = ar ^ bl ^ br;
        uint64_t ci = al & 1, cj = bl & 1, x = ci ^ cj;
        uint64_t z0 = get_bit(ctl, q), z1 = get_bit(ctl, n + q), z2 = get_bit(ctl, 2 * n + q),
                 z3 = get_bit(ctl, 3 * n + q), z4 = get_bit(ctl, 4 * n + q);
        uint64_t r1 = z0 ^ (ci & z2) ^ (x & z4) ^ hb[0] ^ hb[2];
        uint64_t r2 = z1 ^ (cj & z3) ^ (x & z4) ^ hb[1] ^ hb[2];
        uint64_t g0 = load64(tab + q), g1 = load64(tab + n + q), g2 = load64(tab + 2 * n + q);
        uint64_t mx = -x, mi = -ci, mj = -cj, mr1 = -r1, mr2 = -r2;
        uint64_t cl = h[0] ^ h[2] ^ (mx & g2) ^ (mi & g0) ^ (mr1 & s0) ^ (mr2 & s1) ^ (~mi & bl);
        uint64_t cr = h[1] ^ h[2] ^ (mx & g2) ^ (mj & g1) ^ (mr1 & s1) ^ (mr2 & s2) ^ (~mj & ar);
        ST(ch->o[j + k], _mm_set_epi64x((long long)cr, (long long)cl));
    }
}


/* a chunk's gates in batches of `batch`, the rest one by one */
#define BATCHED(batch, call)                                             \
    do {                                                                 \
        int j = 0;                                                       \
        for (; j + (batch) <= m; j += (batch)) call(i0 + j, j, (batch)); \
        for (; j < m; j++) call(i0 + j, j, 1);                           \
    } while (0)

/* half-gates AND op with VAES (and_op's half-gates branch, twice the blocks per batch) */
TGTV static void hg_and_op_v(ctx_t *c, const rows_t *r, int64_t dst, int64_t n,
                             uint64_t first, int64_t r0, int64_t r1) {
    chunk_t ch;
    for (int64_t i0 = r0; i0 < r1; i0 += CHUNK) {
        int m = (int)(r1 - i0 < CHUNK ? r1 - i0 : CHUNK);
        row_ptrs(&r[1], i0, m, c->values, c->width, ch.a);
        row_ptrs(&r[2], i0, m, c->values, c->width, ch.b);
        out_ptrs(c, &r[0], dst, i0, m, ch.o);
        for (int64_t lane = 0; lane < c->lanes; lane++) {
            if (c->mode == MODE_GARBLE) {
#define HG_GV(i, j, g) if ((g) > 1) hg_garble_v(c, &ch, n, first, i, j, g, lane); \
                          else hg_garble(c, &ch, n, first, i, j, g, lane)
                BATCHED(HG_GARBLE_BATCH_V, HG_GV);
            } else {
#define HG_EV(i, j, g) if ((g) > 1) hg_evaluate_v(c, &ch, n, first, i, j, g, lane); \
                          else hg_evaluate(c, &ch, n, first, i, j, g, lane)
                BATCHED(HG_EVAL_BATCH_V, HG_EV);
            }
        }
    }
}

/* gates r0 .. r1-1 of an AND op of n gates (three-halves: all of them, one thread) */
TGT static void and_op(ctx_t *c, const rows_t *r, int64_t dst, int64_t n, uint64_t first,
                       int64_t r0, int64_t r1) {
    chunk_t ch;
    if (c->scheme == SCHEME_HALF_GATES && c->vaes) {
        hg_and_op_v(c, r, dst, n, first, r0, r1);
        return;
    }
    if (c->scheme == SCHEME_THREE_HALVES && c->mode == MODE_GARBLE)
        memset(c->tables + 3 * n, 0, 8 * (size_t)((5 * n + 63) / 64));
    for (int64_t i0 = r0; i0 < r1; i0 += CHUNK) {
        int m = (int)(r1 - i0 < CHUNK ? r1 - i0 : CHUNK);
        row_ptrs(&r[1], i0, m, c->values, c->width, ch.a);
        row_ptrs(&r[2], i0, m, c->values, c->width, ch.b);
        out_ptrs(c, &r[0], dst, i0, m, ch.o);
        if (c->scheme == SCHEME_HALF_GATES) {
            for (int64_t lane = 0; lane < c->lanes; lane++) {
                if (c->mode == MODE_GARBLE) {
#define HG_G(i, j, g) hg_garble(c, &ch, n, first, i, j, g, lane)
                    BATCHED(HG_GARBLE_BATCH, HG_G);
                } else {
#define HG_E(i, j, g) hg_evaluate(c, &ch, n, first, i, j, g, lane)
                    BATCHED(HG_EVAL_BATCH, HG_E);
                }
            }
        } else if (c->mode == MODE_GARBLE) {
#define TH_G(i, j, g) th_garble(c, &ch, n, first, i, j, g)
            BATCHED(TH_GARBLE_BATCH, TH_G);
        } else {
#define TH_E(i, j, g) th_evaluate(c, &ch, n, first, i, j, g)
            BATCHED(TH_EVAL_BATCH, TH_E);
        }
    }
}

/* ---------------------------------------------------------------- linear ops */

#define REG_COLUMNS 8 /* up to this many columns, a row's XOR stays in registers */

/* out[i] = XOR over columns, chunk by chunk: a row's XOR in registers when the columns
 * are few, else column by column through the output row */
TGT INLINE void xor_rows(ctx_t *c, const rows_t *r, int64_t dst, int64_t r0, int64_t r1,
                         int64_t k, int64_t width) {
    uint64_t *o[CHUNK], *p[REG_COLUMNS][CHUNK];
    for (int64_t i0 = r0; i0 < r1; i0 += CHUNK) {
        int64_t m = r1 - i0 < CHUNK ? r1 - i0 : CHUNK;
        out_ptrs(c, &r[0], dst, i0, m, o);
        if (k <= REG_COLUMNS) {
            for (int64_t col = 0; col < k; col++)
                row_ptrs(&r[1 + col], i0, m, c->values, width, p[col]);
            for (int64_t q = 0; q < m; q++)
                for (int64_t w = 0; w < width; w += 2) {
                    __m128i acc = LD(p[0][q] + w);
                    for (int64_t col = 1; col < k; col++)
                        acc = _mm_xor_si128(acc, LD(p[col][q] + w));
                    ST(o[q] + w, acc);
                }
            continue;
        }
        row_ptrs(&r[1], i0, m, c->values, width, p[0]);
        for (int64_t q = 0; q < m; q++) /* the first column, then XOR the others in */
            for (int64_t w = 0; w < width; w += 2) ST(o[q] + w, LD(p[0][q] + w));
        for (int64_t col = 1; col < k; col++) {
            row_ptrs(&r[1 + col], i0, m, c->values, width, p[0]);
            for (int64_t q = 0; q < m; q++)
                for (int64_t w = 0; w < width; w += 2)
                    ST(o[q] + w, _mm_xor_si128(LD(o[q] + w), LD(p[0][q] + w)));
        }
    }
}

TGT INLINE void ragged_rows(ctx_t *c, const rows_t *r, int64_t dst, int64_t n, int64_t r0,
                            int64_t r1, int64_t terms, int64_t width) {
    uint64_t *o[CHUNK];
    for (int64_t i0 = r0; i0 < r1; i0 += CHUNK) {
        int64_t m = r1 - i0 < CHUNK ? r1 - i0 : CHUNK;
        out_ptrs(c, &r[0], dst, i0, m, o);
        for (int64_t q = 0; q < m; q++) {
            int64_t i = i0 + q;
            int64_t lo = row_at(&r[2], i), hi = i + 1 < n ? row_at(&r[2], i + 1) : terms;
            for (int64_t w = 0; w < width; w += 2) {
                __m128i acc = LD(c->values + row_at(&r[1], lo) * width + w);
                for (int64_t t = lo + 1; t < hi; t++)
                    acc = _mm_xor_si128(acc, LD(c->values + row_at(&r[1], t) * width + w));
                ST(o[q] + w, acc);
            }
        }
    }
}

/* the loop of ragged_rows for int64 term and start lists (the plan's kinds), `w` words a
 * row (2 a lane), out row i at OUT(i): every index kind fixed outside the loop */
#define RAGGED_FIXED(OUT)                                                               \
    for (int64_t i = r0; i < r1; i++) {                                                 \
        int64_t lo = starts[i], hi = i + 1 < n ? starts[i + 1] : nterms;               \
        uint64_t *out = (OUT);                                                          \
        for (int64_t l = 0; l < w; l += 2) {                                            \
            __m128i acc = LD(v + w * terms[lo] + l);                                    \
            for (int64_t t = lo + 1; t < hi; t++)                                       \
                acc = _mm_xor_si128(acc, LD(v + w * terms[t] + l));                     \
            ST(out + l, acc);                                                           \
        }                                                                               \
    }

TGT INLINE void ragged_fixed_w(ctx_t *c, const rows_t *r, int64_t dst, int64_t n, int64_t r0,
                               int64_t r1, int64_t nterms, int64_t w) {
    const int64_t *terms = (const int64_t *)(intptr_t)r[1].a;
    const int64_t *starts = (const int64_t *)(intptr_t)r[2].a;
    const uint64_t *v = c->values;
    if (dst >= 0) {
        uint64_t *o = c->scratch + w * dst;
        RAGGED_FIXED(o + w * i);
    } else if (r[0].kind == R_SLICE) {
        uint64_t *o = c->values + w * r[0].a;
        int64_t os = w * r[0].b;
        RAGGED_FIXED(o + os * i);
    } else if (r[0].kind == R_I32) {
        const int32_t *q = (const int32_t *)(intptr_t)r[0].a;
        RAGGED_FIXED(c->values + w * (int64_t)q[i]);
    } else {
        const int64_t *q = (const int64_t *)(intptr_t)r[0].a;
        RAGGED_FIXED(c->values + w * q[i]);
    }
}

/* ragged_rows with RAGGED_FIXED where the lists are int64 (one lane: the row's width a
 * constant): 1 when it ran the rows, 0 when the caller must */
TGT INLINE int ragged_fixed(ctx_t *c, const rows_t *r, int64_t dst, int64_t n, int64_t r0,
                            int64_t r1, int64_t nterms) {
    if (r[1].kind != R_I64 || r[2].kind != R_I64) return 0;
    if (c->width == 2) ragged_fixed_w(c, r, dst, n, r0, r1, nterms, 2);
    else ragged_fixed_w(c, r, dst, n, r0, r1, nterms, c->width);
    return 1;
}

#define SLICE_COLUMNS 4 /* columns an XOR of slices takes in one pass over its rows */
#define SLICE_BLOCK 128 /* rows per pass when the columns take several passes */

/* rows r0 .. r1-1 of an XOR op's K columns (all slices), L lanes (16-byte blocks) a row,
 * stored (`into` 0) or XORed into the output rows (1): each row's address is its slice's
 * start plus i times its step, no list of row addresses */
TGT INLINE void xor_slices(__m128i *o, int64_t os, const __m128i **p, const int64_t *ps,
                           int64_t r0, int64_t r1, int K, int into, int64_t L) {
    const __m128i *p0 = p[0], *p1 = p[K > 1], *p2 = p[K > 2 ? 2 : 0], *p3 = p[K > 3 ? 3 : 0];
    int64_t s0 = ps[0], s1 = ps[K > 1], s2 = ps[K > 2 ? 2 : 0], s3 = ps[K > 3 ? 3 : 0];
    for (int64_t i = r0; i < r1; i++)
        for (int64_t l = 0; l < L; l++) {
            __m128i acc = LD(p0 + i * s0 + l);
            if (K > 1) acc = _mm_xor_si128(acc, LD(p1 + i * s1 + l));
            if (K > 2) acc = _mm_xor_si128(acc, LD(p2 + i * s2 + l));
            if (K > 3) acc = _mm_xor_si128(acc, LD(p3 + i * s3 + l));
            if (into) acc = _mm_xor_si128(acc, LD(o + i * os + l));
            ST(o + i * os + l, acc);
        }
}

#define XOR_SLICES(L)                                                                   \
    switch (K) {                                                                        \
    case 1: xor_slices(o, os, p, ps, b0, b1, 1, col > 0, L); break;                       \
    case 2: xor_slices(o, os, p, ps, b0, b1, 2, col > 0, L); break;                       \
    case 3: xor_slices(o, os, p, ps, b0, b1, 3, col > 0, L); break;                       \
    default: xor_slices(o, os, p, ps, b0, b1, 4, col > 0, L);                             \
    }

/* an XOR op whose row descriptors are all slices (one lane: the row's width a constant),
 * its columns SLICE_COLUMNS at a time: with more, over blocks of SLICE_BLOCK rows, the
 * first pass stores and the others XOR into the block's output rows (a direct op reads
 * none of the rows it writes, so the order is free): 1 when it ran the rows, 0 when the
 * caller must */
TGT INLINE int xor_op_of_slices(ctx_t *c, const rows_t *r, int64_t dst, int64_t r0,
                                int64_t r1, int64_t k) {
    if (k < 1 || (dst < 0 && r[0].kind != R_SLICE)) return 0;
    for (int64_t col = 0; col < k; col++)
        if (r[1 + col].kind != R_SLICE) return 0;
    int64_t lanes = c->width / 2;
    __m128i *o = dst < 0 ? (__m128i *)c->values + lanes * r[0].a
                         : (__m128i *)c->scratch + lanes * dst;
    int64_t os = lanes * (dst < 0 ? r[0].b : 1);
    int64_t block = k <= SLICE_COLUMNS ? r1 - r0 : SLICE_BLOCK;
    for (int64_t b0 = r0; b0 < r1; b0 += block) {
        int64_t b1 = r1 - b0 < block ? r1 : b0 + block;
        for (int64_t col = 0; col < k; col += SLICE_COLUMNS) {
            int K = (int)(k - col < SLICE_COLUMNS ? k - col : SLICE_COLUMNS);
            const __m128i *p[SLICE_COLUMNS];
            int64_t ps[SLICE_COLUMNS];
            for (int j = 0; j < K; j++) {
                p[j] = (const __m128i *)c->values + lanes * r[1 + col + j].a;
                ps[j] = lanes * r[1 + col + j].b;
            }
            if (lanes == 1) XOR_SLICES(1)
            else XOR_SLICES(lanes)
        }
    }
    return 1;
}

/* rows r0 .. r1-1 of a linear op of n rows */
TGT static void linear_op(ctx_t *c, int64_t kind, const rows_t *r, int64_t dst, int64_t n,
                          int64_t k, int64_t aux, int64_t r0, int64_t r1) {
    if (kind == OP_XOR) {
        if (xor_op_of_slices(c, r, dst, r0, r1, k)) return;
        if (c->width == 2) xor_rows(c, r, dst, r0, r1, k, 2);
        else xor_rows(c, r, dst, r0, r1, k, c->width);
    } else if (kind == OP_RAGGED) {
        if (ragged_fixed(c, r, dst, n, r0, r1, aux)) return;
        if (c->width == 2) ragged_rows(c, r, dst, n, r0, r1, aux, 2);
        else ragged_rows(c, r, dst, n, r0, r1, aux, c->width);
    } else { /* PUBLISH */
        uint64_t *o[CHUNK];
        for (int64_t i0 = r0; i0 < r1; i0 += CHUNK) {
            int64_t m = r1 - i0 < CHUNK ? r1 - i0 : CHUNK;
            row_ptrs(&r[0], i0, m, c->values, c->width, o);
            for (int64_t q = 0; q < m; q++)
                memcpy(o[q], c->scratch + (dst + i0 + q) * c->width, 8 * (size_t)c->width);
        }
    }
}

/* ---------------------------------------------------------------- threads */

/* Ops marked OP_PARALLEL (program.py: rows independent, none reads what another writes)
 * and big enough are cut into pieces the threads take in turn (a thread that lost its
 * core holds up at most one piece); the others run on thread 0 alone. Threads meet at a
 * barrier before a cut op when thread 0 ran others since the last one, and after every
 * cut op, so each op sees every earlier op's results. */
#define PAR_MIN_AND 1024     /* gates: a cut costs a barrier, ~1 us */
#define PAR_MIN_LINEAR 8192  /* rows */
#define PIECE_AND 1024
#define PIECE_LINEAR 4096
#define SPIN_BEFORE_SLEEP 4000

typedef struct {
    atomic_int count, gen, sleepers;
    int parties;
    atomic_long *reset; /* set to 0 by the last to arrive, before the others go on */
} barrier_t;

static void futex_wait(atomic_int *addr, int value) {
    syscall(SYS_futex, addr, FUTEX_WAIT_PRIVATE, value, NULL, NULL, 0);
}

static void futex_wake(atomic_int *addr) {
    syscall(SYS_futex, addr, FUTEX_WAKE_PRIVATE, INT_MAX, NULL, NULL, 0);
}

static void barrier_wait(barrier_t *b) {
    int gen = atomic_load(&b->gen);
    if (atomic_fetch_add(&b->count, 1) == b->parties - 1) {
        atomic_store(&b->count, 0);
        atomic_store(b->reset, 0);
        atomic_store(&b->gen, gen + 1);
        if (atomic_load(&b->sleepers))
            futex_wake(&b->gen);
        return;
    }
    for (int spin = 0; spin < SPIN_BEFORE_SLEEP; spin++) {
        if (atomic_load_explicit(&b->gen, memory_order_acquire) != gen) return;
        _mm_pause();
    }
    /* the other thread may wait for a core: sleep, so this one is free to run it */
    atomic_fetch_add(&b->sleepers, 1);
    while (atomic_load(&b->gen) == gen)
        futex_wait(&b->gen, gen);
    atomic_fetch_sub(&b->sleepers, 1);
}

typedef struct {
    const int64_t *ops;
    int64_t lo, hi;
    const rows_t *rows;
    uint64_t *tables;
    int threads;
    barrier_t bar;
    atomic_long next; /* the next piece of the op being cut */
    ctx_t *ctx[MAX_THREADS];
} job_t;

/* whether an op is cut across the threads */
static int is_cut(const job_t *jb, const int64_t *op, int scheme) {
    int64_t kind = op[0] & OP_KIND, n = op[1];
    return jb->threads > 1 && (op[0] & OP_PARALLEL)
           && (kind == OP_AND ? scheme == SCHEME_HALF_GATES && n >= PAR_MIN_AND
                              : n >= PAR_MIN_LINEAR);
}

TGT INLINE void run_rows(ctx_t *c, const int64_t *op, const rows_t *r, uint64_t *t, int64_t r0,
                         int64_t r1) {
    int64_t kind = op[0] & OP_KIND, n = op[1];
    if (kind == OP_AND) {
        c->tables = t;
        and_op(c, r, op[4], n, (uint64_t)op[2], r0, r1);
    } else {
        linear_op(c, kind, r, op[4], n, op[2], op[5], r0, r1);
    }
}

TGT static void run_part(job_t *jb, int tid) {
    ctx_t *c = jb->ctx[tid];
    uint64_t *t = jb->tables;
    int dirty = 0; /* thread 0 ran ops the others have not met after */
    for (int64_t p = jb->lo; p < jb->hi; p++) {
        const int64_t *op = jb->ops + OP_WORDS * p;
        int64_t kind = op[0] & OP_KIND, n = op[1];
        const rows_t *r = jb->rows + op[3];
        if (is_cut(jb, op, c->scheme)) {
            if (dirty) barrier_wait(&jb->bar);
            int64_t piece = kind == OP_AND ? PIECE_AND : PIECE_LINEAR;
            for (int64_t k; (k = atomic_fetch_add(&jb->next, 1)) * piece < n;)
                run_rows(c, op, r, t, k * piece, (k + 1) * piece < n ? (k + 1) * piece : n);
            barrier_wait(&jb->bar); /* resets `next` for the next cut op */
            dirty = 0;
        } else if (tid == 0) {
            run_rows(c, op, r, t, 0, n);
            dirty = 1;
        } else {
            dirty = 1; /* thread 0 ran it */
        }
        if (kind == OP_AND) t += c->scheme == SCHEME_HALF_GATES ? 4 * n : 3 * n + (5 * n + 63) / 64;
    }
}

/* One helper thread per process, started on first use and kept: a call that cuts its ops
 * hands it the job rather than create a thread (tens of microseconds a call). Of calls
 * made from several threads at once, the one that holds the helper shares its ops, the
 * others run theirs alone. A forked child starts a helper of its own. */
static struct {
    pthread_mutex_t lock; /* held by the call that has the helper */
    atomic_int posted;    /* jobs handed over so far */
    atomic_int done;      /* jobs the helper has finished */
    job_t *job;
    pid_t pid; /* the process the helper runs in */
} helper = {.lock = PTHREAD_MUTEX_INITIALIZER};

static void *helper_main(void *arg) {
    int seen = (int)(intptr_t)arg;
    for (;;) {
        int now;
        while ((now = atomic_load(&helper.posted)) == seen) futex_wait(&helper.posted, seen);
        seen = now;
        run_part(helper.job, 1);
        atomic_store(&helper.done, seen);
        futex_wake(&helper.done);
    }
    return NULL;
}

/* 1 when this call now holds the helper (started if this process has none yet) */
static int helper_take(void) {
    if (pthread_mutex_trylock(&helper.lock)) return 0;
    if (helper.pid == getpid()) return 1;
    pthread_attr_t attr;
    pthread_t th;
    int seen = atomic_load(&helper.posted), ok = 0;
    atomic_store(&helper.done, seen);
    if (pthread_attr_init(&attr) == 0) {
        ok = pthread_attr_setdetachstate(&attr, PTHREAD_CREATE_DETACHED) == 0
             && pthread_create(&th, &attr, helper_main, (void *)(intptr_t)seen) == 0;
        pthread_attr_destroy(&attr);
    }
    if (!ok) {
        pthread_mutex_unlock(&helper.lock);
        return 0;
    }
    helper.pid = getpid();
    return 1;
}

/* run `jb` on this thread and the helper; back once both are done with it */
static void run_with_helper(job_t *jb) {
    helper.job = jb;
    int seq = atomic_load(&helper.posted) + 1;
    atomic_store(&helper.posted, seq);
    futex_wake(&helper.posted);
    run_part(jb, 0);
    for (int spin = 0, done; (done = atomic_load(&helper.done)) != seq; spin++) {
        if (spin < SPIN_BEFORE_SLEEP) _mm_pause();
        else futex_wait(&helper.done, done);
    }
    pthread_mutex_unlock(&helper.lock);
}

/* ---------------------------------------------------------------- entry point */

/* Run ops lo .. hi-1 of a program over the slot array `values` (n_slots rows of 2*lanes
 * words), garbling (mode 0: writes `tables`, reads `deltas`) or evaluating (mode 1:
 * reads `tables`). Tables of the ops follow each other from `tables`, lane k's at
 * tables + k * lane_words. `keys`: 16 bytes per lane; `rand_key`: three-halves garbling.
 * `threads` (1 .. MAX_THREADS) share the ops marked parallel (see run_part).
 * Returns 0, or a negative number for an argument this file cannot run. */
TGT int snail_run(int mode, int scheme, const int64_t *ops, int64_t lo, int64_t hi,
                  const rows_t *rows, uint64_t *values, int64_t lanes, uint64_t *scratch,
                  uint64_t *tables, int64_t lane_words, const uint8_t *keys,
                  const uint64_t *deltas, const uint8_t *rand_key, int threads) {
    if (lanes < 1 || lanes > MAX_LANES) return -1;
    if (scheme != SCHEME_HALF_GATES && (scheme != SCHEME_THREE_HALVES || lanes != 1)) return -2;
    if (mode != MODE_GARBLE && mode != MODE_EVALUATE) return -3;
    if (mode == MODE_GARBLE && scheme == SCHEME_THREE_HALVES && !rand_key) return -4;
    if (threads < 1 || threads > MAX_THREADS) return -6;
    for (int64_t p = lo; p < hi; p++)
        if ((ops[OP_WORDS * p] & OP_KIND) > OP_PUBLISH) return -5;
    ctx_t c[MAX_THREADS];
    c[0].mode = mode;
    c[0].scheme = scheme;
    c[0].lanes = lanes;
    c[0].width = 2 * lanes;
    c[0].values = values;
    c[0].scratch = scratch;
    c[0].lane_words = lane_words;
    c[0].vaes = snail_isa(-1);
    for (int64_t k = 0; k < lanes; k++) {
        aes_expand(&c[0].keys[k], keys + 16 * k);
        c[0].delta[k] = mode == MODE_GARBLE
                            ? _mm_loadu_si128((const __m128i *)(deltas + 2 * k))
                            : _mm_setzero_si128();
    }
    c[0].rand_block = -1;
    c[0].rand_bits = _mm_setzero_si128();
    if (rand_key) aes_expand(&c[0].rand_key, rand_key);
    job_t jb = {.ops = ops, .lo = lo, .hi = hi, .rows = rows, .tables = tables,
                .threads = 1, .ctx = {&c[0]}};
    /* threads only when some op is cut: a narrow range runs on this one alone */
    for (int64_t p = lo; p < hi && threads > 1 && jb.threads == 1; p++) {
        jb.threads = threads;
        if (!is_cut(&jb, ops + OP_WORDS * p, scheme)) jb.threads = 1;
    }
    atomic_init(&jb.bar.count, 0);
    atomic_init(&jb.bar.gen, 0);
    atomic_init(&jb.bar.sleepers, 0);
    atomic_init(&jb.next, 0);
    jb.bar.reset = &jb.next;
    jb.bar.parties = jb.threads;
    _Static_assert(MAX_THREADS == 2, "one helper thread beside the caller");
    if (jb.threads == 2 && helper_take()) {
        c[1] = c[0];
        jb.ctx[1] = &c[1];
        run_with_helper(&jb);
        return 0;
    }
    jb.threads = jb.bar.parties = 1; /* one thread, or the helper is busy: this one runs all */
    run_part(&jb, 0);
    return 0;
}
