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
// The per-tile functions are compiled for AVX2 and baseline x86-64 (target_clones; no FMA, so
// the results are bitwise identical on both paths).
//
// Determinism: each (tile, Gaussian) pair owns a gradient / weight slot written by exactly one
// thread (pixels accumulated in a fixed order); a final pass sums the slots of every Gaussian in
// pair order. Results are bitwise independent of the thread count.
#pragma once

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

namespace b3dgs {

constexpr double kMinAlpha = 1.0 / 255.0;
constexpr double kMaxAlpha = 0.99;
constexpr double kMinT = 1e-4;
constexpr int kMaxTile = 64;  // largest supported tile size (row buffers)
// Safety margin of the conservative culling (pixels); far above rounding errors.
constexpr double kPixMargin = 1e-3;

#if defined(__GNUC__) && !defined(__clang__) && (defined(__x86_64__) || defined(__i386__))
#define B3_CLONES __attribute__((target_clones("avx2", "default")))
#else
#define B3_CLONES
#endif
#define B3_INLINE inline __attribute__((always_inline))

// exp for x <= 0. float: inline Cody-Waite + degree-6 polynomial (~1-2 ulp, result 0 below
// -87); double: libm (exact reference for float64 comparisons with the PyTorch backend).
B3_INLINE float exp_neg(float x) {
  x = std::max(x, -87.0f);
  const float t = x * 1.44269504088896341f;
  const float n = (t + 12582912.0f) - 12582912.0f;  // round to nearest integer (|t| < 2^22)
  float r = x - n * 0.693145751953125f;               // ln2 hi
  r = r - n * 1.428606765330187045e-06f;              // ln2 lo
  float p = 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * r * r + r + 1.0f;
  const int32_t bits = ((int32_t)n + 127) << 23;
  float scale;
  std::memcpy(&scale, &bits, sizeof(float));
  return x > -87.0f ? p * scale : 0.0f;
}
B3_INLINE double exp_neg(double x) { return std::exp(x); }

struct Geometry {
  int S, N, W, H, ts, tiles_x, tiles_y;
  int64_t P;
};

// Per-tile, per-sample gathered Gaussian data (structure of arrays, in list order).
template <typename scalar_t>
struct TileCache {
  std::vector<scalar_t> x, y, a, b, c, o, cr, cg, cb, z;
  std::vector<int> x0, x1, y0, y1;  // pixel bbox, absolute coords, [x0, x1) x [y0, y1)
  // Row intervals: for row centre offset dy, alpha >= 1/255 needs the pixel centre in
  // [x + (b dy - s) / a, x + (b dy + s) / a], s = sqrt(max(0, k2 a - det dy^2)). ra = 0 means
  // "no row interval" (non-SPD conic): use the bbox.
  std::vector<double> rk2a, rdet, ra, rinv_a;

  void resize(int64_t K) {
    for (auto* v : {&x, &y, &a, &b, &c, &o, &cr, &cg, &cb, &z}) v->resize(K);
    for (auto* v : {&x0, &x1, &y0, &y1}) v->resize(K);
    for (auto* v : {&rk2a, &rdet, &ra, &rinv_a}) v->resize(K);
  }

  // Pixel columns [xa, xb) of row yy (absolute) that may reach alpha >= 1/255.
  B3_INLINE void row_range(int64_t k, int yy, int& xa, int& xb) const {
    xa = x0[k];
    xb = x1[k];
    const double aa = ra[k];
    if (aa > 0) {
      const double dy = (double)y[k] - ((double)yy + 0.5);
      const double sq = std::sqrt(std::max(0.0, rk2a[k] - rdet[k] * dy * dy));
      const double ia = rinv_a[k];
      const double cx = (double)x[k] + (double)b[k] * dy * ia - 0.5;
      const double hw = sq * ia * (1.0 + 1e-6) + kPixMargin;
      const double lo = std::ceil(cx - hw), hi = std::floor(cx + hw) + 1.0;
      if (lo > xa) xa = (int)std::min(lo, (double)xb);
      if (hi < xb) xb = (int)std::max(hi, (double)xa);
    }
  }

  // Gathers the K Gaussians of one tile for sample s and computes their pixel bounding boxes,
  // clipped to the tile rectangle [px0, px1) x [py0, py1).
  void gather(const scalar_t* means, const scalar_t* conics, const scalar_t* colors,
              const scalar_t* opac, const scalar_t* depths, const int64_t* ids, int64_t K,
              int64_t N, int s, int px0, int px1, int py0, int py1) {
    resize(K);
    const int64_t base = (int64_t)s * N;
    for (int64_t k = 0; k < K; ++k) {
      const int64_t g = base + ids[k];
      const scalar_t gx = means[2 * g], gy = means[2 * g + 1];
      const scalar_t ca = conics[3 * g], cbv = conics[3 * g + 1], cc = conics[3 * g + 2];
      const scalar_t go = opac[g];
      x[k] = gx;
      y[k] = gy;
      a[k] = ca;
      b[k] = cbv;
      c[k] = cc;
      o[k] = go;
      cr[k] = colors[3 * g];
      cg[k] = colors[3 * g + 1];
      cb[k] = colors[3 * g + 2];
      z[k] = depths[g];
      ra[k] = 0;
      // alpha <= o, so o < 1/255 never contributes.
      if (!(go >= (scalar_t)kMinAlpha)) {
        x0[k] = x1[k] = px0;
        y0[k] = y1[k] = py0;
        continue;
      }
      x0[k] = px0;
      x1[k] = px1;
      y0[k] = py0;
      y1[k] = py1;
      // alpha >= 1/255 needs power >= L = log(1 / (255 o)) (<= 0): ellipse d^T Q d <= -2L,
      // half extents sqrt(-2L * Sigma_ii), Sigma = Q^-1. Slightly enlarged (conservative).
      const double L = std::log(kMinAlpha / (double)go) - 1e-3;
      const double da = ca, db = cbv, dc = cc;
      const double det = da * dc - db * db;
      if (da > 0 && dc > 0 && det > 0 && std::isfinite(det)) {
        const double k2 = std::max(-2.0 * L, 0.0);
        const double hx = std::sqrt(k2 * dc / det) * (1.0 + 1e-6) + kPixMargin;
        const double hy = std::sqrt(k2 * da / det) * (1.0 + 1e-6) + kPixMargin;
        const double lx = std::ceil((double)gx - hx - 0.5), ux = std::floor((double)gx + hx - 0.5) + 1.0;
        const double ly = std::ceil((double)gy - hy - 0.5), uy = std::floor((double)gy + hy - 0.5) + 1.0;
        x0[k] = (int)std::max((double)px0, std::min((double)px1, lx));
        x1[k] = (int)std::max((double)px0, std::min((double)px1, ux));
        y0[k] = (int)std::max((double)py0, std::min((double)py1, ly));
        y1[k] = (int)std::max((double)py0, std::min((double)py1, uy));
        rk2a[k] = k2 * da;
        rdet[k] = det;
        ra[k] = da;
        rinv_a[k] = 1.0 / da;
      }
    }
  }
};

// Per-pixel state of one tile, row-major over the tile's in-image pixels (row stride tw).
template <typename scalar_t>
struct FwdState {
  scalar_t T[kMaxTile * kMaxTile], Cr[kMaxTile * kMaxTile], Cg[kMaxTile * kMaxTile],
      Cb[kMaxTile * kMaxTile], D[kMaxTile * kMaxTile];
  int32_t last[kMaxTile * kMaxTile], nc[kMaxTile * kMaxTile];
};

template <typename scalar_t>
struct BwdState {
  scalar_t T[kMaxTile * kMaxTile], Rr[kMaxTile * kMaxTile], Rg[kMaxTile * kMaxTile],
      Rb[kMaxTile * kMaxTile], Rd[kMaxTile * kMaxTile], gr[kMaxTile * kMaxTile],
      gg[kMaxTile * kMaxTile], gb[kMaxTile * kMaxTile], gd[kMaxTile * kMaxTile],
      gaT[kMaxTile * kMaxTile];
  int32_t last[kMaxTile * kMaxTile];
};

// Composites the K Gaussians of a tile; st is initialised by the caller (T = 1, last = K, ...).
// pair_w: (K, 2) per-pair (sum w, sum w^2) or nullptr.
template <typename scalar_t>
B3_INLINE void forward_tile_body(const TileCache<scalar_t>& tc, int64_t K, int px0, int py0, int tw,
                                 int npix, FwdState<scalar_t>& st, scalar_t* pair_w) {
  const scalar_t min_alpha = (scalar_t)kMinAlpha, max_alpha = (scalar_t)kMaxAlpha;
  const scalar_t min_T = (scalar_t)kMinT, half = (scalar_t)0.5, mhalf = (scalar_t)-0.5;
  const int32_t KK = (int32_t)K;
  scalar_t wbuf[kMaxTile];
  int ndone = 0;
  for (int64_t k = 0; k < K && ndone < npix; ++k) {
    const int by0 = tc.y0[k], by1 = tc.y1[k];
    if (tc.x0[k] >= tc.x1[k] || by0 >= by1) continue;
    const scalar_t gx = tc.x[k], gy = tc.y[k], ca = tc.a[k], cbv = tc.b[k], cc = tc.c[k];
    const scalar_t go = tc.o[k];
    const scalar_t r = tc.cr[k], g = tc.cg[k], bl = tc.cb[k], zz = tc.z[k];
    const int32_t kk = (int32_t)k;
    scalar_t wsum = 0, wsq = 0;
    for (int yy = by0; yy < by1; ++yy) {
      int xa, xb;
      tc.row_range(k, yy, xa, xb);
      const int n = xb - xa;
      if (n <= 0) continue;
      const scalar_t dy = gy - ((scalar_t)yy + half);
      const int off = (yy - py0) * tw + (xa - px0);
      scalar_t* __restrict__ Tp = st.T + off;
      scalar_t* __restrict__ Crp = st.Cr + off;
      scalar_t* __restrict__ Cgp = st.Cg + off;
      scalar_t* __restrict__ Cbp = st.Cb + off;
      scalar_t* __restrict__ Dp = st.D + off;
      int32_t* __restrict__ lp = st.last + off;
      int32_t* __restrict__ ncp = st.nc + off;
      const scalar_t x0c = (scalar_t)xa + half;
      if (pair_w)
        for (int i = 0; i < n; ++i) wbuf[i] = 0;
      int nd = 0;
      for (int i = 0; i < n; ++i) {
        if (lp[i] != KK) continue;  // pixel already terminated
        const scalar_t dx = gx - (x0c + (scalar_t)i);
        const scalar_t power = mhalf * (ca * dx * dx + cc * dy * dy) - cbv * dx * dy;
        if (power > 0) continue;
        const scalar_t alpha = std::min(max_alpha, go * exp_neg(power));
        if (alpha < min_alpha) {
          wbuf[i] = 0;
          continue;
        }
        const scalar_t t0 = Tp[i];
        const scalar_t test_T = t0 * (1 - alpha);
        if (test_T < min_T) {
          lp[i] = kk;
          ++nd;
          wbuf[i] = 0;
          continue;
        }
        const scalar_t w = alpha * t0;
        Crp[i] += w * r;
        Cgp[i] += w * g;
        Cbp[i] += w * bl;
        Dp[i] += w * zz;
        Tp[i] = test_T;
        ncp[i] += 1;
        wbuf[i] = w;
      }
      ndone += nd;
      if (pair_w) {
        for (int i = 0; i < n; ++i) {
          wsum += wbuf[i];
          wsq += wbuf[i] * wbuf[i];
        }
      }
    }
    if (pair_w) {
      pair_w[2 * k] = wsum;
      pair_w[2 * k + 1] = wsq;
    }
  }
}

// Reverse walk of a tile from list position kmax - 1 down to 0. pair_g: (kmax, 10) slots
// (mean x, mean y, conic a, b, c, opacity, colour r, g, b, depth).
template <typename scalar_t>
B3_INLINE void backward_tile_body(const TileCache<scalar_t>& tc, int64_t kmax, int px0, int py0,
                                  int tw, BwdState<scalar_t>& st, scalar_t* pair_g) {
  const scalar_t min_alpha = (scalar_t)kMinAlpha, max_alpha = (scalar_t)kMaxAlpha;
  const scalar_t half = (scalar_t)0.5, mhalf = (scalar_t)-0.5;
  for (int64_t k = kmax - 1; k >= 0; --k) {
    scalar_t acc[10] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0};
    const int by0 = tc.y0[k], by1 = tc.y1[k];
    if (tc.x0[k] < tc.x1[k] && by0 < by1) {
      const scalar_t gx = tc.x[k], gy = tc.y[k], ca = tc.a[k], cbv = tc.b[k], cc = tc.c[k];
      const scalar_t go = tc.o[k];
      const scalar_t r = tc.cr[k], g = tc.cg[k], bl = tc.cb[k], zz = tc.z[k];
      const int32_t kk = (int32_t)k;
      for (int yy = by0; yy < by1; ++yy) {
        int xa, xb;
        tc.row_range(k, yy, xa, xb);
        const int n = xb - xa;
        if (n <= 0) continue;
        const scalar_t dy = gy - ((scalar_t)yy + half);
        const int off = (yy - py0) * tw + (xa - px0);
        scalar_t* __restrict__ Tp = st.T + off;
        scalar_t* __restrict__ Rrp = st.Rr + off;
        scalar_t* __restrict__ Rgp = st.Rg + off;
        scalar_t* __restrict__ Rbp = st.Rb + off;
        scalar_t* __restrict__ Rdp = st.Rd + off;
        const scalar_t* __restrict__ grp = st.gr + off;
        const scalar_t* __restrict__ ggp = st.gg + off;
        const scalar_t* __restrict__ gbp = st.gb + off;
        const scalar_t* __restrict__ gdp = st.gd + off;
        const scalar_t* __restrict__ gap = st.gaT + off;
        const int32_t* __restrict__ lp = st.last + off;
        const scalar_t x0c = (scalar_t)xa + half;
        for (int i = 0; i < n; ++i) {
          if (kk >= lp[i]) continue;  // not composited (behind the termination point)
          const scalar_t dx = gx - (x0c + (scalar_t)i);
          const scalar_t power = mhalf * (ca * dx * dx + cc * dy * dy) - cbv * dx * dy;
          if (power > 0) continue;
          const scalar_t G = exp_neg(power);
          const scalar_t raw = go * G;
          const scalar_t alpha = std::min(max_alpha, raw);
          if (alpha < min_alpha) continue;
          const scalar_t one_m = 1 - alpha;
          const scalar_t inv_om = 1 / one_m;
          const scalar_t Ti = Tp[i] * inv_om;  // transmittance in front of this Gaussian
          const scalar_t w = alpha * Ti;
          const scalar_t gR = grp[i], gG = ggp[i], gB = gbp[i], gD = gdp[i];
          const scalar_t rr = Rrp[i], rg = Rgp[i], rb = Rbp[i], rd = Rdp[i];
          // d out / d alpha_i = T_i (c_i - R_i) for colour/depth (R: what lies behind, incl.
          // background), T_final / (1 - alpha_i) for alpha_out.
          const scalar_t dal =
              Ti * ((r - rr) * gR + (g - rg) * gG + (bl - rb) * gB + (zz - rd) * gD) + gap[i] * inv_om;
          Rrp[i] = alpha * r + one_m * rr;
          Rgp[i] = alpha * g + one_m * rg;
          Rbp[i] = alpha * bl + one_m * rb;
          Rdp[i] = alpha * zz + one_m * rd;
          Tp[i] = Ti;
          acc[6] += w * gR;
          acc[7] += w * gG;
          acc[8] += w * gB;
          acc[9] += w * gD;
          // True derivative of the 0.99 clamp: zero when clamped.
          if (raw <= max_alpha) {
            const scalar_t dpow = alpha * dal;
            acc[0] -= dpow * (ca * dx + cbv * dy);
            acc[1] -= dpow * (cbv * dx + cc * dy);
            acc[2] += dpow * (mhalf * dx * dx);
            acc[3] -= dpow * (dx * dy);
            acc[4] += dpow * (mhalf * dy * dy);
            acc[5] += G * dal;
          }
        }
      }
    }
    for (int j = 0; j < 10; ++j) pair_g[10 * k + j] = acc[j];
  }
}

// Instruction-set clones (identical arithmetic: no FMA contraction, -ffp-contract=off).
B3_CLONES void forward_tile(const TileCache<float>& tc, int64_t K, int px0, int py0, int tw, int npix,
                            FwdState<float>& st, float* pair_w) {
  forward_tile_body<float>(tc, K, px0, py0, tw, npix, st, pair_w);
}
B3_CLONES void forward_tile(const TileCache<double>& tc, int64_t K, int px0, int py0, int tw, int npix,
                            FwdState<double>& st, double* pair_w) {
  forward_tile_body<double>(tc, K, px0, py0, tw, npix, st, pair_w);
}
B3_CLONES void backward_tile(const TileCache<float>& tc, int64_t kmax, int px0, int py0, int tw,
                             BwdState<float>& st, float* pair_g) {
  backward_tile_body<float>(tc, kmax, px0, py0, tw, st, pair_g);
}
B3_CLONES void backward_tile(const TileCache<double>& tc, int64_t kmax, int px0, int py0, int tw,
                             BwdState<double>& st, double* pair_g) {
  backward_tile_body<double>(tc, kmax, px0, py0, tw, st, pair_g);
}

inline void tile_rect(const Geometry& G, int t, int& px0, int& px1, int& py0, int& py1) {
  const int tx = t % G.tiles_x, ty = t / G.tiles_x;
  px0 = tx * G.ts;
  py0 = ty * G.ts;
  px1 = std::min(px0 + G.ts, G.W);
  py1 = std::min(py0 + G.ts, G.H);
}

template <typename scalar_t>
void forward_impl(const Geometry& G, const scalar_t* means, const scalar_t* conics,
                  const scalar_t* colors, const scalar_t* opac, const scalar_t* depths,
                  const int64_t* offsets, const int64_t* ids, const scalar_t* bg, scalar_t* out_rgb,
                  scalar_t* out_depth, scalar_t* out_T, int32_t* out_last, int32_t* out_nc,
                  scalar_t* pair_w,  // (S, P, 2), zero-initialised, or nullptr
                  int nthreads) {
  const int num_tiles = G.tiles_x * G.tiles_y;
  const int64_t items = (int64_t)G.S * num_tiles;
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
      const int tw = px1 - px0, th = py1 - py0, npix = tw * th;
      const int64_t start = offsets[t], K = offsets[t + 1] - offsets[t];
      tc.gather(means, conics, colors, opac, depths, ids + start, K, G.N, s, px0, px1, py0, py1);
      for (int p = 0; p < npix; ++p) {
        st.T[p] = 1;
        st.Cr[p] = st.Cg[p] = st.Cb[p] = st.D[p] = 0;
        st.last[p] = (int32_t)K;
        st.nc[p] = 0;
      }
      forward_tile(tc, K, px0, py0, tw, npix, st,
                   pair_w ? pair_w + 2 * ((int64_t)s * G.P + start) : nullptr);
      for (int yy = py0; yy < py1; ++yy) {
        for (int xx = px0; xx < px1; ++xx) {
          const int p = (yy - py0) * tw + (xx - px0);
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
}

template <typename scalar_t>
void backward_impl(const Geometry& G, const scalar_t* means, const scalar_t* conics,
                   const scalar_t* colors, const scalar_t* opac, const scalar_t* depths,
                   const int64_t* offsets, const int64_t* ids, const scalar_t* bg,
                   const scalar_t* Tfin, const int32_t* lastbuf, const scalar_t* g_rgb,
                   const scalar_t* g_depth, const scalar_t* g_alpha,
                   scalar_t* pair_g,  // (S, P, 10)
                   int nthreads) {
  const int num_tiles = G.tiles_x * G.tiles_y;
  const int64_t items = (int64_t)G.S * num_tiles;
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
      const int tw = px1 - px0;
      const int64_t start = offsets[t], K = offsets[t + 1] - offsets[t];
      if (K == 0) continue;
      int64_t kmax = 0;
      for (int yy = py0; yy < py1; ++yy) {
        for (int xx = px0; xx < px1; ++xx) {
          const int p = (yy - py0) * tw + (xx - px0);
          const int64_t pix = ((int64_t)s * G.H + yy) * G.W + xx;
          st.T[p] = Tfin[pix];
          st.last[p] = lastbuf[pix];
          kmax = std::max<int64_t>(kmax, st.last[p]);
          st.Rr[p] = bg[0];
          st.Rg[p] = bg[1];
          st.Rb[p] = bg[2];
          st.Rd[p] = 0;
          st.gr[p] = g_rgb[3 * pix];
          st.gg[p] = g_rgb[3 * pix + 1];
          st.gb[p] = g_rgb[3 * pix + 2];
          st.gd[p] = g_depth[pix];
          // d alpha_out / d alpha_i = T_final / (1 - alpha_i); store g_alpha * T_final.
          st.gaT[p] = g_alpha[pix] * Tfin[pix];
        }
      }
      scalar_t* pg_tile = pair_g + 10 * ((int64_t)s * G.P + start);
      for (int64_t k = kmax; k < K; ++k)
        for (int j = 0; j < 10; ++j) pg_tile[10 * k + j] = 0;
      if (kmax == 0) continue;
      tc.gather(means, conics, colors, opac, depths, ids + start, kmax, G.N, s, px0, px1, py0, py1);
      backward_tile(tc, kmax, px0, py0, tw, st, pg_tile);
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
