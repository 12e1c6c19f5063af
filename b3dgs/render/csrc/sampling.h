// NIW posterior draws for native uncertainty (paper Eq. 4) in one pass, the C++ twin of
// draw_niw() + NIWBlock's covariance modes in b3dgs/posterior/niw.py and plugins/posterior/niw.py:
//
//   A lower-triangular, A_ii = sqrt(max(chi2(nu - i), floor)) (i = 0..2), A_ij ~ N(0, 1) (i > j)
//   X = A^{-1} L^T (L L^T = S_n), mu = m + X^T z / sqrt(kappa), z ~ N(0, I)
//   rendered covariance: X^T X (absolute) or Y^T Y with Y = sqrt(c) A^{-1} Lr^T (relative)
//
// Random numbers come from a counter-based generator keyed by (seed, sample, Gaussian), so a draw
// does not depend on the thread count or the order of work; normals by Box-Muller, gammas by
// Marsaglia-Tsang (with the U^(1/alpha) boost below alpha = 1). Float64 inside.
#pragma once

#include <omp.h>

#include <cmath>
#include <cstdint>

namespace b3dgs {

// SplitMix64 stream: a 64-bit state advanced by a Weyl step and finalised (Steele et al. 2014).
struct SplitMix64 {
  uint64_t s;
  explicit SplitMix64(uint64_t seed) : s(seed) {}
  inline uint64_t next() {
    uint64_t z = (s += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
  }
  // uniform in (0, 1): 53 random bits, never 0
  inline double uniform() { return ((double)(next() >> 11) + 0.5) * (1.0 / 9007199254740992.0); }
  inline double normal() {
    if (has_spare) {
      has_spare = false;
      return spare;
    }
    const double u1 = uniform(), u2 = uniform();
    const double r = std::sqrt(-2.0 * std::log(u1)), t = 6.283185307179586 * u2;
    spare = r * std::sin(t);
    has_spare = true;
    return r * std::cos(t);
  }
  inline double gamma(double alpha) {  // Gamma(alpha, 1), alpha > 0
    if (alpha < 1.0) return gamma(alpha + 1.0) * std::pow(uniform(), 1.0 / alpha);
    const double d = alpha - 1.0 / 3.0, c = 1.0 / std::sqrt(9.0 * d);
    for (;;) {
      double x, v;
      do {
        x = normal();
        v = 1.0 + c * x;
      } while (v <= 0.0);
      v = v * v * v;
      const double u = uniform();
      if (std::log(u) < 0.5 * x * x + d - d * v + d * std::log(v)) return d * v;
    }
  }
  double spare = 0;
  bool has_spare = false;
};

inline uint64_t mix_key(uint64_t seed, uint64_t a, uint64_t b) {
  SplitMix64 g(seed ^ (a * 0xD1B54A32D192ED03ull) ^ (b * 0xABC98388FB8FAC03ull));
  return g.next();
}

// x = A^{-1} b for lower-triangular A (3x3 row-major) and a column b.
inline void tril_solve3(const double* A, const double* b, double* x) {
  x[0] = b[0] / A[0];
  x[1] = (b[1] - A[3] * x[0]) / A[4];
  x[2] = (b[2] - A[6] * x[0] - A[7] * x[1]) / A[8];
}

// cov_mode: 0 none, 1 absolute, 2 relative. Outputs (S, K, 3) means and (S, K, 3, 3) covariances
// (nullptr for mode 0). Returns how many chi-square draws were floored.
template <typename T>
int64_t niw_draw(const double* m, const double* kappa, const double* nu, const double* L,
                 const double* LrT, const double* sqrt_c, int64_t K, int64_t S, int cov_mode,
                 double chi2_floor, uint64_t seed, T* means, T* covs, int nthreads) {
  int64_t floored = 0;
#pragma omp parallel for schedule(static) num_threads(nthreads) reduction(+ : floored)
  for (int64_t k = 0; k < K; ++k) {
    const double* Lk = L + 9 * k;
    const double LT[9] = {Lk[0], Lk[3], Lk[6], Lk[1], Lk[4], Lk[7], Lk[2], Lk[5], Lk[8]};
    const double isk = 1.0 / std::sqrt(kappa[k]);
    for (int64_t s = 0; s < S; ++s) {
      SplitMix64 g(mix_key(seed, (uint64_t)s, (uint64_t)k));
      double A[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
      for (int i = 0; i < 3; ++i) {
        double chi2 = 2.0 * g.gamma(0.5 * (nu[k] - i));
        if (!(chi2 >= chi2_floor)) {
          chi2 = chi2_floor;
          ++floored;
        }
        A[4 * i] = std::sqrt(chi2);
      }
      A[3] = g.normal();
      A[6] = g.normal();
      A[7] = g.normal();
      // X = A^{-1} L^T, column by column
      double X[9], col[3], xc[3];
      for (int j = 0; j < 3; ++j) {
        for (int i = 0; i < 3; ++i) col[i] = LT[3 * i + j];
        tril_solve3(A, col, xc);
        for (int i = 0; i < 3; ++i) X[3 * i + j] = xc[i];
      }
      const double z[3] = {g.normal(), g.normal(), g.normal()};
      T* mo = means + 3 * (s * K + k);
      for (int j = 0; j < 3; ++j)
        mo[j] = (T)(m[3 * k + j] + (X[j] * z[0] + X[3 + j] * z[1] + X[6 + j] * z[2]) * isk);
      if (cov_mode == 0) continue;
      double Y[9];
      if (cov_mode == 1) {
        for (int e = 0; e < 9; ++e) Y[e] = X[e];
      } else {
        const double* R = LrT + 9 * k;
        for (int j = 0; j < 3; ++j) {
          for (int i = 0; i < 3; ++i) col[i] = R[3 * i + j];
          tril_solve3(A, col, xc);
          for (int i = 0; i < 3; ++i) Y[3 * i + j] = xc[i] * sqrt_c[k];
        }
      }
      T* co = covs + 9 * (s * K + k);
      for (int i = 0; i < 3; ++i)
        for (int l = i; l < 3; ++l) {
          const double v = Y[i] * Y[l] + Y[3 + i] * Y[3 + l] + Y[6 + i] * Y[6 + l];  // (Y^T Y)_il
          co[3 * i + l] = (T)v;
          co[3 * l + i] = (T)v;
        }
    }
  }
  return floored;
}

}  // namespace b3dgs
