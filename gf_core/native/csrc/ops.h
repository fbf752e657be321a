// The native ops, each with a CPU implementation (render_cpu.cpp, sph_cpu.cpp) and, when built
// with CUDA (WITH_CUDA), a CUDA one (render_cuda.cu, sph_cuda.cu). ext.cpp holds the one entry
// per op that checks devices and dtypes and dispatches (the shape of PyTorch3D's csrc).
#pragma once
#include <torch/extension.h>

#include <vector>

#include "gaussian_math.h"

namespace gf {

// Camera from a 4x4 world-to-camera matrix and [fx, fy, cx, cy] (any device; read on the host).
inline Cam make_cam(const torch::Tensor& viewmat, const torch::Tensor& intr, int64_t W, int64_t H, double near) {
  TORCH_CHECK(viewmat.numel() == 16 && intr.numel() == 4, "viewmat must be 4x4 and intr [fx, fy, cx, cy]");
  auto vm = viewmat.to(torch::kCPU, torch::kFloat64).contiguous();
  auto in = intr.to(torch::kCPU, torch::kFloat64).contiguous();
  const double* m = vm.data_ptr<double>();
  const double* k = in.data_ptr<double>();
  Cam c;
  for (int r = 0; r < 3; ++r) {
    for (int j = 0; j < 3; ++j) c.R[3 * r + j] = m[4 * r + j];
    c.t[r] = m[4 * r + 3];
  }
  for (int j = 0; j < 3; ++j) c.campos[j] = -(c.R[j] * c.t[0] + c.R[3 + j] * c.t[1] + c.R[6 + j] * c.t[2]);
  c.fx = k[0]; c.fy = k[1]; c.cx = k[2]; c.cy = k[3];
  c.width = (int)W; c.height = (int)H; c.near = near;
  return c;
}

#define GF_RENDER_OPS(SUFFIX)                                                                              \
  std::vector<torch::Tensor> project_forward_##SUFFIX(                                                    \
      torch::Tensor means, torch::Tensor scales, torch::Tensor quats, torch::Tensor opac, torch::Tensor sh, \
      torch::Tensor viewmat, torch::Tensor intr, int64_t W, int64_t H, double near, double min_alpha,      \
      int64_t degree);                                                                                     \
  std::vector<torch::Tensor> project_backward_##SUFFIX(                                                   \
      torch::Tensor means, torch::Tensor scales, torch::Tensor quats, torch::Tensor sh,                   \
      torch::Tensor viewmat, torch::Tensor intr, int64_t W, int64_t H, double near, int64_t degree,       \
      torch::Tensor radii, torch::Tensor g_means2d, torch::Tensor g_conics, torch::Tensor g_depths,        \
      torch::Tensor g_colors);                                                                             \
  std::vector<torch::Tensor> bin_gaussians_##SUFFIX(torch::Tensor means2d, torch::Tensor depths,         \
                                                    torch::Tensor radii, int64_t W, int64_t H, int64_t tile); \
  std::vector<torch::Tensor> rasterize_forward_##SUFFIX(                                                  \
      torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac, torch::Tensor feat, torch::Tensor bg, \
      torch::Tensor radii, torch::Tensor offsets, torch::Tensor ids, int64_t W, int64_t H, int64_t tile,  \
      double min_alpha);                                                                                   \
  std::vector<torch::Tensor> rasterize_backward_##SUFFIX(                                                 \
      torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac, torch::Tensor radii,                \
      torch::Tensor feat, torch::Tensor bg, torch::Tensor offsets, torch::Tensor ids, torch::Tensor T_final, \
      torch::Tensor n_contrib, torch::Tensor g_out, torch::Tensor g_T, int64_t W, int64_t H, int64_t tile, \
      double min_alpha);                                                                                   \
  std::vector<torch::Tensor> knn_##SUFFIX(torch::Tensor x, torch::Tensor y, int64_t k, double radius,      \
                                          bool exclude_self, bool sorted);                                 \
  std::vector<torch::Tensor> sph_density_forward_##SUFFIX(torch::Tensor x, torch::Tensor idx, double h);   \
  std::vector<torch::Tensor> sph_density_backward_##SUFFIX(torch::Tensor x, torch::Tensor idx, double h,   \
                                                           torch::Tensor gD);

GF_RENDER_OPS(cpu)

// The simulators' SPH engine (sim_cpu.cpp), CPU only: CUDA tensors use the solvers' torch path.
std::vector<torch::Tensor> grid_build_cpu(torch::Tensor y, double cell);
std::vector<torch::Tensor> radius_pairs_cpu(torch::Tensor x, torch::Tensor y, std::vector<torch::Tensor> grid,
                                            double radius, bool exclude_self);
std::vector<torch::Tensor> dfsph_neighbourhood_cpu(torch::Tensor x, torch::Tensor wall, torch::Tensor rowptr,
                                                   torch::Tensor col, torch::Tensor browptr, torch::Tensor bcol,
                                                   torch::Tensor wall_rho, torch::Tensor wall_count, double V,
                                                   double h, double wall_alpha_cap);
std::vector<torch::Tensor> dfsph_solve_cpu(torch::Tensor v, torch::Tensor kappa0, torch::Tensor rowptr,
                                           torch::Tensor col, torch::Tensor browptr, torch::Tensor bcol,
                                           std::vector<torch::Tensor> nb, int64_t mode, int64_t min_count, double dt,
                                           double scale, double tol, int64_t min_iters, int64_t max_iters);
std::vector<torch::Tensor> pbf_iteration_cpu(torch::Tensor x, torch::Tensor wall, torch::Tensor rowptr,
                                             torch::Tensor col, torch::Tensor browptr, torch::Tensor bcol, double V,
                                             double h, double eps, double scorr_k, double scorr_n, double w_dq,
                                             double grad2_lattice);
torch::Tensor viscosity_apply_cpu(torch::Tensor u, torch::Tensor x, torch::Tensor wall, torch::Tensor rowptr,
                                  torch::Tensor col, torch::Tensor browptr, torch::Tensor bcol, double V, double h,
                                  double nu_dt, bool no_slip, int64_t kernel);
torch::Tensor kernel_sum_cpu(torch::Tensor x, torch::Tensor y, std::vector<torch::Tensor> grid, double h,
                             int64_t kernel, bool exclude_self);
torch::Tensor csr_xsph_cpu(torch::Tensor v, torch::Tensor rowptr, torch::Tensor col, torch::Tensor w, double cV);
#ifdef WITH_CUDA
GF_RENDER_OPS(cuda)
#endif

}  // namespace gf
