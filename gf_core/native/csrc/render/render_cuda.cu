// CUDA backend of the splatting renderer, the twin of render_cpu.cpp (same math from
// gaussian_math.h, same order of operations, so outputs and gradients agree):
// - projection: one thread per Gaussian (forward and hand-written backward);
// - binning: a stable radix sort (CUB) of the depths gives each drawn Gaussian its depth rank;
//   tile/Gaussian pairs keyed (tile << 32 | rank) are radix-sorted over the key's used bits, and a
//   kernel finds each tile's range (the CPU's order exactly: by tile, then depth, then index);
// - rasterisation: one block per tile, one thread per pixel; splats are loaded in batches into
//   shared memory and composited front to back with early termination (paper Eq. 3);
// - backward: back to front from each pixel's last contributor, the transmittance recovered as
//   T / (1 - alpha); per-splat gradients summed over the warp with shuffles, then one atomicAdd.
#include <torch/extension.h>

#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAGuard.h>
#include <cuda_runtime.h>

#include <cub/cub.cuh>

#include "gaussian_math.h"
#include "ops.h"

namespace gf {
namespace {

constexpr int kThreads = 256;
constexpr int kMaxFeatures = 8;

inline int blocks_for(int64_t n) { return (int)((n + kThreads - 1) / kThreads); }

// ================================ projection ======================================================
template <typename S>
__global__ void project_fwd_kernel(Cam cam, int64_t N, int K, int Cc, int degree, double min_alpha,
                                   const S* __restrict__ means, const S* __restrict__ scales,
                                   const S* __restrict__ quats, const S* __restrict__ opac, const S* __restrict__ sh,
                                   S* means2d, S* conics, S* depths, S* colors, int32_t* radii) {
  int64_t i = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= N) return;
  double p[3], s[3], q[4];
  for (int j = 0; j < 3; ++j) { p[j] = means[3 * i + j]; s[j] = scales[3 * i + j]; }
  for (int j = 0; j < 4; ++j) q[j] = quats[4 * i + j];
  Proj P;
  int r = 0;
  bool valid = inputs_valid(p, s, q, (double)opac[i]);
  for (int k = 0; valid && k < K * Cc; ++k) valid = isfinite((double)sh[i * K * Cc + k]);
  if (valid && project_core(cam, p, s, q, P)) r = splat_radius(P, (double)opac[i], min_alpha, cam.width, cam.height);
  radii[i] = valid ? r : -1;
  if (r <= 0 || !valid) {
    means2d[2 * i] = means2d[2 * i + 1] = 0;
    conics[3 * i] = conics[3 * i + 1] = conics[3 * i + 2] = 0;
    depths[i] = 0;
    for (int c = 0; c < Cc; ++c) colors[Cc * i + c] = 0;
    return;
  }
  means2d[2 * i] = (S)P.u; means2d[2 * i + 1] = (S)P.v;
  conics[3 * i] = (S)(P.c / P.det); conics[3 * i + 1] = (S)(-P.b / P.det); conics[3 * i + 2] = (S)(P.a / P.det);
  depths[i] = (S)P.t[2];
  double Y[16];
  sh_basis(degree, P.dir, Y);
  int nb = sh_count(degree);
  for (int c = 0; c < Cc; ++c) {
    double acc = 0.5;
    for (int k = 0; k < nb; ++k) acc += Y[k] * (double)sh[(i * K + k) * Cc + c];
    colors[Cc * i + c] = (S)(acc > 0 ? acc : 0);
  }
}

template <typename S>
__global__ void project_bwd_kernel(Cam cam, int64_t N, int K, int Cc, int degree, const S* __restrict__ means,
                                   const S* __restrict__ scales, const S* __restrict__ quats,
                                   const S* __restrict__ sh, const int32_t* __restrict__ radii,
                                   const S* __restrict__ g_means2d, const S* __restrict__ g_conics,
                                   const S* __restrict__ g_depths, const S* __restrict__ g_colors, S* g_means,
                                   S* g_scales, S* g_quats, S* g_sh) {
  int64_t i = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= N) return;
  const int nb = sh_count(degree);
  // the output buffers are not zeroed: every entry of this Gaussian is written here
  for (int k = (radii[i] > 0 ? nb : 0); k < K; ++k)
    for (int c = 0; c < Cc; ++c) g_sh[(i * K + k) * Cc + c] = 0;
  if (radii[i] <= 0) {
    for (int j = 0; j < 3; ++j) g_means[3 * i + j] = g_scales[3 * i + j] = 0;
    for (int j = 0; j < 4; ++j) g_quats[4 * i + j] = 0;
    return;
  }
  double p[3], s[3], q[4];
  for (int j = 0; j < 3; ++j) { p[j] = means[3 * i + j]; s[j] = scales[3 * i + j]; }
  for (int j = 0; j < 4; ++j) q[j] = quats[4 * i + j];
  Proj P;
  project_core(cam, p, s, q, P);
  double Y[16];
  sh_basis(degree, P.dir, Y);
  double gY[16];
  for (int k = 0; k < 16; ++k) gY[k] = 0;
  for (int c = 0; c < Cc; ++c) {
    double acc = 0.5;
    for (int k = 0; k < nb; ++k) acc += Y[k] * (double)sh[(i * K + k) * Cc + c];
    double g = acc >= 0 ? (double)g_colors[Cc * i + c] : 0.0;
    for (int k = 0; k < nb; ++k) {
      g_sh[(i * K + k) * Cc + c] = (S)(Y[k] * g);
      gY[k] += (double)sh[(i * K + k) * Cc + c] * g;
    }
  }
  double guv[2] = {(double)g_means2d[2 * i], (double)g_means2d[2 * i + 1]};
  double gcon[3] = {(double)g_conics[3 * i], (double)g_conics[3 * i + 1], (double)g_conics[3 * i + 2]};
  double gp[3], gs[3], gq[4];
  project_core_vjp(cam, s, P, guv, gcon, (double)g_depths[i], gY, degree, gp, gs, gq);
  for (int j = 0; j < 3; ++j) { g_means[3 * i + j] = (S)gp[j]; g_scales[3 * i + j] = (S)gs[j]; }
  for (int j = 0; j < 4; ++j) g_quats[4 * i + j] = (S)gq[j];
}

// ================================ binning =========================================================
// One pass per Gaussian: its number of tile pairs, its key for the stable depth sort (the bits of
// a positive float order like the number; Gaussians that are not drawn sort last) and the count of
// invalid inputs (radius -1 from the projection), so that binning needs no ATen op before its sync.
template <typename S>
__global__ void bin_prep_kernel(int64_t N, const S* __restrict__ means2d, const S* __restrict__ depths,
                                const int32_t* __restrict__ radii, int tile, int tiles_x, int tiles_y,
                                int64_t* counts, uint64_t* dkeys, int32_t* didx, unsigned long long* n_invalid) {
  int64_t i = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= N) return;
  const int rad = radii[i];
  int r[4];
  counts[i] = tile_rect((double)means2d[2 * i], (double)means2d[2 * i + 1], rad, tile, tiles_x, tiles_y, r)
                  ? (int64_t)(r[2] - r[0] + 1) * (r[3] - r[1] + 1)
                  : 0;
  uint64_t b;
  if (sizeof(S) == 8) {
    b = (uint64_t)__double_as_longlong((double)depths[i]);
  } else {
    b = (uint64_t)__float_as_uint((float)depths[i]);
  }
  dkeys[i] = rad > 0 ? b : ~0ull;
  didx[i] = (int32_t)i;
  if (rad < 0) atomicAdd(n_invalid, 1ull);
}

// Pairs are emitted in depth order (rank r = position in the stable depth sort), keyed
// (tile << 32 | r): one stable radix sort over the key's used bits then orders by tile and, within
// a tile, by depth with ties by index -- exactly the CPU's order.
template <typename S>
__global__ void emit_pairs_kernel(int64_t N, const int32_t* __restrict__ order, const S* __restrict__ means2d,
                                  const int32_t* __restrict__ radii, const int64_t* __restrict__ ends, int tile,
                                  int tiles_x, int tiles_y, int64_t* keys, int32_t* vals) {
  int64_t rnk = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (rnk >= N) return;
  int32_t i = order[rnk];
  int r[4];
  if (!tile_rect((double)means2d[2 * i], (double)means2d[2 * i + 1], radii[i], tile, tiles_x, tiles_y, r)) return;
  int64_t k = ends[rnk] - (int64_t)(r[2] - r[0] + 1) * (r[3] - r[1] + 1);
  for (int ty = r[1]; ty <= r[3]; ++ty)
    for (int tx = r[0]; tx <= r[2]; ++tx) {
      keys[k] = ((int64_t)(ty * tiles_x + tx) << 32) | rnk;
      vals[k] = i;
      ++k;
    }
}

__global__ void gather_counts_kernel(int64_t N, const int32_t* __restrict__ order, const int64_t* __restrict__ counts,
                                     int64_t* out) {
  int64_t r = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (r < N) out[r] = counts[order[r]];
}

// offsets[t] = first pair of tile t (pairs sorted by tile); offsets[n_tiles] = total
__global__ void tile_offsets_kernel(int64_t total, int64_t n_tiles, const int64_t* __restrict__ keys, int64_t* offsets) {
  int64_t p = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (p > total) return;
  int64_t t = p < total ? (keys[p] >> 32) : n_tiles;
  int64_t prev = p > 0 ? (keys[p - 1] >> 32) : -1;
  for (int64_t tt = prev + 1; tt <= t; ++tt) offsets[tt] = p;
}

// ================================ rasterisation ===================================================
template <typename S>
struct SharedSplat {
  S u, v, A, B, C, o, log_cut;
  int x0, x1, y0, y1, id;
};

template <typename S>
__device__ inline void load_splat(SharedSplat<S>& sp, int32_t g, const S* means2d, const S* conics, const S* opac,
                                  const int32_t* radii, double min_alpha) {
  double u = (double)means2d[2 * g], v = (double)means2d[2 * g + 1], r = radii[g];
  sp.u = means2d[2 * g]; sp.v = means2d[2 * g + 1];
  sp.A = conics[3 * g]; sp.B = conics[3 * g + 1]; sp.C = conics[3 * g + 2];
  sp.o = opac[g];
  sp.log_cut = (S)(log(min_alpha / (double)opac[g]) - 1e-3);
  sp.x0 = (int)ceil(u - r - 0.5); sp.x1 = (int)floor(u + r - 0.5);
  sp.y0 = (int)ceil(v - r - 0.5); sp.y1 = (int)floor(v + r - 0.5);
  sp.id = g;
}

template <typename S>
__global__ void raster_fwd_kernel(int W, int H, int tile, int F, double min_alpha, const S* __restrict__ means2d,
                                  const S* __restrict__ conics, const S* __restrict__ opac,
                                  const int32_t* __restrict__ radii, const S* __restrict__ feat,
                                  const S* __restrict__ bg, const int64_t* __restrict__ offsets,
                                  const int32_t* __restrict__ ids, S* out, S* T_out, int32_t* n_contrib) {
  extern __shared__ unsigned char smem[];
  SharedSplat<S>* sp = reinterpret_cast<SharedSplat<S>*>(smem);
  S* sf = reinterpret_cast<S*>(sp + blockDim.x);  // features of the batch
  const int bs = blockDim.x;
  const int tid = threadIdx.x;
  const int tiles_x = (W + tile - 1) / tile;
  const int t = blockIdx.x;
  const int px = (t % tiles_x) * tile + tid % tile, py = (t / tiles_x) * tile + tid / tile;
  const bool inside = px < W && py < H;
  const S amin = (S)min_alpha, amax = (S)kAlphaMax, tmin = (S)kTransmittanceMin;
  const S cx = (S)px + (S)0.5, cy = (S)py + (S)0.5;
  const int64_t beg = offsets[t], end = offsets[t + 1];
  const int n = (int)(end - beg);
  S T = 1;
  S acc[kMaxFeatures];
  for (int c = 0; c < kMaxFeatures; ++c) acc[c] = 0;
  int last = 0;
  bool done = !inside;
  for (int base = 0; base < n; base += bs) {
    if (__syncthreads_count(done) == bs) break;
    int k = base + tid;
    if (k < n) {
      int32_t g = ids[beg + k];
      load_splat(sp[tid], g, means2d, conics, opac, radii, min_alpha);
      for (int c = 0; c < F; ++c) sf[tid * F + c] = feat[(int64_t)g * F + c];
    }
    __syncthreads();
    int cnt = min(bs, n - base);
    for (int j = 0; j < cnt && !done; ++j) {
      const SharedSplat<S>& s = sp[j];
      if (py < s.y0 || py > s.y1 || px < s.x0 || px > s.x1) continue;
      S power = splat_power<S>(s.A, s.B, s.C, s.u - cx, s.v - cy);
      if (power > 0 || power < s.log_cut) continue;
      S alpha = min(amax, s.o * exp(power));
      if (alpha < amin) continue;
      S Tn = T * (1 - alpha);
      if (Tn < tmin) {
        done = true;
        break;
      }
      S w = alpha * T;
      for (int c = 0; c < F; ++c) acc[c] += w * sf[j * F + c];
      T = Tn;
      last = base + j + 1;
    }
  }
  if (!inside) return;
  int64_t pix = (int64_t)py * W + px;
  for (int c = 0; c < F; ++c) out[pix * F + c] = acc[c] + T * bg[c];
  T_out[pix] = T;
  n_contrib[pix] = last;
}

template <typename S>
__device__ inline S warp_sum(S v) {
  for (int off = 16; off > 0; off >>= 1) v += __shfl_down_sync(0xffffffffu, v, off);
  return v;
}

template <typename S>
__global__ void raster_bwd_kernel(int W, int H, int tile, int F, double min_alpha, const S* __restrict__ means2d,
                                  const S* __restrict__ conics, const S* __restrict__ opac,
                                  const int32_t* __restrict__ radii, const S* __restrict__ feat,
                                  const S* __restrict__ bg, const int64_t* __restrict__ offsets,
                                  const int32_t* __restrict__ ids, const S* __restrict__ T_final,
                                  const int32_t* __restrict__ n_contrib, const S* __restrict__ g_out,
                                  const S* __restrict__ g_T, S* g_means2d, S* g_conics, S* g_opac, S* g_feat) {
  extern __shared__ unsigned char smem[];
  SharedSplat<S>* sp = reinterpret_cast<SharedSplat<S>*>(smem);
  S* sf = reinterpret_cast<S*>(sp + blockDim.x);
  __shared__ int max_last;
  const int bs = blockDim.x;
  const int tid = threadIdx.x;
  const int lane = tid & 31;
  const int tiles_x = (W + tile - 1) / tile;
  const int t = blockIdx.x;
  const int px = (t % tiles_x) * tile + tid % tile, py = (t / tiles_x) * tile + tid / tile;
  const bool inside = px < W && py < H;
  const S amin = (S)min_alpha, amax = (S)kAlphaMax;
  const S cx = (S)px + (S)0.5, cy = (S)py + (S)0.5;
  const int64_t beg = offsets[t];
  const int64_t pix = inside ? (int64_t)py * W + px : 0;
  const int last = inside ? n_contrib[pix] : 0;
  if (tid == 0) max_last = 0;
  __syncthreads();
  atomicMax(&max_last, last);
  S T = inside ? T_final[pix] : (S)1;
  const S Tf = T;
  const S gT = inside ? g_T[pix] : (S)0;
  S go[kMaxFeatures], sacc[kMaxFeatures];
  for (int c = 0; c < kMaxFeatures; ++c) {
    go[c] = (inside && c < F) ? g_out[pix * F + c] : (S)0;
    sacc[c] = (inside && c < F) ? Tf * bg[c] : (S)0;
  }
  __syncthreads();
  const int n = max_last;
  const int rounds = (n + bs - 1) / bs;
  for (int r = rounds - 1; r >= 0; --r) {
    const int base = r * bs;
    int k = base + tid;
    if (k < n) {
      int32_t g = ids[beg + k];
      load_splat(sp[tid], g, means2d, conics, opac, radii, min_alpha);
      for (int c = 0; c < F; ++c) sf[tid * F + c] = feat[(int64_t)g * F + c];
    }
    __syncthreads();
    int cnt = min(bs, n - base);
    for (int j = cnt - 1; j >= 0; --j) {
      const SharedSplat<S>& s = sp[j];
      const int kidx = base + j;
      S gu = 0, gv = 0, gA = 0, gB = 0, gC = 0, gop = 0;
      S gf[kMaxFeatures];
      for (int c = 0; c < kMaxFeatures; ++c) gf[c] = 0;
      bool contrib = false;
      if (kidx < last && !(py < s.y0 || py > s.y1 || px < s.x0 || px > s.x1)) {
        const S dx = s.u - cx, dy = s.v - cy;
        S power = splat_power<S>(s.A, s.B, s.C, dx, dy);
        if (!(power > 0 || power < s.log_cut)) {
          S Gk = exp(power);
          S raw = s.o * Gk;
          S alpha = min(amax, raw);
          if (alpha >= amin) {
            contrib = true;
            S one_m = 1 - alpha;
            T = T / one_m;  // transmittance in front of this splat
            S w = alpha * T;
            S g_alpha = -gT * Tf / one_m;
            for (int c = 0; c < F; ++c) {
              S f = sf[j * F + c];
              gf[c] = w * go[c];
              g_alpha += go[c] * (T * f - sacc[c] / one_m);
              sacc[c] += w * f;
            }
            if (raw <= amax) {  // a clamped alpha passes no gradient to opacity or shape
              gop = g_alpha * Gk;
              S g_power = g_alpha * s.o * Gk;
              gu = g_power * -(s.A * dx + s.B * dy);
              gv = g_power * -(s.B * dx + s.C * dy);
              gA = g_power * (S)-0.5 * dx * dx;
              gB = g_power * -dx * dy;
              gC = g_power * (S)-0.5 * dy * dy;
            }
          }
        }
      }
      if (__any_sync(0xffffffffu, contrib)) {
        gu = warp_sum(gu); gv = warp_sum(gv); gA = warp_sum(gA); gB = warp_sum(gB); gC = warp_sum(gC);
        gop = warp_sum(gop);
        for (int c = 0; c < F; ++c) gf[c] = warp_sum(gf[c]);
        if (lane == 0) {
          const int g = s.id;
          atomicAdd(&g_means2d[2 * g], gu); atomicAdd(&g_means2d[2 * g + 1], gv);
          atomicAdd(&g_conics[3 * g], gA); atomicAdd(&g_conics[3 * g + 1], gB); atomicAdd(&g_conics[3 * g + 2], gC);
          atomicAdd(&g_opac[g], gop);
          for (int c = 0; c < F; ++c) atomicAdd(&g_feat[(int64_t)g * F + c], gf[c]);
        }
      }
    }
    __syncthreads();
  }
}

void check_cuda_launch(const char* what) {
  cudaError_t e = cudaGetLastError();
  TORCH_CHECK(e == cudaSuccess, what, ": CUDA error ", cudaGetErrorString(e));
}

size_t raster_smem(int threads, int F, size_t elem, size_t splat) { return (size_t)threads * (splat + F * elem); }

}  // namespace

// ================================ entry points (called by ext.cpp) ================================
std::vector<torch::Tensor> project_forward_cuda(torch::Tensor means, torch::Tensor scales, torch::Tensor quats,
                                                torch::Tensor opac, torch::Tensor sh, torch::Tensor viewmat,
                                                torch::Tensor intr, int64_t W, int64_t H, double near,
                                                double min_alpha, int64_t degree) {
  const c10::cuda::CUDAGuard guard(means.device());
  means = means.contiguous(); scales = scales.contiguous(); quats = quats.contiguous();
  opac = opac.contiguous(); sh = sh.contiguous();
  int64_t N = means.size(0);
  int K = (int)sh.size(1), Cc = (int)sh.size(2);
  Cam cam = make_cam(viewmat, intr, W, H, near);
  auto opts = means.options();
  auto means2d = torch::empty({N, 2}, opts), conics = torch::empty({N, 3}, opts);
  auto depths = torch::empty({N}, opts), colors = torch::empty({N, Cc}, opts);
  auto radii = torch::empty({N}, opts.dtype(torch::kInt32));
  if (N == 0) return {means2d, conics, depths, colors, radii};
  auto stream = at::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_forward_cuda", [&] {
    project_fwd_kernel<scalar_t><<<blocks_for(N), kThreads, 0, stream>>>(
        cam, N, K, Cc, (int)degree, min_alpha, means.data_ptr<scalar_t>(), scales.data_ptr<scalar_t>(),
        quats.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(), sh.data_ptr<scalar_t>(), means2d.data_ptr<scalar_t>(),
        conics.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(), colors.data_ptr<scalar_t>(),
        radii.data_ptr<int32_t>());
  });
  check_cuda_launch("project_forward_cuda");
  return {means2d, conics, depths, colors, radii};
}

std::vector<torch::Tensor> project_backward_cuda(torch::Tensor means, torch::Tensor scales, torch::Tensor quats,
                                                 torch::Tensor sh, torch::Tensor viewmat, torch::Tensor intr,
                                                 int64_t W, int64_t H, double near, int64_t degree,
                                                 torch::Tensor radii, torch::Tensor g_means2d, torch::Tensor g_conics,
                                                 torch::Tensor g_depths, torch::Tensor g_colors) {
  const c10::cuda::CUDAGuard guard(means.device());
  means = means.contiguous(); scales = scales.contiguous(); quats = quats.contiguous(); sh = sh.contiguous();
  radii = radii.contiguous();
  g_means2d = g_means2d.contiguous(); g_conics = g_conics.contiguous();
  g_depths = g_depths.contiguous(); g_colors = g_colors.contiguous();
  int64_t N = means.size(0);
  int K = (int)sh.size(1), Cc = (int)sh.size(2);
  Cam cam = make_cam(viewmat, intr, W, H, near);
  auto g_means = torch::empty_like(means), g_scales = torch::empty_like(scales);  // the kernel writes every entry
  auto g_quats = torch::empty_like(quats), g_sh = torch::empty_like(sh);
  if (N == 0) return {g_means, g_scales, g_quats, g_sh};
  auto stream = at::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_backward_cuda", [&] {
    project_bwd_kernel<scalar_t><<<blocks_for(N), kThreads, 0, stream>>>(
        cam, N, K, Cc, (int)degree, means.data_ptr<scalar_t>(), scales.data_ptr<scalar_t>(),
        quats.data_ptr<scalar_t>(), sh.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(),
        g_means2d.data_ptr<scalar_t>(), g_conics.data_ptr<scalar_t>(), g_depths.data_ptr<scalar_t>(),
        g_colors.data_ptr<scalar_t>(), g_means.data_ptr<scalar_t>(), g_scales.data_ptr<scalar_t>(),
        g_quats.data_ptr<scalar_t>(), g_sh.data_ptr<scalar_t>());
  });
  check_cuda_launch("project_backward_cuda");
  return {g_means, g_scales, g_quats, g_sh};
}

std::vector<torch::Tensor> bin_gaussians_cuda(torch::Tensor means2d, torch::Tensor depths, torch::Tensor radii,
                                              int64_t W, int64_t H, int64_t tile) {
  const c10::cuda::CUDAGuard guard(means2d.device());
  means2d = means2d.contiguous(); depths = depths.contiguous(); radii = radii.contiguous();
  int64_t N = means2d.size(0);
  int tiles_x = (int)((W + tile - 1) / tile), tiles_y = (int)((H + tile - 1) / tile);
  int64_t n_tiles = (int64_t)tiles_x * tiles_y;
  auto i64 = means2d.options().dtype(torch::kInt64);
  auto i32 = means2d.options().dtype(torch::kInt32);
  if (N == 0) return {torch::zeros({n_tiles + 1}, i64), torch::zeros({0}, i32), torch::zeros({1}, torch::kInt64)};
  auto stream = at::cuda::getCurrentCUDAStream();
  // 1. pairs per Gaussian, depth keys, invalid inputs (radius < 0 from the projection) counted
  auto counts = torch::empty({N}, i64);
  auto dkeys = torch::empty({N}, i64), dkeys_out = torch::empty({N}, i64);
  auto didx = torch::empty({N}, i32), order = torch::empty({N}, i32);
  auto stats = torch::empty({2}, i64);  // [pairs, invalid Gaussians]
  AT_CUDA_CHECK(cudaMemsetAsync(stats.data_ptr<int64_t>(), 0, 2 * sizeof(int64_t), stream));
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "bin_prep_cuda", [&] {
    bin_prep_kernel<scalar_t><<<blocks_for(N), kThreads, 0, stream>>>(
        N, means2d.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(), (int)tile, tiles_x,
        tiles_y, counts.data_ptr<int64_t>(), reinterpret_cast<uint64_t*>(dkeys.data_ptr<int64_t>()),
        didx.data_ptr<int32_t>(), reinterpret_cast<unsigned long long*>(stats.data_ptr<int64_t>() + 1));
  });
  check_cuda_launch("bin_gaussians_cuda (prep)");
  // 2. stable depth order (radix sort of the depth bits, index order kept on ties)
  int depth_bits = depths.scalar_type() == torch::kFloat64 ? 64 : 32;
  {
    size_t tmp_bytes = 0;
    auto* kin = reinterpret_cast<uint64_t*>(dkeys.data_ptr<int64_t>());
    auto* kout = reinterpret_cast<uint64_t*>(dkeys_out.data_ptr<int64_t>());
    cub::DeviceRadixSort::SortPairs(nullptr, tmp_bytes, kin, kout, didx.data_ptr<int32_t>(), order.data_ptr<int32_t>(),
                                    (int)N, 0, depth_bits, stream);
    auto tmp = torch::empty({(int64_t)tmp_bytes}, means2d.options().dtype(torch::kUInt8));
    cub::DeviceRadixSort::SortPairs(tmp.data_ptr(), tmp_bytes, kin, kout, didx.data_ptr<int32_t>(),
                                    order.data_ptr<int32_t>(), (int)N, 0, depth_bits, stream);
  }
  // 3. pair counts in depth order, their running sum: each Gaussian's end in the pair buffer
  auto counts_sorted = torch::empty({N}, i64), ends = torch::empty({N}, i64);
  gather_counts_kernel<<<blocks_for(N), kThreads, 0, stream>>>(N, order.data_ptr<int32_t>(), counts.data_ptr<int64_t>(),
                                                               counts_sorted.data_ptr<int64_t>());
  {
    size_t tmp_bytes = 0;
    cub::DeviceScan::InclusiveSum(nullptr, tmp_bytes, counts_sorted.data_ptr<int64_t>(), ends.data_ptr<int64_t>(),
                                  (int)N, stream);
    auto tmp = torch::empty({(int64_t)tmp_bytes}, means2d.options().dtype(torch::kUInt8));
    cub::DeviceScan::InclusiveSum(tmp.data_ptr(), tmp_bytes, counts_sorted.data_ptr<int64_t>(),
                                  ends.data_ptr<int64_t>(), (int)N, stream);
  }
  check_cuda_launch("bin_gaussians_cuda (scan)");
  // the one host sync: the pair buffers' size, and how many Gaussians had invalid inputs
  int64_t host[2] = {0, 0};
  AT_CUDA_CHECK(cudaMemcpyAsync(stats.data_ptr<int64_t>(), ends.data_ptr<int64_t>() + (N - 1), sizeof(int64_t),
                                cudaMemcpyDeviceToDevice, stream));
  AT_CUDA_CHECK(cudaMemcpyAsync(host, stats.data_ptr<int64_t>(), 2 * sizeof(int64_t), cudaMemcpyDeviceToHost, stream));
  AT_CUDA_CHECK(cudaStreamSynchronize(stream));
  const int64_t total = host[0];
  auto invalid = torch::full({1}, host[1], torch::TensorOptions().dtype(torch::kInt64));
  auto keys = torch::empty({total}, i64), keys_out = torch::empty({total}, i64);
  auto vals = torch::empty({total}, i32), ids = torch::empty({total}, i32);
  auto offsets = torch::empty({n_tiles + 1}, i64);
  if (total > 0) {
    AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "bin_emit_cuda", [&] {
      emit_pairs_kernel<scalar_t><<<blocks_for(N), kThreads, 0, stream>>>(
          N, order.data_ptr<int32_t>(), means2d.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(),
          ends.data_ptr<int64_t>(), (int)tile, tiles_x, tiles_y, keys.data_ptr<int64_t>(), vals.data_ptr<int32_t>());
    });
    check_cuda_launch("bin_gaussians_cuda (emit)");
    int tile_bits = 1;
    while ((int64_t{1} << tile_bits) <= n_tiles) ++tile_bits;
    size_t tmp_bytes = 0;
    cub::DeviceRadixSort::SortPairs(nullptr, tmp_bytes, keys.data_ptr<int64_t>(), keys_out.data_ptr<int64_t>(),
                                    vals.data_ptr<int32_t>(), ids.data_ptr<int32_t>(), (int)total, 0, 32 + tile_bits,
                                    stream);
    auto tmp = torch::empty({(int64_t)tmp_bytes}, means2d.options().dtype(torch::kUInt8));
    cub::DeviceRadixSort::SortPairs(tmp.data_ptr(), tmp_bytes, keys.data_ptr<int64_t>(), keys_out.data_ptr<int64_t>(),
                                    vals.data_ptr<int32_t>(), ids.data_ptr<int32_t>(), (int)total, 0, 32 + tile_bits,
                                    stream);
  }
  tile_offsets_kernel<<<blocks_for(total + 1), kThreads, 0, stream>>>(total, n_tiles, keys_out.data_ptr<int64_t>(),
                                                                     offsets.data_ptr<int64_t>());
  check_cuda_launch("bin_gaussians_cuda (offsets)");
  return {offsets, ids, invalid};
}

std::vector<torch::Tensor> rasterize_forward_cuda(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                                  torch::Tensor feat, torch::Tensor bg, torch::Tensor radii,
                                                  torch::Tensor offsets, torch::Tensor ids, int64_t W, int64_t H,
                                                  int64_t tile, double min_alpha) {
  const c10::cuda::CUDAGuard guard(means2d.device());
  means2d = means2d.contiguous(); conics = conics.contiguous(); opac = opac.contiguous();
  feat = feat.contiguous(); bg = bg.contiguous(); radii = radii.contiguous();
  offsets = offsets.contiguous(); ids = ids.contiguous();
  int F = (int)feat.size(1);
  TORCH_CHECK(F <= kMaxFeatures, "rasterize_forward_cuda: at most ", kMaxFeatures, " feature channels, got ", F);
  auto opts = means2d.options();
  auto out = torch::empty({H, W, F}, opts), T = torch::empty({H, W}, opts);
  auto nc = torch::empty({H, W}, opts.dtype(torch::kInt32));
  int tiles_x = (int)((W + tile - 1) / tile), tiles_y = (int)((H + tile - 1) / tile);
  int threads = (int)(tile * tile);
  auto stream = at::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_forward_cuda", [&] {
    size_t smem = raster_smem(threads, F, sizeof(scalar_t), sizeof(SharedSplat<scalar_t>));
    raster_fwd_kernel<scalar_t><<<tiles_x * tiles_y, threads, smem, stream>>>(
        (int)W, (int)H, (int)tile, F, min_alpha, means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
        opac.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(), feat.data_ptr<scalar_t>(), bg.data_ptr<scalar_t>(),
        offsets.data_ptr<int64_t>(), ids.data_ptr<int32_t>(), out.data_ptr<scalar_t>(), T.data_ptr<scalar_t>(),
        nc.data_ptr<int32_t>());
  });
  check_cuda_launch("rasterize_forward_cuda");
  return {out, T, nc};
}

std::vector<torch::Tensor> rasterize_backward_cuda(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                                   torch::Tensor radii, torch::Tensor feat, torch::Tensor bg,
                                                   torch::Tensor offsets, torch::Tensor ids, torch::Tensor T_final,
                                                   torch::Tensor n_contrib, torch::Tensor g_out, torch::Tensor g_T,
                                                   int64_t W, int64_t H, int64_t tile, double min_alpha) {
  const c10::cuda::CUDAGuard guard(means2d.device());
  means2d = means2d.contiguous(); conics = conics.contiguous(); opac = opac.contiguous(); radii = radii.contiguous();
  feat = feat.contiguous(); bg = bg.contiguous(); g_out = g_out.contiguous(); g_T = g_T.contiguous();
  offsets = offsets.contiguous(); ids = ids.contiguous(); T_final = T_final.contiguous();
  n_contrib = n_contrib.contiguous();
  int F = (int)feat.size(1);
  TORCH_CHECK(F <= kMaxFeatures, "rasterize_backward_cuda: at most ", kMaxFeatures, " feature channels, got ", F);
  TORCH_CHECK((tile * tile) % 32 == 0, "rasterize_backward_cuda: tile * tile must be a multiple of 32, got tile ", tile);
  // the four gradients are summed into with atomics: one zeroed buffer (one memset), four views
  const int64_t N = means2d.size(0);
  auto g_all = torch::zeros({N * (6 + F)}, means2d.options());
  auto g_m = g_all.narrow(0, 0, 2 * N).view({N, 2}), g_c = g_all.narrow(0, 2 * N, 3 * N).view({N, 3});
  auto g_o = g_all.narrow(0, 5 * N, N).view_as(opac), g_f = g_all.narrow(0, 6 * N, F * N).view({N, F});
  int tiles_x = (int)((W + tile - 1) / tile), tiles_y = (int)((H + tile - 1) / tile);
  int threads = (int)(tile * tile);
  auto stream = at::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_backward_cuda", [&] {
    size_t smem = raster_smem(threads, F, sizeof(scalar_t), sizeof(SharedSplat<scalar_t>));
    raster_bwd_kernel<scalar_t><<<tiles_x * tiles_y, threads, smem, stream>>>(
        (int)W, (int)H, (int)tile, F, min_alpha, means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
        opac.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(), feat.data_ptr<scalar_t>(), bg.data_ptr<scalar_t>(),
        offsets.data_ptr<int64_t>(), ids.data_ptr<int32_t>(), T_final.data_ptr<scalar_t>(),
        n_contrib.data_ptr<int32_t>(), g_out.data_ptr<scalar_t>(), g_T.data_ptr<scalar_t>(), g_m.data_ptr<scalar_t>(),
        g_c.data_ptr<scalar_t>(), g_o.data_ptr<scalar_t>(), g_f.data_ptr<scalar_t>());
  });
  check_cuda_launch("rasterize_backward_cuda");
  return {g_m, g_c, g_o, g_f};
}

}  // namespace gf
