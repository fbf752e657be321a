// The one native extension: an entry per op that checks its tensors (device, dtype, shape) with
// messages that name them, then dispatches to the CPU or the CUDA implementation (PyTorch3D's
// op.h shape). Built with CUDA only where nvcc and a CUDA torch exist (WITH_CUDA).
#include <torch/extension.h>

#include <string>
#include <vector>

#include "ops.h"

namespace {

using torch::Tensor;

// Every floating tensor of an op must share one dtype, float32 or float64, and one device.
void check_same(const std::vector<std::pair<const char*, const Tensor*>>& ts, const char* op) {
  const Tensor& first = *ts[0].second;
  auto dt = first.scalar_type();
  TORCH_CHECK(dt == torch::kFloat32 || dt == torch::kFloat64, op, ": ", ts[0].first, " is ",
              c10::toString(dt), "; the native backend takes float32 or float64 tensors");
  for (auto& [name, t] : ts) {
    TORCH_CHECK(t->scalar_type() == dt, op, ": ", name, " is ", c10::toString(t->scalar_type()), " but ",
                ts[0].first, " is ", c10::toString(dt), "; pass every tensor in one dtype");
    TORCH_CHECK(t->device() == first.device(), op, ": ", name, " is on ", t->device().str(), " but ", ts[0].first,
                " is on ", first.device().str());
  }
}

void check_int(const Tensor& t, const char* name, torch::ScalarType st, const Tensor& like, const char* op) {
  TORCH_CHECK(t.scalar_type() == st, op, ": ", name, " must be ", c10::toString(st), ", got ",
              c10::toString(t.scalar_type()));
  TORCH_CHECK(t.device() == like.device(), op, ": ", name, " is on ", t.device().str(), " but the data is on ",
              like.device().str());
}

#ifdef WITH_CUDA
#define GF_DISPATCH(OP, FIRST, ...)                                        \
  if ((FIRST).is_cuda()) return gf::OP##_cuda(__VA_ARGS__);                \
  TORCH_CHECK((FIRST).device().is_cpu(), #OP ": unsupported device ", (FIRST).device().str()); \
  return gf::OP##_cpu(__VA_ARGS__);
#else
#define GF_DISPATCH(OP, FIRST, ...)                                        \
  TORCH_CHECK(!(FIRST).is_cuda(), #OP ": this build of the native extension has no CUDA (built without nvcc or " \
              "a CUDA torch); use the reference backend for CUDA tensors"); \
  TORCH_CHECK((FIRST).device().is_cpu(), #OP ": unsupported device ", (FIRST).device().str()); \
  return gf::OP##_cpu(__VA_ARGS__);
#endif

std::vector<Tensor> project_forward(Tensor means, Tensor scales, Tensor quats, Tensor opac, Tensor sh,
                                    Tensor viewmat, Tensor intr, int64_t W, int64_t H, double near,
                                    double min_alpha, int64_t degree) {
  check_same({{"means", &means}, {"scales", &scales}, {"quats", &quats}, {"opacities", &opac}, {"sh", &sh}},
             "project_forward");
  TORCH_CHECK(gf::sh_count((int)degree) <= sh.size(1), "project_forward: sh has too few coefficients for degree ",
              degree);
  GF_DISPATCH(project_forward, means, means, scales, quats, opac, sh, viewmat, intr, W, H, near, min_alpha, degree)
}

std::vector<Tensor> project_backward(Tensor means, Tensor scales, Tensor quats, Tensor sh, Tensor viewmat,
                                     Tensor intr, int64_t W, int64_t H, double near, int64_t degree, Tensor radii,
                                     Tensor g_means2d, Tensor g_conics, Tensor g_depths, Tensor g_colors) {
  check_same({{"means", &means}, {"scales", &scales}, {"quats", &quats}, {"sh", &sh}, {"grad means2d", &g_means2d},
              {"grad conics", &g_conics}, {"grad depths", &g_depths}, {"grad colors", &g_colors}},
             "project_backward");
  check_int(radii, "radii", torch::kInt32, means, "project_backward");
  GF_DISPATCH(project_backward, means, means, scales, quats, sh, viewmat, intr, W, H, near, degree, radii,
              g_means2d, g_conics, g_depths, g_colors)
}

std::vector<Tensor> bin_gaussians(Tensor means2d, Tensor depths, Tensor radii, int64_t W, int64_t H, int64_t tile) {
  check_same({{"means2d", &means2d}, {"depths", &depths}}, "bin_gaussians");
  check_int(radii, "radii", torch::kInt32, means2d, "bin_gaussians");
  TORCH_CHECK(tile >= 1 && tile <= 32, "bin_gaussians: tile size must be in [1, 32], got ", tile);
  GF_DISPATCH(bin_gaussians, means2d, means2d, depths, radii, W, H, tile)
}

std::vector<Tensor> rasterize_forward(Tensor means2d, Tensor conics, Tensor opac, Tensor feat, Tensor bg,
                                      Tensor radii, Tensor offsets, Tensor ids, int64_t W, int64_t H, int64_t tile,
                                      double min_alpha) {
  check_same({{"means2d", &means2d}, {"conics", &conics}, {"opacities", &opac}, {"features", &feat},
              {"background", &bg}}, "rasterize_forward");
  check_int(radii, "radii", torch::kInt32, means2d, "rasterize_forward");
  check_int(offsets, "offsets", torch::kInt64, means2d, "rasterize_forward");
  check_int(ids, "ids", torch::kInt32, means2d, "rasterize_forward");
  TORCH_CHECK(bg.numel() == feat.size(1), "rasterize_forward: background has ", bg.numel(), " values for ",
              feat.size(1), " feature channels");
  GF_DISPATCH(rasterize_forward, means2d, means2d, conics, opac, feat, bg, radii, offsets, ids, W, H, tile, min_alpha)
}

std::vector<Tensor> rasterize_backward(Tensor means2d, Tensor conics, Tensor opac, Tensor radii, Tensor feat,
                                       Tensor bg, Tensor offsets, Tensor ids, Tensor T_final, Tensor n_contrib,
                                       Tensor g_out, Tensor g_T, int64_t W, int64_t H, int64_t tile, double min_alpha) {
  check_same({{"means2d", &means2d}, {"conics", &conics}, {"opacities", &opac}, {"features", &feat},
              {"background", &bg}, {"T_final", &T_final}, {"grad image", &g_out}, {"grad T", &g_T}},
             "rasterize_backward");
  GF_DISPATCH(rasterize_backward, means2d, means2d, conics, opac, radii, feat, bg, offsets, ids, T_final, n_contrib,
              g_out, g_T, W, H, tile, min_alpha)
}

std::vector<Tensor> knn(Tensor x, Tensor y, int64_t k, double radius, bool exclude_self, bool sorted) {
  check_same({{"x", &x}, {"y", &y}}, "knn");
  TORCH_CHECK(x.dim() == 2 && x.size(1) == 3 && y.dim() == 2 && y.size(1) == 3, "knn: x and y must be (N, 3)");
  TORCH_CHECK(k >= 0, "knn: k must be >= 0, got ", k);
  TORCH_CHECK(radius > 0 && std::isfinite(radius), "knn: radius must be positive and finite, got ", radius);
  GF_DISPATCH(knn, x, x, y, k, radius, exclude_self, sorted)
}

void check_density(const Tensor& x, const Tensor& idx, double h, const char* op) {
  TORCH_CHECK(x.dim() == 2 && x.size(1) == 3, op, ": x must be (N, 3)");
  TORCH_CHECK(idx.dim() == 2 && idx.size(0) == x.size(0), op, ": idx must be (N, K) with N = ", x.size(0));
  check_int(idx, "idx", torch::kInt64, x, op);
  TORCH_CHECK(h > 0 && std::isfinite(h), op, ": h must be positive and finite, got ", h);
}

std::vector<Tensor> sph_density_forward(Tensor x, Tensor idx, double h) {
  check_same({{"x", &x}}, "sph_density_forward");
  check_density(x, idx, h, "sph_density_forward");
  GF_DISPATCH(sph_density_forward, x, x, idx, h)
}

std::vector<Tensor> sph_density_backward(Tensor x, Tensor idx, double h, Tensor gD) {
  check_same({{"x", &x}, {"grad density", &gD}}, "sph_density_backward");
  check_density(x, idx, h, "sph_density_backward");
  GF_DISPATCH(sph_density_backward, x, x, idx, h, gD)
}

// ---- the simulators' SPH engine: CPU tensors only ------------------------------------------------
void check_cpu(const Tensor& t, const char* name, const char* op) {
  TORCH_CHECK(t.device().is_cpu(), op, ": ", name, " is on ", t.device().str(),
              "; the native SPH engine runs on CPU tensors (CUDA tensors use the solvers' torch path)");
}

void check_points(const Tensor& t, const char* name, const char* op) {
  check_cpu(t, name, op);
  TORCH_CHECK(t.dim() == 2 && t.size(1) == 3, op, ": ", name, " must be (N, 3), got ", t.sizes());
}

// exclude_self means "x is y": the queries are then the grid's own points (read in grid order)
void check_self(const Tensor& x, const Tensor& y, bool exclude_self, const char* op) {
  TORCH_CHECK(!exclude_self || (x.data_ptr() == y.data_ptr() && x.sizes() == y.sizes()), op,
              ": exclude_self needs x and y to be the same tensor (neighbours of a set among itself)");
}

void check_csr(const Tensor& rowptr, const Tensor& col, int64_t rows, const char* name, const char* op) {
  TORCH_CHECK(rowptr.scalar_type() == torch::kInt64 && col.scalar_type() == torch::kInt64, op, ": ", name,
              " must be int64");
  TORCH_CHECK(rowptr.is_contiguous() && col.is_contiguous() && rowptr.dim() == 1 && col.dim() == 1, op, ": ", name,
              " must be contiguous 1-D tensors");
  TORCH_CHECK(rowptr.size(0) == rows + 1, op, ": ", name, " has ", rowptr.size(0) - 1, " rows, expected ", rows);
}

std::vector<Tensor> grid_build(Tensor y, double cell) {
  check_same({{"y", &y}}, "grid_build");
  check_points(y, "y", "grid_build");
  TORCH_CHECK(cell > 0 && std::isfinite(cell), "grid_build: cell size must be positive and finite, got ", cell);
  return gf::grid_build_cpu(y, cell);
}

std::vector<Tensor> radius_pairs(Tensor x, Tensor y, std::vector<Tensor> grid, double radius, bool exclude_self) {
  check_same({{"x", &x}, {"y", &y}}, "radius_pairs");
  check_points(x, "x", "radius_pairs");
  check_points(y, "y", "radius_pairs");
  TORCH_CHECK(radius > 0 && std::isfinite(radius), "radius_pairs: radius must be positive and finite, got ", radius);
  check_self(x.contiguous(), y.contiguous(), exclude_self, "radius_pairs");
  return gf::radius_pairs_cpu(x, y, grid, radius, exclude_self);
}

std::vector<Tensor> dfsph_neighbourhood(Tensor x, Tensor wall, Tensor rowptr, Tensor col, Tensor browptr,
                                        Tensor bcol, Tensor wall_rho, Tensor wall_count, double V, double h,
                                        double wall_alpha_cap) {
  const char* op = "dfsph_neighbourhood";
  check_same({{"x", &x}, {"wall", &wall}, {"wall_rho", &wall_rho}}, op);
  check_points(x, "x", op);
  check_points(wall, "wall", op);
  check_csr(rowptr, col, x.size(0), "the fluid neighbour lists", op);
  check_csr(browptr, bcol, x.size(0), "the wall neighbour lists", op);
  TORCH_CHECK(wall_rho.numel() == wall.size(0) && wall_count.numel() == wall.size(0) &&
                  wall_count.scalar_type() == torch::kInt64 && wall_rho.is_contiguous() && wall_count.is_contiguous(),
              op, ": wall_rho and wall_count (int64) need one value per wall particle");
  return gf::dfsph_neighbourhood_cpu(x, wall, rowptr, col, browptr, bcol, wall_rho, wall_count, V, h, wall_alpha_cap);
}

std::vector<Tensor> dfsph_solve(Tensor v, Tensor kappa0, Tensor rowptr, Tensor col, Tensor browptr, Tensor bcol,
                                std::vector<Tensor> nb, int64_t mode, int64_t min_count, double dt, double scale,
                                double tol, int64_t min_iters, int64_t max_iters) {
  const char* op = "dfsph_solve";
  TORCH_CHECK(nb.size() == 10, op, ": nb must be what dfsph_neighbourhood returned");
  check_same({{"v", &v}, {"gw", &nb[1]}, {"gwb", &nb[3]}, {"rho_all", &nb[4]}, {"alpha", &nb[5]}}, op);
  check_points(v, "v", op);
  check_csr(rowptr, col, v.size(0), "the fluid neighbour lists", op);
  check_csr(browptr, bcol, v.size(0), "the wall neighbour lists", op);
  TORCH_CHECK(kappa0.numel() == nb[5].numel(), op, ": kappa has ", kappa0.numel(), " values for ", nb[5].numel(),
              " particles");
  TORCH_CHECK(mode == 0 || mode == 1, op, ": mode must be 0 (density) or 1 (divergence)");
  TORCH_CHECK(dt > 0 && scale > 0 && max_iters >= 1, op, ": dt, scale and max_iters must be positive");
  return gf::dfsph_solve_cpu(v, kappa0, rowptr, col, browptr, bcol, nb, mode, min_count, dt, scale, tol, min_iters,
                             max_iters);
}

std::vector<Tensor> pbf_iteration(Tensor x, Tensor wall, Tensor rowptr, Tensor col, Tensor browptr, Tensor bcol,
                                  double V, double h, double eps, double scorr_k, double scorr_n, double w_dq,
                                  double grad2_lattice) {
  const char* op = "pbf_iteration";
  check_same({{"x", &x}, {"wall", &wall}}, op);
  check_points(x, "x", op);
  check_points(wall, "wall", op);
  check_csr(rowptr, col, x.size(0), "the fluid neighbour lists", op);
  check_csr(browptr, bcol, x.size(0), "the wall neighbour lists", op);
  TORCH_CHECK(h > 0 && V > 0 && eps >= 0 && w_dq > 0 && grad2_lattice > 0, op, ": h, V, w_dq and grad2_lattice must be "
              "positive and eps >= 0");
  return gf::pbf_iteration_cpu(x, wall, rowptr, col, browptr, bcol, V, h, eps, scorr_k, scorr_n, w_dq, grad2_lattice);
}

Tensor viscosity_apply(Tensor u, Tensor x, Tensor wall, Tensor rowptr, Tensor col, Tensor browptr, Tensor bcol,
                       double V, double h, double nu_dt, bool no_slip, int64_t kernel) {
  const char* op = "viscosity_apply";
  check_same({{"u", &u}, {"x", &x}, {"wall", &wall}}, op);
  check_points(u, "u", op);
  check_points(x, "x", op);
  check_points(wall, "wall", op);
  TORCH_CHECK(u.size(0) == x.size(0), op, ": u and x need the same rows");
  check_csr(rowptr, col, x.size(0), "the fluid neighbour lists", op);
  check_csr(browptr, bcol, x.size(0), "the wall neighbour lists", op);
  TORCH_CHECK(kernel == 0 || kernel == 1, op, ": kernel must be 0 (cubic) or 1 (Wendland)");
  return gf::viscosity_apply_cpu(u, x, wall, rowptr, col, browptr, bcol, V, h, nu_dt, no_slip, kernel);
}

Tensor kernel_sum(Tensor x, Tensor y, std::vector<Tensor> grid, double h, int64_t kernel, bool exclude_self) {
  check_same({{"x", &x}, {"y", &y}}, "kernel_sum");
  check_points(x, "x", "kernel_sum");
  check_points(y, "y", "kernel_sum");
  TORCH_CHECK(h > 0 && std::isfinite(h), "kernel_sum: h must be positive and finite, got ", h);
  TORCH_CHECK(kernel >= 0 && kernel <= 2, "kernel_sum: kernel must be 0 (cubic), 1 (Wendland) or 2 (poly6)");
  check_self(x.contiguous(), y.contiguous(), exclude_self, "kernel_sum");
  return gf::kernel_sum_cpu(x, y, grid, h, kernel, exclude_self);
}

Tensor csr_xsph(Tensor v, Tensor rowptr, Tensor col, Tensor w, double cV) {
  check_same({{"v", &v}, {"w", &w}}, "csr_xsph");
  check_points(v, "v", "csr_xsph");
  check_csr(rowptr, col, v.size(0), "the neighbour lists", "csr_xsph");
  TORCH_CHECK(w.numel() == col.numel() && w.is_contiguous(), "csr_xsph: w needs one value per pair");
  return gf::csr_xsph_cpu(v, rowptr, col, w, cV);
}

std::vector<double> constants() {
  return {gf::kLowPass, gf::kAlphaMax, gf::kTransmittanceMin, gf::kFrustumSlack, gf::kShC0, gf::kShC1,
          gf::kShC2_0, gf::kShC2_1, gf::kShC2_2, gf::kShC2_3, gf::kShC2_4, gf::kShC3_0, gf::kShC3_1,
          gf::kShC3_2, gf::kShC3_3, gf::kShC3_4, gf::kShC3_5, gf::kShC3_6};
}

bool has_cuda() {
#ifdef WITH_CUDA
  return true;
#else
  return false;
#endif
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("project_forward", &project_forward, "per-Gaussian projection (forward)");
  m.def("project_backward", &project_backward, "per-Gaussian projection (backward)");
  m.def("bin_gaussians", &bin_gaussians, "tile/Gaussian pairs sorted by tile, then depth: (offsets, ids, number of invalid Gaussians)");
  m.def("rasterize_forward", &rasterize_forward, "front-to-back compositing (forward)");
  m.def("rasterize_backward", &rasterize_backward, "compositing (backward)");
  m.def("knn", &knn, "K nearest neighbours within a radius on a hashed grid: (idx, dist)");
  m.def("sph_density_forward", &sph_density_forward, "SPH density (Poly6, unit mass) over neighbour lists");
  m.def("sph_density_backward", &sph_density_backward, "gradient of the SPH density with respect to positions");
  m.def("grid_build", &grid_build, "hashed uniform grid over points (lo, cell, starts, order, cells), reusable");
  m.def("radius_pairs", &radius_pairs, "fixed-radius neighbours as CSR (rowptr, col), columns ascending per row");
  m.def("dfsph_neighbourhood", &dfsph_neighbourhood, "DFSPH pair kernels, densities and factors over CSR lists");
  m.def("dfsph_solve", &dfsph_solve, "DFSPH Jacobi solve (density or divergence) over CSR lists");
  m.def("pbf_iteration", &pbf_iteration, "one PBF constraint iteration over CSR lists: (dx, C)");
  m.def("viscosity_apply", &viscosity_apply, "(I - nu dt L) u, the implicit viscosity operator, over CSR lists");
  m.def("kernel_sum", &kernel_sum, "sum_j W(|x_i - y_j|, h) over neighbours within h (cubic, Wendland or poly6)");
  m.def("csr_xsph", &csr_xsph, "XSPH velocity smoothing over CSR lists");
  m.def("constants", &constants, "the renderer constants compiled into the extension");
  m.def("has_cuda", &has_cuda, "whether this build includes the CUDA ops");
}
