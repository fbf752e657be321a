// CPU SPH engine for the simulators (OpenMP): fixed-radius neighbour lists in CSR form on the
// hashed grid of sph_math.h, and the DFSPH pair sums over them (Bender & Koschier 2017). The
// Python solver (gf_core/sim/dfsph.py) keeps the algorithm's steps; the loops over particles and
// pairs are here. CPU tensors only: CUDA tensors use the torch path of the solver.
//
// Neighbour lists: rows are query particles, columns the neighbours' indices, ascending within a
// row. A grid over the neighbour set (points sorted by the hash of their cell, counting sort) can
// be built once and reused: the static wall particles are indexed once per solver.
#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "parallel.h"
#include "sph_math.h"

namespace gf {

namespace {

// Cell coordinates bounded so that far-away (finite) points cannot overflow the integer maths;
// points beyond the bound share an edge cell, which stays correct (distances are checked exactly).
constexpr double kCellBound = 1e12;

inline void cell_clamped(const double lo[3], double inv, double x, double y, double z, int64_t c[3]) {
  const double p[3] = {x, y, z};
  for (int a = 0; a < 3; ++a) {
    double q = std::floor((p[a] - lo[a]) * inv);
    q = std::min(std::max(q, -kCellBound), kCellBound);
    c[a] = (int64_t)q;
  }
}

template <typename S>
void check_finite(const S* p, int64_t n, const char* what) {
  bool ok = true;
#pragma omp parallel for reduction(&& : ok) schedule(static)
  for (int64_t i = 0; i < 3 * n; ++i) ok = ok && std::isfinite((double)p[i]);
  TORCH_CHECK(ok, what, ": positions contain NaN or infinite values");
}

// The grid's tensors: lo (3, float64), cell size (1, float64), starts (table + 1), order (M),
// cells (M, 3), pos (M, 3): the points sorted by the hash bucket of their cell (counting sort,
// index order kept inside a bucket), bucket b holding sorted entries starts[b] .. starts[b+1];
// order maps a sorted entry to the point's index, cells and pos are the sorted entries' cell and
// position. Scanning a bucket reads contiguous memory.
template <typename S>
struct GridView {
  double lo[3];
  double inv;
  int64_t table;
  const int64_t* starts;
  const int64_t* order;
  const int64_t* cells;
  const S* pos;
};

template <typename S>
GridView<S> view_of(const std::vector<torch::Tensor>& g) {
  GridView<S> v;
  const double* lo = g[0].data_ptr<double>();
  for (int a = 0; a < 3; ++a) v.lo[a] = lo[a];
  v.inv = 1.0 / g[1].data_ptr<double>()[0];
  v.starts = g[2].data_ptr<int64_t>();
  v.table = g[2].size(0) - 1;
  v.order = g[3].data_ptr<int64_t>();
  v.cells = g[4].data_ptr<int64_t>();
  v.pos = g[5].data_ptr<S>();
  return v;
}

void check_grid(const std::vector<torch::Tensor>& grid, const torch::Tensor& y, double cell, const char* op) {
  TORCH_CHECK(grid.size() == 6 && grid[3].size(0) == y.size(0), op, ": the grid was not built over y (",
              grid.size() == 6 ? grid[3].size(0) : -1, " points, y has ", y.size(0), ")");
  TORCH_CHECK(grid[5].scalar_type() == y.scalar_type(), op, ": the grid was built for ",
              c10::toString(grid[5].scalar_type()), " points, y is ", c10::toString(y.scalar_type()));
  TORCH_CHECK(std::abs(grid[1].data_ptr<double>()[0] - cell) <= 1e-12 * cell, op,
              ": the grid's cell size must equal the radius (", grid[1].data_ptr<double>()[0], " vs ", cell, ")");
}

template <typename S>
std::vector<torch::Tensor> build_grid(const torch::Tensor& y, double cell) {
  const int64_t M = y.size(0);
  const S* p = y.data_ptr<S>();
  auto f64 = torch::TensorOptions().dtype(torch::kFloat64);
  auto i64 = torch::TensorOptions().dtype(torch::kInt64);
  auto lo_t = torch::zeros({3}, f64);
  double* lo = lo_t.data_ptr<double>();
  for (int a = 0; a < 3; ++a) {
    double m = M ? INFINITY : 0.0;
    for (int64_t j = 0; j < M; ++j) m = std::min(m, (double)p[3 * j + a]);
    lo[a] = m;
  }
  auto cell_t = torch::full({1}, cell, f64);
  const int64_t table = hash_table_size(std::max<int64_t>(M, 1));
  auto starts_t = torch::zeros({table + 1}, i64), order_t = torch::empty({M}, i64);
  auto cells_t = torch::empty({M, 3}, i64), pos_t = torch::empty({M, 3}, y.options());
  int64_t* starts = starts_t.data_ptr<int64_t>();
  int64_t* order = order_t.data_ptr<int64_t>();
  std::vector<int64_t> hash(M), cells(3 * M);
  GridSpec g;
  g.table = table;
  const double inv = 1.0 / cell;
#pragma omp parallel for schedule(static)
  for (int64_t j = 0; j < M; ++j) {
    cell_clamped(lo, inv, (double)p[3 * j], (double)p[3 * j + 1], (double)p[3 * j + 2], &cells[3 * j]);
    hash[j] = cell_hash(g, cells[3 * j], cells[3 * j + 1], cells[3 * j + 2]);
  }
  for (int64_t j = 0; j < M; ++j) starts[hash[j] + 1]++;
  for (int64_t b = 0; b < table; ++b) starts[b + 1] += starts[b];
  std::vector<int64_t> fill(starts, starts + table);
  for (int64_t j = 0; j < M; ++j) order[fill[hash[j]]++] = j;
  int64_t* sc = cells_t.data_ptr<int64_t>();
  S* sp = pos_t.data_ptr<S>();
#pragma omp parallel for schedule(static)
  for (int64_t q = 0; q < M; ++q)
    for (int a = 0; a < 3; ++a) {
      sc[3 * q + a] = cells[3 * order[q] + a];
      sp[3 * q + a] = p[3 * order[q] + a];
    }
  return {lo_t, cell_t, starts_t, order_t, cells_t, pos_t};
}

// Calls f(j, d2) for every grid point j within sqrt(r2) of (x, y, z) in cell c (j != skip).
template <typename S, typename F>
inline void for_neighbours(const GridView<S>& g, const GridSpec& gs, const int64_t c[3], S x, S y, S z, S r2,
                           int64_t skip, F&& f) {
  for (int dx = -1; dx <= 1; ++dx)
    for (int dy = -1; dy <= 1; ++dy)
      for (int dz = -1; dz <= 1; ++dz) {
        const int64_t cx = c[0] + dx, cy = c[1] + dy, cz = c[2] + dz;
        const int64_t b = cell_hash(gs, cx, cy, cz);
        for (int64_t q = g.starts[b]; q < g.starts[b + 1]; ++q) {
          if (g.cells[3 * q] != cx || g.cells[3 * q + 1] != cy || g.cells[3 * q + 2] != cz) continue;
          const S ex = x - g.pos[3 * q], ey = y - g.pos[3 * q + 1], ez = z - g.pos[3 * q + 2];
          const S d2 = ex * ex + ey * ey + ez * ez;
          if (d2 < r2) {
            const int64_t j = g.order[q];
            if (j != skip) f(j, d2);
          }
        }
      }
}

// The query points in grid order when they are the grid's own points (neighbouring queries then
// read the same buckets), else in input order: query k is point qi(k) at (x, y, z) in cell c.
template <typename S>
struct Queries {
  const S* px;
  int64_t N;
  bool same;
  const GridView<S>* g;
  int64_t index(int64_t k) const { return same ? g->order[k] : k; }
  void get(int64_t k, S xyz[3], int64_t c[3]) const {
    if (same) {
      for (int a = 0; a < 3; ++a) { xyz[a] = g->pos[3 * k + a]; c[a] = g->cells[3 * k + a]; }
    } else {
      for (int a = 0; a < 3; ++a) xyz[a] = px[3 * k + a];
      cell_clamped(g->lo, g->inv, (double)xyz[0], (double)xyz[1], (double)xyz[2], c);
    }
  }
};

// Neighbours of each x_i among the grid's points y_j with |x_i - y_j| < radius (j != i when
// exclude_self, x being y): CSR (rowptr (N+1), col (P)), columns ascending within a row. One
// search: each thread collects the rows of its block of queries, then copies them into place.
template <typename S>
std::vector<torch::Tensor> pairs_impl(const torch::Tensor& x, const GridView<S>& g, double radius, bool exclude_self) {
  const int64_t N = x.size(0);
  auto i64 = torch::TensorOptions().dtype(torch::kInt64);
  auto rowptr_t = torch::zeros({N + 1}, i64);
  int64_t* rowptr = rowptr_t.data_ptr<int64_t>();
  const int nt = num_threads();
  std::vector<std::vector<int64_t>> cols(nt);
  const S r2 = (S)(radius * radius);
  GridSpec gs;
  gs.table = g.table;
  const Queries<S> Q{x.data_ptr<S>(), N, exclude_self, &g};
  std::vector<int64_t> bounds(nt + 1, N);
  bounds[0] = 0;
  torch::Tensor col_t;
#pragma omp parallel num_threads(nt)
  {
    const int t = thread_id(), T = team_size();
    const int64_t b0 = N * t / T, b1 = N * (t + 1) / T;
    std::vector<int64_t>& mine = cols[t];
    mine.reserve((size_t)(b1 - b0) * 48);
    for (int64_t k = b0; k < b1; ++k) {
      S p[3];
      int64_t c[3];
      Q.get(k, p, c);
      const int64_t i = Q.index(k);
      const size_t begin = mine.size();
      for_neighbours(g, gs, c, p[0], p[1], p[2], r2, exclude_self ? i : -1,
                     [&](int64_t j, S) { mine.push_back(j); });
      std::sort(mine.begin() + begin, mine.end());
      rowptr[i + 1] = (int64_t)(mine.size() - begin);
    }
#pragma omp barrier
#pragma omp single
    {
      for (int64_t i = 0; i < N; ++i) rowptr[i + 1] += rowptr[i];
      col_t = torch::empty({rowptr[N]}, i64);
    }
    int64_t* col = col_t.data_ptr<int64_t>();
    size_t at = 0;
    for (int64_t k = b0; k < b1; ++k) {
      const int64_t i = Q.index(k), m = rowptr[i + 1] - rowptr[i];
      std::copy(mine.begin() + at, mine.begin() + at + m, col + rowptr[i]);
      at += m;
    }
  }
  return {rowptr_t, col_t};
}

// ---- Wendland C2 (support h), 3D: W(q) = 21 / (2 pi h^3) (1 - q)^4 (1 + 4 q) ---------------------
struct Wendland {
  double h, cw, cg;
  explicit Wendland(double h_) : h(h_), cw(21.0 / (2.0 * M_PI * h_ * h_ * h_)), cg(-210.0 / (M_PI * h_ * h_ * h_ * h_)) {}
  double W(double r) const {
    double q = std::min(r / h, 1.0), a = 1.0 - q;
    return cw * a * a * a * a * (1.0 + 4.0 * q);
  }
  // grad_i W(x_i - x_j) = d * f / r with f = dW/dr = -210 / (pi h^4) q (1 - q)^3; zero for r ~ 0
  double grad_scale(double r) const {
    if (!(r > 1e-9 * h)) return 0.0;
    double q = std::min(r / h, 1.0), a = 1.0 - q;
    return cg * q * a * a * a / r;
  }
};

// SPH kernels by value (kernels.py): 0 cubic spline (SPlisHSPlasH's normalisation), 1 Wendland C2, 2 poly6
inline double kernel_value(int kind, double r, double h) {
  const double q = r / h;
  if (q >= 1.0) return 0.0;
  if (kind == 0) {
    const double k = 8.0 / (M_PI * h * h * h);
    return q <= 0.5 ? k * (6.0 * q * q * q - 6.0 * q * q + 1.0) : k * 2.0 * (1.0 - q) * (1.0 - q) * (1.0 - q);
  }
  if (kind == 1) return Wendland(h).W(r);
  const double d = h * h - r * r;
  return 315.0 / (64.0 * M_PI * std::pow(h, 9)) * d * d * d;
}

// sum_j W(|x_i - y_j|) over the grid's points within h (j != i when exclude_self), without storing pairs
template <typename S>
void kernel_sum_impl(const torch::Tensor& x, const GridView<S>& g, double h, int kind, bool exclude_self, S* out) {
  GridSpec gs;
  gs.table = g.table;
  const Queries<S> Q{x.data_ptr<S>(), x.size(0), exclude_self, &g};
  const S h2 = (S)(h * h);
#pragma omp parallel for schedule(static)
  for (int64_t k = 0; k < Q.N; ++k) {
    S p[3];
    int64_t c[3];
    Q.get(k, p, c);
    const int64_t i = Q.index(k);
    double acc = 0;
    for_neighbours(g, gs, c, p[0], p[1], p[2], h2, exclude_self ? i : -1,
                   [&](int64_t, S d2) { acc += kernel_value(kind, std::sqrt((double)d2), h); });
    out[i] = (S)acc;
  }
}

}  // namespace

std::vector<torch::Tensor> grid_build_cpu(torch::Tensor y, double cell) {
  y = y.contiguous();
  std::vector<torch::Tensor> out;
  AT_DISPATCH_FLOATING_TYPES(y.scalar_type(), "grid_build_cpu", [&] {
    check_finite<scalar_t>(y.data_ptr<scalar_t>(), y.size(0), "grid_build");
    out = build_grid<scalar_t>(y, cell);
  });
  return out;
}

std::vector<torch::Tensor> radius_pairs_cpu(torch::Tensor x, torch::Tensor y, std::vector<torch::Tensor> grid,
                                            double radius, bool exclude_self) {
  x = x.contiguous();
  y = y.contiguous();
  std::vector<torch::Tensor> out;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "radius_pairs_cpu", [&] {
    check_finite<scalar_t>(x.data_ptr<scalar_t>(), x.size(0), "radius_pairs");
    if (grid.empty()) {
      check_finite<scalar_t>(y.data_ptr<scalar_t>(), y.size(0), "radius_pairs");
      grid = build_grid<scalar_t>(y, radius);
    }
    check_grid(grid, y, radius, "radius_pairs");
    out = pairs_impl<scalar_t>(x, view_of<scalar_t>(grid), radius, exclude_self);
  });
  return out;
}

namespace {

template <typename S>
void neighbourhood_impl(const torch::Tensor& x, const torch::Tensor& wall, const int64_t* rp, const int64_t* cj,
                        const int64_t* brp, const int64_t* bc, const int64_t* wrow, const int64_t* wfl,
                        const int64_t* wpair, const torch::Tensor& wall_rho, const torch::Tensor& wall_count, double V,
                        double h, double wall_alpha_cap, int64_t n, int64_t nw, torch::Tensor& w_t, torch::Tensor& gw_t,
                        torch::Tensor& wb_t, torch::Tensor& gwb_t, torch::Tensor& rho_t, torch::Tensor& alpha_t,
                        int64_t* count) {
  const int64_t* wcount = wall_count.data_ptr<int64_t>();
  const Wendland K(h);
  const double tiny = 1e-9 / (h * h), cap = wall_alpha_cap;
    const S* px = x.data_ptr<S>();
    const S* pw = wall.data_ptr<S>();
    S* w = w_t.data_ptr<S>();
    S* gw = gw_t.data_ptr<S>();
    S* wb = wb_t.data_ptr<S>();
    S* gwb = gwb_t.data_ptr<S>();
    S* rho = rho_t.data_ptr<S>();
    S* alpha = alpha_t.data_ptr<S>();
    const S* wrho = wall_rho.data_ptr<S>();
    const double W0 = K.W(0.0);
#pragma omp parallel for schedule(static)
    for (int64_t i = 0; i < n; ++i) {
      double r_acc = W0, gf[3] = {0, 0, 0}, s2 = 0;
      for (int64_t p = rp[i]; p < rp[i + 1]; ++p) {
        const int64_t j = cj[p];
        double d[3] = {(double)px[3 * i] - px[3 * j], (double)px[3 * i + 1] - px[3 * j + 1],
                       (double)px[3 * i + 2] - px[3 * j + 2]};
        const double r = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        const double Wr = K.W(r), f = V * K.grad_scale(r);
        w[p] = (S)Wr;
        r_acc += Wr;
        double g2 = 0;
        for (int a = 0; a < 3; ++a) {
          const S ga = (S)(f * d[a]);
          gw[3 * p + a] = ga;
          gf[a] += ga;
          g2 += (double)ga * ga;
        }
        s2 += g2;
      }
      for (int64_t p = brp[i]; p < brp[i + 1]; ++p) {
        const int64_t b = bc[p];
        double d[3] = {(double)px[3 * i] - pw[3 * b], (double)px[3 * i + 1] - pw[3 * b + 1],
                       (double)px[3 * i + 2] - pw[3 * b + 2]};
        const double r = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        const double Wr = K.W(r), f = V * K.grad_scale(r);
        wb[p] = (S)Wr;
        r_acc += Wr;
        for (int a = 0; a < 3; ++a) {
          const S ga = (S)(f * d[a]);
          gwb[3 * p + a] = ga;
          gf[a] += ga;
        }
      }
      rho[i] = (S)(V * r_acc);
      const double D = gf[0] * gf[0] + gf[1] * gf[1] + gf[2] * gf[2] + s2;
      alpha[i] = D > tiny ? (S)(1.0 / D) : S(0);
      count[i] = (rp[i + 1] - rp[i]) + (brp[i + 1] - brp[i]);
    }
#pragma omp parallel for schedule(static)
    for (int64_t b = 0; b < nw; ++b) {
      double r_acc = 0, D = 0;
      for (int64_t q = wrow[b]; q < wrow[b + 1]; ++q) {
        const int64_t p = wpair[q];
        r_acc += wb[p];
        D += (double)gwb[3 * p] * gwb[3 * p] + (double)gwb[3 * p + 1] * gwb[3 * p + 1] +
             (double)gwb[3 * p + 2] * gwb[3 * p + 2];
      }
      rho[n + b] = (S)((double)wrho[b] + V * r_acc);
      double a = D > tiny ? 1.0 / D : 0.0;
      alpha[n + b] = (S)std::min(a, cap);
      count[n + b] = wcount[b] + (wrow[b + 1] - wrow[b]);
    }
}

}  // namespace

torch::Tensor kernel_sum_cpu(torch::Tensor x, torch::Tensor y, std::vector<torch::Tensor> grid, double h,
                             int64_t kernel, bool exclude_self) {
  x = x.contiguous();
  y = y.contiguous();
  auto out = torch::zeros({x.size(0)}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "kernel_sum_cpu", [&] {
    check_finite<scalar_t>(x.data_ptr<scalar_t>(), x.size(0), "kernel_sum");
    if (grid.empty()) {
      check_finite<scalar_t>(y.data_ptr<scalar_t>(), y.size(0), "kernel_sum");
      grid = build_grid<scalar_t>(y, h);
    }
    check_grid(grid, y, h, "kernel_sum");
    kernel_sum_impl<scalar_t>(x, view_of<scalar_t>(grid), h, (int)kernel, exclude_self, out.data_ptr<scalar_t>());
  });
  return out;
}

// DFSPH neighbourhood (dfsph.py, step 4): per fluid particle i with fluid neighbours j (CSR
// rowptr/col) and wall neighbours b (CSR browptr/bcol):
//   W_ij, V gradW_ij, rho~_i = V (W(0) + sum_j W_ij + sum_b W_ib), g_f = sum_j V gradW_ij,
//   g_b = sum_b V gradW_ib, alpha_i = 1 / (|g_f + g_b|^2 + sum_j |V gradW_ij|^2);
// per wall particle b (its fluid neighbours through the transposed wall CSR):
//   rho~_b = wall_rho_b + V sum_i W_ib, alpha_b = 1 / sum_i |V gradW_ib|^2 (capped);
// alpha = 0 where the diagonal is below 1e-9 / h^2. Returns
//   {w (P), gw (P, 3), wb (Pb), gwb (Pb, 3), rho_all (n + nw), alpha (n + nw), count (n + nw),
//    wrowptr (nw + 1), wfluid (Pb), wpair (Pb)}.
std::vector<torch::Tensor> dfsph_neighbourhood_cpu(torch::Tensor x, torch::Tensor wall, torch::Tensor rowptr,
                                                   torch::Tensor col, torch::Tensor browptr, torch::Tensor bcol,
                                                   torch::Tensor wall_rho, torch::Tensor wall_count, double V,
                                                   double h, double wall_alpha_cap) {
  x = x.contiguous(); wall = wall.contiguous();
  const int64_t n = x.size(0), nw = wall.size(0), P = col.size(0), Pb = bcol.size(0);
  auto opt = x.options();
  auto i64 = torch::TensorOptions().dtype(torch::kInt64);
  auto w_t = torch::empty({P}, opt), gw_t = torch::empty({P, 3}, opt);
  auto wb_t = torch::empty({Pb}, opt), gwb_t = torch::empty({Pb, 3}, opt);
  auto rho_t = torch::empty({n + nw}, opt), alpha_t = torch::empty({n + nw}, opt);
  auto count_t = torch::empty({n + nw}, i64);
  auto wrow_t = torch::zeros({nw + 1}, i64), wfl_t = torch::empty({Pb}, i64), wpair_t = torch::empty({Pb}, i64);
  const int64_t* rp = rowptr.data_ptr<int64_t>();
  const int64_t* cj = col.data_ptr<int64_t>();
  const int64_t* brp = browptr.data_ptr<int64_t>();
  const int64_t* bc = bcol.data_ptr<int64_t>();
  int64_t* wrow = wrow_t.data_ptr<int64_t>();
  int64_t* wfl = wfl_t.data_ptr<int64_t>();
  int64_t* wpair = wpair_t.data_ptr<int64_t>();
  int64_t* count = count_t.data_ptr<int64_t>();
  // transpose of the wall CSR (counting sort by wall index; pairs stay in fluid order)
  for (int64_t p = 0; p < Pb; ++p) wrow[bc[p] + 1]++;
  for (int64_t b = 0; b < nw; ++b) wrow[b + 1] += wrow[b];
  {
    std::vector<int64_t> fill(wrow, wrow + nw);
    for (int64_t i = 0; i < n; ++i)
      for (int64_t p = brp[i]; p < brp[i + 1]; ++p) {
        const int64_t q = fill[bc[p]]++;
        wfl[q] = i;
        wpair[q] = p;
      }
  }
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "dfsph_neighbourhood_cpu", [&] {
    neighbourhood_impl<scalar_t>(x, wall, rp, cj, brp, bc, wrow, wfl, wpair, wall_rho, wall_count, V, h, wall_alpha_cap,
                                 n, nw, w_t, gw_t, wb_t, gwb_t, rho_t, alpha_t, count);
  });
  return {w_t, gw_t, wb_t, gwb_t, rho_t, alpha_t, count_t, wrow_t, wfl_t, wpair_t};
}

namespace {

// The DFSPH operators over the neighbourhood (see dfsph.py), one row at a time:
//   div_k(v):  fluid i: sum_j (v_i - v_j) . V gradW_ij + sum_b v_i . V gradW_ib;  wall b: sum_i v_i . V gradW_ib
//   dv(kappa): fluid i: -dt [sum_j (k_i + k_j) V gradW_ij + sum_b (k_i + k_b) V gradW_ib]   (= -dt D^T kappa)
template <typename S>
struct DfsphOps {
  int64_t n, nw;
  const int64_t *rp, *cj, *brp, *bc, *wrow, *wfl, *wpair;
  const S *gw, *gwb;

  double div(const S* v, int64_t k) const {
    double acc = 0;
    if (k < n) {
      const int64_t i = k;
      const double vi[3] = {v[3 * i], v[3 * i + 1], v[3 * i + 2]};
      for (int64_t p = rp[i]; p < rp[i + 1]; ++p) {
        const int64_t j = cj[p];
        acc += (vi[0] - v[3 * j]) * gw[3 * p] + (vi[1] - v[3 * j + 1]) * gw[3 * p + 1] +
               (vi[2] - v[3 * j + 2]) * gw[3 * p + 2];
      }
      for (int64_t p = brp[i]; p < brp[i + 1]; ++p)
        acc += vi[0] * gwb[3 * p] + vi[1] * gwb[3 * p + 1] + vi[2] * gwb[3 * p + 2];
    } else {
      const int64_t b = k - n;
      for (int64_t q = wrow[b]; q < wrow[b + 1]; ++q) {
        const int64_t i = wfl[q], p = wpair[q];
        acc += (double)v[3 * i] * gwb[3 * p] + (double)v[3 * i + 1] * gwb[3 * p + 1] + (double)v[3 * i + 2] * gwb[3 * p + 2];
      }
    }
    return acc;
  }

  // v_i = v0_i - dt (D^T kappa)_i
  void apply(const S* v0, const double* kappa, double dt, S* v, int64_t i) const {
    double acc[3] = {0, 0, 0};
    const double ki = kappa[i];
    for (int64_t p = rp[i]; p < rp[i + 1]; ++p) {
      const double k = ki + kappa[cj[p]];
      for (int a = 0; a < 3; ++a) acc[a] += k * gw[3 * p + a];
    }
    for (int64_t p = brp[i]; p < brp[i + 1]; ++p) {
      const double k = ki + kappa[n + bc[p]];
      for (int a = 0; a < 3; ++a) acc[a] += k * gwb[3 * p + a];
    }
    for (int a = 0; a < 3; ++a) v[3 * i + a] = (S)((double)v0[3 * i + a] - dt * acc[a]);
  }
};

}  // namespace

namespace {

// One parallel region for the whole solve: per iteration three barriers (after the velocities,
// after the residuals and their sum, after the kappa update); every thread takes the same
// decision from the same sum, so no serial section is needed. Fewer thread wake-ups matter most
// on a busy machine or with OMP_WAIT_POLICY=PASSIVE.
template <typename S>
void solve_impl(torch::Tensor& v, double* kappa, const std::vector<torch::Tensor>& nb, const int64_t* rp,
                const int64_t* cj, const int64_t* brp, const int64_t* bc, int64_t n, int64_t m, int64_t mode,
                int64_t min_count, double dt, double scale, double tol, int64_t min_iters, int64_t max_iters,
                double* out) {
  const DfsphOps<S> ops{n, m - n, rp, cj, brp, bc, nb[7].data_ptr<int64_t>(), nb[8].data_ptr<int64_t>(),
                        nb[9].data_ptr<int64_t>(), nb[1].data_ptr<S>(), nb[3].data_ptr<S>()};
  S* pv = v.data_ptr<S>();
  const S* rho = nb[4].data_ptr<S>();
  const S* alpha = nb[5].data_ptr<S>();
  const int64_t* count = nb[6].data_ptr<int64_t>();
  std::vector<S> v0(pv, pv + 3 * n);
  std::vector<double> res(m), update(m, 0.0), kprev(m);
  const int nt = num_threads();
  std::vector<double> partial(nt, 0.0);
  int64_t it_out = max_iters, halvings_out = 0;
  double err_out = 0;
#pragma omp parallel num_threads(nt)
  {
    const int t = thread_id(), T = team_size();
    const int64_t f0 = n * t / T, f1 = n * (t + 1) / T, k0 = m * t / T, k1 = m * (t + 1) / T;
    double err = 0, err_prev = INFINITY, omega = 1.0;
    int64_t halvings = 0, it;
    bool have_update = false;
    for (it = 1; it <= max_iters; ++it) {
      for (int64_t i = f0; i < f1; ++i) ops.apply(v0.data(), kappa, dt, pv, i);
#pragma omp barrier
      double esum = 0;
      for (int64_t k = k0; k < k1; ++k) {
        const double d = ops.div(pv, k);
        const double r = mode == 0 ? (double)rho[k] + dt * d - 1.0 : (count[k] >= min_count ? d * dt : 0.0);
        res[k] = r;
        esum += r > 0 ? r : 0.0;
      }
      partial[t] = esum;
#pragma omp barrier
      esum = 0;
      for (int u = 0; u < T; ++u) esum += partial[u];  // the same order in every thread
      err = esum / (double)std::max<int64_t>(n, 1);
      if (have_update && !(err <= 2.0 * err_prev) && halvings < 20) {
        omega *= 0.5;
        ++halvings;
        for (int64_t k = k0; k < k1; ++k) kappa[k] = kprev[k] + omega * update[k];
#pragma omp barrier
        continue;
      }
      if (it > min_iters && err <= tol) break;
      err_prev = err;
      have_update = true;
      for (int64_t k = k0; k < k1; ++k) {
        kprev[k] = kappa[k];
        update[k] = (res[k] > 0 ? res[k] : 0.0) * (double)alpha[k] / scale;
        kappa[k] += omega * update[k];
      }
#pragma omp barrier
    }
    if (t == 0) {
      it_out = std::min(it, max_iters);
      err_out = err;
      halvings_out = halvings;
    }
  }
  out[0] = (double)it_out;
  out[1] = err_out;
  out[2] = (double)halvings_out;
}

template <typename S>
void xsph_impl(const S* pv, const int64_t* rp, const int64_t* cj, const S* pw, double cV, int64_t n, S* po) {
#pragma omp parallel for schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    double acc[3] = {0, 0, 0};
    for (int64_t p = rp[i]; p < rp[i + 1]; ++p) {
      const int64_t j = cj[p];
      for (int a = 0; a < 3; ++a) acc[a] += ((double)pv[3 * j + a] - pv[3 * i + a]) * pw[p];
    }
    for (int a = 0; a < 3; ++a) po[3 * i + a] = (S)((double)pv[3 * i + a] + cV * acc[a]);
  }
}

}  // namespace

// The Jacobi solve of dfsph.py `_solve` (Bender & Koschier 2017, Alg. 2/3), the whole loop here:
// residual_k = rho_all_k + dt div_k(v) - 1 (mode 0, constant density) or dt div_k(v) where
// count_k >= min_count, else 0 (mode 1, divergence free); kappa_k += omega max(residual_k, 0) alpha_k / scale;
// an update after which the error more than doubles (or turns NaN) is taken back and redone with
// half the relaxation. v (n, 3) is updated in place; kappa (n + nw) is the warm start.
// Returns {kappa, [iterations, error, halvings] (float64)}.
std::vector<torch::Tensor> dfsph_solve_cpu(torch::Tensor v, torch::Tensor kappa0, torch::Tensor rowptr,
                                           torch::Tensor col, torch::Tensor browptr, torch::Tensor bcol,
                                           std::vector<torch::Tensor> nb, int64_t mode, int64_t min_count, double dt,
                                           double scale, double tol, int64_t min_iters, int64_t max_iters) {
  TORCH_CHECK(v.is_contiguous(), "dfsph_solve: v must be contiguous (it is updated in place)");
  const int64_t n = v.size(0), m = nb[5].size(0);
  auto kappa_t = kappa0.to(torch::kFloat64).contiguous().clone();
  auto info = torch::zeros({3}, torch::TensorOptions().dtype(torch::kFloat64));
  AT_DISPATCH_FLOATING_TYPES(v.scalar_type(), "dfsph_solve_cpu", [&] {
    solve_impl<scalar_t>(v, kappa_t.data_ptr<double>(), nb, rowptr.data_ptr<int64_t>(), col.data_ptr<int64_t>(),
                         browptr.data_ptr<int64_t>(), bcol.data_ptr<int64_t>(), n, m, mode, min_count, dt, scale, tol, min_iters,
                         max_iters, info.data_ptr<double>());
  });
  return {kappa_t.to(v.scalar_type()), info};
}

namespace {

// PBF kernels (Mueller et al. 2003; pbf.py): poly6 for densities, the spiky gradient for constraint gradients
struct PbfKernels {
  double h, h2, c6, cs;
  explicit PbfKernels(double h_)
      : h(h_), h2(h_ * h_), c6(315.0 / (64.0 * M_PI * std::pow(h_, 9))), cs(-45.0 / (M_PI * std::pow(h_, 6))) {}
  double poly6(double r2) const {
    const double q = h2 - r2;
    return q > 0 ? c6 * q * q * q : 0.0;
  }
  double spiky_scale(double r) const {  // grad W = d * spiky_scale(|d|)
    if (!(r > 1e-9 * h) || r >= h) return 0.0;
    return cs * (h - r) * (h - r) / r;
  }
};

template <typename S>
void pbf_iteration_impl(const S* px, const S* pw, const int64_t* rp, const int64_t* cj, const int64_t* brp,
                        const int64_t* bc, int64_t n, double V, double h, double eps, double scorr_k,
                        double scorr_n, double w_dq, double grad2_lattice, S* dx, S* C, double* lam) {
  const PbfKernels K(h);
  const double W0 = K.poly6(0.0);
#pragma omp parallel for schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    double rho = W0, g[3] = {0, 0, 0}, s2 = 0;
    for (int64_t p = rp[i]; p < rp[i + 1]; ++p) {
      const int64_t j = cj[p];
      const double d[3] = {(double)px[3 * i] - px[3 * j], (double)px[3 * i + 1] - px[3 * j + 1],
                           (double)px[3 * i + 2] - px[3 * j + 2]};
      const double r2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
      rho += K.poly6(r2);
      const double f = V * K.spiky_scale(std::sqrt(r2));
      for (int a = 0; a < 3; ++a) g[a] += f * d[a];
      s2 += f * f * r2;
    }
    for (int64_t p = brp[i]; p < brp[i + 1]; ++p) {
      const int64_t b = bc[p];
      const double d[3] = {(double)px[3 * i] - pw[3 * b], (double)px[3 * i + 1] - pw[3 * b + 1],
                           (double)px[3 * i + 2] - pw[3 * b + 2]};
      const double r2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
      rho += K.poly6(r2);
      const double f = V * K.spiky_scale(std::sqrt(r2));
      for (int a = 0; a < 3; ++a) g[a] += f * d[a];
    }
    const double c = std::max(V * rho - 1.0, 0.0);
    C[i] = (S)c;
    lam[i] = -c / (g[0] * g[0] + g[1] * g[1] + g[2] * g[2] + s2 + eps);
  }
#pragma omp parallel for schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    double acc[3] = {0, 0, 0};
    for (int64_t p = rp[i]; p < rp[i + 1]; ++p) {
      const int64_t j = cj[p];
      const double d[3] = {(double)px[3 * i] - px[3 * j], (double)px[3 * i + 1] - px[3 * j + 1],
                           (double)px[3 * i + 2] - px[3 * j + 2]};
      const double r2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
      const double f = V * K.spiky_scale(std::sqrt(r2));
      double k = lam[i] + lam[j];
      if (scorr_k != 0.0) k += -scorr_k * std::pow(K.poly6(r2) / w_dq, scorr_n) / grad2_lattice;
      for (int a = 0; a < 3; ++a) acc[a] += k * f * d[a];
    }
    for (int64_t p = brp[i]; p < brp[i + 1]; ++p) {
      const int64_t b = bc[p];
      const double d[3] = {(double)px[3 * i] - pw[3 * b], (double)px[3 * i + 1] - pw[3 * b + 1],
                           (double)px[3 * i + 2] - pw[3 * b + 2]};
      const double r = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
      const double f = V * K.spiky_scale(r);
      for (int a = 0; a < 3; ++a) acc[a] += lam[i] * f * d[a];
    }
    for (int a = 0; a < 3; ++a) dx[3 * i + a] = (S)acc[a];
  }
}

}  // namespace

// One PBF constraint iteration (pbf.py step 3; Macklin & Mueller 2013, Alg. 1) over CSR lists:
//   C_i = max(rho~_i - 1, 0), rho~_i = V (W(0) + sum_j W_ij + sum_b W_ib)                       (poly6)
//   lambda_i = -C_i / (|sum_j V gradW_ij + sum_b V gradW_ib|^2 + sum_j |V gradW_ij|^2 + eps)      (spiky)
//   dx_i = sum_j V (lambda_i + lambda_j + s_corr_ij) gradW_ij + sum_b V lambda_i gradW_ib,
//   s_corr_ij = -k (W_ij / W(dq h))^n / G.     Returns {dx (n, 3), C (n)}.
std::vector<torch::Tensor> pbf_iteration_cpu(torch::Tensor x, torch::Tensor wall, torch::Tensor rowptr,
                                             torch::Tensor col, torch::Tensor browptr, torch::Tensor bcol, double V,
                                             double h, double eps, double scorr_k, double scorr_n, double w_dq,
                                             double grad2_lattice) {
  x = x.contiguous();
  wall = wall.contiguous();
  const int64_t n = x.size(0);
  auto dx = torch::empty_like(x), C = torch::empty({n}, x.options());
  std::vector<double> lam(n);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "pbf_iteration_cpu", [&] {
    pbf_iteration_impl<scalar_t>(x.data_ptr<scalar_t>(), wall.data_ptr<scalar_t>(), rowptr.data_ptr<int64_t>(),
                                 col.data_ptr<int64_t>(), browptr.data_ptr<int64_t>(), bcol.data_ptr<int64_t>(), n, V,
                                 h, eps, scorr_k, scorr_n, w_dq, grad2_lattice, dx.data_ptr<scalar_t>(),
                                 C.data_ptr<scalar_t>(), lam.data());
  });
  return {dx, C};
}

namespace {

// grad W(d) = d * grad_scale(|d|) for the cubic spline (kind 0, kernels.cubic_grad) or Wendland C2 (kind 1)
inline double kernel_grad_scale(int kind, double r, double h) {
  if (kind == 1) return Wendland(h).grad_scale(r);
  if (!(r > 1e-9 * h)) return 0.0;
  const double q = r / h, l = 48.0 / (M_PI * h * h * h);
  const double f = q <= 0.5 ? l * q * (3.0 * q - 2.0) : -l * std::max(1.0 - q, 0.0) * std::max(1.0 - q, 0.0);
  return f / (h * r);
}

template <typename S>
void viscosity_impl(const S* pu, const S* px, const S* pw, const int64_t* rp, const int64_t* cj, const int64_t* brp,
                    const int64_t* bc, int64_t n, double V, double h, double nu_dt, bool no_slip, int kind, S* out) {
  const double eta = 0.01 * h * h;
#pragma omp parallel for schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    double L[3] = {0, 0, 0};
    for (int64_t p = rp[i]; p < rp[i + 1]; ++p) {
      const int64_t j = cj[p];
      double d[3], du = 0, r2 = 0;
      for (int a = 0; a < 3; ++a) {
        d[a] = (double)px[3 * i + a] - px[3 * j + a];
        du += ((double)pu[3 * i + a] - pu[3 * j + a]) * d[a];
        r2 += d[a] * d[a];
      }
      const double c = 10.0 * V / (r2 + eta) * du * kernel_grad_scale(kind, std::sqrt(r2), h);
      for (int a = 0; a < 3; ++a) L[a] += c * d[a];
    }
    if (no_slip)
      for (int64_t p = brp[i]; p < brp[i + 1]; ++p) {
        const int64_t b = bc[p];
        double d[3], du = 0, r2 = 0;
        for (int a = 0; a < 3; ++a) {
          d[a] = (double)px[3 * i + a] - pw[3 * b + a];
          du += (double)pu[3 * i + a] * d[a];
          r2 += d[a] * d[a];
        }
        const double c = 10.0 * V / (r2 + eta) * du * kernel_grad_scale(kind, std::sqrt(r2), h);
        for (int a = 0; a < 3; ++a) L[a] += c * d[a];
      }
    for (int a = 0; a < 3; ++a) out[3 * i + a] = (S)((double)pu[3 * i + a] - nu_dt * L[a]);
  }
}

}  // namespace

// (I - nu dt L) u with L the SPH Laplacian of Weiler et al. 2018 (common.implicit_viscosity):
// (L u)_i = 10 sum_j V ((u_i - u_j) . x_ij) / (|x_ij|^2 + 0.01 h^2) grad W_ij, plus the same with
// the wall particles at rest when no_slip; the conjugate-gradient loop stays in Python.
torch::Tensor viscosity_apply_cpu(torch::Tensor u, torch::Tensor x, torch::Tensor wall, torch::Tensor rowptr,
                                  torch::Tensor col, torch::Tensor browptr, torch::Tensor bcol, double V, double h,
                                  double nu_dt, bool no_slip, int64_t kernel) {
  u = u.contiguous();
  x = x.contiguous();
  wall = wall.contiguous();
  auto out = torch::empty_like(u);
  AT_DISPATCH_FLOATING_TYPES(u.scalar_type(), "viscosity_apply_cpu", [&] {
    viscosity_impl<scalar_t>(u.data_ptr<scalar_t>(), x.data_ptr<scalar_t>(), wall.data_ptr<scalar_t>(),
                             rowptr.data_ptr<int64_t>(), col.data_ptr<int64_t>(), browptr.data_ptr<int64_t>(),
                             bcol.data_ptr<int64_t>(), u.size(0), V, h, nu_dt, no_slip, (int)kernel,
                             out.data_ptr<scalar_t>());
  });
  return out;
}

// XSPH (Monaghan 1989) over CSR pairs with stored kernel values w: v_i + c V sum_j (v_j - v_i) W_ij
torch::Tensor csr_xsph_cpu(torch::Tensor v, torch::Tensor rowptr, torch::Tensor col, torch::Tensor w, double cV) {
  v = v.contiguous();
  auto out = torch::empty_like(v);
  AT_DISPATCH_FLOATING_TYPES(v.scalar_type(), "csr_xsph_cpu", [&] {
    xsph_impl<scalar_t>(v.data_ptr<scalar_t>(), rowptr.data_ptr<int64_t>(), col.data_ptr<int64_t>(),
                        w.data_ptr<scalar_t>(), cV, v.size(0), out.data_ptr<scalar_t>());
  });
  return out;
}

}  // namespace gf
