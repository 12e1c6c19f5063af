// Tile rasterizer of 3D Gaussian splatting: torch bindings of the CPU kernels in kernels.h.
#include <torch/extension.h>

#include "kernels.h"

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
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "b3dgs_rasterize_forward", [&] {
    torch::Tensor pair_w;
    if (want_weights) pair_w = torch::zeros({G.S, G.P, 2}, opts);
    forward_impl<scalar_t>(G, means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                           colors.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(),
                           depths.data_ptr<scalar_t>(), offsets.data_ptr<int64_t>(),
                           ids.data_ptr<int64_t>(), bg.data_ptr<scalar_t>(),
                           rgb.data_ptr<scalar_t>(), depth.data_ptr<scalar_t>(),
                           T.data_ptr<scalar_t>(), last.data_ptr<int32_t>(), nc.data_ptr<int32_t>(),
                           want_weights ? pair_w.data_ptr<scalar_t>() : nullptr, (int)nthreads);
    if (want_weights) {
      auto red = torch::empty({G.S, G.N, 2}, opts);
      reduce_pairs<scalar_t>(pair_w.data_ptr<scalar_t>(), 2, ids.data_ptr<int64_t>(), G.P, G.S,
                             G.N, red.data_ptr<scalar_t>(), (int)nthreads);
      wsum = red.select(2, 0).contiguous();
      wsq = red.select(2, 1).contiguous();
    }
  });
  return {rgb, depth, T, last, nc, wsum, wsq};
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
                            g_rgb.data_ptr<scalar_t>(), g_depth.data_ptr<scalar_t>(),
                            g_alpha.data_ptr<scalar_t>(), pair_g.data_ptr<scalar_t>(),
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

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &rasterize_forward, "3DGS tile rasterizer forward (CPU)");
  m.def("backward", &rasterize_backward, "3DGS tile rasterizer backward (CPU)");
}
