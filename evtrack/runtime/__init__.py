"""Process-level helpers: OpenMP's wait policy, BLAS threads and numba's warm-up."""
