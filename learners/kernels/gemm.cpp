// Float32 matrix products whose every output element is one fixed chain of fused multiply-adds.
//
//     c[i][j] = (... fma(a[i][K-1], b[K-1][j], ... fma(a[i][1], b[1][j], fma(a[i][0], b[0][j], 0)) ...))
//
// then, if a bias is given, one rounded addition c[i][j] + bias[j]. Each fma rounds once (IEEE
// 754), so the result is the same on every CPU that has FMA, whatever the vector width: the
// AVX-512 path (16 lanes), the AVX2 path (8 lanes) and the portable scalar path (std::fmaf, on
// any architecture) give the same bits. Vectorising across output elements, across rows, across
// members, tiling in registers, packing operands and cutting K into cache-sized blocks (the
// partial chains wait in float32 memory, which is exact) never changes an element's chain; the
// only thing that would, splitting or reordering the sum over k, is never done.
//
// Built by learners/kernels/__init__.py with -ffp-contract=off: plain C++ arithmetic is never
// fused behind the code's back. Each instruction set's code carries its own target attribute,
// so one library serves every x86-64 CPU and the path is chosen at run time.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

#if defined(__x86_64__) || defined(_M_X64)
#include <immintrin.h>
#define RACING_X86 1
#endif

typedef int64_t i64;

namespace {

constexpr i64 KC = 1536;  // K block: a block of packed B panels stays in L2 (2 MB here), the chains continue in memory

// A strided matrix: element (i, j) at p[i * s0 + j * s1].
struct View {
    const float* p;
    i64 s0, s1;
    inline float at(i64 i, i64 j) const { return p[i * s0 + j * s1]; }
};

// Pack rows [i0, i0 + mr) of A, columns [k0, k0 + kc), as dst[k * mr + i] (one broadcast stream).
void pack_a(View a, i64 i0, i64 mr, i64 k0, i64 kc, float* dst) {
    const float* src = a.p + i0 * a.s0 + k0 * a.s1;
    if (a.s0 == 1) {  // columns contiguous: each k's mr values are one run
        for (i64 k = 0; k < kc; ++k) std::memcpy(dst + k * mr, src + k * a.s1, size_t(mr) * sizeof(float));
    } else if (a.s1 == 1) {  // rows contiguous: read along rows
        for (i64 i = 0; i < mr; ++i) {
            const float* row = src + i * a.s0;
            for (i64 k = 0; k < kc; ++k) dst[k * mr + i] = row[k];
        }
    } else {
        for (i64 k = 0; k < kc; ++k)
            for (i64 i = 0; i < mr; ++i) dst[k * mr + i] = src[i * a.s0 + k * a.s1];
    }
}

// Pack columns [j0, j0 + nr) of B, rows [k0, k0 + kc), as dst[k * width + j], zero-padded to width.
void pack_b(View b, i64 j0, i64 nr, i64 width, i64 k0, i64 kc, float* dst) {
    const float* src = b.p + k0 * b.s0 + j0 * b.s1;
    if (b.s1 == 1) {  // rows contiguous
        for (i64 k = 0; k < kc; ++k) std::memcpy(dst + k * width, src + k * b.s0, size_t(nr) * sizeof(float));
    } else if (b.s0 == 1) {  // columns contiguous (a transposed weight): read along columns
        for (i64 j = 0; j < nr; ++j) {
            const float* col = src + j * b.s1;
            for (i64 k = 0; k < kc; ++k) dst[k * width + j] = col[k];
        }
    } else {
        for (i64 k = 0; k < kc; ++k)
            for (i64 j = 0; j < nr; ++j) dst[k * width + j] = src[k * b.s0 + j * b.s1];
    }
    if (nr < width)
        for (i64 k = 0; k < kc; ++k) std::memset(dst + k * width + nr, 0, size_t(width - nr) * sizeof(float));
}

// The register tile: continues the chains of MR rows x width columns by kc steps, from zero (in
// == nullptr) or from the partial chains at in (row stride ldi), and stores them at out (row
// stride ldo), after adding bias[j] once (if bias is given: the last block only). A's element (i,
// k) at a[i * ai + k * ak] (packed by pack_a: ai = 1, ak = MR; or read in place), B's row k at b +
// k * bk (packed by pack_b: bk = width; or read in place).
typedef void (*TileFn)(i64 kc, const float* a, i64 ai, i64 ak, const float* b, i64 bk, const float* in, i64 ldi,
                       float* out, i64 ldo, const float* bias);

void tile_scalar(i64 mr, i64 width, i64 kc, const float* a, i64 ai, i64 ak, const float* b, i64 bk,
                 const float* in, i64 ldi, float* out, i64 ldo, const float* bias) {
    for (i64 i = 0; i < mr; ++i)
        for (i64 j = 0; j < width; ++j) {
            float s = in ? in[i * ldi + j] : 0.0f;
            for (i64 k = 0; k < kc; ++k) s = std::fmaf(a[i * ai + k * ak], b[k * bk + j], s);
            out[i * ldo + j] = bias ? s + bias[j] : s;
        }
}

#ifdef RACING_X86

#define RACING_AVX512 __attribute__((target("avx512f,fma")))
#define RACING_AVX512VL __attribute__((target("avx512f,avx512vl,fma")))
#define RACING_AVX2 __attribute__((target("avx2,fma")))

// One register tile per vector type: MR rows x NV vectors of accumulators. The 256-bit tile is
// compiled twice: for AVX2 CPUs, and for AVX-512 CPUs (32 registers), where it serves panels of
// at most 8 columns.
#define RACING_TILE(NAME, ATTR, V, W, ZERO, LOAD, STORE, SET1, FMA, ADD)                            \
    template <int MR, int NV>                                                                     \
    ATTR void NAME(i64 kc, const float* a, i64 ai, i64 ak, const float* b, i64 bk, const float* in, \
                   i64 ldi, float* out, i64 ldo, const float* bias) {                             \
        V c[MR][NV];                                                                              \
        _Pragma("GCC unroll 16") for (int i = 0; i < MR; ++i)                                     \
            _Pragma("GCC unroll 4") for (int v = 0; v < NV; ++v)                                  \
                c[i][v] = in ? LOAD(in + i * ldi + W * v) : ZERO();                               \
        for (i64 k = 0; k < kc; ++k) {                                                            \
            V bv[NV];                                                                             \
            _Pragma("GCC unroll 4") for (int v = 0; v < NV; ++v) bv[v] = LOAD(b + k * bk + W * v); \
            _Pragma("GCC unroll 16") for (int i = 0; i < MR; ++i) {                               \
                const V av = SET1(a[k * ak + i * ai]);                                            \
                _Pragma("GCC unroll 4") for (int v = 0; v < NV; ++v) c[i][v] = FMA(av, bv[v], c[i][v]); \
            }                                                                                     \
        }                                                                                         \
        if (bias) {                                                                               \
            _Pragma("GCC unroll 4") for (int v = 0; v < NV; ++v) {                                \
                const V bb = LOAD(bias + W * v);                                                  \
                _Pragma("GCC unroll 16") for (int i = 0; i < MR; ++i) c[i][v] = ADD(c[i][v], bb); \
            }                                                                                     \
        }                                                                                         \
        _Pragma("GCC unroll 16") for (int i = 0; i < MR; ++i)                                     \
            _Pragma("GCC unroll 4") for (int v = 0; v < NV; ++v) STORE(out + i * ldo + W * v, c[i][v]); \
    }

RACING_TILE(tile512, RACING_AVX512, __m512, 16, _mm512_setzero_ps, _mm512_loadu_ps, _mm512_storeu_ps,
            _mm512_set1_ps, _mm512_fmadd_ps, _mm512_add_ps)
RACING_TILE(tile256vl, RACING_AVX512VL, __m256, 8, _mm256_setzero_ps, _mm256_loadu_ps, _mm256_storeu_ps,
            _mm256_set1_ps, _mm256_fmadd_ps, _mm256_add_ps)
RACING_TILE(tile256, RACING_AVX2, __m256, 8, _mm256_setzero_ps, _mm256_loadu_ps, _mm256_storeu_ps,
            _mm256_set1_ps, _mm256_fmadd_ps, _mm256_add_ps)

#define RACING_ROWS6(F, NV) F<1, NV>, F<2, NV>, F<3, NV>, F<4, NV>, F<5, NV>, F<6, NV>
#define RACING_ROWS14(F, NV) \
    RACING_ROWS6(F, NV), F<7, NV>, F<8, NV>, F<9, NV>, F<10, NV>, F<11, NV>, F<12, NV>, F<13, NV>, F<14, NV>

// Indexed [rows - 1]. AVX-512 (32 registers): up to 14 rows of 2 x 16 lanes, of 16 lanes, or of 8
// lanes. AVX2 (16 registers): up to 6 rows of 2 x 8 lanes or of 8 lanes.
const TileFn t512x2[14] = {RACING_ROWS14(tile512, 2)};
const TileFn t512x1[14] = {RACING_ROWS14(tile512, 1)};
const TileFn t256vl[14] = {RACING_ROWS14(tile256vl, 1)};
const TileFn t256x2[6] = {RACING_ROWS6(tile256, 2)};
const TileFn t256x1[6] = {RACING_ROWS6(tile256, 1)};

#define RACING_FMA_LOOP(NAME, ATTR, V, SET, FMA, ADD, FIRST)                                       \
    ATTR float NAME(i64 n) {                                                                       \
        V acc[24];                                                                                 \
        for (int i = 0; i < 24; ++i) acc[i] = SET(1.0f + i * 1e-3f);                               \
        const V x = SET(0.999999f), y = SET(1e-7f);                                                \
        for (i64 r = 0; r < n; ++r)                                                                \
            _Pragma("GCC unroll 24") for (int i = 0; i < 24; ++i) acc[i] = FMA(acc[i], x, y);      \
        V s = acc[0];                                                                              \
        for (int i = 1; i < 24; ++i) s = ADD(s, acc[i]);                                           \
        return FIRST(s);                                                                           \
    }
RACING_FMA_LOOP(fma_loop512, RACING_AVX512, __m512, _mm512_set1_ps, _mm512_fmadd_ps, _mm512_add_ps, _mm512_cvtss_f32)
RACING_FMA_LOOP(fma_loop256, RACING_AVX2, __m256, _mm256_set1_ps, _mm256_fmadd_ps, _mm256_add_ps, _mm256_cvtss_f32)

bool has_avx2() { return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma"); }
bool has_avx512() { return has_avx2() && __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512vl"); }

#else
bool has_avx2() { return false; }
bool has_avx512() { return false; }
#endif

// Instruction sets: 0 portable scalar (std::fmaf), 1 AVX2 + FMA, 2 AVX-512F (+VL).
struct Isa {
    i64 mr;           // rows of A per tile
    i64 widths[3];    // panel widths of B, widest first (0: none)
};
const Isa ISAS[3] = {{8, {16, 0, 0}}, {6, {16, 8, 0}}, {14, {32, 16, 8}}};

// The width of the panel that covers `rest` columns (the widest while they fill it, then the
// narrowest that covers the remainder).
i64 panel_width(i64 rest, const Isa& isa) {
    if (rest >= isa.widths[0]) return isa.widths[0];
    i64 w = isa.widths[0];
    for (i64 x : isa.widths)
        if (x >= rest && x > 0) w = x;
    return w;
}

// Lanes computed (useful or not) to cover n columns.
i64 padded(i64 n, const Isa& isa) {
    i64 total = 0;
    for (i64 j = 0; j < n;) {
        const i64 w = panel_width(n - j, isa);
        total += w;
        j += w;
    }
    return total;
}

// Vector instructions per row and k to cover n columns (8-column panels take one 8-lane vector).
i64 vectors(i64 n, const Isa& isa, i64 lanes) {
    i64 total = 0;
    for (i64 j = 0; j < n;) {
        const i64 w = panel_width(n - j, isa);
        total += (w + lanes - 1) / lanes;
        j += w;
    }
    return total;
}

void run_tile(int isa, i64 mr, i64 width, i64 kc, const float* a, i64 ai, i64 ak, const float* b, i64 bk,
              const float* in, i64 ldi, float* out, i64 ldo, const float* bias) {
#ifdef RACING_X86
    if (isa == 2) {
        const TileFn* t = width == 32 ? t512x2 : width == 16 ? t512x1 : t256vl;
        return t[mr - 1](kc, a, ai, ak, b, bk, in, ldi, out, ldo, bias);
    }
    if (isa == 1) return (width == 16 ? t256x2 : t256x1)[mr - 1](kc, a, ai, ak, b, bk, in, ldi, out, ldo, bias);
#endif
    tile_scalar(mr, width, kc, a, ai, ak, b, bk, in, ldi, out, ldo, bias);
}

thread_local std::vector<float> ws_a, ws_b, ws_acc;

// c[i * cm + j * cn] = acc[i * ld + j] (+ bias[j * bs], or bias[i * bs] with bias_rows), one rounded
// addition per element.
void write_out(const float* acc, i64 ld, i64 mr, i64 nr, float* c, i64 cm, i64 cn, const float* bias, i64 bs,
               bool bias_rows) {
    if (cn == 1 && (!bias || (!bias_rows && bs == 1))) {
        for (i64 i = 0; i < mr; ++i) {
            const float* src = acc + i * ld;
            float* dst = c + i * cm;
            if (bias)
                for (i64 j = 0; j < nr; ++j) dst[j] = src[j] + bias[j];
            else
                std::memcpy(dst, src, size_t(nr) * sizeof(float));
        }
        return;
    }
    if (cm == 1) {  // a transposed product: write along C's rows
        for (i64 j = 0; j < nr; ++j)
            for (i64 i = 0; i < mr; ++i) {
                const float s = acc[i * ld + j];
                c[i + j * cn] = bias ? s + bias[(bias_rows ? i : j) * bs] : s;
            }
        return;
    }
    for (i64 i = 0; i < mr; ++i)
        for (i64 j = 0; j < nr; ++j) {
            const float s = acc[i * ld + j];
            c[i * cm + j * cn] = bias ? s + bias[(bias_rows ? i : j) * bs] : s;
        }
}

// One product: C (M x N, element (i, j) at c[i * cm + j * cn]) = A (M x K) B (K x N), plus a bias
// per column (bias[j * bs]) or, with bias_rows, per row (bias[i * bs]).
void gemm_one(int isa_id, i64 M, i64 N, i64 K, View a, View b, float* c, i64 cm, i64 cn, const float* bias,
              i64 bs, bool bias_rows) {
    const Isa& isa = ISAS[isa_id];
    if (M == 0 || N == 0) return;
    if (K == 0) {
        for (i64 i = 0; i < M; ++i)
            for (i64 j = 0; j < N; ++j) c[i * cm + j * cn] = bias ? 0.0f + bias[(bias_rows ? i : j) * bs] : 0.0f;
        return;
    }
    const i64 npad = padded(N, isa);
    const bool blocked = K > KC;
    const i64 kc_max = std::min(K, KC);
    ws_b.resize(size_t(kc_max * npad));
    ws_a.resize(size_t(kc_max * isa.mr));
    ws_acc.resize(size_t(blocked ? M * npad : isa.mr * isa.widths[0]));
    for (i64 k0 = 0; k0 < K; k0 += KC) {
        const i64 kc = std::min(KC, K - k0);
        const bool first = k0 == 0, last = k0 + kc == K;
        // B's panels, one after the other in ws_b (the panel at column j0 from j0 * kc); where A has a
        // single block of rows, B's full panels are read in place if its rows are contiguous.
        const bool b_in_place = b.s1 == 1 && M <= isa.mr;
        for (i64 j0 = 0; j0 < N;) {
            const i64 width = panel_width(N - j0, isa), nr = std::min(width, N - j0);
            if (!(b_in_place && nr == width)) pack_b(b, j0, nr, width, k0, kc, ws_b.data() + j0 * kc);
            j0 += width;
        }
        // Row blocks of equal size (at most isa.mr rows): no short block of a few rows, whose
        // tile would wait on the FMA latency.
        const i64 blocks = (M + isa.mr - 1) / isa.mr, rows = (M + blocks - 1) / blocks;
        for (i64 i0 = 0; i0 < M; i0 += rows) {
            const i64 mr = std::min(rows, M - i0);
            // A's rows are read in place where they are contiguous, else packed.
            const bool in_place = a.s1 == 1;
            const float* ap = in_place ? a.p + i0 * a.s0 + k0 : ws_a.data();
            const i64 ai = in_place ? a.s0 : 1, ak = in_place ? 1 : mr;
            if (!in_place) pack_a(a, i0, mr, k0, kc, ws_a.data());
            for (i64 j0 = 0; j0 < N;) {
                const i64 width = panel_width(N - j0, isa), nr = std::min(width, N - j0);
                const bool in_place_b = b_in_place && nr == width;
                const float* bp = in_place_b ? b.p + k0 * b.s0 + j0 : ws_b.data() + j0 * kc;
                const i64 bk = in_place_b ? b.s0 : width;
                // The chains continue from ws_acc (later K blocks) and end in C itself where a full
                // panel meets contiguous rows of C (the bias added in registers), else in ws_acc,
                // from where write_out copies them.
                float* part = blocked ? ws_acc.data() + i0 * npad + j0 : ws_acc.data();
                const i64 ldp = blocked ? npad : width;
                const float* in = first ? nullptr : part;
                const bool direct = last && nr == width && cn == 1 && !(bias && (bias_rows || bs != 1));
                if (direct) {
                    run_tile(isa_id, mr, width, kc, ap, ai, ak, bp, bk, in, ldp, c + i0 * cm + j0, cm,
                             bias ? bias + j0 * bs : nullptr);
                } else {
                    run_tile(isa_id, mr, width, kc, ap, ai, ak, bp, bk, in, ldp, part, ldp, nullptr);
                    if (last) write_out(part, ldp, mr, nr, c + i0 * cm + j0 * cn, cm, cn,
                                        bias ? bias + (bias_rows ? i0 : j0) * bs : nullptr, bs, bias_rows);
                }
                j0 += width;
            }
        }
    }
}

// A rough cost, in cycles, of gemm_one on these operands: the tiles' FMAs (two a cycle; a block of
// fewer rows than a tile costs a tile: its chains wait on the FMA latency), packing (one element a
// cycle: B unless read in place, A where its rows are not contiguous) and writing C.
double cost(const Isa& isa, i64 lanes, i64 M, i64 N, i64 K, View a, View b, i64 cn) {
    const double rows = double((M + isa.mr - 1) / isa.mr * isa.mr);
    const double fmas = rows * double(vectors(N, isa, lanes)) * double(K) / 2.0;
    const double pack_b = (b.s1 == 1 && M <= isa.mr) ? 0.0 : double(K) * double(N);
    const double pack_a = a.s1 == 1 ? 0.0 : double(M) * double(K);
    return fmas + pack_a + pack_b + double(M) * double(N) * (cn == 1 ? 0.25 : 1.0);
}

#ifdef RACING_X86
// Square roots a vector at a time, from i up to the last whole vector; IEEE 754 sqrt, correctly
// rounded on every path (the scalar tail's std::sqrt too).
RACING_AVX512 void sqrt512(i64 n, const float* x, float* out, i64& i) {
    for (; i + 16 <= n; i += 16) _mm512_storeu_ps(out + i, _mm512_sqrt_ps(_mm512_loadu_ps(x + i)));
}

RACING_AVX2 void sqrt256(i64 n, const float* x, float* out, i64& i) {
    for (; i + 8 <= n; i += 8) _mm256_storeu_ps(out + i, _mm256_sqrt_ps(_mm256_loadu_ps(x + i)));
}
#endif

}  // namespace

extern "C" {

// The instruction sets this CPU can run: bit 0 scalar (always), bit 1 AVX2 + FMA, bit 2 AVX-512F.
int racing_gemm_isas() { return 1 | (has_avx2() ? 2 : 0) | (has_avx512() ? 4 : 0); }

// R products, member r: C_r = A_r B_r [+ bias_r], A_r (M x K), B_r (K x N), C_r (M x N), all float32
// with the given element strides (members at sa_r, sb_r, sc_r, sbias_r). isa: 0, 1 or 2 (see
// racing_gemm_isas); returns 0, or -1 if this CPU cannot run it. The computation is oriented
// (C or its transpose, C^T = B^T A^T) to waste fewer vector lanes; an element's chain is the
// same either way.
int racing_gemm(int isa, i64 R, i64 M, i64 N, i64 K, const float* a, i64 sa_r, i64 sa_m, i64 sa_k,
                const float* b, i64 sb_r, i64 sb_k, i64 sb_n, float* c, i64 sc_r, i64 sc_m, i64 sc_n,
                const float* bias, i64 sbias_r, i64 sbias_n) {
    if (isa < 0 || isa > 2 || !(racing_gemm_isas() >> isa & 1)) return -1;
    // C, or its transpose C^T = B^T A^T, whichever costs less (an element's chain is the same).
    const Isa& spec = ISAS[isa];
    const i64 lanes = isa == 2 ? 16 : isa == 1 ? 8 : 1;
    const bool transpose = cost(spec, lanes, N, M, K, View{b, sb_n, sb_k}, View{a, sa_k, sa_m}, sc_m) <
                           cost(spec, lanes, M, N, K, View{a, sa_m, sa_k}, View{b, sb_k, sb_n}, sc_n);
    for (i64 r = 0; r < R; ++r) {
        const View ar{a + r * sa_r, sa_m, sa_k}, br{b + r * sb_r, sb_k, sb_n};
        float* cr = c + r * sc_r;
        if (transpose)  // C^T (N x M) = B^T (N x K) A^T (K x M)
            gemm_one(isa, N, M, K, View{br.p, sb_n, sb_k}, View{ar.p, sa_k, sa_m}, cr, sc_n, sc_m,
                     bias ? bias + r * sbias_r : nullptr, sbias_n, true);
        else
            gemm_one(isa, M, N, K, ar, br, cr, sc_m, sc_n, bias ? bias + r * sbias_r : nullptr, sbias_n, false);
    }
    return 0;
}

// R column sums, member r: out_r[j] = x_r[0][j] + x_r[1][j] + ... + x_r[M-1][j], added in row
// order from zero (x_r (M x N) with strides sx_m, sx_n; out_r contiguous at out + r * so_r).
void racing_colsum(i64 R, i64 M, i64 N, const float* x, i64 sx_r, i64 sx_m, i64 sx_n, float* out, i64 so_r) {
    for (i64 r = 0; r < R; ++r) {
        float* o = out + r * so_r;
        for (i64 j = 0; j < N; ++j) o[j] = 0.0f;
        const float* xr = x + r * sx_r;
        if (sx_n == 1)
            for (i64 i = 0; i < M; ++i) {
                const float* row = xr + i * sx_m;
                for (i64 j = 0; j < N; ++j) o[j] += row[j];
            }
        else
            for (i64 i = 0; i < M; ++i)
                for (i64 j = 0; j < N; ++j) o[j] += xr[i * sx_m + j * sx_n];
    }
}

// out[i] = sqrt(x[i]) for i < n (contiguous float32), correctly rounded (IEEE 754) on every path,
// so the same bits on every CPU; torch's float32 sqrt on the CPU goes through MKL's vector math,
// whose last bit depends on the CPU (learners/optim.py: Adam's denominator).
// isa as racing_gemm's (each path gives the same bits); returns 0, or -1 if this CPU cannot run it.
int racing_sqrt(int isa, i64 n, const float* x, float* out) {
    if (isa < 0 || isa > 2 || !(racing_gemm_isas() >> isa & 1)) return -1;
    i64 i = 0;
#ifdef RACING_X86
    if (isa == 2)
        sqrt512(n, x, out, i);
    else if (isa == 1)
        sqrt256(n, x, out, i);
#endif
    for (; i < n; ++i) out[i] = std::sqrt(x[i]);
    return 0;
}

// The core's FMA peak, for benchmarks: n rounds of 24 independent vector FMAs (enough chains to
// hide the latency of two FMA units) on the given path; returns a value that depends on all of
// them, so that nothing is optimised away. Floating-point operations: n * 24 * lanes * 2.
float racing_fma_loop(int isa, i64 n) {
#ifdef RACING_X86
    if (isa == 2 && has_avx512()) return fma_loop512(n);
    if (isa == 1 && has_avx2()) return fma_loop256(n);
#endif
    (void)isa;
    (void)n;
    return -1.0f;
}

}  // extern "C"
