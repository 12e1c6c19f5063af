// Torch bindings of the CPU kernels: preprocessing and binning (preprocess.h), tile rasterizer
// (kernels.h), SSIM loss with its gradient (ssim.h), NIW posterior draws (sampling.h).
#include <torch/extension.h>

#include "kernels.h"
#include "preprocess.h"
#include "sampling.h"
#include "ssim.h"

namespace {

using b3dgs::Geometry;
using b3dgs::forward_impl;
using b3dgs::backward_impl;
using b3dgs::reduce_pairs;

void check_cpu_contig(const torch::Tensor& t, const char* name) {
  TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor");
  TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
}

Geometry make_geometry(const torch::Tensor& means2d, const torch::Tensor& ids, int64_t W, int64_t H,
                       int64_t ts, int64_t tiles_x, int64_t tiles_y) {
  Geometry G;
  G.S = (int)means2d.size(0);
  G.N = (int)means2d.size(1);
  G.W = (int)W;
  G.H = (int)H;
  G.ts = (int)ts;
  G.tiles_x = (int)tiles_x;
  G.tiles_y = (int)tiles_y;
  G.P = ids.numel();
  return G;
}

std::vector<torch::Tensor> rasterize_forward(torch::Tensor means2d, torch::Tensor conics,
                                             torch::Tensor colors, torch::Tensor opac,
                                             torch::Tensor depths, torch::Tensor offsets,
                                             torch::Tensor ids, torch::Tensor bg, int64_t W,
                                             int64_t H, int64_t ts, int64_t tiles_x,
                                             int64_t tiles_y, bool want_weights,
                                             int64_t nthreads) {
  for (auto& pr : {std::make_pair(&means2d, "means2d"), std::make_pair(&conics, "conics"),
                   std::make_pair(&colors, "colors"), std::make_pair(&opac, "opacities"),
                   std::make_pair(&depths, "depths"), std::make_pair(&offsets, "tile_offsets"),
                   std::make_pair(&ids, "flat_ids"), std::make_pair(&bg, "background")})
    check_cpu_contig(*pr.first, pr.second);
  TORCH_CHECK(offsets.scalar_type() == torch::kInt64 && ids.scalar_type() == torch::kInt64,
              "tile_offsets / flat_ids must be int64");
  TORCH_CHECK(ts >= 1 && ts <= b3dgs::kMaxTile, "tile_size must be in [1, ", b3dgs::kMaxTile, "]");
  const Geometry G = make_geometry(means2d, ids, W, H, ts, tiles_x, tiles_y);
  auto opts = means2d.options();
  auto rgb = torch::empty({G.S, G.H, G.W, 3}, opts);
  auto depth = torch::empty({G.S, G.H, G.W}, opts);
  auto T = torch::empty({G.S, G.H, G.W}, opts);
  auto last = torch::empty({G.S, G.H, G.W}, opts.dtype(torch::kInt32));
  auto nc = torch::empty({G.S, G.H, G.W}, opts.dtype(torch::kInt32));
  torch::Tensor wsum = torch::empty({0}, opts), wsq = torch::empty({0}, opts);
  // (non-finite input entries, out-of-range Gaussian ids): checked inside the kernel's own passes
  auto flags = torch::zeros({2}, opts.dtype(torch::kInt64));
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "b3dgs_rasterize_forward", [&] {
    torch::Tensor pair_w;
    if (want_weights) pair_w = torch::zeros({G.S, G.P, 2}, opts);
    const bool ok = forward_impl<scalar_t>(
        G, means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(), colors.data_ptr<scalar_t>(),
        opac.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(), offsets.data_ptr<int64_t>(),
        ids.data_ptr<int64_t>(), bg.data_ptr<scalar_t>(), rgb.data_ptr<scalar_t>(), depth.data_ptr<scalar_t>(),
        T.data_ptr<scalar_t>(), last.data_ptr<int32_t>(), nc.data_ptr<int32_t>(),
        want_weights ? pair_w.data_ptr<scalar_t>() : nullptr, (int)nthreads, flags.data_ptr<int64_t>());
    if (ok && want_weights) {
      auto red = torch::empty({G.S, G.N, 2}, opts);
      reduce_pairs<scalar_t>(pair_w.data_ptr<scalar_t>(), 2, ids.data_ptr<int64_t>(), G.P, G.S,
                             G.N, red.data_ptr<scalar_t>(), (int)nthreads);
      wsum = red.select(2, 0).contiguous();
      wsq = red.select(2, 1).contiguous();
    }
  });
  return {rgb, depth, T, last, nc, wsum, wsq, flags};
}

std::vector<torch::Tensor> rasterize_backward(
    torch::Tensor means2d, torch::Tensor conics, torch::Tensor colors, torch::Tensor opac,
    torch::Tensor depths, torch::Tensor offsets, torch::Tensor ids, torch::Tensor bg,
    torch::Tensor Tfin, torch::Tensor last, torch::Tensor g_rgb, torch::Tensor g_depth,
    torch::Tensor g_alpha, int64_t W, int64_t H, int64_t ts, int64_t tiles_x, int64_t tiles_y,
    int64_t nthreads) {
  for (auto& pr : {std::make_pair(&means2d, "means2d"), std::make_pair(&conics, "conics"),
                   std::make_pair(&colors, "colors"), std::make_pair(&opac, "opacities"),
                   std::make_pair(&depths, "depths"), std::make_pair(&offsets, "tile_offsets"),
                   std::make_pair(&ids, "flat_ids"), std::make_pair(&bg, "background"),
                   std::make_pair(&Tfin, "T"), std::make_pair(&last, "last"),
                   std::make_pair(&g_rgb, "grad_rgb"), std::make_pair(&g_depth, "grad_depth"),
                   std::make_pair(&g_alpha, "grad_alpha")})
    check_cpu_contig(*pr.first, pr.second);
  // an empty grad_depth / grad_alpha: that output has no gradient
  TORCH_CHECK(ts >= 1 && ts <= b3dgs::kMaxTile, "tile_size must be in [1, ", b3dgs::kMaxTile, "]");
  const Geometry G = make_geometry(means2d, ids, W, H, ts, tiles_x, tiles_y);
  auto opts = means2d.options();
  auto red = torch::empty({G.S, G.N, 10}, opts);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "b3dgs_rasterize_backward", [&] {
    auto pair_g = torch::empty({G.S, G.P, 10}, opts);
    backward_impl<scalar_t>(G, means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                            colors.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(),
                            depths.data_ptr<scalar_t>(), offsets.data_ptr<int64_t>(),
                            ids.data_ptr<int64_t>(), bg.data_ptr<scalar_t>(),
                            Tfin.data_ptr<scalar_t>(), last.data_ptr<int32_t>(),
                            g_rgb.data_ptr<scalar_t>(),
                            g_depth.numel() ? g_depth.data_ptr<scalar_t>() : nullptr,
                            g_alpha.numel() ? g_alpha.data_ptr<scalar_t>() : nullptr, pair_g.data_ptr<scalar_t>(),
                            (int)nthreads);
    reduce_pairs<scalar_t>(pair_g.data_ptr<scalar_t>(), 10, ids.data_ptr<int64_t>(), G.P, G.S, G.N,
                           red.data_ptr<scalar_t>(), (int)nthreads);
  });
  auto g_means = red.narrow(2, 0, 2).contiguous();
  auto g_conics = red.narrow(2, 2, 3).contiguous();
  auto g_opac = red.select(2, 5).contiguous();
  auto g_colors = red.narrow(2, 6, 3).contiguous();
  auto g_depths = red.select(2, 9).contiguous();
  return {g_means, g_conics, g_colors, g_opac, g_depths};
}


// ----------------------------------------------------------------------------------- preprocess
template <typename T>
b3dgs::CameraParams<T> make_camera(const std::vector<double>& viewmat, const std::vector<double>& intr,
                                   const std::vector<double>& campos, int64_t W, int64_t H, double near) {
  TORCH_CHECK(viewmat.size() == 12, "viewmat must have 12 entries (3x4 row-major)");
  TORCH_CHECK(intr.size() == 4, "intrinsics must be (fx, fy, cx, cy)");
  TORCH_CHECK(campos.size() == 3, "camera centre must have 3 entries");
  b3dgs::CameraParams<T> c;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) c.Rv[3 * i + j] = (T)viewmat[4 * i + j];
    c.t[i] = (T)viewmat[4 * i + 3];
    c.campos[i] = (T)campos[i];
  }
  c.fx = (T)intr[0];
  c.fy = (T)intr[1];
  c.cx = (T)intr[2];
  c.cy = (T)intr[3];
  c.near = (T)near;
  c.W = (int)W;
  c.H = (int)H;
  return c;
}

// Element stride between samples of an input with leading dimension 1 (shared) or S.
int64_t sample_stride(const torch::Tensor& t, int64_t S, const char* name) {
  if (t.numel() == 0) return 0;
  TORCH_CHECK(t.size(0) == 1 || t.size(0) == S, name, " must have a leading sample dimension of 1 or ", S);
  return t.size(0) == 1 ? 0 : t.stride(0);
}

template <typename T>
b3dgs::PreInputs<T> make_inputs(const torch::Tensor& means, const torch::Tensor& quats,
                                const torch::Tensor& scales, const torch::Tensor& cov6,
                                const torch::Tensor& logits, const torch::Tensor& sh0,
                                const torch::Tensor& shN, int64_t S, int64_t degree) {
  b3dgs::PreInputs<T> in;
  in.S = S;
  in.N = means.size(1);
  in.BN = shN.numel() == 0 ? 0 : shN.size(2);
  in.degree = (int)degree;
  TORCH_CHECK((degree + 1) * (degree + 1) <= in.BN + 1, "SH degree ", degree, " needs ",
              (degree + 1) * (degree + 1) - 1, " shN coefficients, got ", in.BN);
  in.means = means.data_ptr<T>();
  in.quats = quats.numel() ? quats.data_ptr<T>() : nullptr;
  in.scales = scales.numel() ? scales.data_ptr<T>() : nullptr;
  in.cov6 = cov6.numel() ? cov6.data_ptr<T>() : nullptr;
  in.logits = logits.data_ptr<T>();
  in.sh0 = sh0.data_ptr<T>();
  in.shN = shN.numel() ? shN.data_ptr<T>() : nullptr;
  in.ss.means = sample_stride(means, S, "means");
  in.ss.quats = sample_stride(quats, S, "quats");
  in.ss.scales = sample_stride(scales, S, "scales");
  in.ss.cov6 = sample_stride(cov6, S, "cov6");
  in.ss.opac = sample_stride(logits, S, "opacities");
  in.ss.sh0 = sample_stride(sh0, S, "sh0");
  in.ss.shN = sample_stride(shN, S, "shN");
  return in;
}

std::vector<torch::Tensor> preprocess_forward(torch::Tensor means, torch::Tensor quats,
                                              torch::Tensor scales, torch::Tensor cov6,
                                              torch::Tensor logits, torch::Tensor sh0,
                                              torch::Tensor shN, std::vector<double> viewmat,
                                              std::vector<double> intr, std::vector<double> campos,
                                              int64_t W, int64_t H, double near, int64_t degree,
                                              int64_t S, bool rot_mode, int64_t nthreads,
                                              double log_cap) {
  for (auto& pr : {std::make_pair(&means, "means"), std::make_pair(&quats, "quats"),
                   std::make_pair(&scales, "scales"), std::make_pair(&cov6, "cov6"),
                   std::make_pair(&logits, "opacities"), std::make_pair(&sh0, "sh0"),
                   std::make_pair(&shN, "shN")})
    check_cpu_contig(*pr.first, pr.second);
  const int64_t N = means.size(1);
  auto opts = means.options();
  auto means2d = torch::empty({S, N, 2}, opts), conics = torch::empty({S, N, 3}, opts);
  auto colors = torch::empty({S, N, 3}, opts), opac = torch::empty({S, N}, opts);
  auto depths = torch::empty({S, N}, opts), radii = torch::empty({S, N}, opts);
  auto extent = torch::empty({S, N, 2}, opts);
  auto flags = torch::zeros({3}, opts.dtype(torch::kInt64));  // guard detection (preprocess.h)
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "b3dgs_preprocess_forward", [&] {
    auto cam = make_camera<scalar_t>(viewmat, intr, campos, W, H, near);
    auto in = make_inputs<scalar_t>(means, quats, scales, cov6, logits, sh0, shN, S, degree);
    b3dgs::PreOutputs<scalar_t> out{means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                                    colors.data_ptr<scalar_t>(),  opac.data_ptr<scalar_t>(),
                                    depths.data_ptr<scalar_t>(),  radii.data_ptr<scalar_t>(),
                                    extent.data_ptr<scalar_t>()};
    b3dgs::preprocess_forward<scalar_t>(in, cam, rot_mode, out, (int)nthreads, log_cap,
                                        flags.data_ptr<int64_t>());
  });
  return {means2d, conics, colors, opac, depths, radii, extent, flags};
}

std::vector<torch::Tensor> preprocess_backward(
    torch::Tensor means, torch::Tensor quats, torch::Tensor scales, torch::Tensor cov6,
    torch::Tensor logits, torch::Tensor sh0, torch::Tensor shN, std::vector<double> viewmat,
    std::vector<double> intr, std::vector<double> campos, int64_t W, int64_t H, double near,
    int64_t degree, int64_t S, bool rot_mode, torch::Tensor radii, torch::Tensor g_means2d,
    torch::Tensor g_conics, torch::Tensor g_colors, torch::Tensor g_opac, torch::Tensor g_depths,
    int64_t nthreads) {
  for (auto& pr : {std::make_pair(&radii, "radii"), std::make_pair(&g_means2d, "grad_means2d"),
                   std::make_pair(&g_conics, "grad_conics"), std::make_pair(&g_colors, "grad_colors"),
                   std::make_pair(&g_opac, "grad_opacities"), std::make_pair(&g_depths, "grad_depths")})
    check_cpu_contig(*pr.first, pr.second);
  auto gm = torch::zeros_like(means), gq = torch::zeros_like(quats), gs = torch::zeros_like(scales);
  auto gc = torch::zeros_like(cov6), gl = torch::zeros_like(logits);
  auto g0 = torch::zeros_like(sh0), gN = torch::zeros_like(shN);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "b3dgs_preprocess_backward", [&] {
    auto cam = make_camera<scalar_t>(viewmat, intr, campos, W, H, near);
    auto in = make_inputs<scalar_t>(means, quats, scales, cov6, logits, sh0, shN, S, degree);
    b3dgs::PreGrads<scalar_t> g;
    g.g_means2d = g_means2d.data_ptr<scalar_t>();
    g.g_conics = g_conics.data_ptr<scalar_t>();
    g.g_colors = g_colors.data_ptr<scalar_t>();
    g.g_opac = g_opac.data_ptr<scalar_t>();
    g.g_depths = g_depths.data_ptr<scalar_t>();
    g.means = gm.data_ptr<scalar_t>();
    g.quats = gq.numel() ? gq.data_ptr<scalar_t>() : nullptr;
    g.scales = gs.numel() ? gs.data_ptr<scalar_t>() : nullptr;
    g.cov6 = gc.numel() ? gc.data_ptr<scalar_t>() : nullptr;
    g.logits = gl.data_ptr<scalar_t>();
    g.sh0 = g0.data_ptr<scalar_t>();
    g.shN = gN.numel() ? gN.data_ptr<scalar_t>() : nullptr;
    b3dgs::preprocess_backward<scalar_t>(in, cam, rot_mode, radii.data_ptr<scalar_t>(), g, (int)nthreads);
  });
  return {gm, gq, gs, gc, gl, g0, gN};
}

std::vector<torch::Tensor> bin_tiles(torch::Tensor means2d, torch::Tensor radii, torch::Tensor extent,
                                     torch::Tensor depths, int64_t W, int64_t H, int64_t ts, int64_t nthreads) {
  for (auto& pr : {std::make_pair(&means2d, "means2d"), std::make_pair(&radii, "radii"),
                   std::make_pair(&extent, "extent"), std::make_pair(&depths, "depths")})
    check_cpu_contig(*pr.first, pr.second);
  const int64_t S = means2d.size(0), N = means2d.size(1);
  const int64_t tiles = ((W + ts - 1) / ts) * ((H + ts - 1) / ts);
  auto offsets = torch::empty({tiles + 1}, torch::dtype(torch::kInt64));
  std::vector<int64_t> ids;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "b3dgs_bin_tiles", [&] {
    b3dgs::bin_tiles<scalar_t>(means2d.data_ptr<scalar_t>(), radii.data_ptr<scalar_t>(),
                               extent.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(), S, N,
                               (int)W, (int)H, (int)ts, offsets.data_ptr<int64_t>(), ids, (int)nthreads);
  });
  auto flat = torch::empty({(int64_t)ids.size()}, torch::dtype(torch::kInt64));
  if (!ids.empty()) std::memcpy(flat.data_ptr<int64_t>(), ids.data(), ids.size() * sizeof(int64_t));
  return {offsets, flat};
}

std::vector<torch::Tensor> ssim_value_grad(torch::Tensor pred, torch::Tensor gt, bool want_grad,
                                           int64_t nthreads) {
  check_cpu_contig(pred, "pred");
  check_cpu_contig(gt, "gt");
  TORCH_CHECK(pred.dim() == 3 && pred.size(2) == 3 && pred.sizes() == gt.sizes(),
              "ssim: expected two (H, W, 3) images of the same shape");
  TORCH_CHECK(pred.scalar_type() == gt.scalar_type(), "ssim: pred and gt must have the same dtype");
  const int H = (int)pred.size(0), W = (int)pred.size(1);
  TORCH_CHECK(H >= b3dgs::kSsimWin && W >= b3dgs::kSsimWin, "ssim: images must be at least 11x11");
  auto grad = want_grad ? torch::empty_like(pred) : torch::empty({0}, pred.options());
  auto value = torch::empty({}, pred.options());
  AT_DISPATCH_FLOATING_TYPES(pred.scalar_type(), "b3dgs_ssim", [&] {
    value.fill_(b3dgs::ssim_value_grad<scalar_t>(pred.data_ptr<scalar_t>(), gt.data_ptr<scalar_t>(), H, W,
                                                 want_grad ? grad.data_ptr<scalar_t>() : nullptr,
                                                 (int)nthreads));
  });
  return {value, grad};
}

std::vector<torch::Tensor> niw_draw(torch::Tensor m, torch::Tensor kappa, torch::Tensor nu, torch::Tensor L,
                                    torch::Tensor LrT, torch::Tensor sqrt_c, int64_t S, int64_t cov_mode,
                                    double chi2_floor, int64_t seed, bool out_double, int64_t nthreads) {
  for (auto& pr : {std::make_pair(&m, "m_n"), std::make_pair(&kappa, "kappa_n"), std::make_pair(&nu, "nu_n"),
                   std::make_pair(&L, "L"), std::make_pair(&LrT, "LrT"), std::make_pair(&sqrt_c, "sqrt_c")}) {
    check_cpu_contig(*pr.first, pr.second);
    TORCH_CHECK(pr.first->scalar_type() == torch::kFloat64, pr.second, " must be float64");
  }
  const int64_t K = m.size(0);
  TORCH_CHECK(m.dim() == 2 && m.size(1) == 3 && L.numel() == 9 * K, "niw_draw: expected m (K, 3), L (K, 3, 3)");
  TORCH_CHECK(cov_mode >= 0 && cov_mode <= 2, "niw_draw: cov_mode must be 0 (none), 1 (absolute) or 2 (relative)");
  TORCH_CHECK(cov_mode != 2 || (LrT.numel() == 9 * K && sqrt_c.numel() == K), "niw_draw: relative mode needs LrT, sqrt_c");
  auto opts = torch::dtype(out_double ? torch::kFloat64 : torch::kFloat32);
  auto means = torch::empty({S, K, 3}, opts);
  auto covs = cov_mode ? torch::empty({S, K, 3, 3}, opts) : torch::empty({0}, opts);
  int64_t floored = 0;
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "b3dgs_niw_draw", [&] {
    floored = b3dgs::niw_draw<scalar_t>(
        m.data_ptr<double>(), kappa.data_ptr<double>(), nu.data_ptr<double>(), L.data_ptr<double>(),
        cov_mode == 2 ? LrT.data_ptr<double>() : nullptr, cov_mode == 2 ? sqrt_c.data_ptr<double>() : nullptr,
        K, S, (int)cov_mode, chi2_floor, (uint64_t)seed, means.data_ptr<scalar_t>(),
        cov_mode ? covs.data_ptr<scalar_t>() : nullptr, (int)nthreads);
  });
  return {means, covs, torch::tensor(floored)};
}

// The lane-occupancy counters (bench/lanes.py) since the last reset, or an empty list when the extension was built
// without -DB3_LANE_STATS (the default).
std::vector<int64_t> lane_stats(bool reset) {
#ifdef B3_LANE_STATS
  std::vector<int64_t> out(b3dgs::g_lane_stats, b3dgs::g_lane_stats + b3dgs::kLaneStats);
  if (reset)
    for (auto& v : b3dgs::g_lane_stats) v = 0;
  return out;
#else
  (void)reset;
  return {};
#endif
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("lane_stats", &lane_stats, "lane-occupancy counters of an instrumented build (empty otherwise)");
  m.def("forward", &rasterize_forward, "3DGS tile rasterizer forward (CPU)");
  m.def("backward", &rasterize_backward, "3DGS tile rasterizer backward (CPU)");
  m.def("preprocess_forward", &preprocess_forward, "projection + SH + opacity (CPU)");
  m.def("preprocess_backward", &preprocess_backward, "backward of preprocess_forward (CPU)");
  m.def("bin_tiles", &bin_tiles, "shared tile binning (CPU)");
  m.def("ssim_value_grad", &ssim_value_grad, "mean SSIM and its gradient w.r.t. pred (CPU)");
  m.def("niw_draw", &niw_draw, "NIW posterior draws: means and rendered covariances (CPU)");
}
