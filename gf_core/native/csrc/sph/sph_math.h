// Neighbour search on a uniform grid with a hashed cell table (compact hashing, as in
// SPlisHSPlasH / Ihmsen et al. 2011): cells of size `radius`, each cell's points stored
// contiguously by a counting sort of their hash; a query visits the 27 cells around it and keeps
// the K nearest points closer than `radius` (ties broken by index). Shared by sph_cpu.cpp and
// sph_cuda.cu (GF_HD functions).
#pragma once
#include <cmath>
#include <cstdint>

#include "gaussian_math.h"

namespace gf {

struct GridSpec {
  double lo[3];   // grid origin (the data's minimum corner)
  double inv;     // 1 / cell size
  int64_t table;  // number of hash buckets (a power of two)
};

// Buckets of a hash table for m points: a power of two, at least 2m (few collisions)
inline int64_t hash_table_size(int64_t m) {
  int64_t t = 1;
  while (t < 2 * m) t <<= 1;
  return t;
}

GF_HD void cell_of(const GridSpec& g, double x, double y, double z, int64_t c[3]) {
  c[0] = (int64_t)floor((x - g.lo[0]) * g.inv);
  c[1] = (int64_t)floor((y - g.lo[1]) * g.inv);
  c[2] = (int64_t)floor((z - g.lo[2]) * g.inv);
}

GF_HD int64_t cell_hash(const GridSpec& g, int64_t cx, int64_t cy, int64_t cz) {
  // Teschner et al. 2003 primes, on 64-bit integers, then masked into the table
  uint64_t h = ((uint64_t)cx * 73856093ull) ^ ((uint64_t)cy * 19349663ull) ^ ((uint64_t)cz * 83492791ull);
  return (int64_t)(h & (uint64_t)(g.table - 1));
}

// (d, j) before (d', j') when nearer, ties by index
template <typename S>
GF_HD bool nearer(S d, int64_t j, S d2, int64_t j2) { return d < d2 || (d == d2 && j < j2); }

// Keep the k nearest of the pairs pushed so far in (dk, jk), unordered: append while there is
// room, then replace the farthest kept one (found by a scan only once the list is full, which
// is rare when k is the neighbourhood size). `far` holds the farthest slot (-1 until full).
template <typename S>
GF_HD int topk_push(S d, int64_t j, S* dk, int64_t* jk, int n, int k, int& far) {
  if (n < k) {
    dk[n] = d;
    jk[n] = j;
    ++n;
    if (n < k) return n;
  } else {
    if (!nearer(d, j, dk[far], jk[far])) return n;
    dk[far] = d;
    jk[far] = j;
  }
  far = 0;
  for (int s = 1; s < k; ++s)
    if (nearer(dk[far], jk[far], dk[s], jk[s])) far = s;
  return n;
}

// Ascending order of the n kept pairs (insertion sort: n is at most a neighbourhood).
template <typename S>
GF_HD void sort_nearest(S* dk, int64_t* jk, int n) {
  for (int a = 1; a < n; ++a) {
    S d = dk[a];
    int64_t j = jk[a];
    int b = a;
    while (b > 0 && nearer(d, j, dk[b - 1], jk[b - 1])) {
      dk[b] = dk[b - 1];
      jk[b] = jk[b - 1];
      --b;
    }
    dk[b] = d;
    jk[b] = j;
  }
}

// Poly6 kernel of a squared distance (GaussFluids Eq. 6): c (h^2 - r^2)^3 inside the support.
template <typename S>
GF_HD S poly6(S r2, S h2, S c) {
  S q = h2 - r2;
  return q > 0 ? c * q * q * q : S(0);
}

}  // namespace gf
