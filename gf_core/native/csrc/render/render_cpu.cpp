// CPU backend of the splatting renderer: OpenMP over Gaussians (projection) and over tiles
// (rasterisation), hand-written forward and backward. Math in gaussian_math.h; the device
// dispatch and the Python bindings are in ext.cpp, the CUDA twin in render_cuda.cu.
#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <numeric>
#include <vector>

#include "gaussian_math.h"
#include "parallel.h"
#include "ops.h"

namespace {

using gf::Cam;
using gf::num_threads;
using gf::Proj;
using gf::thread_id;

// ================================ projection ======================================================
template <typename S>
void project_fwd_impl(const Cam& cam, int64_t N, int K, int Cc, int degree, double min_alpha,
                      const S* means, const S* scales, const S* quats, const S* opac, const S* sh,
                      S* means2d, S* conics, S* depths, S* colors, int32_t* radii) {
#pragma omp parallel for schedule(static)
  for (int64_t i = 0; i < N; ++i) {
    double p[3], s[3], q[4];
    for (int j = 0; j < 3; ++j) { p[j] = means[3 * i + j]; s[j] = scales[3 * i + j]; }
    for (int j = 0; j < 4; ++j) q[j] = quats[4 * i + j];
    Proj P;
    int r = 0;
    bool valid = gf::inputs_valid(p, s, q, (double)opac[i]);
    for (int k = 0; valid && k < K * Cc; ++k) valid = std::isfinite((double)sh[(int64_t)i * K * Cc + k]);
    if (valid && gf::project_core(cam, p, s, q, P)) r = gf::splat_radius(P, (double)opac[i], min_alpha, cam.width, cam.height);
    radii[i] = valid ? r : -1;
    if (r <= 0 || !valid) {
      means2d[2 * i] = means2d[2 * i + 1] = 0;
      conics[3 * i] = conics[3 * i + 1] = conics[3 * i + 2] = 0;
      depths[i] = 0;
      for (int c = 0; c < Cc; ++c) colors[Cc * i + c] = 0;
      continue;
    }
    means2d[2 * i] = (S)P.u; means2d[2 * i + 1] = (S)P.v;
    conics[3 * i] = (S)(P.c / P.det); conics[3 * i + 1] = (S)(-P.b / P.det); conics[3 * i + 2] = (S)(P.a / P.det);
    depths[i] = (S)P.t[2];
    double Y[16];
    gf::sh_basis(degree, P.dir, Y);
    int nb = gf::sh_count(degree);
    for (int c = 0; c < Cc; ++c) {
      double acc = 0.5;
      for (int k = 0; k < nb; ++k) acc += Y[k] * (double)sh[((int64_t)i * K + k) * Cc + c];
      colors[Cc * i + c] = (S)(acc > 0 ? acc : 0);
    }
  }
}

template <typename S>
void project_bwd_impl(const Cam& cam, int64_t N, int K, int Cc, int degree,
                      const S* means, const S* scales, const S* quats, const S* sh, const int32_t* radii,
                      const S* g_means2d, const S* g_conics, const S* g_depths, const S* g_colors,
                      S* g_means, S* g_scales, S* g_quats, S* g_sh) {
#pragma omp parallel for schedule(static)
  for (int64_t i = 0; i < N; ++i) {
    if (radii[i] <= 0) continue;  // outputs were constant zeros: no gradient (buffers are zeroed)
    double p[3], s[3], q[4];
    for (int j = 0; j < 3; ++j) { p[j] = means[3 * i + j]; s[j] = scales[3 * i + j]; }
    for (int j = 0; j < 4; ++j) q[j] = quats[4 * i + j];
    Proj P;
    gf::project_core(cam, p, s, q, P);
    // colour = max(SH . Y + 0.5, 0): dL/dsh_kc = Y_k g_c ; dL/dY_k = sum_c sh_kc g_c
    int nb = gf::sh_count(degree);
    double Y[16];
    gf::sh_basis(degree, P.dir, Y);
    double gY[16] = {0};
    for (int c = 0; c < Cc; ++c) {
      double acc = 0.5;
      for (int k = 0; k < nb; ++k) acc += Y[k] * (double)sh[((int64_t)i * K + k) * Cc + c];
      double g = acc >= 0 ? (double)g_colors[Cc * i + c] : 0.0;
      for (int k = 0; k < nb; ++k) {
        g_sh[((int64_t)i * K + k) * Cc + c] = (S)(Y[k] * g);
        gY[k] += (double)sh[((int64_t)i * K + k) * Cc + c] * g;
      }
    }
    double guv[2] = {(double)g_means2d[2 * i], (double)g_means2d[2 * i + 1]};
    double gcon[3] = {(double)g_conics[3 * i], (double)g_conics[3 * i + 1], (double)g_conics[3 * i + 2]};
    double gp[3], gs[3], gq[4];
    gf::project_core_vjp(cam, s, P, guv, gcon, (double)g_depths[i], gY, degree, gp, gs, gq);
    for (int j = 0; j < 3; ++j) { g_means[3 * i + j] = (S)gp[j]; g_scales[3 * i + j] = (S)gs[j]; }
    for (int j = 0; j < 4; ++j) g_quats[4 * i + j] = (S)gq[j];
  }
}

// ================================ binning =========================================================
// Tile/Gaussian pairs sorted by tile, then by depth (stable): offsets (tiles+1), ids (pairs).
template <typename S>
void bin_impl(int64_t N, const S* means2d, const S* depths, const int32_t* radii, int W, int H, int tile,
              std::vector<int64_t>& offsets, std::vector<int32_t>& ids) {
  int tiles_x = (W + tile - 1) / tile, tiles_y = (H + tile - 1) / tile;
  int n_tiles = tiles_x * tiles_y;
  std::vector<int32_t> vis;
  vis.reserve(N);
  for (int64_t i = 0; i < N; ++i)
    if (radii[i] > 0) vis.push_back((int32_t)i);
  std::stable_sort(vis.begin(), vis.end(), [&](int32_t a, int32_t b) { return depths[a] < depths[b]; });
  std::vector<int32_t> rects(vis.size() * 4);
  offsets.assign(n_tiles + 1, 0);
  for (size_t k = 0; k < vis.size(); ++k) {
    int32_t i = vis[k];
    int* r = &rects[4 * k];
    if (!gf::tile_rect((double)means2d[2 * i], (double)means2d[2 * i + 1], radii[i], tile, tiles_x, tiles_y, r)) {
      r[0] = 1; r[2] = 0;  // empty
      continue;
    }
    for (int ty = r[1]; ty <= r[3]; ++ty)
      for (int tx = r[0]; tx <= r[2]; ++tx) offsets[ty * tiles_x + tx + 1]++;
  }
  for (int t = 0; t < n_tiles; ++t) offsets[t + 1] += offsets[t];
  ids.resize(offsets[n_tiles]);
  std::vector<int64_t> fill(offsets.begin(), offsets.end() - 1);
  for (size_t k = 0; k < vis.size(); ++k) {  // depth order is kept within each tile
    const int* r = &rects[4 * k];
    for (int ty = r[1]; ty <= r[3]; ++ty)
      for (int tx = r[0]; tx <= r[2]; ++tx) ids[fill[ty * tiles_x + tx]++] = vis[k];
  }
}

// ================================ rasterisation ===================================================
template <typename S>
struct Splat {
  S u, v, A, B, C, o;
  S log_cut;           // log(min_alpha / o) - 1e-3: a power below this cannot reach min_alpha
  int x0, x1, y0, y1;  // pixel box of the splat radius: outside it alpha < min_alpha anyway
};

constexpr int kMaxTile = 64;

// A tile's splats in depth order, with their pixel boxes (pixel j has its centre at j + 0.5).
template <typename S>
void load_tile(int64_t beg, int n, const int32_t* ids, const S* means2d, const S* conics, const S* opac,
               const int32_t* radii, double min_alpha, std::vector<Splat<S>>& sp) {
  sp.resize(n);
  for (int k = 0; k < n; ++k) {
    int32_t g = ids[beg + k];
    double u = (double)means2d[2 * g], v = (double)means2d[2 * g + 1], r = radii[g];
    sp[k] = {means2d[2 * g], means2d[2 * g + 1], conics[3 * g], conics[3 * g + 1], conics[3 * g + 2],
             opac[g], (S)(std::log(min_alpha / (double)opac[g]) - 1e-3),
             (int)std::ceil(u - r - 0.5), (int)std::floor(u + r - 0.5),
             (int)std::ceil(v - r - 0.5), (int)std::floor(v + r - 0.5)};
  }
}

// Powers of splat s at pixels [a, b] of row py (a vectorisable loop: no branches, no exp).
template <typename S>
inline void row_powers(const Splat<S>& s, int a, int b, int py, S* pw) {
  const S dy = s.v - ((S)py + (S)0.5);
  const S cdy = s.C * dy * dy, bdy = s.B * dy;
  for (int px = a; px <= b; ++px) {
    const S dx = s.u - ((S)px + (S)0.5);
    pw[px - a] = (S)-0.5 * (s.A * dx * dx + cdy) - bdy * dx;
  }
}

// Forward: the tile is processed a pixel row at a time, splats in depth order (outer loop) and the
// row's pixels inside; each pixel still sees the same splats in the same order as in Eq. (3).
template <typename S>
void raster_fwd_impl(int W, int H, int tile, int F, double min_alpha, const S* means2d, const S* conics,
                     const S* opac, const int32_t* radii, const S* feat, const S* bg, const int64_t* offsets,
                     const int32_t* ids, S* out, S* T_out, int32_t* n_contrib) {
  int tiles_x = (W + tile - 1) / tile, tiles_y = (H + tile - 1) / tile;
  const S amin = (S)min_alpha, amax = (S)gf::kAlphaMax, tmin = (S)gf::kTransmittanceMin;
#pragma omp parallel
  {
    std::vector<Splat<S>> sp;
    std::vector<S> acc((size_t)kMaxTile * F);
    S T[kMaxTile], pw[kMaxTile];
    int last[kMaxTile];
    bool done[kMaxTile];
#pragma omp for schedule(dynamic, 1)
    for (int t = 0; t < tiles_x * tiles_y; ++t) {
      int64_t beg = offsets[t];
      int n = (int)(offsets[t + 1] - beg);
      int x0 = (t % tiles_x) * tile, y0 = (t / tiles_x) * tile;
      int npx = std::min(tile, W - x0);
      load_tile(beg, n, ids, means2d, conics, opac, radii, min_alpha, sp);
      for (int py = y0; py < std::min(y0 + tile, H); ++py) {
        std::fill(acc.begin(), acc.begin() + (size_t)npx * F, (S)0);
        for (int p = 0; p < npx; ++p) { T[p] = 1; last[p] = 0; done[p] = false; }
        int alive = npx;
        for (int k = 0; k < n && alive > 0; ++k) {
          const Splat<S>& s = sp[k];
          if (py < s.y0 || py > s.y1) continue;
          int a = std::max(s.x0, x0), b = std::min(s.x1, x0 + npx - 1);
          if (a > b) continue;
          row_powers(s, a, b, py, pw);
          const S* f = feat + (int64_t)ids[beg + k] * F;
          for (int px = a; px <= b; ++px) {
            int p = px - x0;
            S power = pw[px - a];
            if (done[p] || power > 0 || power < s.log_cut) continue;
            S alpha = std::min(amax, s.o * std::exp(power));
            if (alpha < amin) continue;
            S Tn = T[p] * (1 - alpha);
            if (Tn < tmin) { done[p] = true; --alive; continue; }
            S w = alpha * T[p];
            S* ac = &acc[(size_t)p * F];
            for (int c = 0; c < F; ++c) ac[c] += w * f[c];
            T[p] = Tn;
            last[p] = k + 1;
          }
        }
        for (int p = 0; p < npx; ++p) {
          int64_t pix = (int64_t)py * W + x0 + p;
          for (int c = 0; c < F; ++c) out[pix * F + c] = acc[(size_t)p * F + c] + T[p] * bg[c];
          T_out[pix] = T[p];
          n_contrib[pix] = last[p];
        }
      }
    }
  }
}

// Backward: per row, splats back to front from the last contributor; the transmittance in front
// of splat k is recovered as T / (1 - alpha_k) (alpha <= 0.99 and T >= 1e-4 keep this exact enough).
template <typename S>
void raster_bwd_impl(int64_t N, int W, int H, int tile, int F, double min_alpha, const S* means2d,
                     const S* conics, const S* opac, const int32_t* radii, const S* feat, const S* bg,
                     const int64_t* offsets, const int32_t* ids, const S* T_final, const int32_t* n_contrib,
                     const S* g_out, const S* g_T, S* g_means2d, S* g_conics, S* g_opac, S* g_feat) {
  int tiles_x = (W + tile - 1) / tile, tiles_y = (H + tile - 1) / tile;
  const S amin = (S)min_alpha, amax = (S)gf::kAlphaMax;
  int nt = num_threads();
  // per-thread accumulators (Gaussians are shared between tiles), reduced at the end
  const int G = 6 + F;  // u, v, A, B, C, o, features
  // gradients are summed over many pixels with cancellation: accumulate them in double
  std::vector<std::vector<double>> per_thread(nt);
#pragma omp parallel
  {
    std::vector<double>& buf = per_thread[thread_id()];
    buf.assign((size_t)N * G, 0.0);
    std::vector<Splat<S>> sp;
    std::vector<double> local;  // gradients of this tile's splats, by position in the tile list
    std::vector<S> Sacc((size_t)kMaxTile * F);
    S T[kMaxTile], Tf[kMaxTile], gT[kMaxTile], pw[kMaxTile];
    int last[kMaxTile];
#pragma omp for schedule(dynamic, 1)
    for (int t = 0; t < tiles_x * tiles_y; ++t) {
      int64_t beg = offsets[t];
      int n = (int)(offsets[t + 1] - beg);
      if (n == 0) continue;
      local.assign((size_t)n * G, 0.0);
      int x0 = (t % tiles_x) * tile, y0 = (t / tiles_x) * tile;
      int npx = std::min(tile, W - x0);
      load_tile(beg, n, ids, means2d, conics, opac, radii, min_alpha, sp);
      for (int py = y0; py < std::min(y0 + tile, H); ++py) {
        int maxlast = 0;
        for (int p = 0; p < npx; ++p) {
          int64_t pix = (int64_t)py * W + x0 + p;
          last[p] = n_contrib[pix];
          maxlast = std::max(maxlast, last[p]);
          Tf[p] = T[p] = T_final[pix];
          gT[p] = g_T[pix];
          for (int c = 0; c < F; ++c) Sacc[(size_t)p * F + c] = Tf[p] * bg[c];  // what lies behind
        }
        for (int k = maxlast - 1; k >= 0; --k) {
          const Splat<S>& s = sp[k];
          if (py < s.y0 || py > s.y1) continue;
          int a = std::max(s.x0, x0), b = std::min(s.x1, x0 + npx - 1);
          if (a > b) continue;
          row_powers(s, a, b, py, pw);
          const S* f = feat + (int64_t)ids[beg + k] * F;
          double* lg = &local[(size_t)k * G];
          const S cyp = (S)py + (S)0.5;
          for (int px = a; px <= b; ++px) {
            int p = px - x0;
            S power = pw[px - a];
            if (k >= last[p] || power > 0 || power < s.log_cut) continue;
            S Gk = std::exp(power);
            S raw = s.o * Gk;
            S alpha = std::min(amax, raw);
            if (alpha < amin) continue;
            S one_m = 1 - alpha;
            T[p] = T[p] / one_m;  // transmittance in front of splat k
            const S* go = g_out + ((int64_t)py * W + px) * F;
            S* sa = &Sacc[(size_t)p * F];
            S w = alpha * T[p];
            S g_alpha = -gT[p] * Tf[p] / one_m;
            for (int c = 0; c < F; ++c) {
              lg[6 + c] += w * go[c];
              g_alpha += go[c] * (T[p] * f[c] - sa[c] / one_m);
              sa[c] += w * f[c];
            }
            if (raw > amax) continue;  // clamped alpha: no gradient to opacity or shape
            S dx = s.u - ((S)px + (S)0.5), dy = s.v - cyp;
            lg[5] += g_alpha * Gk;
            S g_power = g_alpha * s.o * Gk;
            lg[0] += g_power * -(s.A * dx + s.B * dy);
            lg[1] += g_power * -(s.B * dx + s.C * dy);
            lg[2] += g_power * (S)-0.5 * dx * dx;
            lg[3] += g_power * -dx * dy;
            lg[4] += g_power * (S)-0.5 * dy * dy;
          }
        }
      }
      for (int k = 0; k < n; ++k) {
        double* dst = &buf[(size_t)ids[beg + k] * G];
        const double* src = &local[(size_t)k * G];
        for (int j = 0; j < G; ++j) dst[j] += src[j];
      }
    }
  }
#pragma omp parallel for schedule(static)
  for (int64_t i = 0; i < N; ++i) {
    std::vector<double> acc(G, 0.0);
    for (int th = 0; th < nt; ++th) {
      if (per_thread[th].empty()) continue;
      const double* src = &per_thread[th][(size_t)i * G];
      for (int j = 0; j < G; ++j) acc[j] += src[j];
    }
    g_means2d[2 * i] = (S)acc[0]; g_means2d[2 * i + 1] = (S)acc[1];
    g_conics[3 * i] = (S)acc[2]; g_conics[3 * i + 1] = (S)acc[3]; g_conics[3 * i + 2] = (S)acc[4];
    g_opac[i] = (S)acc[5];
    for (int c = 0; c < F; ++c) g_feat[i * F + c] = (S)acc[6 + c];
  }
}

}  // namespace

namespace gf {

// ================================ entry points (called by ext.cpp) ================================
std::vector<torch::Tensor> project_forward_cpu(torch::Tensor means, torch::Tensor scales, torch::Tensor quats,
                                           torch::Tensor opac, torch::Tensor sh, torch::Tensor viewmat,
                                           torch::Tensor intr, int64_t W, int64_t H, double near,
                                           double min_alpha, int64_t degree) {
  means = means.contiguous(); scales = scales.contiguous(); quats = quats.contiguous();
  opac = opac.contiguous(); sh = sh.contiguous();
  int64_t N = means.size(0);
  int K = (int)sh.size(1), Cc = (int)sh.size(2);
  TORCH_CHECK(gf::sh_count((int)degree) <= K, "sh has too few coefficients for degree ", degree);
  Cam cam = make_cam(viewmat, intr, W, H, near);
  auto opts = means.options();
  auto means2d = torch::empty({N, 2}, opts), conics = torch::empty({N, 3}, opts);
  auto depths = torch::empty({N}, opts), colors = torch::empty({N, Cc}, opts);
  auto radii = torch::empty({N}, opts.dtype(torch::kInt32));
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_forward", [&] {
    project_fwd_impl<scalar_t>(cam, N, K, Cc, (int)degree, min_alpha, means.data_ptr<scalar_t>(),
                               scales.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(),
                               sh.data_ptr<scalar_t>(), means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                               depths.data_ptr<scalar_t>(), colors.data_ptr<scalar_t>(), radii.data_ptr<int32_t>());
  });
  return {means2d, conics, depths, colors, radii};
}

std::vector<torch::Tensor> project_backward_cpu(torch::Tensor means, torch::Tensor scales, torch::Tensor quats,
                                            torch::Tensor sh, torch::Tensor viewmat, torch::Tensor intr,
                                            int64_t W, int64_t H, double near, int64_t degree,
                                            torch::Tensor radii, torch::Tensor g_means2d, torch::Tensor g_conics,
                                            torch::Tensor g_depths, torch::Tensor g_colors) {
  means = means.contiguous(); scales = scales.contiguous(); quats = quats.contiguous(); sh = sh.contiguous();
  g_means2d = g_means2d.contiguous(); g_conics = g_conics.contiguous();
  g_depths = g_depths.contiguous(); g_colors = g_colors.contiguous();
  int64_t N = means.size(0);
  int K = (int)sh.size(1), Cc = (int)sh.size(2);
  Cam cam = make_cam(viewmat, intr, W, H, near);
  auto g_means = torch::zeros_like(means), g_scales = torch::zeros_like(scales);
  auto g_quats = torch::zeros_like(quats), g_sh = torch::zeros_like(sh);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_backward", [&] {
    project_bwd_impl<scalar_t>(cam, N, K, Cc, (int)degree, means.data_ptr<scalar_t>(), scales.data_ptr<scalar_t>(),
                               quats.data_ptr<scalar_t>(), sh.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(),
                               g_means2d.data_ptr<scalar_t>(), g_conics.data_ptr<scalar_t>(),
                               g_depths.data_ptr<scalar_t>(), g_colors.data_ptr<scalar_t>(),
                               g_means.data_ptr<scalar_t>(), g_scales.data_ptr<scalar_t>(),
                               g_quats.data_ptr<scalar_t>(), g_sh.data_ptr<scalar_t>());
  });
  return {g_means, g_scales, g_quats, g_sh};
}

std::vector<torch::Tensor> bin_gaussians_cpu(torch::Tensor means2d, torch::Tensor depths, torch::Tensor radii,
                                             int64_t W, int64_t H, int64_t tile) {
  means2d = means2d.contiguous(); depths = depths.contiguous(); radii = radii.contiguous();
  int64_t N = means2d.size(0);
  std::vector<int64_t> offsets;
  std::vector<int32_t> ids;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "bin_gaussians", [&] {
    bin_impl<scalar_t>(N, means2d.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(),
                       (int)W, (int)H, (int)tile, offsets, ids);
  });
  auto off_t = torch::from_blob(offsets.data(), {(int64_t)offsets.size()}, torch::kInt64).clone();
  auto ids_t = torch::from_blob(ids.data(), {(int64_t)ids.size()}, torch::kInt32).clone();
  const int32_t* r = radii.data_ptr<int32_t>();
  int64_t invalid = 0;
  for (int64_t i = 0; i < N; ++i) invalid += r[i] < 0;
  return {off_t, ids_t, torch::full({1}, invalid, torch::kInt64)};
}

std::vector<torch::Tensor> rasterize_forward_cpu(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                                 torch::Tensor feat, torch::Tensor bg, torch::Tensor radii,
                                                 torch::Tensor offsets, torch::Tensor ids, int64_t W, int64_t H,
                                                 int64_t tile, double min_alpha) {
  means2d = means2d.contiguous(); conics = conics.contiguous(); opac = opac.contiguous();
  feat = feat.contiguous(); bg = bg.contiguous(); radii = radii.contiguous();
  offsets = offsets.contiguous(); ids = ids.contiguous();
  int F = (int)feat.size(1);
  TORCH_CHECK(tile >= 1 && tile <= kMaxTile, "tile size must be in [1, ", kMaxTile, "]");
  auto opts = means2d.options();
  auto out = torch::empty({H, W, F}, opts), T = torch::empty({H, W}, opts);
  auto nc = torch::empty({H, W}, opts.dtype(torch::kInt32));
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_forward", [&] {
    raster_fwd_impl<scalar_t>((int)W, (int)H, (int)tile, F, min_alpha, means2d.data_ptr<scalar_t>(),
                              conics.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(),
                              feat.data_ptr<scalar_t>(), bg.data_ptr<scalar_t>(), offsets.data_ptr<int64_t>(),
                              ids.data_ptr<int32_t>(), out.data_ptr<scalar_t>(), T.data_ptr<scalar_t>(),
                              nc.data_ptr<int32_t>());
  });
  return {out, T, nc};
}

std::vector<torch::Tensor> rasterize_backward_cpu(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                              torch::Tensor radii, torch::Tensor feat, torch::Tensor bg, torch::Tensor offsets,
                                              torch::Tensor ids, torch::Tensor T_final, torch::Tensor n_contrib,
                                              torch::Tensor g_out, torch::Tensor g_T, int64_t W, int64_t H,
                                              int64_t tile, double min_alpha) {
  means2d = means2d.contiguous(); conics = conics.contiguous(); opac = opac.contiguous(); radii = radii.contiguous();
  feat = feat.contiguous(); bg = bg.contiguous(); g_out = g_out.contiguous(); g_T = g_T.contiguous();
  offsets = offsets.contiguous(); ids = ids.contiguous(); T_final = T_final.contiguous(); n_contrib = n_contrib.contiguous();
  int64_t N = means2d.size(0);
  int F = (int)feat.size(1);
  auto g_m = torch::zeros_like(means2d), g_c = torch::zeros_like(conics);
  auto g_o = torch::zeros_like(opac), g_f = torch::zeros_like(feat);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_backward", [&] {
    raster_bwd_impl<scalar_t>(N, (int)W, (int)H, (int)tile, F, min_alpha, means2d.data_ptr<scalar_t>(),
                              conics.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(),
                              feat.data_ptr<scalar_t>(),
                              bg.data_ptr<scalar_t>(), offsets.data_ptr<int64_t>(), ids.data_ptr<int32_t>(),
                              T_final.data_ptr<scalar_t>(), n_contrib.data_ptr<int32_t>(),
                              g_out.data_ptr<scalar_t>(), g_T.data_ptr<scalar_t>(), g_m.data_ptr<scalar_t>(),
                              g_c.data_ptr<scalar_t>(), g_o.data_ptr<scalar_t>(), g_f.data_ptr<scalar_t>());
  });
  return {g_m, g_c, g_o, g_f};
}

}  // namespace gf
