// CUDA neighbour search, the twin of sph_cpu.cpp: points hashed into a uniform grid (cells of
// size `radius`), a counting sort by hash (atomics + a prefix sum), then one thread per query
// scanning its 27 cells and keeping the K nearest within the radius (sph_math.h). Results do not
// depend on the order inside a bucket: ties are broken by index.
#include <torch/extension.h>

#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAGuard.h>
#include <cuda_runtime.h>

#include "ops.h"
#include "sph_math.h"

namespace gf {
namespace {

constexpr int kThreads = 256;
inline int blocks_for(int64_t n) { return (int)((n + kThreads - 1) / kThreads); }

template <typename S>
__global__ void hash_kernel(GridSpec g, int64_t M, const S* __restrict__ y, int64_t* cells, int64_t* hash,
                            int32_t* counts) {
  int64_t j = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (j >= M) return;
  int64_t c[3];
  cell_of(g, (double)y[3 * j], (double)y[3 * j + 1], (double)y[3 * j + 2], c);
  cells[3 * j] = c[0]; cells[3 * j + 1] = c[1]; cells[3 * j + 2] = c[2];
  int64_t h = cell_hash(g, c[0], c[1], c[2]);
  hash[j] = h;
  atomicAdd(&counts[h], 1);
}

__global__ void fill_kernel(int64_t M, const int64_t* __restrict__ hash, const int64_t* __restrict__ start,
                            int32_t* cursor, int64_t* order) {
  int64_t j = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (j >= M) return;
  int64_t h = hash[j];
  order[start[h] + atomicAdd(&cursor[h], 1)] = j;
}

template <typename S, int KMAX>
__global__ void query_kernel(GridSpec g, int64_t N, int k, const S* __restrict__ x, const S* __restrict__ y,
                             const int64_t* __restrict__ cells, const int64_t* __restrict__ start,
                             const int64_t* __restrict__ order, double radius, bool exclude_self, bool sorted,
                             int64_t* out_idx, S* out_dist) {
  int64_t i = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= N) return;
  S dk[KMAX];
  int64_t jk[KMAX];
  const S xi = x[3 * i], yi = x[3 * i + 1], zi = x[3 * i + 2];
  const S r2 = (S)(radius * radius);
  int64_t c[3];
  cell_of(g, (double)xi, (double)yi, (double)zi, c);
  int n = 0, far = -1;
  for (int dx = -1; dx <= 1; ++dx)
    for (int dy = -1; dy <= 1; ++dy)
      for (int dz = -1; dz <= 1; ++dz) {
        int64_t cx = c[0] + dx, cy = c[1] + dy, cz = c[2] + dz;
        int64_t b = cell_hash(g, cx, cy, cz);
        for (int64_t q = start[b]; q < start[b + 1]; ++q) {
          int64_t j = order[q];
          if (cells[3 * j] != cx || cells[3 * j + 1] != cy || cells[3 * j + 2] != cz) continue;
          if (exclude_self && j == i) continue;
          S ex = xi - y[3 * j], ey = yi - y[3 * j + 1], ez = zi - y[3 * j + 2];
          S d2 = ex * ex + ey * ey + ez * ez;
          if (!(d2 < r2)) continue;
          n = topk_push<S>(d2, j, dk, jk, n, k, far);
        }
      }
  if (sorted) sort_nearest<S>(dk, jk, n);
  for (int s = 0; s < k; ++s) {
    out_idx[i * k + s] = s < n ? jk[s] : -1;
    out_dist[i * k + s] = s < n ? sqrt(dk[s]) : (S)INFINITY;
  }
}

template <typename S>
__global__ void density_fwd_kernel(int64_t N, int64_t K, const S* __restrict__ x, const int64_t* __restrict__ idx,
                                   S h2, S c, S* D) {
  int64_t i = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= N) return;
  S acc = poly6<S>(0, h2, c);
  const S xi = x[3 * i], yi = x[3 * i + 1], zi = x[3 * i + 2];
  for (int64_t s = 0; s < K; ++s) {
    int64_t j = idx[i * K + s];
    if (j < 0) continue;
    S ex = xi - x[3 * j], ey = yi - x[3 * j + 1], ez = zi - x[3 * j + 2];
    acc += poly6<S>(ex * ex + ey * ey + ez * ez, h2, c);
  }
  D[i] = acc;
}

template <typename S>
__global__ void density_bwd_kernel(int64_t N, int64_t K, const S* __restrict__ x, const int64_t* __restrict__ idx,
                                   S h2, S c, const S* __restrict__ gD, S* gx) {
  int64_t i = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= N) return;
  const S xi = x[3 * i], yi = x[3 * i + 1], zi = x[3 * i + 2];
  const S gi = gD[i];
  S acc[3] = {0, 0, 0};
  for (int64_t s = 0; s < K; ++s) {
    int64_t j = idx[i * K + s];
    if (j < 0) continue;
    S e[3] = {xi - x[3 * j], yi - x[3 * j + 1], zi - x[3 * j + 2]};
    S q = h2 - (e[0] * e[0] + e[1] * e[1] + e[2] * e[2]);
    if (q <= 0) continue;
    S f = gi * (S)-6 * c * q * q;  // dW/dx_i = -6 c q^2 (x_i - x_j)
    for (int a = 0; a < 3; ++a) {
      acc[a] += f * e[a];
      atomicAdd(&gx[3 * j + a], -f * e[a]);
    }
  }
  for (int a = 0; a < 3; ++a) atomicAdd(&gx[3 * i + a], acc[a]);
}

}  // namespace

std::vector<torch::Tensor> sph_density_forward_cuda(torch::Tensor x, torch::Tensor idx, double h) {
  const c10::cuda::CUDAGuard guard(x.device());
  x = x.contiguous();
  idx = idx.contiguous();
  int64_t N = x.size(0), K = idx.size(1);
  auto D = torch::empty({N}, x.options());
  if (N == 0) return {D};
  auto stream = at::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "sph_density_forward_cuda", [&] {
    scalar_t h2 = (scalar_t)(h * h), c = (scalar_t)(315.0 / (64.0 * M_PI * pow(h, 9)));
    density_fwd_kernel<scalar_t><<<blocks_for(N), kThreads, 0, stream>>>(N, K, x.data_ptr<scalar_t>(),
                                                                          idx.data_ptr<int64_t>(), h2, c,
                                                                          D.data_ptr<scalar_t>());
  });
  return {D};
}

std::vector<torch::Tensor> sph_density_backward_cuda(torch::Tensor x, torch::Tensor idx, double h, torch::Tensor gD) {
  const c10::cuda::CUDAGuard guard(x.device());
  x = x.contiguous();
  idx = idx.contiguous();
  gD = gD.contiguous();
  int64_t N = x.size(0), K = idx.size(1);
  auto gx = torch::zeros_like(x);
  if (N == 0) return {gx};
  auto stream = at::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "sph_density_backward_cuda", [&] {
    scalar_t h2 = (scalar_t)(h * h), c = (scalar_t)(315.0 / (64.0 * M_PI * pow(h, 9)));
    density_bwd_kernel<scalar_t><<<blocks_for(N), kThreads, 0, stream>>>(N, K, x.data_ptr<scalar_t>(),
                                                                          idx.data_ptr<int64_t>(), h2, c,
                                                                          gD.data_ptr<scalar_t>(), gx.data_ptr<scalar_t>());
  });
  return {gx};
}

std::vector<torch::Tensor> knn_cuda(torch::Tensor x, torch::Tensor y, int64_t k, double radius, bool exclude_self,
                                    bool sorted) {
  const c10::cuda::CUDAGuard guard(x.device());
  x = x.contiguous();
  y = y.contiguous();
  int64_t N = x.size(0), M = y.size(0);
  TORCH_CHECK(k <= 128, "knn on CUDA: k must be <= 128, got ", k);
  auto idx = torch::full({N, k}, -1, x.options().dtype(torch::kInt64));
  auto dist = torch::full({N, k}, INFINITY, x.options());
  if (N == 0 || M == 0 || k == 0) return {idx, dist};
  auto lo = std::get<0>(y.min(0)).to(torch::kCPU, torch::kFloat64).contiguous();
  GridSpec g;
  for (int a = 0; a < 3; ++a) g.lo[a] = lo.data_ptr<double>()[a];
  g.inv = 1.0 / radius;
  g.table = hash_table_size(M);
  auto i64 = x.options().dtype(torch::kInt64);
  auto cells = torch::empty({M, 3}, i64), hash = torch::empty({M}, i64);
  auto counts = torch::zeros({g.table}, x.options().dtype(torch::kInt32));
#define GF_KNN_LAUNCH(KM)                                                                                  \
  query_kernel<scalar_t, KM><<<blocks_for(N), kThreads, 0, stream>>>(                                      \
      g, N, (int)k, x.data_ptr<scalar_t>(), y.data_ptr<scalar_t>(), cells.data_ptr<int64_t>(),            \
      start.data_ptr<int64_t>(), order.data_ptr<int64_t>(), radius, exclude_self, sorted, idx.data_ptr<int64_t>(), \
      dist.data_ptr<scalar_t>())
  auto stream = at::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "knn_hash_cuda", [&] {
    hash_kernel<scalar_t><<<blocks_for(M), kThreads, 0, stream>>>(g, M, y.data_ptr<scalar_t>(),
                                                                   cells.data_ptr<int64_t>(), hash.data_ptr<int64_t>(),
                                                                   counts.data_ptr<int32_t>());
  });
  auto start = torch::zeros({g.table + 1}, i64);
  start.slice(0, 1).copy_(torch::cumsum(counts, 0));
  auto cursor = torch::zeros({g.table}, x.options().dtype(torch::kInt32));
  auto order = torch::empty({M}, i64);
  fill_kernel<<<blocks_for(M), kThreads, 0, stream>>>(M, hash.data_ptr<int64_t>(), start.data_ptr<int64_t>(),
                                                       cursor.data_ptr<int32_t>(), order.data_ptr<int64_t>());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "knn_query_cuda", [&] {
    if (k <= 16) GF_KNN_LAUNCH(16);
    else if (k <= 32) GF_KNN_LAUNCH(32);
    else if (k <= 64) GF_KNN_LAUNCH(64);
    else GF_KNN_LAUNCH(128);
  });
#undef GF_KNN_LAUNCH
  cudaError_t e = cudaGetLastError();
  TORCH_CHECK(e == cudaSuccess, "knn_cuda: CUDA error ", cudaGetErrorString(e));
  return {idx, dist};
}

}  // namespace gf
