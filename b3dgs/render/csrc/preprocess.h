// Per-Gaussian preprocessing of 3D Gaussian splatting on the CPU: EWA projection, SH colour and
// opacity, fused into one pass with a hand-written backward; and the shared tile binning.
// Plain C++ + OpenMP (no torch headers). Semantics mirror the pure-PyTorch reference in
// b3dgs/render/projection.py and b3dgs/render/rasterize.py (bin_gaussians) line by line:
//
//   q = quat / max(|quat|, 1e-12); R = R(q); M = R diag(exp(log_scale)); Sigma = M M^T
//     (or Sigma given directly as 6 upper-triangular entries xx, xy, xz, yy, yz, zz)
//   p = Rv mean + t; valid = z > near; zs = valid ? z : 1
//   tx = zs clamp(x / zs, -(cx/fx + 0.15 W/fx), (W - cx)/fx + 0.15 W/fx), ty likewise (3DGS / gsplat)
//   J = [[fx/zs, 0, -fx tx/zs^2], [0, fy/zs, -fy ty/zs^2]]; cov2d = J Rv Sigma Rv^T J^T + 0.3 I
//   valid &= det > 0; conic = (c, -b, a) / det; means2d = (fx x/zs + cx, fy y/zs + cy); depth = z
//   radius = ceil(3 sqrt(lambda_max)) (lambda_max with the 3DGS floor 0.1), 0 if invalid/offscreen
//   colour = max(sum_b SH_b(normalize(mean - campos)) coeff_b + 0.5, 0); opacity = sigmoid(logit) [radius > 0]
//   extent (binning half-widths, px) = min(radius, sqrt(k2 * cov2d_ii)) with k2 = 2 ln(255 o) + 2e-3
//
// Every input may be shared by all S samples (leading dimension 1) or given per sample. The
// backward sums a shared input's gradient over the samples in order (deterministic); it is
// parallel over Gaussians only.
#pragma once

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <numeric>
#include <utility>
#include <vector>

namespace b3dgs {

constexpr double kSH_C0 = 0.28209479177387814;
constexpr double kSH_C1 = 0.4886025119029199;
constexpr double kSH_C2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                              -1.0925484305920792, 0.5462742152960396};
constexpr double kSH_C3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
                              0.3731763325901154,  -0.4570457994644658, 1.445305721320277,
                              -0.5900435899266435};
constexpr double kBlurPx = 0.3;
constexpr double kExtentSigma = 3.0;

// Camera: row-major 3x4 world-to-camera [Rv | t], intrinsics, image size, centre.
template <typename T>
struct CameraParams {
  T Rv[9], t[3], fx, fy, cx, cy, campos[3], near;
  int W, H;
};

// Leading-dimension stride of an input given for 1 or S samples.
struct SampleStride {
  int64_t means, quats, scales, cov6, opac, sh0, shN;
};

// Inputs of one call (pointers to contiguous tensors; rot mode: quats + log-scales, else cov6).
template <typename T>
struct PreInputs {
  const T *means, *quats, *scales, *cov6, *logits, *sh0, *shN;
  int64_t S, N, BN;  // BN: number of shN coefficients per Gaussian (bases - 1)
  int degree;        // SH degree used (0..3), already capped by the caller
  SampleStride ss;   // element strides between samples (0 for shared inputs)
};

template <typename T>
struct PreOutputs {
  T *means2d, *conics, *colors, *opac, *depths, *radii, *extent;
};

// Real SH basis values at unit direction d (B = (deg+1)^2 values), identical to sh_basis().
template <typename T>
inline void sh_basis_eval(int deg, T x, T y, T z, T* out) {
  out[0] = (T)kSH_C0;
  if (deg < 1) return;
  out[1] = -(T)kSH_C1 * y;
  out[2] = (T)kSH_C1 * z;
  out[3] = -(T)kSH_C1 * x;
  if (deg < 2) return;
  const T xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  out[4] = (T)kSH_C2[0] * xy;
  out[5] = (T)kSH_C2[1] * yz;
  out[6] = (T)kSH_C2[2] * (2 * zz - xx - yy);
  out[7] = (T)kSH_C2[3] * xz;
  out[8] = (T)kSH_C2[4] * (xx - yy);
  if (deg < 3) return;
  out[9] = (T)kSH_C3[0] * y * (3 * xx - yy);
  out[10] = (T)kSH_C3[1] * xy * z;
  out[11] = (T)kSH_C3[2] * y * (4 * zz - xx - yy);
  out[12] = (T)kSH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy);
  out[13] = (T)kSH_C3[4] * x * (4 * zz - xx - yy);
  out[14] = (T)kSH_C3[5] * z * (xx - yy);
  out[15] = (T)kSH_C3[6] * x * (xx - 3 * yy);
}

// Gradient of sum_b w_b SH_b(x, y, z) with respect to (x, y, z) (polynomial derivative).
template <typename T>
inline void sh_basis_grad(int deg, T x, T y, T z, const T* w, T* g) {
  g[0] = g[1] = g[2] = 0;
  if (deg < 1) return;
  const T C1 = (T)kSH_C1;
  g[0] += -C1 * w[3];
  g[1] += -C1 * w[1];
  g[2] += C1 * w[2];
  if (deg < 2) return;
  const T xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  g[0] += (T)kSH_C2[0] * y * w[4];
  g[1] += (T)kSH_C2[0] * x * w[4];
  g[1] += (T)kSH_C2[1] * z * w[5];
  g[2] += (T)kSH_C2[1] * y * w[5];
  g[0] += (T)kSH_C2[2] * (-2 * x) * w[6];
  g[1] += (T)kSH_C2[2] * (-2 * y) * w[6];
  g[2] += (T)kSH_C2[2] * (4 * z) * w[6];
  g[0] += (T)kSH_C2[3] * z * w[7];
  g[2] += (T)kSH_C2[3] * x * w[7];
  g[0] += (T)kSH_C2[4] * (2 * x) * w[8];
  g[1] += (T)kSH_C2[4] * (-2 * y) * w[8];
  if (deg < 3) return;
  g[0] += (T)kSH_C3[0] * (6 * xy) * w[9];
  g[1] += (T)kSH_C3[0] * (3 * xx - 3 * yy) * w[9];
  g[0] += (T)kSH_C3[1] * yz * w[10];
  g[1] += (T)kSH_C3[1] * xz * w[10];
  g[2] += (T)kSH_C3[1] * xy * w[10];
  g[0] += (T)kSH_C3[2] * (-2 * xy) * w[11];
  g[1] += (T)kSH_C3[2] * (4 * zz - xx - 3 * yy) * w[11];
  g[2] += (T)kSH_C3[2] * (8 * yz) * w[11];
  g[0] += (T)kSH_C3[3] * (-6 * xz) * w[12];
  g[1] += (T)kSH_C3[3] * (-6 * yz) * w[12];
  g[2] += (T)kSH_C3[3] * (6 * zz - 3 * xx - 3 * yy) * w[12];
  g[0] += (T)kSH_C3[4] * (4 * zz - 3 * xx - yy) * w[13];
  g[1] += (T)kSH_C3[4] * (-2 * xy) * w[13];
  g[2] += (T)kSH_C3[4] * (8 * xz) * w[13];
  g[0] += (T)kSH_C3[5] * (2 * xz) * w[14];
  g[1] += (T)kSH_C3[5] * (-2 * yz) * w[14];
  g[2] += (T)kSH_C3[5] * (xx - yy) * w[14];
  g[0] += (T)kSH_C3[6] * (3 * xx - 3 * yy) * w[15];
  g[1] += (T)kSH_C3[6] * (-6 * xy) * w[15];
}

template <typename T>
inline void quat_rotmat(const T* qin, T* q, T& inv_norm, T* R) {
  const T n = std::sqrt(qin[0] * qin[0] + qin[1] * qin[1] + qin[2] * qin[2] + qin[3] * qin[3]);
  const T d = std::max(n, (T)1e-12);
  inv_norm = (T)1 / d;
  for (int i = 0; i < 4; ++i) q[i] = qin[i] / d;
  const T w = q[0], x = q[1], y = q[2], z = q[3];
  R[0] = 1 - 2 * (y * y + z * z);
  R[1] = 2 * (x * y - w * z);
  R[2] = 2 * (x * z + w * y);
  R[3] = 2 * (x * y + w * z);
  R[4] = 1 - 2 * (x * x + z * z);
  R[5] = 2 * (y * z - w * x);
  R[6] = 2 * (x * z - w * y);
  R[7] = 2 * (y * z + w * x);
  R[8] = 1 - 2 * (x * x + y * y);
}

// Intermediate values of one (sample, Gaussian), shared by the forward and the backward.
template <typename T>
struct PreLocal {
  T mean[3], Sig[6];          // world mean, 3D covariance (xx, xy, xz, yy, yz, zz)
  T q[4], qinv, R[9], sc[3];  // rotation mode only
  T p[3], zs, u, v, tx, ty;   // camera-space point, clamp state
  bool valid, clx, cly;       // clx/cly: x/zs (y/zs) inside the clamp range
  T C[6];                     // camera-space covariance (00, 01, 02, 11, 12, 22)
  T ja, jb, jc, jd, a, b, c, det, dets;
  T dir[3], dnorm, dinv;      // view direction (normalised) and the norm of mean - campos
  T col_raw[3];
};

template <typename T>
inline void pre_local(const PreInputs<T>& in, const CameraParams<T>& cam, int64_t s, int64_t n,
                      bool rot_mode, PreLocal<T>& L) {
  const T* m = in.means + s * in.ss.means + 3 * n;
  for (int i = 0; i < 3; ++i) L.mean[i] = m[i];
  if (rot_mode) {
    quat_rotmat(in.quats + s * in.ss.quats + 4 * n, L.q, L.qinv, L.R);
    const T* ls = in.scales + s * in.ss.scales + 3 * n;
    for (int j = 0; j < 3; ++j) L.sc[j] = std::exp(ls[j]);
    T M[9];
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) M[3 * i + j] = L.R[3 * i + j] * L.sc[j];
    // Sigma_ik = sum_j M_ij M_kj
    const int idx[6][2] = {{0, 0}, {0, 1}, {0, 2}, {1, 1}, {1, 2}, {2, 2}};
    for (int e = 0; e < 6; ++e) {
      const int i = idx[e][0], k = idx[e][1];
      L.Sig[e] = M[3 * i] * M[3 * k] + M[3 * i + 1] * M[3 * k + 1] + M[3 * i + 2] * M[3 * k + 2];
    }
  } else {
    const T* cv = in.cov6 + s * in.ss.cov6 + 6 * n;
    for (int e = 0; e < 6; ++e) L.Sig[e] = cv[e];
  }
  const T* Rv = cam.Rv;
  for (int i = 0; i < 3; ++i)
    L.p[i] = L.mean[0] * Rv[3 * i] + L.mean[1] * Rv[3 * i + 1] + L.mean[2] * Rv[3 * i + 2] + cam.t[i];
  const T x = L.p[0], y = L.p[1], z = L.p[2];
  L.valid = z > cam.near;
  L.zs = L.valid ? z : (T)1;
  const T W = (T)cam.W, H = (T)cam.H;
  const T mx = (T)0.15 * W / cam.fx, my = (T)0.15 * H / cam.fy;  // 0.3 tan(fov/2), as 3DGS and gsplat
  const T lox = -(cam.cx / cam.fx + mx), hix = (W - cam.cx) / cam.fx + mx;
  const T loy = -(cam.cy / cam.fy + my), hiy = (H - cam.cy) / cam.fy + my;
  L.u = x / L.zs;
  L.v = y / L.zs;
  L.clx = L.u >= lox && L.u <= hix;
  L.cly = L.v >= loy && L.v <= hiy;
  L.tx = L.zs * std::min(std::max(L.u, lox), hix);
  L.ty = L.zs * std::min(std::max(L.v, loy), hiy);
  // C = Rv Sigma Rv^T (entries 00, 01, 02, 11, 12, 22)
  T S3[9] = {L.Sig[0], L.Sig[1], L.Sig[2], L.Sig[1], L.Sig[3], L.Sig[4], L.Sig[2], L.Sig[4], L.Sig[5]};
  T RS[9];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      RS[3 * i + j] = Rv[3 * i] * S3[j] + Rv[3 * i + 1] * S3[3 + j] + Rv[3 * i + 2] * S3[6 + j];
  const int idx[6][2] = {{0, 0}, {0, 1}, {0, 2}, {1, 1}, {1, 2}, {2, 2}};
  for (int e = 0; e < 6; ++e) {
    const int i = idx[e][0], l = idx[e][1];
    L.C[e] = RS[3 * i] * Rv[3 * l] + RS[3 * i + 1] * Rv[3 * l + 1] + RS[3 * i + 2] * Rv[3 * l + 2];
  }
  const T zs2 = L.zs * L.zs;
  L.ja = cam.fx / L.zs;
  L.jb = -cam.fx * L.tx / zs2;
  L.jc = cam.fy / L.zs;
  L.jd = -cam.fy * L.ty / zs2;
  const T c00 = L.C[0], c01 = L.C[1], c02 = L.C[2], c11 = L.C[3], c12 = L.C[4], c22 = L.C[5];
  L.a = L.ja * L.ja * c00 + 2 * L.ja * L.jb * c02 + L.jb * L.jb * c22 + (T)kBlurPx;
  L.b = L.ja * L.jc * c01 + L.ja * L.jd * c02 + L.jb * L.jc * c12 + L.jb * L.jd * c22;
  L.c = L.jc * L.jc * c11 + 2 * L.jc * L.jd * c12 + L.jd * L.jd * c22 + (T)kBlurPx;
  L.det = L.a * L.c - L.b * L.b;
  L.valid = L.valid && L.det > 0;
  L.dets = L.valid ? L.det : (T)1;
  // view direction for SH
  T d[3];
  for (int i = 0; i < 3; ++i) d[i] = L.mean[i] - cam.campos[i];
  L.dnorm = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
  L.dinv = (T)1 / std::max(L.dnorm, (T)1e-12);
  for (int i = 0; i < 3; ++i) L.dir[i] = d[i] * L.dinv;
}

// Raw SH colour (before + 0.5 and the clamp) of Gaussian n in sample s; fills basis (B values).
template <typename T>
inline void sh_color_raw(const PreInputs<T>& in, int64_t s, int64_t n, const T* dir, T* basis, T* raw) {
  const int64_t B = (int64_t)(in.degree + 1) * (in.degree + 1);
  const T* c0 = in.sh0 + s * in.ss.sh0 + 3 * n;
  const T* cN = in.shN + s * in.ss.shN + 3 * in.BN * n;
  sh_basis_eval(in.degree, dir[0], dir[1], dir[2], basis);
  for (int ch = 0; ch < 3; ++ch) {
    T acc = basis[0] * c0[ch];
    for (int64_t b = 1; b < B; ++b) acc += basis[b] * cN[3 * (b - 1) + ch];
    raw[ch] = acc;
  }
}

// Guard detection inside the forward pass (b3dgs.render.preprocess.guarded_params applies the guards):
// flags[0]: quaternion rows that are all zero (rendered with the identity rotation by the 1e-12 floor);
// flags[1]: quaternion rows whose largest |component| is outside [1e-15, 1e15] (need rescaling first);
// flags[2]: log-scales that may exceed the overflow cap log(max(z, near)) + log_cap (checked with a
// margin, so that every entry the exact test would clamp is flagged). Rows of an input shared by
// the samples are counted once.
constexpr double kQuatLo = 1e-15, kQuatHi = 1e15, kScaleCapMargin = 1e-3;

template <typename T>
void preprocess_forward(const PreInputs<T>& in, const CameraParams<T>& cam, bool rot_mode,
                        PreOutputs<T>& out, int nthreads, double log_cap, int64_t* flags) {
  const int64_t S = in.S, N = in.N;
  int64_t qzero = 0, qextreme = 0, sover = 0;
  const double cap_factor = std::exp(log_cap - kScaleCapMargin);
#pragma omp parallel for schedule(static) num_threads(nthreads) reduction(+ : qzero, qextreme, sover)
  for (int64_t n = 0; n < N; ++n) {
    PreLocal<T> L;
    T basis[16];
    for (int64_t s = 0; s < S; ++s) {
      if (rot_mode && (s == 0 || in.ss.quats != 0)) {
        const T* q = in.quats + s * in.ss.quats + 4 * n;
        const T amax = std::max(std::max(std::abs(q[0]), std::abs(q[1])), std::max(std::abs(q[2]), std::abs(q[3])));
        qzero += amax == 0 ? 1 : 0;
        qextreme += (amax != 0 && (amax < (T)kQuatLo || amax > (T)kQuatHi)) ? 1 : 0;
      }
      pre_local(in, cam, s, n, rot_mode, L);
      if (rot_mode) {  // exp(log_scale) > max(z, near) exp(log_cap - margin), with the scales pre_local took
        const double cap = std::max((double)L.p[2], (double)cam.near) * cap_factor;
        sover += ((double)L.sc[0] > cap || (double)L.sc[1] > cap || (double)L.sc[2] > cap) ? 1 : 0;
      }
      const int64_t o = s * N + n;
      const T W = (T)cam.W, H = (T)cam.H;
      const T m2x = cam.fx * L.p[0] / L.zs + cam.cx, m2y = cam.fy * L.p[1] / L.zs + cam.cy;
      out.means2d[2 * o] = m2x;
      out.means2d[2 * o + 1] = m2y;
      out.conics[3 * o] = L.c / L.dets;
      out.conics[3 * o + 1] = -L.b / L.dets;
      out.conics[3 * o + 2] = L.a / L.dets;
      out.depths[o] = L.p[2];
      const T mid = (T)0.5 * (L.a + L.c);
      const T lam = mid + std::sqrt(std::max(mid * mid - L.det, (T)0.1));
      T r = std::ceil((T)kExtentSigma * std::sqrt(lam));
      const bool onscreen = (m2x + r > 0) && (m2x - r < W) && (m2y + r > 0) && (m2y - r < H);
      if (!(L.valid && onscreen && std::isfinite(r))) r = 0;
      out.radii[o] = r;
      T raw[3];
      sh_color_raw(in, s, n, L.dir, basis, raw);
      for (int ch = 0; ch < 3; ++ch) {
        const T cr = raw[ch] + (T)0.5;
        out.colors[3 * o + ch] = cr > 0 ? cr : (T)0;
      }
      const T lg = in.logits[s * in.ss.opac + n];
      const T sig = (T)1 / ((T)1 + std::exp(-lg));
      const T op = r > 0 ? sig : (T)0;
      out.opac[o] = op;
      // binning half-extents: where alpha = o G can reach 1/255 (conservative), within the radius
      T ex = 0, ey = 0;
      if (r > 0 && op >= (T)(1.0 / 255.0)) {
        const double k2 = 2.0 * std::log(255.0 * (double)op) + 2e-3;
        ex = (T)std::min((double)r, std::sqrt(k2 * (double)L.a) * (1.0 + 1e-6) + 1e-3);
        ey = (T)std::min((double)r, std::sqrt(k2 * (double)L.c) * (1.0 + 1e-6) + 1e-3);
      }
      out.extent[2 * o] = ex;
      out.extent[2 * o + 1] = ey;
    }
  }
  flags[0] = qzero;
  flags[1] = qextreme;
  flags[2] = sover;
}

// Output gradients (S, N, ...) and input gradients (shaped like the inputs: 1 or S samples).
template <typename T>
struct PreGrads {
  const T *g_means2d, *g_conics, *g_colors, *g_opac, *g_depths;  // upstream
  T *means, *quats, *scales, *cov6, *logits, *sh0, *shN;         // accumulated (zeroed by caller)
};

template <typename T>
void preprocess_backward(const PreInputs<T>& in, const CameraParams<T>& cam, bool rot_mode,
                         const T* radii, PreGrads<T>& g, int nthreads) {
  const int64_t S = in.S, N = in.N, B = (int64_t)(in.degree + 1) * (in.degree + 1);
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int64_t n = 0; n < N; ++n) {
    PreLocal<T> L;
    T basis[16];
    for (int64_t s = 0; s < S; ++s) {
      const int64_t o = s * N + n;
      const T* gm = g.g_means2d + 2 * o;
      const T* gk = g.g_conics + 3 * o;
      const T* gcol = g.g_colors + 3 * o;
      const T gop = g.g_opac[o], gz = g.g_depths[o];
      if (gm[0] == 0 && gm[1] == 0 && gk[0] == 0 && gk[1] == 0 && gk[2] == 0 && gcol[0] == 0 &&
          gcol[1] == 0 && gcol[2] == 0 && gop == 0 && gz == 0)
        continue;  // exact: every term below is a product with one of these
      pre_local(in, cam, s, n, rot_mode, L);
      // --- opacity: o = sigmoid(logit) [r > 0]
      {
        const T lg = in.logits[s * in.ss.opac + n];
        const T sig = (T)1 / ((T)1 + std::exp(-lg));
        if (radii[o] > 0) g.logits[s * in.ss.opac + n] += gop * sig * ((T)1 - sig);
      }
      // --- colour
      T g_mean[3] = {0, 0, 0};
      {
        const T* cN = in.shN + s * in.ss.shN + 3 * in.BN * n;
        T* gc0 = g.sh0 + s * in.ss.sh0 + 3 * n;
        T* gcN = g.shN + s * in.ss.shN + 3 * in.BN * n;
        T raw[3], gr[3];
        sh_color_raw(in, s, n, L.dir, basis, raw);
        for (int ch = 0; ch < 3; ++ch) gr[ch] = (raw[ch] + (T)0.5) >= 0 ? gcol[ch] : (T)0;  // clamp_min: input >= 0
        for (int ch = 0; ch < 3; ++ch) gc0[ch] += basis[0] * gr[ch];
        for (int64_t b = 1; b < B; ++b)
          for (int ch = 0; ch < 3; ++ch) gcN[3 * (b - 1) + ch] += basis[b] * gr[ch];
        if (in.degree > 0) {
          T w[16];
          w[0] = 0;
          for (int64_t b = 1; b < B; ++b)
            w[b] = cN[3 * (b - 1)] * gr[0] + cN[3 * (b - 1) + 1] * gr[1] + cN[3 * (b - 1) + 2] * gr[2];
          T gd[3];
          sh_basis_grad(in.degree, L.dir[0], L.dir[1], L.dir[2], w, gd);
          // dir = d / max(|d|, eps)
          if (L.dnorm > (T)1e-12) {
            const T dot = gd[0] * L.dir[0] + gd[1] * L.dir[1] + gd[2] * L.dir[2];
            for (int i = 0; i < 3; ++i) g_mean[i] += (gd[i] - L.dir[i] * dot) * L.dinv;
          } else {
            for (int i = 0; i < 3; ++i) g_mean[i] += gd[i] * L.dinv;
          }
        }
      }
      // --- conics -> (a, b, c)
      const T D = L.dets;
      T ga = gk[2] / D, gb = -gk[1] / D, gc = gk[0] / D;
      if (L.valid) {
        const T gD = -(gk[0] * L.c - gk[1] * L.b + gk[2] * L.a) / (D * D);
        ga += gD * L.c;
        gc += gD * L.a;
        gb += -2 * L.b * gD;
      }
      const T c00 = L.C[0], c01 = L.C[1], c02 = L.C[2], c11 = L.C[3], c12 = L.C[4], c22 = L.C[5];
      const T ja = L.ja, jb = L.jb, jc = L.jc, jd = L.jd;
      // (a, b, c) -> J entries and camera covariance
      const T gja = ga * (2 * ja * c00 + 2 * jb * c02) + gb * (jc * c01 + jd * c02);
      const T gjb = ga * (2 * ja * c02 + 2 * jb * c22) + gb * (jc * c12 + jd * c22);
      const T gjc = gb * (ja * c01 + jb * c12) + gc * (2 * jc * c11 + 2 * jd * c12);
      const T gjd = gb * (ja * c02 + jb * c22) + gc * (2 * jc * c12 + 2 * jd * c22);
      // dC entries (upper triangle, as used)
      const T dC00 = ga * ja * ja, dC01 = gb * ja * jc;
      const T dC02 = ga * 2 * ja * jb + gb * ja * jd;
      const T dC11 = gc * jc * jc;
      const T dC12 = gb * jb * jc + gc * 2 * jc * jd;
      const T dC22 = ga * jb * jb + gb * jb * jd + gc * jd * jd;
      // J -> zs, tx, ty
      const T zs = L.zs, zs2 = zs * zs, zs3 = zs2 * zs;
      T gzs = -gja * cam.fx / zs2 + gjb * 2 * cam.fx * L.tx / zs3 - gjc * cam.fy / zs2 +
              gjd * 2 * cam.fy * L.ty / zs3;
      const T gtx = -gjb * cam.fx / zs2, gty = -gjd * cam.fy / zs2;
      T gp[3] = {0, 0, 0};
      // tx = zs * clamp(x / zs): inside the range d/dx = 1 (via u), d/dzs = clamp(u) - u = 0
      if (L.clx) {
        gp[0] += gtx;
      } else {
        gzs += gtx * (L.tx / zs);
      }
      if (L.cly) {
        gp[1] += gty;
      } else {
        gzs += gty * (L.ty / zs);
      }
      // means2d = (fx x/zs + cx, fy y/zs + cy)
      gp[0] += gm[0] * cam.fx / zs;
      gp[1] += gm[1] * cam.fy / zs;
      gzs += -(gm[0] * cam.fx * L.p[0] + gm[1] * cam.fy * L.p[1]) / zs2;
      // depth = z; zs = valid ? z : 1 (z > near only; det does not gate zs)
      gp[2] += gz;
      if (L.p[2] > cam.near) gp[2] += gzs;
      // p = Rv mean + t
      const T* Rv = cam.Rv;
      for (int j = 0; j < 3; ++j) g_mean[j] += Rv[j] * gp[0] + Rv[3 + j] * gp[1] + Rv[6 + j] * gp[2];
      T* gmo = g.means + s * in.ss.means + 3 * n;
      for (int j = 0; j < 3; ++j) gmo[j] += g_mean[j];
      // C = Rv Sigma Rv^T: G = dC + dC^T (symmetric), dSigma_sym = Rv^T G Rv
      const T G[9] = {2 * dC00, dC01, dC02, dC01, 2 * dC11, dC12, dC02, dC12, 2 * dC22};
      T GR[9], Gs[9];
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
          GR[3 * i + j] = G[3 * i] * Rv[j] + G[3 * i + 1] * Rv[3 + j] + G[3 * i + 2] * Rv[6 + j];
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
          Gs[3 * i + j] = Rv[i] * GR[j] + Rv[3 + i] * GR[3 + j] + Rv[6 + i] * GR[6 + j];
      // Gs = dSigma + dSigma^T for a symmetric Sigma
      if (rot_mode) {
        // Sigma = M M^T, M = R diag(sc): dM = Gs M
        T M[9], dM[9];
        for (int i = 0; i < 3; ++i)
          for (int j = 0; j < 3; ++j) M[3 * i + j] = L.R[3 * i + j] * L.sc[j];
        for (int i = 0; i < 3; ++i)
          for (int j = 0; j < 3; ++j)
            dM[3 * i + j] = Gs[3 * i] * M[j] + Gs[3 * i + 1] * M[3 + j] + Gs[3 * i + 2] * M[6 + j];
        T dR[9];
        T* gsc = g.scales + s * in.ss.scales + 3 * n;
        for (int j = 0; j < 3; ++j) {
          T dsc = 0;
          for (int i = 0; i < 3; ++i) {
            dR[3 * i + j] = dM[3 * i + j] * L.sc[j];
            dsc += dM[3 * i + j] * L.R[3 * i + j];
          }
          gsc[j] += dsc * L.sc[j];
        }
        const T w = L.q[0], x = L.q[1], y = L.q[2], z = L.q[3];
        T dq[4];
        dq[0] = 2 * (-z * dR[1] + y * dR[2] + z * dR[3] - x * dR[5] - y * dR[6] + x * dR[7]);
        dq[1] = 2 * (y * dR[1] + z * dR[2] + y * dR[3] - 2 * x * dR[4] - w * dR[5] + z * dR[6] +
                     w * dR[7] - 2 * x * dR[8]);
        dq[2] = 2 * (-2 * y * dR[0] + x * dR[1] + w * dR[2] + x * dR[3] + z * dR[5] - w * dR[6] +
                     z * dR[7] - 2 * y * dR[8]);
        dq[3] = 2 * (-2 * z * dR[0] - w * dR[1] + x * dR[2] + w * dR[3] - 2 * z * dR[4] + y * dR[5] +
                     x * dR[6] + y * dR[7]);
        T* gq = g.quats + s * in.ss.quats + 4 * n;
        const T* qin = in.quats + s * in.ss.quats + 4 * n;
        const T qn = std::sqrt(qin[0] * qin[0] + qin[1] * qin[1] + qin[2] * qin[2] + qin[3] * qin[3]);
        if (qn > (T)1e-12) {
          const T dot = dq[0] * L.q[0] + dq[1] * L.q[1] + dq[2] * L.q[2] + dq[3] * L.q[3];
          for (int i = 0; i < 4; ++i) gq[i] += (dq[i] - L.q[i] * dot) * L.qinv;
        } else {
          for (int i = 0; i < 4; ++i) gq[i] += dq[i] * L.qinv;
        }
      } else {
        // Sigma from 6 entries: diagonal entries appear once, off-diagonal twice
        T* gcv = g.cov6 + s * in.ss.cov6 + 6 * n;
        gcv[0] += (T)0.5 * Gs[0];
        gcv[1] += Gs[1];
        gcv[2] += Gs[2];
        gcv[3] += (T)0.5 * Gs[4];
        gcv[4] += Gs[5];
        gcv[5] += (T)0.5 * Gs[8];
      }
    }
  }
}

// Shared tile binning (see bin_gaussians in rasterize.py): Gaussian k goes to every tile that
// overlaps the union over samples with radius > 0 of [x - ex, x + ex] x [y - ey, y + ey], sorted
// by tile, then by mean depth over those samples, then by index. Returns P.
// Outputs: tile_offsets (num_tiles + 1); ids is (re)sized to P.
// Sort positions 0..M-1 by key ascending, ties in position order (a stable LSD radix sort on the keys'
// order-preserving 64-bit images, 8 bits a pass, passes where every key has the same byte skipped):
// the order of std::stable_sort with operator<, in O(M). Keys must not be NaN.
inline void stable_order_by_key(const std::vector<double>& key, std::vector<int64_t>& order) {
  const int64_t M = (int64_t)key.size();
  std::vector<uint64_t> bits(M), bits2(M);
  std::vector<int64_t> order2(M);
  for (int64_t i = 0; i < M; ++i) {
    const double k = key[i] + 0.0;  // -0 -> +0 (they compare equal)
    uint64_t u;
    std::memcpy(&u, &k, sizeof(u));
    bits[i] = (u >> 63) ? ~u : (u | (1ull << 63));  // monotone map of doubles to unsigned integers
  }
  order.resize(M);
  std::iota(order.begin(), order.end(), 0);
  for (int shift = 0; shift < 64; shift += 8) {
    int64_t cnt[257] = {0};
    for (int64_t i = 0; i < M; ++i) cnt[((bits[i] >> shift) & 0xff) + 1]++;
    bool trivial = false;
    for (int b = 1; b <= 256; ++b) trivial |= cnt[b] == M;
    if (trivial) continue;
    for (int b = 0; b < 256; ++b) cnt[b + 1] += cnt[b];
    for (int64_t i = 0; i < M; ++i) {
      const int64_t dst = cnt[(bits[i] >> shift) & 0xff]++;
      bits2[dst] = bits[i];
      order2[dst] = order[i];
    }
    bits.swap(bits2);
    order.swap(order2);
  }
}

template <typename T>
int64_t bin_tiles(const T* means2d, const T* radii, const T* extent, const T* depths, int64_t S,
                  int64_t N, int W, int H, int ts, int64_t* tile_offsets, std::vector<int64_t>& ids,
                  int nthreads) {
  const int tiles_x = (W + ts - 1) / ts, tiles_y = (H + ts - 1) / ts;
  const int64_t num_tiles = (int64_t)tiles_x * tiles_y;
  std::vector<int32_t> rect(4 * N);  // tx0, tx1, ty0, ty1
  std::vector<double> key(N);
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int64_t n = 0; n < N; ++n) {
    double xmin = INFINITY, xmax = -INFINITY, ymin = INFINITY, ymax = -INFINITY, dsum = 0;
    int64_t nv = 0;
    for (int64_t s = 0; s < S; ++s) {
      const int64_t o = s * N + n;
      const double x = means2d[2 * o], y = means2d[2 * o + 1], r = radii[o], d = depths[o];
      const double ex = extent[2 * o], ey = extent[2 * o + 1];
      if (!(r > 0) || !std::isfinite(r) || !std::isfinite(x) || !std::isfinite(y) || !std::isfinite(d))
        continue;
      ++nv;
      dsum += d;
      if (!(ex > 0 && ey > 0)) continue;  // visible but can never reach alpha 1/255 here
      xmin = std::min(xmin, x - ex);
      xmax = std::max(xmax, x + ex);
      ymin = std::min(ymin, y - ey);
      ymax = std::max(ymax, y + ey);
    }
    key[n] = nv > 0 ? dsum / (double)nv : 0.0;
    int32_t* rc = rect.data() + 4 * n;
    rc[0] = rc[1] = rc[2] = rc[3] = 0;
    if (nv == 0 || !(xmax >= xmin)) continue;
    rc[0] = (int32_t)std::min(std::max(std::floor(xmin / ts), 0.0), (double)tiles_x);
    rc[1] = (int32_t)std::min(std::max(std::ceil(xmax / ts), 0.0), (double)tiles_x);
    rc[2] = (int32_t)std::min(std::max(std::floor(ymin / ts), 0.0), (double)tiles_y);
    rc[3] = (int32_t)std::min(std::max(std::ceil(ymax / ts), 0.0), (double)tiles_y);
  }
  // depth order of the Gaussians that touch a tile (ties keep the index order), then a stable counting
  // sort by tile
  std::vector<int64_t> touch;
  std::vector<double> tkey;
  touch.reserve(N);
  tkey.reserve(N);
  std::vector<int64_t> cnt(num_tiles + 1, 0);
  for (int64_t n = 0; n < N; ++n) {
    const int32_t* rc = rect.data() + 4 * n;
    if (!(rc[0] < rc[1] && rc[2] < rc[3])) continue;
    touch.push_back(n);
    tkey.push_back(key[n]);
    for (int ty = rc[2]; ty < rc[3]; ++ty)
      for (int tx = rc[0]; tx < rc[1]; ++tx) cnt[(int64_t)ty * tiles_x + tx + 1]++;
  }
  for (int64_t t = 0; t < num_tiles; ++t) cnt[t + 1] += cnt[t];
  for (int64_t t = 0; t <= num_tiles; ++t) tile_offsets[t] = cnt[t];
  const int64_t P = cnt[num_tiles];
  ids.resize(P);
  std::vector<int64_t> order;
  stable_order_by_key(tkey, order);
  std::vector<int64_t> pos(cnt.begin(), cnt.end() - 1);
  for (size_t r = 0; r < order.size(); ++r) {
    const int64_t n = touch[order[r]];
    const int32_t* rc = rect.data() + 4 * n;
    for (int ty = rc[2]; ty < rc[3]; ++ty)
      for (int tx = rc[0]; tx < rc[1]; ++tx) ids[pos[(int64_t)ty * tiles_x + tx]++] = n;
  }
  return P;
}

}  // namespace b3dgs
