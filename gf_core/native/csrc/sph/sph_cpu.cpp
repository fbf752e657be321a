// CPU neighbour search (OpenMP over queries): K nearest within a radius on a hashed grid.
// Math in sph_math.h; dispatch and bindings in ext.cpp; the CUDA twin in sph_cuda.cu.
#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "ops.h"
#include "parallel.h"
#include "sph_math.h"

namespace gf {

namespace {

template <typename S>
void knn_impl(const S* x, int64_t N, const S* y, int64_t M, int k, double radius, bool exclude_self, bool sorted,
              int64_t* out_idx, S* out_dist) {
  GridSpec g;
  for (int a = 0; a < 3; ++a) {
    double lo = INFINITY;
    for (int64_t j = 0; j < M; ++j) lo = std::min(lo, (double)y[3 * j + a]);
    g.lo[a] = lo;
  }
  g.inv = 1.0 / radius;
  g.table = hash_table_size(M);
  // counting sort of y by cell hash; the sorted cells and positions are copied out so that a
  // bucket's points lie contiguously in memory
  std::vector<int64_t> hash(M), start(g.table + 1, 0), order(M);
  std::vector<int64_t> cells(3 * M), scells(3 * M);
  std::vector<S> spos(3 * M);
  for (int64_t j = 0; j < M; ++j) {
    int64_t c[3];
    cell_of(g, y[3 * j], y[3 * j + 1], y[3 * j + 2], c);
    cells[3 * j] = c[0]; cells[3 * j + 1] = c[1]; cells[3 * j + 2] = c[2];
    hash[j] = cell_hash(g, c[0], c[1], c[2]);
    start[hash[j] + 1]++;
  }
  for (int64_t b = 0; b < g.table; ++b) start[b + 1] += start[b];
  std::vector<int64_t> fill(start.begin(), start.end() - 1);
  for (int64_t j = 0; j < M; ++j) order[fill[hash[j]]++] = j;  // index order kept inside a bucket
  for (int64_t q = 0; q < M; ++q)
    for (int a = 0; a < 3; ++a) {
      scells[3 * q + a] = cells[3 * order[q] + a];
      spos[3 * q + a] = y[3 * order[q] + a];
    }
  const S r2 = (S)(radius * radius);
  // x is y when exclude_self: its queries then run in grid order (neighbouring queries share buckets)
  const bool same = exclude_self;
#pragma omp parallel
  {
    std::vector<S> dk(k);
    std::vector<int64_t> jk(k);
#pragma omp for schedule(dynamic, 256)
    for (int64_t qk = 0; qk < N; ++qk) {
      const int64_t i = same ? order[qk] : qk;
      const S xi[3] = {x[3 * i], x[3 * i + 1], x[3 * i + 2]};
      int64_t c[3];
      if (same) {
        c[0] = scells[3 * qk]; c[1] = scells[3 * qk + 1]; c[2] = scells[3 * qk + 2];
      } else {
        cell_of(g, xi[0], xi[1], xi[2], c);
      }
      int n = 0, far = -1;
      for (int dx = -1; dx <= 1; ++dx)
        for (int dy = -1; dy <= 1; ++dy)
          for (int dz = -1; dz <= 1; ++dz) {
            const int64_t cx = c[0] + dx, cy = c[1] + dy, cz = c[2] + dz;
            const int64_t b = cell_hash(g, cx, cy, cz);
            for (int64_t q = start[b]; q < start[b + 1]; ++q) {
              if (scells[3 * q] != cx || scells[3 * q + 1] != cy || scells[3 * q + 2] != cz) continue;  // hash collision
              const S ex = xi[0] - spos[3 * q], ey = xi[1] - spos[3 * q + 1], ez = xi[2] - spos[3 * q + 2];
              const S d2 = ex * ex + ey * ey + ez * ez;
              if (!(d2 < r2)) continue;
              const int64_t j = order[q];
              if (same && j == i) continue;
              n = topk_push<S>(d2, j, dk.data(), jk.data(), n, k, far);
            }
          }
      if (sorted) sort_nearest<S>(dk.data(), jk.data(), n);
      for (int s = 0; s < k; ++s) {
        out_idx[i * k + s] = s < n ? jk[s] : -1;
        out_dist[i * k + s] = s < n ? std::sqrt(dk[s]) : (S)INFINITY;
      }
    }
  }
}

template <typename S>
void density_fwd_impl(int64_t N, int64_t K, const S* p, const int64_t* nb, double h, S* d) {
  const S h2 = (S)(h * h), c = (S)(315.0 / (64.0 * M_PI * std::pow(h, 9)));
#pragma omp parallel for schedule(static)
  for (int64_t i = 0; i < N; ++i) {
    S acc = poly6<S>(0, h2, c);
    for (int64_t s = 0; s < K; ++s) {
      int64_t j = nb[i * K + s];
      if (j < 0) continue;
      S ex = p[3 * i] - p[3 * j], ey = p[3 * i + 1] - p[3 * j + 1], ez = p[3 * i + 2] - p[3 * j + 2];
      acc += poly6<S>(ex * ex + ey * ey + ez * ez, h2, c);
    }
    d[i] = acc;
  }
}

// Deterministic: each thread accumulates into its own buffer (static schedule), and the buffers
// are summed in thread order, so the result does not depend on timing (no atomics).
template <typename S>
void density_bwd_impl(int64_t N, int64_t K, const S* p, const int64_t* nb, double h, const S* g, S* out) {
  const S h2 = (S)(h * h), c = (S)(315.0 / (64.0 * M_PI * std::pow(h, 9)));
  const int nt = num_threads();
  std::vector<std::vector<double>> bufs(nt);
#pragma omp parallel
  {
    const int tid = thread_id();
    std::vector<double>& acc = bufs[tid];
    acc.assign((size_t)N * 3, 0.0);
#pragma omp for schedule(static)
    for (int64_t i = 0; i < N; ++i) {
      for (int64_t s = 0; s < K; ++s) {
        int64_t j = nb[i * K + s];
        if (j < 0) continue;
        S e[3] = {p[3 * i] - p[3 * j], p[3 * i + 1] - p[3 * j + 1], p[3 * i + 2] - p[3 * j + 2]};
        S q = h2 - (e[0] * e[0] + e[1] * e[1] + e[2] * e[2]);
        if (q <= 0) continue;
        double f = (double)g[i] * -6.0 * (double)c * (double)q * (double)q;  // dW/dx_i = -6 c q^2 (x_i - x_j)
        for (int a = 0; a < 3; ++a) {
          acc[3 * i + a] += f * e[a];
          acc[3 * j + a] -= f * e[a];
        }
      }
    }
  }
#pragma omp parallel for schedule(static)
  for (int64_t k = 0; k < N * 3; ++k) {
    double v = 0;
    for (int t = 0; t < nt; ++t)
      if (!bufs[t].empty()) v += bufs[t][k];
    out[k] = (S)v;
  }
}

}  // namespace

std::vector<torch::Tensor> knn_cpu(torch::Tensor x, torch::Tensor y, int64_t k, double radius, bool exclude_self,
                                   bool sorted) {
  x = x.contiguous();
  y = y.contiguous();
  int64_t N = x.size(0), M = y.size(0);
  auto idx = torch::full({N, k}, -1, x.options().dtype(torch::kInt64));
  auto dist = torch::full({N, k}, INFINITY, x.options());
  if (N == 0 || M == 0 || k == 0) return {idx, dist};
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "knn_cpu", [&] {
    knn_impl<scalar_t>(x.data_ptr<scalar_t>(), N, y.data_ptr<scalar_t>(), M, (int)k, radius, exclude_self, sorted,
                       idx.data_ptr<int64_t>(), dist.data_ptr<scalar_t>());
  });
  return {idx, dist};
}

// D_i = W(0) + sum_s W(|x_i - x_idx[i,s]|) over the non-padded neighbours (unit mass, Eq. 5)
std::vector<torch::Tensor> sph_density_forward_cpu(torch::Tensor x, torch::Tensor idx, double h) {
  x = x.contiguous();
  idx = idx.contiguous();
  int64_t N = x.size(0), K = idx.size(1);
  auto D = torch::empty({N}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "sph_density_forward_cpu", [&] {
    density_fwd_impl<scalar_t>(N, K, x.data_ptr<scalar_t>(), idx.data_ptr<int64_t>(), h, D.data_ptr<scalar_t>());
  });
  return {D};
}

// dL/dx from dL/dD: each pair (i, j) moves x_i by +g and x_j by -g (atomics on j)
std::vector<torch::Tensor> sph_density_backward_cpu(torch::Tensor x, torch::Tensor idx, double h, torch::Tensor gD) {
  x = x.contiguous();
  idx = idx.contiguous();
  gD = gD.contiguous();
  int64_t N = x.size(0), K = idx.size(1);
  auto gx = torch::zeros_like(x);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "sph_density_backward_cpu", [&] {
    density_bwd_impl<scalar_t>(N, K, x.data_ptr<scalar_t>(), idx.data_ptr<int64_t>(), h, gD.data_ptr<scalar_t>(),
                               gx.data_ptr<scalar_t>());
  });
  return {gx};
}

}  // namespace gf
