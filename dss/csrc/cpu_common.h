// What every CPU stage of the renderer shares (dss_cpu.h lists the stages): the includes, the
// instruction-set switches, the packed splat layout, the vector-level switch, the pooled output
// blocks, the work distribution and the float32 exp's AVX2 twin.
//
// One contract with the pure-torch reference (dss/rasterizer/reference.py,
// dss/visibility/reference.py): same inputs (packed screen-space splats, see dss/splats.py),
// same per-pixel tests in the same float32 operation order (compiled with -ffp-contract=off so
// no fused multiply-add changes a rounding), same (depth, index) ordering of the top-K cache.
//
// Work is split over screen tiles (forward) and over points (backward) and handed out
// dynamically from an atomic counter inside at::parallel_for, so one view still uses every core
// and the object's uneven screen coverage does not leave a thread idle.
#pragma once

#include <torch/types.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <map>
#include <mutex>
#include <type_traits>
#include <vector>

#include <sys/mman.h>

#include "splat_math.h"
// x86-64 builds compile AVX2 versions of the hot loops (function target attributes, so the rest of
// the file stays baseline x86-64) and take them at run time when the CPU has AVX2.
#if defined(__x86_64__) && defined(__GNUC__)
#define DSS_HAVE_AVX2 1
#include <immintrin.h>
#define DSS_AVX2 __attribute__((target("avx2")))
// AVX-512 builds (taken where the CPU has AVX-512F/VL/DQ/BW, vector level 2): the visibility
// backward's 16-lane walk and the binning's box scan (scan_boxes, auto-vectorised for 512-bit
// vectors: 1.03x on the rasteriser). The other auto-vectorised loops gained nothing from it
// (projection forward 1.00x, backward 1.01x, smape 1.00x: memory-bound) and keep their AVX2 build.
#define DSS_AVX512 __attribute__((target("avx2,avx512f,avx512vl,avx512dq,avx512bw,prefer-vector-width=512")))
#endif
// Bodies shared by a baseline and an AVX2 function: inlined into both, so each is compiled (and
// vectorised) for its caller's instruction set.
#define DSS_INLINE inline __attribute__((always_inline))

namespace dss_cpu {

constexpr int kFields = 10;  // u v conic_a conic_b2 conic_c norm depth rx ry valid
// How far ahead the pixel loops of the backward passes prefetch the rows of the splats cached at
// a pixel: pixels along a row (visibility backward), pixels of the visit list (blend backward).
constexpr int64_t kPixelsAhead = 8;

using dss_splat::Box;  // a splat's pixel box (splat_math.h)

inline float quad(const float* s, float dx, float dy) { return dss_splat::quad(s[2], s[3], s[4], dx, dy); }

#ifdef DSS_HAVE_AVX2
// 8 packed rows (kFields floats apart, src at row 0's first wanted field) transposed: 8
// consecutive fields into planes dst[0..7] at columns j..j+7 (an 8x8 transpose in registers).
DSS_AVX2 inline void transpose8_avx2(const float* src, float (*dst)[64], int j) {
  __m256 r[8], t[8], u[8];
  for (int l = 0; l < 8; ++l) r[l] = _mm256_loadu_ps(src + l * kFields);
  for (int l = 0; l < 8; l += 2) {
    t[l] = _mm256_unpacklo_ps(r[l], r[l + 1]);
    t[l + 1] = _mm256_unpackhi_ps(r[l], r[l + 1]);
  }
  for (int h = 0; h < 8; h += 4) {
    u[h] = _mm256_shuffle_ps(t[h], t[h + 2], 0x44);
    u[h + 1] = _mm256_shuffle_ps(t[h], t[h + 2], 0xEE);
    u[h + 2] = _mm256_shuffle_ps(t[h + 1], t[h + 3], 0x44);
    u[h + 3] = _mm256_shuffle_ps(t[h + 1], t[h + 3], 0xEE);
  }
  for (int c = 0; c < 4; ++c) {
    _mm256_storeu_ps(dst[c] + j, _mm256_permute2f128_ps(u[c], u[4 + c], 0x20));
    _mm256_storeu_ps(dst[4 + c] + j, _mm256_permute2f128_ps(u[c], u[4 + c], 0x31));
  }
}
#endif

// Fields [f0, f0 + nf) of n <= 64 packed rows into planes: dst[c][j] = rows[j * kFields + f0 + c]
// (nf >= 8, f0 + nf <= kFields), so that the vectoriser reads planes instead of strided rows.
// kVec (only in AVX2 functions): 8 rows at a time by 8x8 transposes, the second one overlapping
// the first when nf > 8; the rest one value at a time.
template <bool kVec>
DSS_INLINE void rows_to_planes(const float* rows, int n, int f0, int nf, float (*dst)[64]) {
  int j = 0;
#ifdef DSS_HAVE_AVX2
  if constexpr (kVec)
    for (; j + 8 <= n; j += 8) {
      transpose8_avx2(rows + j * kFields + f0, dst, j);
      if (nf > 8) transpose8_avx2(rows + j * kFields + f0 + nf - 8, dst + nf - 8, j);
    }
#endif
  for (; j < n; ++j)
    for (int c = 0; c < nf; ++c) dst[c][j] = rows[j * kFields + f0 + c];
}

// Which vector paths the kernels take (cpu_runtime.cpp): 0 the baseline (scalar) loops, 1 the
// AVX2 paths, 2 also the AVX-512 ones, each level where both this build and the CPU have it.
int64_t vector_level();
bool use_vector_path();  // vector_level() >= 1
bool use_avx512();       // vector_level() >= 2

// An uninitialised output tensor from the block cache (cpu_runtime.cpp): see pooled_empty there.
torch::Tensor pooled_empty(at::IntArrayRef sizes, at::ScalarType dtype);

// Run fn(item) for item in [0, n) on all intra-op threads, items handed out dynamically.
template <typename F>
void dynamic_for(int64_t n, int64_t chunk, const F& fn) {
  std::atomic<int64_t> next(0);
  int nthreads = std::max<int>(1, at::get_num_threads());
  at::parallel_for(0, nthreads, 1, [&](int64_t, int64_t) {
    while (true) {
      int64_t start = next.fetch_add(chunk);
      if (start >= n) break;
      int64_t end = std::min(n, start + chunk);
      for (int64_t it = start; it < end; ++it) fn(it);
    }
  });
}

// The AVX2 twin of dss_splat::splat_exp (splat_math.h): the same float32 operations lane for lane
// in the same order, so the vector and scalar paths give the same bits. It replaced glibc's expf,
// a call per inserted fragment (about 0.8 of the rasteriser's 10 ms at 20K points); the tile loop
// now takes it for 8 list slots at a time once a tile's lists are complete.
#ifdef DSS_HAVE_AVX2
DSS_AVX2 inline __m256 splat_exp_avx2(__m256 x) {
  using namespace dss_splat::splat_exp_c;
  x = _mm256_max_ps(x, _mm256_set1_ps(kLo));
  x = _mm256_min_ps(x, _mm256_set1_ps(kHi));
  const __m256 fx = _mm256_floor_ps(_mm256_add_ps(_mm256_mul_ps(x, _mm256_set1_ps(kLog2e)), _mm256_set1_ps(0.5f)));
  const __m256 r = _mm256_sub_ps(_mm256_sub_ps(x, _mm256_mul_ps(fx, _mm256_set1_ps(kLn2Hi))),
                                 _mm256_mul_ps(fx, _mm256_set1_ps(kLn2Lo)));
  __m256 y = _mm256_add_ps(_mm256_mul_ps(_mm256_set1_ps(kP0), r), _mm256_set1_ps(kP1));
  y = _mm256_add_ps(_mm256_mul_ps(y, r), _mm256_set1_ps(kP2));
  y = _mm256_add_ps(_mm256_mul_ps(y, r), _mm256_set1_ps(kP3));
  y = _mm256_add_ps(_mm256_mul_ps(y, r), _mm256_set1_ps(kP4));
  y = _mm256_add_ps(_mm256_mul_ps(y, r), _mm256_set1_ps(kP5));
  y = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(y, _mm256_mul_ps(r, r)), r), _mm256_set1_ps(1.f));
  const __m256i n = _mm256_cvtps_epi32(fx), n1 = _mm256_srai_epi32(n, 1), n2 = _mm256_sub_epi32(n, n1);
  const __m256i bias = _mm256_set1_epi32(127);
  const __m256 s1 = _mm256_castsi256_ps(_mm256_slli_epi32(_mm256_add_epi32(n1, bias), 23));
  const __m256 s2 = _mm256_castsi256_ps(_mm256_slli_epi32(_mm256_add_epi32(n2, bias), 23));
  return _mm256_mul_ps(_mm256_mul_ps(y, s1), s2);
}
#endif

}  // namespace dss_cpu
