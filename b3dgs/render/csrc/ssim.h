// SSIM of two (H, W, 3) images and its gradient with respect to the first, in one pass (the
// training loss). Same definition as b3dgs.metrics.image.ssim_separable: an 11-tap Gaussian
// window (sigma 1.5) applied separably, 'valid' windows only, C1 = 0.01^2, C2 = 0.03^2, the map
// averaged over the (H-10) x (W-10) x 3 values.
//
//   ssim = A1 A2 / (B1 B2), A1 = 2 m1 m2 + C1, A2 = 2 (s12 - m1 m2) + C2,
//          B1 = m1^2 + m2^2 + C1, B2 = (s11 - m1^2) + (s22 - m2^2) + C2
//   d ssim / d m1 = 2 m2 (A2 - A1) / (B1 B2) - 2 m1 ssim (B2 - B1) / (B1 B2)
//   d ssim / d s11 = -ssim / B2, d ssim / d s12 = 2 A1 / (B1 B2)
//   d mean / d x = G^T [d m1] + 2 x G^T [d s11] + y G^T [d s12]   (G^T: the window scattered back)
//
// Parallel over planes (channels x maps); every sum has a fixed order, so the result is
// independent of the thread count.
#pragma once

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace b3dgs {

constexpr int kSsimWin = 11;

// Normalised 1-D Gaussian window (kornia's get_gaussian_kernel1d(11, 1.5)).
template <typename T>
inline void ssim_window(T* w) {
  double s = 0, v[kSsimWin];
  for (int k = 0; k < kSsimWin; ++k) {
    const double x = k - (kSsimWin - 1) / 2.0;
    v[k] = std::exp(-(x * x) / (2.0 * 1.5 * 1.5));
    s += v[k];
  }
  for (int k = 0; k < kSsimWin; ++k) w[k] = (T)(v[k] / s);
}

// Valid separable blur of an (H, W) plane into (H - 10, W - 10); tmp: (H, W - 10). The plane's row y is
// produced by row(y, buffer) (so that it can be formed on the fly from interleaved images).
template <typename T, typename RowFn>
inline void blur_valid(RowFn row, int H, int W, const T* __restrict__ w, T* __restrict__ rowbuf,
                       T* __restrict__ tmp, T* __restrict__ out) {
  const int Wv = W - kSsimWin + 1, Hv = H - kSsimWin + 1;
  for (int y = 0; y < H; ++y) {
    row(y, rowbuf);
    const T* __restrict__ r = rowbuf;
    T* __restrict__ o = tmp + (int64_t)y * Wv;
    // each output accumulated in a register, taps in ascending order from 0 (the sum order is fixed)
    for (int x = 0; x < Wv; ++x) {
      T acc = 0;
      for (int k = 0; k < kSsimWin; ++k) acc += w[k] * r[x + k];
      o[x] = acc;
    }
  }
  for (int y = 0; y < Hv; ++y) {
    T* __restrict__ o = out + (int64_t)y * Wv;
    const T* __restrict__ r = tmp + (int64_t)y * Wv;
    for (int x = 0; x < Wv; ++x) {
      T acc = 0;
      for (int k = 0; k < kSsimWin; ++k) acc += w[k] * r[(int64_t)k * Wv + x];
      o[x] = acc;
    }
  }
}

// Adjoint of blur_valid: scatters an (H - 10, W - 10) plane back to (H, W); tmp: (H, W - 10). Written as
// a gather (each output accumulated in a register) that adds the terms in the order of the scatter
// (input rows ascending, then taps ascending), so the sums are those of the plain scatter loops.
template <typename T>
inline void blur_valid_adjoint(const T* __restrict__ in, int H, int W, const T* __restrict__ w,
                               T* __restrict__ tmp, T* __restrict__ out) {
  const int Wv = W - kSsimWin + 1, Hv = H - kSsimWin + 1;
  for (int j = 0; j < H; ++j) {  // tmp row j gets input rows y = j - k, ascending (k descending)
    const int y0 = std::max(0, j - (kSsimWin - 1)), y1 = std::min(Hv - 1, j);
    T* __restrict__ o = tmp + (int64_t)j * Wv;
    for (int x = 0; x < Wv; ++x) o[x] = 0;
    for (int y = y0; y <= y1; ++y) {
      const T wk = w[j - y];
      const T* __restrict__ r = in + (int64_t)y * Wv;
      for (int x = 0; x < Wv; ++x) o[x] += wk * r[x];
    }
  }
  for (int y = 0; y < H; ++y) {  // out column X gets tmp columns X - k, k ascending
    const T* __restrict__ r = tmp + (int64_t)y * Wv;
    T* __restrict__ o = out + (int64_t)y * W;
    auto edge = [&](int X) {
      T acc = 0;
      for (int k = 0; k < kSsimWin; ++k)
        if (X - k >= 0 && X - k < Wv) acc += w[k] * r[X - k];
      o[X] = acc;
    };
    const int lo = std::min(kSsimWin - 1, W), hi = std::max(lo, Wv);  // interior: every tap in range
    for (int X = 0; X < lo; ++X) edge(X);
    for (int X = lo; X < hi; ++X) {
      T acc = 0;
      for (int k = 0; k < kSsimWin; ++k) acc += w[k] * r[X - k];
      o[X] = acc;
    }
    for (int X = hi; X < W; ++X) edge(X);
  }
}

// Returns mean SSIM; writes d mean / d pred into grad (H, W, 3) (nullptr: value only).
template <typename T>
T ssim_value_grad(const T* pred, const T* gt, int H, int W, T* grad, int nthreads) {
  const int Hv = H - kSsimWin + 1, Wv = W - kSsimWin + 1;
  const int64_t np = (int64_t)H * W, nv = (int64_t)Hv * Wv;
  T w[kSsimWin];
  ssim_window(w);
  // planes: for channel c, maps x, y, xx, yy, xy -> blurred m1, m2, s11, s22, s12
  // reused between calls (one image size per training run): no page faults on fresh buffers. The
  // buffers belong to the calling thread; OpenMP workers reach them through these pointers only.
  static thread_local std::vector<T> blur_buf, dmap_buf, back_buf;
  blur_buf.resize(15 * nv);
  dmap_buf.resize(grad ? 9 * nv : 0);
  back_buf.resize(grad ? 9 * np : 0);
  T *const blur = blur_buf.data();
  T *const dmap = dmap_buf.data(), *const back = back_buf.data();
#pragma omp parallel num_threads(nthreads)
  {
    std::vector<T> tmp((int64_t)H * Wv), rowbuf(W);
    // plane p = 5 c + m: map m of channel c (x, y, x x, y y, x y), formed row by row from the images
#pragma omp for schedule(dynamic, 1)
    for (int p = 0; p < 15; ++p) {
      const int c = p / 5, m = p % 5;
      auto row = [&](int y, T* r) {
        const T *a = pred + 3 * (int64_t)y * W + c, *b = gt + 3 * (int64_t)y * W + c;
        switch (m) {
          case 0: for (int x = 0; x < W; ++x) r[x] = a[3 * x]; break;
          case 1: for (int x = 0; x < W; ++x) r[x] = b[3 * x]; break;
          case 2: for (int x = 0; x < W; ++x) r[x] = a[3 * x] * a[3 * x]; break;
          case 3: for (int x = 0; x < W; ++x) r[x] = b[3 * x] * b[3 * x]; break;
          default: for (int x = 0; x < W; ++x) r[x] = a[3 * x] * b[3 * x]; break;
        }
      };
      blur_valid(row, H, W, w, rowbuf.data(), tmp.data(), blur + p * nv);
    }
  }
  const T C1 = (T)1e-4, C2 = (T)9e-4;
  // the gradient maps d m1, d s11, d s12 (scaled by 1 / count)
  const T inv = (T)1 / (T)(3 * nv);
  // per-row partial sums (rows of all channels in parallel), then summed in row order
  std::vector<double> row_sum(3 * (int64_t)Hv);
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int64_t cy = 0; cy < 3 * (int64_t)Hv; ++cy) {
    const int64_t c = cy / Hv, off = (cy % Hv) * Wv;
    const T *m1 = blur + (5 * c) * nv + off, *m2 = m1 + nv, *s11 = m1 + 2 * nv, *s22 = m1 + 3 * nv,
            *s12 = m1 + 4 * nv;
    double acc = 0;
    for (int64_t i = 0; i < Wv; ++i) {
      const T mm = m1[i] * m2[i], m1s = m1[i] * m1[i], m2s = m2[i] * m2[i];
      const T A1 = 2 * mm + C1, A2 = 2 * (s12[i] - mm) + C2;
      const T B1 = m1s + m2s + C1, B2 = (s11[i] - m1s) + (s22[i] - m2s) + C2;
      const T den = B1 * B2, val = (A1 * A2) / den;
      acc += (double)val;
      if (grad) {
        T* d = dmap + (3 * c) * nv + off;
        d[i] = inv * (2 * m2[i] * (A2 - A1) / den - 2 * m1[i] * val * (B2 - B1) / den);
        d[nv + i] = inv * (-val / B2);
        d[2 * nv + i] = inv * (2 * A1 / den);
      }
    }
    row_sum[cy] = acc;
  }
  double total = 0;
  for (double v : row_sum) total += v;
  if (grad) {
#pragma omp parallel num_threads(nthreads)
    {
      std::vector<T> tmp((int64_t)H * Wv);
#pragma omp for schedule(dynamic, 1)
      for (int p = 0; p < 9; ++p)
        blur_valid_adjoint(dmap + p * nv, H, W, w, tmp.data(), back + p * np);
    }
#pragma omp parallel for schedule(static) num_threads(nthreads)
    for (int64_t i = 0; i < np; ++i)
      for (int c = 0; c < 3; ++c) {
        const T *bm = back + (3 * c) * np, *b11 = bm + np, *b12 = bm + 2 * np;
        grad[3 * i + c] = bm[i] + 2 * pred[3 * i + c] * b11[i] + gt[3 * i + c] * b12[i];
      }
  }
  return (T)(total / (double)(3 * nv));
}

}  // namespace b3dgs
