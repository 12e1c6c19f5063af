// Tile rasterizer of 3D Gaussian splatting: CPU forward/backward kernels (plain C++ + OpenMP,
// no torch headers so that they can be compiled and inspected standalone).
//
// Semantics (identical to the pure-PyTorch backend in b3dgs/render/rasterize.py):
//   pixel (px, py) has centre (px + 0.5, py + 0.5); each pixel walks its tile's list front to back
//   with T = 1:
//     d = mean - centre; power = -0.5 * (a*dx*dx + c*dy*dy) - b*dx*dy; skip if power > 0
//     alpha = min(0.99, o * exp(power)); skip if alpha < 1/255
//     test_T = T * (1 - alpha); stop if test_T < 1e-4 (this Gaussian is not composited)
//     w = alpha * T; rgb += w * colour; depth += w * z; T = test_T
//   final: rgb += T * background; alpha_out = 1 - T.
//
// Work is parallel over (sample, tile) items. Inside a tile the loop runs Gaussian-outer,
// pixel-inner over the rows / columns where alpha can reach 1/255 (a conservative ellipse test);
// every pixel still sees its Gaussians in list order, so the result equals the per-pixel walk.
// The pixels of a row are processed as SIMD chunks of kLanes columns starting at the row's first
// column (branch-free: masks and selects apply the skip / stop rules per lane). Each Gaussian's
// culling box and row-interval coefficients are computed once per pass (cull_gaussians), which also
// detects non-finite inputs. The per-tile functions are compiled for AVX2 and baseline x86-64
// (target_clones; no FMA, so the results are bitwise identical on both paths).
//
// Determinism: each (tile, Gaussian) pair owns a gradient / weight slot written by exactly one
// thread (per-lane partial sums over the pixels in a fixed order, each pixel in lane column mod
// kLanes wherever its chunk starts, then a fixed tree over the lanes); a final pass sums the slots
// of every Gaussian in pair order. Results are bitwise
// independent of the thread count.
#pragma once

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>
#include <vector>
#if defined(__x86_64__)
#include <immintrin.h>
#endif

namespace b3dgs {

constexpr double kMinAlpha = 1.0 / 255.0;
constexpr double kMaxAlpha = 0.99;
constexpr double kMinT = 1e-4;
constexpr int kMaxTile = 64;  // largest supported tile size (row buffers)
// Safety margin of the conservative culling (pixels); far above rounding errors.
constexpr double kPixMargin = 1e-3;

#if defined(__GNUC__) && !defined(__clang__) && (defined(__x86_64__) || defined(__i386__))
#ifdef B3_FMA  // opt-in build (B3DGS_FMA=1, -ffp-contract=fast): fused multiply-adds on AVX2 + FMA machines
#define B3_CLONES __attribute__((target_clones("arch=x86-64-v3", "default")))
#else
#define B3_CLONES __attribute__((target_clones("avx2", "default")))
#endif
#else
#define B3_CLONES
#endif
#define B3_INLINE inline __attribute__((always_inline))

// Vector types (GCC vector extensions) of kLanes pixels: the per-pixel loops are written on whole
// chunks of kLanes pixels with masks and selects, so that they run as SIMD code on both
// target clones (the default clone splits the vectors into SSE halves; same arithmetic per lane).
constexpr int kLanes = 8;  // pixels per chunk (fixed: also defines the gradient summation order)
typedef int32_t VI __attribute__((vector_size(4 * kLanes)));  // int32 lanes (last, nc, columns)
template <typename scalar_t>
struct Vec;
template <>
struct Vec<float> {
  typedef float V __attribute__((vector_size(4 * kLanes)));
  typedef int32_t M __attribute__((vector_size(4 * kLanes)));  // lane masks (0 / -1)
};
template <>
struct Vec<double> {
  typedef double V __attribute__((vector_size(8 * kLanes)));
  typedef int64_t M __attribute__((vector_size(8 * kLanes)));
};

// True if any lane of the mask is set.
B3_INLINE bool any_lane(const VI& m) {
  typedef uint64_t U __attribute__((vector_size(4 * kLanes)));
  const U u = (U)m;
  uint64_t a = 0;
  for (int l = 0; l < kLanes / 2; ++l) a |= u[l];
  return a != 0;
}

// load<V>(p) / store(p, v): the kLanes elements at p as one vector, at any alignment (chunks start at any
// column). memcpy, not a dereference of a reduced-alignment vector type, which clang compiles to aligned moves.
template <typename V, typename T>
B3_INLINE V load(const T* p) {
  V v;
  __builtin_memcpy(&v, p, sizeof(V));
  return v;
}
template <typename T, typename V>
B3_INLINE void store(T* p, const V& v) {
  __builtin_memcpy(p, &v, sizeof(V));
}

// exp for x <= 0 (lanes with x > 0 give garbage, callers mask them out). float: inline
// Cody-Waite + degree-6 polynomial (~1-2 ulp, result 0 for x <= -87 and for NaN); double: libm
// per lane (exact reference for float64 comparisons with the PyTorch backend).
B3_INLINE void exp_neg(const Vec<float>::V& xin, Vec<float>::V& out) {
  typedef Vec<float>::V V;
  typedef Vec<float>::M M;
  const M ok = xin > -87.0f;  // false for x <= -87 and NaN
  V x = ok ? xin : -87.0f;
  x = x > 0.0f ? 0.0f : x;  // keeps the exponent in range on masked-out lanes
  const V t = x * 1.44269504088896341f;
  const V n = (t + 12582912.0f) - 12582912.0f;  // round to nearest integer (|t| < 2^22)
  V r = x - n * 0.693145751953125f;               // ln2 hi
  r = r - n * 1.428606765330187045e-06f;          // ln2 lo
  V p = r * 1.3981999507e-3f + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * r * r + r + 1.0f;
  const M bits = (__builtin_convertvector(n, M) + 127) << 23;  // n in [-126, 0]
  const V scale = (V)bits;
  out = ok ? p * scale : 0.0f;
}
B3_INLINE void exp_neg(const Vec<double>::V& x, Vec<double>::V& out) {
  for (int l = 0; l < kLanes; ++l) out[l] = std::exp(x[l]);
}

// Lane-occupancy counters of the SIMD chunks (diagnostic for bench/lanes.py): compiled only with -DB3_LANE_STATS
// (B3DGS_LANE_STATS=1 builds a separate extension), so the default kernels carry no counting at all.
enum LaneStat { kFwdChunks, kFwdLive, kFwdUsed, kBwdChunks, kBwdLive, kBwdUsed, kBwdRows, kBwdRowPixels,
                kBwdNarrowRows, kBwdUnalignedChunks, kBwdAlignedChunks, kLaneStats };
#ifdef B3_LANE_STATS
inline int64_t g_lane_stats[kLaneStats] = {};
template <typename Mask>
B3_INLINE int64_t lanes_set(const Mask& m) {
  int64_t n = 0;
  for (int l = 0; l < kLanes; ++l) n += m[l] != 0;
  return n;
}
#define B3_COUNT(i, v) __atomic_fetch_add(&g_lane_stats[i], (int64_t)(v), __ATOMIC_RELAXED)
#else
#define B3_COUNT(i, v) ((void)0)
#endif

struct Geometry {
  int S, N, W, H, ts, tiles_x, tiles_y;
  int64_t P;
};

// Per-(sample, Gaussian) culling data, computed once per pass (cull_gaussians) instead of once per
// tile pair: the pixel bounding box where alpha can reach 1/255 (clamped to the image; empty when
// o < 1/255; the whole image when the conic is not SPD), and float coefficients of the per-row column
// intervals (see row_ranges). Culling only decides which pixels are evaluated: a pixel outside every
// interval would get alpha < 1/255 and add nothing, so any conservative interval gives bitwise the same
// render and gradients. The intervals are therefore computed in float with a margin that covers float
// rounding, eight rows per AVX instruction.
struct GaussCull {
  int32_t x0, x1, y0, y1;  // [x0, x1) x [y0, y1), absolute pixel coordinates
  float gx, gy;            // pixel-centre frame: row centre y + 0.5 has offset dy = gy - y, column cx - x
  float k2a, det, bia, ia, margin;  // interval of row dy: centre gx + bia dy, half width sqrt(k2a - det dy^2) ia
};

// alpha >= 1/255 needs power >= L = log(1 / (255 o)) (<= 0): ellipse d^T Q d <= -2L, half extents
// sqrt(-2L * Sigma_ii), Sigma = Q^-1. Slightly enlarged (conservative): culling never changes a pixel.
// Returns the number of (sample, Gaussian) entries with a non-finite input (the caller raises: checked
// here, where the data is read anyway, instead of in separate passes over every input tensor).
template <typename scalar_t>
int64_t cull_gaussians(const scalar_t* means, const scalar_t* conics, const scalar_t* colors, const scalar_t* opac,
                       const scalar_t* depths, int64_t SN, int W, int H, GaussCull* out, int nthreads) {
  int64_t nonfinite = 0;
#pragma omp parallel for schedule(static) num_threads(nthreads) reduction(+ : nonfinite)
  for (int64_t g = 0; g < SN; ++g) {
    // x - x is 0 for finite x and NaN for NaN / Inf: one test for all ten inputs
    const scalar_t probe = (means[2 * g] - means[2 * g]) + (means[2 * g + 1] - means[2 * g + 1]) +
                           (conics[3 * g] - conics[3 * g]) + (conics[3 * g + 1] - conics[3 * g + 1]) +
                           (conics[3 * g + 2] - conics[3 * g + 2]) + (colors[3 * g] - colors[3 * g]) +
                           (colors[3 * g + 1] - colors[3 * g + 1]) + (colors[3 * g + 2] - colors[3 * g + 2]) +
                           (opac[g] - opac[g]) + (depths[g] - depths[g]);
    nonfinite += probe == probe ? 0 : 1;
    GaussCull& q = out[g];
    // default: every row spans the whole box (finite centre, zero width, margin far beyond the image)
    q.gx = q.gy = q.k2a = q.det = q.bia = q.ia = 0;
    q.margin = 1e9f;
    const scalar_t go = opac[g];
    if (!(go >= (scalar_t)kMinAlpha)) {  // alpha <= o, so o < 1/255 never contributes
      q.x0 = q.x1 = q.y0 = q.y1 = 0;
      continue;
    }
    q.x0 = 0;
    q.x1 = W;
    q.y0 = 0;
    q.y1 = H;
    const double gx = means[2 * g], gy = means[2 * g + 1];
    const double da = conics[3 * g], db = conics[3 * g + 1], dc = conics[3 * g + 2];
    const double L = std::log(kMinAlpha / (double)go) - 1e-3;
    const double det = da * dc - db * db;
    if (da > 0 && dc > 0 && det > 0 && std::isfinite(det)) {
      const double k2 = std::max(-2.0 * L, 0.0);
      const double hx = std::sqrt(k2 * dc / det) * (1.0 + 1e-6) + kPixMargin;
      const double hy = std::sqrt(k2 * da / det) * (1.0 + 1e-6) + kPixMargin;
      const double lx = std::ceil(gx - hx - 0.5), ux = std::floor(gx + hx - 0.5) + 1.0;
      const double ly = std::ceil(gy - hy - 0.5), uy = std::floor(gy + hy - 0.5) + 1.0;
      // clamped to the image here, to each tile in gather: the same box as clamping to the tile alone
      q.x0 = (int32_t)std::max(0.0, std::min((double)W, lx));
      q.x1 = (int32_t)std::max(0.0, std::min((double)W, ux));
      q.y0 = (int32_t)std::max(0.0, std::min((double)H, ly));
      q.y1 = (int32_t)std::max(0.0, std::min((double)H, uy));
      const double ia = 1.0 / da, hw_max = std::sqrt(k2 * da) * ia;
      if (std::isfinite(ia) && std::isfinite(hw_max) && std::fabs(gx) < 1e6 && std::fabs(gy) < 1e6) {
        q.gx = (float)(gx - 0.5);
        q.gy = (float)(gy - 0.5);
        q.k2a = (float)(k2 * da);
        q.det = (float)det;
        q.bia = (float)(db * ia);
        q.ia = (float)ia;
        // float rounding: of k2a - det dy^2 (a few ulp of k2a) and of dy moves the half width by at most
        // ~sqrt(4 eps) hw_max = 7e-4 hw_max; of the centre gx + bia dy by a few ulp of its magnitude.
        // Margin: 4e-3 hw_max + 1e-5 (|gx| + |bia| (|gy| + H)) + 0.05 px, several times both.
        const double cmax = std::fabs(gx) + std::fabs(db * ia) * (std::fabs(gy) + H);
        q.margin = (float)(4e-3 * hw_max + 1e-5 * cmax + 0.05);
      }
    }
  }
  return nonfinite;
}

// Pixel columns [px0 + xa[r], px0 + xb[r]) of the rows y0 + r, r < y1 - y0, where alpha may reach 1/255:
// the pixel centre must lie within sqrt(max(0, k2a - det dy^2)) ia + margin of gx + bia dy (dy the row
// centre's offset); intersected with [x0, x1). Conservative; every step monotone in its inputs.
B3_INLINE void row_ranges_body(const GaussCull& q, int px0, int x0, int x1, int y0, int y1, int16_t* xa,
                               int16_t* xb) {
  const float fx0 = (float)x0, fx1 = (float)x1;
  for (int r = 0; r < y1 - y0; ++r) {
    const float dy = q.gy - (float)(y0 + r);
    const float sq = std::sqrt(std::max(0.0f, q.k2a - q.det * dy * dy));
    const float cx = q.gx + q.bia * dy;
    const float hw = sq * q.ia + q.margin;
    const float lo = std::ceil(cx - hw), hi = std::floor(cx + hw) + 1.0f;
    const float a = std::max(fx0, std::min(lo, fx1));  // clamp to [x0, x1] (all values finite), then b >= a
    const float b = std::max(std::min(hi, fx1), a);
    xa[r] = (int16_t)((int32_t)a - px0);
    xb[r] = (int16_t)((int32_t)b - px0);
  }
}
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
// row_ranges_body, eight rows per AVX instruction. Writes up to 7 entries past n (the buffers have the slack).
__attribute__((target("avx"))) inline void row_ranges_avx(const GaussCull& q, int px0, int x0, int x1, int y0,
                                                          int n, int16_t* xa, int16_t* xb) {
  const __m256 vgy = _mm256_set1_ps(q.gy), vgx = _mm256_set1_ps(q.gx), vbia = _mm256_set1_ps(q.bia);
  const __m256 via = _mm256_set1_ps(q.ia), vk2a = _mm256_set1_ps(q.k2a), vdet = _mm256_set1_ps(q.det);
  const __m256 vm = _mm256_set1_ps(q.margin), one = _mm256_set1_ps(1.0f), zero = _mm256_setzero_ps();
  const __m256 fx0 = _mm256_set1_ps((float)x0), fx1 = _mm256_set1_ps((float)x1);
  const __m256 steps = _mm256_set_ps(7, 6, 5, 4, 3, 2, 1, 0);
  const __m128i off = _mm_set1_epi32(px0);
  for (int r = 0; r < n; r += 8) {
    const __m256 dy = _mm256_sub_ps(vgy, _mm256_add_ps(_mm256_set1_ps((float)(y0 + r)), steps));
    const __m256 t = _mm256_sub_ps(vk2a, _mm256_mul_ps(_mm256_mul_ps(vdet, dy), dy));
    const __m256 sq = _mm256_sqrt_ps(_mm256_max_ps(t, zero));
    const __m256 cx = _mm256_add_ps(vgx, _mm256_mul_ps(vbia, dy));
    const __m256 hw = _mm256_add_ps(_mm256_mul_ps(sq, via), vm);
    const __m256 lo = _mm256_round_ps(_mm256_sub_ps(cx, hw), _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC);
    const __m256 hi =
        _mm256_add_ps(_mm256_round_ps(_mm256_add_ps(cx, hw), _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC), one);
    // clamp to [x0, x1] (all values finite), then b >= a
    const __m256 a = _mm256_max_ps(fx0, _mm256_min_ps(lo, fx1));
    const __m256 b = _mm256_max_ps(_mm256_min_ps(hi, fx1), a);
    const __m256i ia = _mm256_cvttps_epi32(a), ib = _mm256_cvttps_epi32(b);
    // int32 -> int16 (values fit): pack the two 128-bit halves
    const __m128i pa = _mm_packs_epi32(_mm_sub_epi32(_mm256_castsi256_si128(ia), off),
                                       _mm_sub_epi32(_mm256_extractf128_si256(ia, 1), off));
    const __m128i pb = _mm_packs_epi32(_mm_sub_epi32(_mm256_castsi256_si128(ib), off),
                                       _mm_sub_epi32(_mm256_extractf128_si256(ib, 1), off));
    _mm_storeu_si128((__m128i*)(xa + r), pa);
    _mm_storeu_si128((__m128i*)(xb + r), pb);
  }
}
#define B3_ROWS_AVX 1
#endif

// Row-interval buffers: kMaxTile rows plus the slack of the eight-row AVX stores.
constexpr int kRowBuf = kMaxTile + 8;

B3_INLINE void row_ranges(const GaussCull& q, int px0, int x0, int x1, int y0, int y1, int16_t* xa, int16_t* xb) {
#ifdef B3_ROWS_AVX
  static const bool avx = __builtin_cpu_supports("avx");
  if (avx) {
    row_ranges_avx(q, px0, x0, x1, y0, y1 - y0, xa, xb);
    return;
  }
#endif
  row_ranges_body(q, px0, x0, x1, y0, y1, xa, xb);
}

// Per-tile, per-sample gathered Gaussian data (structure of arrays, in list order) with each pair's
// pixel box clipped to the tile; rows() gives a pair's per-row column intervals on demand.
template <typename scalar_t>
struct TileCache {
  std::vector<scalar_t> x, y, a, b, c, o, cr, cg, cb, z;
  std::vector<int> x0, x1, y0, y1;  // pixel bbox, absolute coords, [x0, x1) x [y0, y1)
  std::vector<GaussCull> q;  // each pair's culling data (row interval coefficients), copied in list order
  int64_t cap = 0;
  int px0 = 0;                      // left pixel column of the gathered tile

  void resize(int64_t K) {
    if (K <= cap) return;
    cap = std::max<int64_t>(K, 2 * cap);
    for (auto* v : {&x, &y, &a, &b, &c, &o, &cr, &cg, &cb, &z}) v->resize(cap);
    for (auto* v : {&x0, &x1, &y0, &y1}) v->resize(cap);
    q.resize(cap);
  }

  // Column intervals of pair k's rows y0[k] .. y1[k] - 1 into xa, xb (kRowBuf entries each), relative
  // to the tile's left column px0.
  B3_INLINE void rows(int64_t k, int16_t* xa, int16_t* xb) const {
    row_ranges(q[k], px0, x0[k], x1[k], y0[k], y1[k], xa, xb);
  }

  // Gathers the K Gaussians of one tile for sample s, their boxes clipped to the tile rectangle
  // [px0, px1) x [py0, py1), and their row intervals.
  void gather(const scalar_t* means, const scalar_t* conics, const scalar_t* colors,
              const scalar_t* opac, const scalar_t* depths, const GaussCull* cull, const int64_t* ids,
              int64_t K, int64_t N, int s, int tx0, int px1, int py0, int py1) {
    resize(K);
    px0 = tx0;
    const int64_t base = (int64_t)s * N;
    constexpr int64_t kAhead = 16;  // prefetch distance (Gaussians are accessed in random order)
    for (int64_t k = 0; k < K; ++k) {
      if (k + kAhead < K) {
        const int64_t gp = base + ids[k + kAhead];
        __builtin_prefetch(means + 2 * gp);
        __builtin_prefetch(conics + 3 * gp);
        __builtin_prefetch(colors + 3 * gp);
        __builtin_prefetch(opac + gp);
        __builtin_prefetch(depths + gp);
        __builtin_prefetch(cull + gp);
        __builtin_prefetch(reinterpret_cast<const char*>(cull + gp + 1) - 1);  // a struct may span two lines
      }
      const int64_t g = base + ids[k];
      const GaussCull& cq = cull[g];
      q[k] = cq;
      x[k] = means[2 * g];
      y[k] = means[2 * g + 1];
      a[k] = conics[3 * g];
      b[k] = conics[3 * g + 1];
      c[k] = conics[3 * g + 2];
      o[k] = opac[g];
      cr[k] = colors[3 * g];
      cg[k] = colors[3 * g + 1];
      cb[k] = colors[3 * g + 2];
      z[k] = depths[g];
      x0[k] = std::max(px0, std::min(px1, cq.x0));
      x1[k] = std::max(px0, std::min(px1, cq.x1));
      y0[k] = std::max(py0, std::min(py1, cq.y0));
      y1[k] = std::max(py0, std::min(py1, cq.y1));
    }
  }
};

// Per-pixel state of one tile, row-major over the tile's in-image pixels with a row stride ps
// rounded up to a multiple of kLanes (padding columns are never composited).
static_assert(kMaxTile % kLanes == 0, "kMaxTile must be a multiple of kLanes");
inline int padded_stride(int tw) { return (tw + kLanes - 1) / kLanes * kLanes; }

// kStateLen: a chunk may start at any column of the last row (kLanes slack).
constexpr int kStateLen = kMaxTile * kMaxTile + kLanes;
template <typename scalar_t>
struct FwdState {
  scalar_t T[kStateLen], Cr[kStateLen], Cg[kStateLen], Cb[kStateLen], D[kStateLen];
  int32_t last[kStateLen], nc[kStateLen];
};

template <typename scalar_t>
struct BwdState {
  scalar_t T[kStateLen], Rr[kStateLen], Rg[kStateLen], Rb[kStateLen], Rd[kStateLen], gr[kStateLen],
      gg[kStateLen], gb[kStateLen], gd[kStateLen], gaT[kStateLen];
  int32_t last[kStateLen];
};

// Lane l of the result is lane (l - c) mod kLanes of v: the values of a chunk starting at column c moved
// to the lanes of their columns mod kLanes, so that per-lane sums add each pixel in the same lane and
// order wherever its chunk starts (results independent of the chunking).
template <typename scalar_t>
B3_INLINE typename Vec<scalar_t>::V to_column_lanes(const typename Vec<scalar_t>::V& v,
                                                    const typename Vec<scalar_t>::M& idx) {
#if defined(__GNUC__) && !defined(__clang__)
  return __builtin_shuffle(v, idx);
#else
  typename Vec<scalar_t>::V r;
  for (int l = 0; l < kLanes; ++l) r[l] = v[idx[l]];
  return r;
#endif
}

// Fixed-order (pairwise tree) sum of the kLanes lanes.
// The element type comes from Vec<scalar_t>, never from decltype(v[0]): GCC 13 and clang type a
// const vector's subscript as a const reference, GCC 12 as a plain value.
template <typename scalar_t>
B3_INLINE scalar_t lane_sum(const typename Vec<scalar_t>::V& v) {
  scalar_t s[kLanes];
  for (int l = 0; l < kLanes; ++l) s[l] = v[l];
  for (int w = kLanes / 2; w >= 1; w /= 2)
    for (int l = 0; l < w; ++l) s[l] = s[l] + s[l + w];
  return s[0];
}

// Composites the K Gaussians of a tile; st is initialised by the caller (T = 1, last = K, ...).
// ps: row stride of st (multiple of kLanes). pair_w: (K, 2) per-pair (sum w, sum w^2) or nullptr.
// Each row [xa, xb) is processed in chunks of kLanes pixels starting at xa (the state arrays have the
// slack), lanes outside it masked out; within a chunk every lane follows the per-pixel rules with masks /
// selects instead of branches. Per-pair sums take each pixel's value in lane (column mod kLanes).
template <typename scalar_t, bool kWeights>
B3_INLINE void forward_tile_body(const TileCache<scalar_t>& tc, int64_t K, int px0, int py0, int ps,
                                 int npix, FwdState<scalar_t>& st, scalar_t* pair_w) {
  typedef typename Vec<scalar_t>::V V;
  typedef typename Vec<scalar_t>::M M;
  const scalar_t min_alpha = (scalar_t)kMinAlpha, max_alpha = (scalar_t)kMaxAlpha;
  const scalar_t min_T = (scalar_t)kMinT, half = (scalar_t)0.5, mhalf = (scalar_t)-0.5;
  const scalar_t zero = 0, one = 1;
  const int32_t KK = (int32_t)K;
  VI iota;  // lane offsets 0, 1, ..., kLanes - 1
  for (int l = 0; l < kLanes; ++l) iota[l] = l;
  VI ndv = {};  // per-lane counts of terminated pixels
  int ndone = 0;
  for (int64_t k = 0; k < K && ndone < npix; ++k) {
    const int by0 = tc.y0[k], by1 = tc.y1[k];
    if (tc.x0[k] >= tc.x1[k] || by0 >= by1) {
      if (kWeights) pair_w[2 * k] = pair_w[2 * k + 1] = 0;
      continue;
    }
    const scalar_t gx = tc.x[k], gy = tc.y[k], ca = tc.a[k], cbv = tc.b[k], cc = tc.c[k];
    const scalar_t go = tc.o[k];
    const scalar_t r = tc.cr[k], g = tc.cg[k], bl = tc.cb[k], zz = tc.z[k];
    const int32_t kk = (int32_t)k;
    V wl = {}, ql = {};
    int16_t rxa[kRowBuf], rxb[kRowBuf];
    tc.rows(k, rxa, rxb);
    for (int yy = by0; yy < by1; ++yy) {
      const int xa = px0 + rxa[yy - by0], xb = px0 + rxb[yy - by0];
      if (xb <= xa) continue;
      const scalar_t dy = gy - ((scalar_t)yy + half);
      const scalar_t cdy2 = cc * dy * dy;
      const int lo = xa - px0, hi = xb - px0;
      const int row = (yy - py0) * ps;
      for (int c = lo; c < hi; c += kLanes) {
        const int off = row + c;
        const VI col = iota + c;
        const VI lv = load<VI>(st.last + off);
        const VI live_i = (lv == KK) & (col < hi);
        if (!any_lane(live_i)) continue;  // all lanes terminated or outside the row range
        const M live = __builtin_convertvector(live_i, M);
        const V dx = gx - (__builtin_convertvector(col + px0, V) + half);
        const V power = mhalf * (ca * dx * dx + cdy2) - cbv * dx * dy;
        V G;
        exp_neg(power, G);
        const V ra = go * G;
        const V alpha = ra < max_alpha ? ra : max_alpha;  // std::min(max_alpha, raw)
        const M contrib = live & ~(power > zero) & ~(alpha < min_alpha);
        const V t0 = load<V>(st.T + off);
        const V test_T = t0 * (one - alpha);
        const M stop = contrib & (test_T < min_T);
#ifdef B3_LANE_STATS
        B3_COUNT(kFwdChunks, 1);
        B3_COUNT(kFwdLive, lanes_set(live));
        B3_COUNT(kFwdUsed, lanes_set(contrib));
#endif
        const M use = contrib & ~stop;
        const V w = use ? alpha * t0 : zero;
        // w = +0 on unused lanes, and x + (+-0) = x for the accumulators (never -0): no selects
        store(st.Cr + off, load<V>(st.Cr + off) + w * r);
        store(st.Cg + off, load<V>(st.Cg + off) + w * g);
        store(st.Cb + off, load<V>(st.Cb + off) + w * bl);
        store(st.D + off, load<V>(st.D + off) + w * zz);
        store(st.T + off, V(use ? test_T : t0));
        const VI stop_i = __builtin_convertvector(stop, VI);
        store(st.nc + off, VI(load<VI>(st.nc + off) - __builtin_convertvector(use, VI)));
        store(st.last + off, VI(stop_i ? kk : lv));
        ndv -= stop_i;
        if (kWeights) {  // per-pair weight sums only when a block asks for them
          const M lanes = __builtin_convertvector((iota - c) & (kLanes - 1), M);
          wl += to_column_lanes<scalar_t>(w, lanes);
          ql += to_column_lanes<scalar_t>(w * w, lanes);
        }
      }
    }
    ndone = 0;
    for (int l = 0; l < kLanes; ++l) ndone += ndv[l];
    if (kWeights) {
      pair_w[2 * k] = lane_sum<scalar_t>(wl);
      pair_w[2 * k + 1] = lane_sum<scalar_t>(ql);
    }
  }
}

// Reverse walk of a tile from list position kmax - 1 down to 0. pair_g: (kmax, 10) slots
// (mean x, mean y, conic a, b, c, opacity, colour r, g, b, depth). Chunks as in the forward; the
// per-pair sums are accumulated per lane and the lanes summed in a fixed order at the end.
// kRGBOnly: the depth and alpha outputs have no gradient (the training loss): their terms, which would
// only add zeros, and the depth-behind state are skipped (the same sums: see the note on +-0 below).
template <typename scalar_t, bool kRGBOnly>
B3_INLINE void backward_tile_body(const TileCache<scalar_t>& tc, int64_t kmax, int px0, int py0,
                                  int ps, BwdState<scalar_t>& st, scalar_t* pair_g) {
  typedef typename Vec<scalar_t>::V V;
  typedef typename Vec<scalar_t>::M M;
  const scalar_t min_alpha = (scalar_t)kMinAlpha, max_alpha = (scalar_t)kMaxAlpha;
  const scalar_t half = (scalar_t)0.5, mhalf = (scalar_t)-0.5, zero = 0, one = 1;
  VI iota;  // lane offsets 0, 1, ..., kLanes - 1
  for (int l = 0; l < kLanes; ++l) iota[l] = l;
  for (int64_t k = kmax - 1; k >= 0; --k) {
    V a0 = {}, a1 = {}, a2 = {}, a3 = {}, a4 = {}, a5 = {}, a6 = {}, a7 = {}, a8 = {}, a9 = {};
    const int by0 = tc.y0[k], by1 = tc.y1[k];
    if (tc.x0[k] < tc.x1[k] && by0 < by1) {
      const scalar_t gx = tc.x[k], gy = tc.y[k], ca = tc.a[k], cbv = tc.b[k], cc = tc.c[k];
      const scalar_t go = tc.o[k];
      const scalar_t r = tc.cr[k], g = tc.cg[k], bl = tc.cb[k], zz = tc.z[k];
      const int32_t kk = (int32_t)k;
      int16_t rxa[kRowBuf], rxb[kRowBuf];
      tc.rows(k, rxa, rxb);
      for (int yy = by0; yy < by1; ++yy) {
        const int xa = px0 + rxa[yy - by0], xb = px0 + rxb[yy - by0];
        if (xb <= xa) continue;
        const scalar_t dy = gy - ((scalar_t)yy + half);
        const scalar_t cdy2 = cc * dy * dy, hdy2 = mhalf * dy * dy;
        const int lo = xa - px0, hi = xb - px0;
        const int row = (yy - py0) * ps;
        B3_COUNT(kBwdRows, 1);
        B3_COUNT(kBwdRowPixels, hi - lo);
        B3_COUNT(kBwdNarrowRows, hi - lo <= kLanes / 2);
        B3_COUNT(kBwdUnalignedChunks, (hi - lo + kLanes - 1) / kLanes);
        B3_COUNT(kBwdAlignedChunks, (hi + kLanes - 1) / kLanes - lo / kLanes);  // before skipping dead chunks
        // chunks aligned to multiples of kLanes (lanes before lo masked): every pixel already sits in the lane
        // of its column mod kLanes, so the per-pair sums need no lane moves, and each lane adds its pixels in
        // the same order as the forward's chunks starting at lo would (increasing column): the same bits
        for (int c = lo & ~(kLanes - 1); c < hi; c += kLanes) {
          const int off = row + c;
          const VI col = iota + c;
          // composited: in front of the termination point, power <= 0, alpha >= 1/255
          const VI live_i = (kk < load<VI>(st.last + off)) & (col < hi) & (col >= lo);
          if (!any_lane(live_i)) continue;  // all lanes terminated earlier or outside the row
          const M live = __builtin_convertvector(live_i, M);
          const V dx = gx - (__builtin_convertvector(col + px0, V) + half);
          const V power = mhalf * (ca * dx * dx + cdy2) - cbv * dx * dy;
          V G;
          exp_neg(power, G);
          const V raw = go * G;
          const V alpha = raw < max_alpha ? raw : max_alpha;  // std::min(max_alpha, raw)
          const M use = live & ~(power > zero) & ~(alpha < min_alpha);
#ifdef B3_LANE_STATS
          B3_COUNT(kBwdChunks, 1);
          B3_COUNT(kBwdLive, lanes_set(live));
          B3_COUNT(kBwdUsed, lanes_set(use));
#endif
          const V one_m = one - alpha;
          const V inv_om = one / one_m;
          const V t0 = load<V>(st.T + off);
          const V Ti = t0 * inv_om;  // transmittance in front of this Gaussian
          const V w = alpha * Ti;
          const V gR = load<V>(st.gr + off), gG = load<V>(st.gg + off), gB = load<V>(st.gb + off);
          const V rr = load<V>(st.Rr + off), rg = load<V>(st.Rg + off), rb = load<V>(st.Rb + off);
          // d out / d alpha_i = T_i (c_i - R_i) for colour/depth (R: what lies behind, incl.
          // background), T_final / (1 - alpha_i) for alpha_out.
          V dal, gD = {};
          if (kRGBOnly) {
            dal = Ti * ((r - rr) * gR + (g - rg) * gG + (bl - rb) * gB);
          } else {
            gD = load<V>(st.gd + off);
            const V rd = load<V>(st.Rd + off);
            dal = Ti * ((r - rr) * gR + (g - rg) * gG + (bl - rb) * gB + (zz - rd) * gD) +
                  load<V>(st.gaT + off) * inv_om;
            store(st.Rd + off, V(use ? alpha * zz + one_m * rd : rd));
          }
          store(st.Rr + off, V(use ? alpha * r + one_m * rr : rr));
          store(st.Rg + off, V(use ? alpha * g + one_m * rg : rg));
          store(st.Rb + off, V(use ? alpha * bl + one_m * rb : rb));
          store(st.T + off, V(use ? Ti : t0));
          // Per-pair sums. Masked lanes contribute +-0 (finite factors times a zeroed weight), and adding
          // +-0 leaves an accumulator unchanged (it starts at +0 and never becomes -0): one select per
          // weight instead of one per sum.
          const V wu = use ? w : zero;
          a6 += wu * gR;
          a7 += wu * gG;
          a8 += wu * gB;
          if (!kRGBOnly) a9 += wu * gD;
          // True derivative of the 0.99 clamp: zero when clamped.
          const M unc = use & (raw <= max_alpha);
          const V dpow = unc ? alpha * dal : zero;
          const V gdal = unc ? G * dal : zero;
          const V& dxc = dx;
          a0 -= dpow * (ca * dxc + cbv * dy);
          a1 -= dpow * (cbv * dxc + cc * dy);
          a2 += dpow * (mhalf * dxc * dxc);
          a3 -= dpow * (dxc * dy);
          a4 += dpow * hdy2;
          a5 += gdal;
        }
      }
    }
    scalar_t* pg = pair_g + 10 * k;
    pg[0] = lane_sum<scalar_t>(a0);
    pg[1] = lane_sum<scalar_t>(a1);
    pg[2] = lane_sum<scalar_t>(a2);
    pg[3] = lane_sum<scalar_t>(a3);
    pg[4] = lane_sum<scalar_t>(a4);
    pg[5] = lane_sum<scalar_t>(a5);
    pg[6] = lane_sum<scalar_t>(a6);
    pg[7] = lane_sum<scalar_t>(a7);
    pg[8] = lane_sum<scalar_t>(a8);
    pg[9] = lane_sum<scalar_t>(a9);
  }
}

// Instruction-set clones (identical arithmetic: no FMA contraction, -ffp-contract=off).
B3_CLONES void forward_tile(const TileCache<float>& tc, int64_t K, int px0, int py0, int ps, int npix,
                            FwdState<float>& st, float* pair_w) {
  if (pair_w)
    forward_tile_body<float, true>(tc, K, px0, py0, ps, npix, st, pair_w);
  else
    forward_tile_body<float, false>(tc, K, px0, py0, ps, npix, st, pair_w);
}
B3_CLONES void forward_tile(const TileCache<double>& tc, int64_t K, int px0, int py0, int ps, int npix,
                            FwdState<double>& st, double* pair_w) {
  if (pair_w)
    forward_tile_body<double, true>(tc, K, px0, py0, ps, npix, st, pair_w);
  else
    forward_tile_body<double, false>(tc, K, px0, py0, ps, npix, st, pair_w);
}
B3_CLONES void backward_tile(const TileCache<float>& tc, int64_t kmax, int px0, int py0, int ps,
                             BwdState<float>& st, float* pair_g, bool rgb_only) {
  if (rgb_only)
    backward_tile_body<float, true>(tc, kmax, px0, py0, ps, st, pair_g);
  else
    backward_tile_body<float, false>(tc, kmax, px0, py0, ps, st, pair_g);
}
B3_CLONES void backward_tile(const TileCache<double>& tc, int64_t kmax, int px0, int py0, int ps,
                             BwdState<double>& st, double* pair_g, bool rgb_only) {
  if (rgb_only)
    backward_tile_body<double, true>(tc, kmax, px0, py0, ps, st, pair_g);
  else
    backward_tile_body<double, false>(tc, kmax, px0, py0, ps, st, pair_g);
}

inline void tile_rect(const Geometry& G, int t, int& px0, int& px1, int& py0, int& py1) {
  const int tx = t % G.tiles_x, ty = t / G.tiles_x;
  px0 = tx * G.ts;
  py0 = ty * G.ts;
  px1 = std::min(px0 + G.ts, G.W);
  py1 = std::min(py0 + G.ts, G.H);
}

template <typename scalar_t>
bool forward_impl(const Geometry& G, const scalar_t* means, const scalar_t* conics,
                  const scalar_t* colors, const scalar_t* opac, const scalar_t* depths,
                  const int64_t* offsets, const int64_t* ids, const scalar_t* bg, scalar_t* out_rgb,
                  scalar_t* out_depth, scalar_t* out_T, int32_t* out_last, int32_t* out_nc,
                  scalar_t* pair_w,  // (S, P, 2), zero-initialised, or nullptr
                  int nthreads, int64_t* flags) {
  const int num_tiles = G.tiles_x * G.tiles_y;
  const int64_t items = (int64_t)G.S * num_tiles;
  // input checks inside the passes (flags[0]: non-finite entries, flags[1]: Gaussian ids out of range);
  // nothing is composited when either is non-zero (the caller raises)
  int64_t bad_ids = 0;
#pragma omp parallel for schedule(static) num_threads(nthreads) reduction(+ : bad_ids)
  for (int64_t i = 0; i < G.P; ++i) bad_ids += (ids[i] < 0 || ids[i] >= G.N) ? 1 : 0;
  std::vector<GaussCull> cull((size_t)G.S * G.N);
  flags[0] = cull_gaussians(means, conics, colors, opac, depths, (int64_t)G.S * G.N, G.W, G.H, cull.data(), nthreads);
  flags[1] = bad_ids;
  if (flags[0] != 0 || flags[1] != 0) return false;
#pragma omp parallel num_threads(nthreads)
  {
    TileCache<scalar_t> tc;
    std::vector<FwdState<scalar_t>> state(1);
    FwdState<scalar_t>& st = state[0];
#pragma omp for schedule(dynamic, 1)
    for (int64_t item = 0; item < items; ++item) {
      const int s = (int)(item / num_tiles);
      const int t = (int)(item % num_tiles);
      int px0, px1, py0, py1;
      tile_rect(G, t, px0, px1, py0, py1);
      const int tw = px1 - px0, th = py1 - py0, npix = tw * th, ps = padded_stride(tw);
      const int64_t start = offsets[t], K = offsets[t + 1] - offsets[t];
      tc.gather(means, conics, colors, opac, depths, cull.data(), ids + start, K, G.N, s, px0, px1, py0, py1);
      for (int p = 0; p < th * ps; ++p) {
        st.T[p] = 1;
        st.Cr[p] = st.Cg[p] = st.Cb[p] = st.D[p] = 0;
        st.last[p] = (int32_t)K;
        st.nc[p] = 0;
      }
      forward_tile(tc, K, px0, py0, ps, npix, st,
                   pair_w ? pair_w + 2 * ((int64_t)s * G.P + start) : nullptr);
      for (int yy = py0; yy < py1; ++yy) {
        for (int xx = px0; xx < px1; ++xx) {
          const int p = (yy - py0) * ps + (xx - px0);
          const int64_t pix = ((int64_t)s * G.H + yy) * G.W + xx;
          out_rgb[3 * pix] = st.Cr[p] + st.T[p] * bg[0];
          out_rgb[3 * pix + 1] = st.Cg[p] + st.T[p] * bg[1];
          out_rgb[3 * pix + 2] = st.Cb[p] + st.T[p] * bg[2];
          out_depth[pix] = st.D[p];
          out_T[pix] = st.T[p];
          out_last[pix] = st.last[p];
          out_nc[pix] = st.nc[p];
        }
      }
    }
  }
  return true;
}

template <typename scalar_t>
void backward_impl(const Geometry& G, const scalar_t* means, const scalar_t* conics,
                   const scalar_t* colors, const scalar_t* opac, const scalar_t* depths,
                   const int64_t* offsets, const int64_t* ids, const scalar_t* bg,
                   const scalar_t* Tfin, const int32_t* lastbuf, const scalar_t* g_rgb,
                   const scalar_t* g_depth, const scalar_t* g_alpha,  // both nullptr: no such gradient
                   scalar_t* pair_g,  // (S, P, 10)
                   int nthreads) {
  const bool rgb_only = g_depth == nullptr && g_alpha == nullptr;
  const int num_tiles = G.tiles_x * G.tiles_y;
  const int64_t items = (int64_t)G.S * num_tiles;
  std::vector<GaussCull> cull((size_t)G.S * G.N);
  cull_gaussians(means, conics, colors, opac, depths, (int64_t)G.S * G.N, G.W, G.H, cull.data(), nthreads);
#pragma omp parallel num_threads(nthreads)
  {
    TileCache<scalar_t> tc;
    std::vector<BwdState<scalar_t>> state(1);
    BwdState<scalar_t>& st = state[0];
#pragma omp for schedule(dynamic, 1)
    for (int64_t item = 0; item < items; ++item) {
      const int s = (int)(item / num_tiles);
      const int t = (int)(item % num_tiles);
      int px0, px1, py0, py1;
      tile_rect(G, t, px0, px1, py0, py1);
      const int tw = px1 - px0, ps = padded_stride(tw);
      const int64_t start = offsets[t], K = offsets[t + 1] - offsets[t];
      if (K == 0) continue;
      int64_t kmax = 0;
      for (int yy = py0; yy < py1; ++yy) {
        for (int xx = px0; xx < px1; ++xx) {
          const int p = (yy - py0) * ps + (xx - px0);
          const int64_t pix = ((int64_t)s * G.H + yy) * G.W + xx;
          st.T[p] = Tfin[pix];
          st.last[p] = lastbuf[pix];
          kmax = std::max<int64_t>(kmax, st.last[p]);
          st.Rr[p] = bg[0];
          st.Rg[p] = bg[1];
          st.Rb[p] = bg[2];
          st.gr[p] = g_rgb[3 * pix];
          st.gg[p] = g_rgb[3 * pix + 1];
          st.gb[p] = g_rgb[3 * pix + 2];
          if (!rgb_only) {
            st.Rd[p] = 0;
            st.gd[p] = g_depth ? g_depth[pix] : (scalar_t)0;
            // d alpha_out / d alpha_i = T_final / (1 - alpha_i); store g_alpha * T_final.
            st.gaT[p] = g_alpha ? g_alpha[pix] * Tfin[pix] : (scalar_t)0;
          }
        }
      }
      scalar_t* pg_tile = pair_g + 10 * ((int64_t)s * G.P + start);
      for (int64_t k = kmax; k < K; ++k)
        for (int j = 0; j < 10; ++j) pg_tile[10 * k + j] = 0;
      if (kmax == 0) continue;
      tc.gather(means, conics, colors, opac, depths, cull.data(), ids + start, kmax, G.N, s, px0, px1, py0, py1);
      backward_tile(tc, kmax, px0, py0, ps, st, pg_tile, rgb_only);
    }
  }
}

// Deterministic reduction of per-pair slots (S, P, C) into per-Gaussian sums (S, N, C), summing
// each Gaussian's slots in pair order.
template <typename scalar_t>
void reduce_pairs(const scalar_t* pair, int64_t C, const int64_t* ids, int64_t P, int S, int64_t N,
                  scalar_t* out, int nthreads) {
  std::vector<int64_t> cnt(N + 1, 0), perm(P);
  for (int64_t i = 0; i < P; ++i) cnt[ids[i] + 1]++;
  for (int64_t n = 0; n < N; ++n) cnt[n + 1] += cnt[n];
  {
    std::vector<int64_t> pos(cnt.begin(), cnt.end() - 1);
    for (int64_t i = 0; i < P; ++i) perm[pos[ids[i]]++] = i;
  }
  const int64_t items = (int64_t)S * N;
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int64_t it = 0; it < items; ++it) {
    const int64_t s = it / N, n = it % N;
    scalar_t* o = out + it * C;
    for (int64_t j = 0; j < C; ++j) o[j] = 0;
    const scalar_t* base = pair + s * P * C;
    for (int64_t q = cnt[n]; q < cnt[n + 1]; ++q) {
      const scalar_t* src = base + perm[q] * C;
      for (int64_t j = 0; j < C; ++j) o[j] += src[j];
    }
  }
}

}  // namespace b3dgs
