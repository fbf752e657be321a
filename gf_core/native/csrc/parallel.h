// OpenMP helpers shared by the CPU sources (and their answers without OpenMP).
#pragma once

#ifdef _OPENMP
#include <omp.h>
#endif

namespace gf {

inline int num_threads() {  // threads a parallel region will get
#ifdef _OPENMP
  return omp_get_max_threads();
#else
  return 1;
#endif
}

inline int team_size() {  // threads in the current parallel region
#ifdef _OPENMP
  return omp_get_num_threads();
#else
  return 1;
#endif
}

inline int thread_id() {
#ifdef _OPENMP
  return omp_get_thread_num();
#else
  return 0;
#endif
}

}  // namespace gf
