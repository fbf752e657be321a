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
  m.def("constants", &constants, "the renderer constants compiled into the extension");
  m.def("has_cuda", &has_cuda, "whether this build includes the CUDA ops");
}
