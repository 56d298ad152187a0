// DSS rasteriser and visibility gradient on the CPU.
//
// One contract with the pure-torch reference (dss/rasterizer/reference.py,
// dss/visibility/reference.py): same inputs (packed screen-space splats, see dss/splats.py),
// same per-pixel tests in the same float32 operation order (compiled with -ffp-contract=off so
// no fused multiply-add changes a rounding), same (depth, index) ordering of the top-K cache.
//
// Work is split over screen tiles (forward) and over points (backward) and handed out
// dynamically from an atomic counter inside at::parallel_for, so one view still uses every core
// and the object's uneven screen coverage does not leave a thread idle.
#include <torch/extension.h>
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

namespace {

constexpr int kFields = 10;  // u v conic_a conic_b2 conic_c norm depth rx ry valid
constexpr int kTile = 16;
constexpr int kDepthBuckets = 1024;
// How far ahead the pixel loops of the backward passes prefetch the rows of the splats cached at
// a pixel: pixels along a row (visibility backward), pixels of the visit list (blend backward).
constexpr int64_t kPixelsAhead = 8;
// The visibility backward's per-point row flags: one byte per window row, windows of up to 15 rows.
constexpr int64_t kFlagRows = 16;

using dss_splat::Box;  // a splat's pixel box (splat_math.h)

// One splat in one tile's bin: what the tile loop reads of it, in one record so that a tile
// streams through its bin instead of gathering each splat's row of the packed array and its box
// (scattered over ~1 MB per view: an L2 miss each). u..c are the packed fields 0-4 in their
// order (quad() reads them), norm and z the fields 5 and 6, k the splat index; the rows and
// columns the splat's box covers in this tile, relative to the tile's corner.
struct Frag {
  float u, v, a, b2, c, norm, z;
  int32_t k;
  uint8_t i0, i1, j0, j1;
};

// A splat the binning draws: its record (tile fields unset) and its box.
struct Drawn {
  Frag f;
  Box b;
};

using dss_splat::splat_box;  // shared with the CUDA kernel

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

// The binning's first pass over one view's splats, kScanBlock at a time: each splat's box
// (splat_box, then tighten_box) and whether it is drawn (valid, centre and extent not NaN, a box
// left on screen), in straight-line code that the compiler vectorises; the caller then takes the
// drawn ones. (One splat at a time, with branches, the pass took about 2.2 of the rasteriser's
// 11.6 ms at 20K points.) A NaN row's fields are replaced by zeros first, so that no float-to-int
// conversion sees a NaN; it is not drawn.
constexpr int kScanBlock = 64;
struct ScanBlock {
  alignas(32) int j0[kScanBlock], j1[kScanBlock], i0[kScanBlock], i1[kScanBlock], drawn[kScanBlock];
};

template <bool kVec>
DSS_INLINE void scan_boxes(const float* P, int n, int H, int W, float cutoff, ScanBlock& o) {
  static_assert(kScanBlock == 64, "rows_to_planes writes planes of 64");
  alignas(32) float f[kFields][kScanBlock];  // the rows transposed: the vector loop reads planes
  rows_to_planes<kVec>(P, n, 0, kFields, f);
  // (no "omp simd" here: with it GCC 12 finds no vector type for the planes' loads and leaves the
  // loop scalar; without it the loop vectorises, for AVX2 with vroundps for floor and ceil)
  for (int j = 0; j < n; ++j) {
    const bool fin = !std::isnan(f[0][j] + f[1][j] + f[7][j] + f[8][j]);
    const float u = fin ? f[0][j] : 0.f, v = fin ? f[1][j] : 0.f;
    Box b = splat_box(u, v, fin ? f[7][j] : 0.f, fin ? f[8][j] : 0.f, H, W);
    const bool on = (b.j0 <= b.j1) & (b.i0 <= b.i1);
    const bool left = dss_splat::tighten_box(u, v, f[2][j], f[3][j], f[4][j], cutoff, b.j0, b.j1, b.i0, b.i1);
    o.j0[j] = b.j0;
    o.j1[j] = b.j1;
    o.i0[j] = b.i0;
    o.i1[j] = b.i1;
    o.drawn[j] = (f[9][j] > 0.f) & fin & on & left;
  }
}

#ifdef DSS_HAVE_AVX2
DSS_AVX2 void scan_boxes_avx2(const float* P, int n, int H, int W, float cutoff, ScanBlock& o) {
  scan_boxes<true>(P, n, H, W, cutoff, o);
}
DSS_AVX512 void scan_boxes_avx512(const float* P, int n, int H, int W, float cutoff, ScanBlock& o) {
  scan_boxes<true>(P, n, H, W, cutoff, o);
}
#endif

// Depth of point k's tangent plane at the pixel centre (px, py), the depth its splat would have
// there (the backward pass's occlusion test, cases (a)/(b)). For a plane 1/z is affine in screen
// space: 1/z = pl[0] px + pl[1] py + pl[2] (computed in dss/render.py; (0, 0, 1/z) reproduces
// the centre depth). Grazing planes are clamped to a slope of kMaxSlope: |zp - z| <= kMaxSlope *
// (pixel distance) * z / f.
// (vis_state evaluates it inline, with the square root only where the clamp applies.)
constexpr float kMaxSlope = 3.f;

// Memory for the pooled output blocks (pooled_empty): blocks of 2 MB or more are 2 MB aligned
// and marked for transparent huge pages (Linux with THP in "madvise" mode, the common default,
// backs only marked ranges with them), so that streaming out the 47 MB cache or reading its rows
// in scattered order costs a few TLB entries instead of one per 4 KB page (rasteriser 1.04-1.06x
// at 20K points). Smaller blocks are a plain 64-byte aligned allocation. Free with std::free.
constexpr size_t kHugePage = size_t(2) << 20;
void* huge_alloc(size_t bytes) {
  if (bytes < kHugePage) return std::aligned_alloc(64, (bytes + 63) / 64 * 64);
  const size_t n = (bytes + kHugePage - 1) / kHugePage * kHugePage;
  void* p = std::aligned_alloc(kHugePage, n);
#ifdef MADV_HUGEPAGE
  if (p != nullptr) madvise(p, n, MADV_HUGEPAGE);
#endif
  return p;
}

// Large outputs (the top-K cache is 47 MB at 12 views of 256x256) come from a block cache: a
// fresh allocation of that size is a fresh mmap, whose page faults and kernel zeroing cost more
// than filling it (14 vs 2 ms for the cache at 20K points on 2 cores, every render). A tensor
// made here owns a block; when its storage dies (no tensor, view or saved variable refers to it
// any more) the deleter parks the block for the next request of the same byte size, up to
// kPoolBytes parked in all (beyond that blocks are freed). Contents are undefined, as with
// torch::empty. empty_cache() frees the parked blocks.
constexpr size_t kPoolBytes = size_t(512) << 20;
struct BlockCache {
  std::mutex mu;
  std::multimap<size_t, void*> parked;
  size_t parked_bytes = 0;
};
BlockCache& block_cache() {
  static BlockCache* cache = new BlockCache();  // never destroyed: tensors may outlive static destructors
  return *cache;
}

torch::Tensor pooled_empty(at::IntArrayRef sizes, at::ScalarType dtype) {
  int64_t numel = 1;
  for (int64_t d : sizes) numel *= d;
  const size_t bytes = (size_t)numel * c10::elementSize(dtype);
  if (bytes == 0) return torch::empty(sizes, torch::TensorOptions().dtype(dtype));
  BlockCache& cache = block_cache();
  void* ptr = nullptr;
  {
    std::lock_guard<std::mutex> lock(cache.mu);
    auto it = cache.parked.find(bytes);
    if (it != cache.parked.end()) {
      ptr = it->second;
      cache.parked.erase(it);
      cache.parked_bytes -= bytes;
    }
  }
  if (ptr == nullptr) {
    ptr = huge_alloc(bytes);
    TORCH_CHECK(ptr != nullptr, "dss: out of memory allocating ", bytes, " bytes");
  }
  auto park = [bytes](void* p) {
    BlockCache& c = block_cache();
    {
      std::lock_guard<std::mutex> lock(c.mu);
      if (c.parked_bytes + bytes <= kPoolBytes) {
        c.parked.emplace(bytes, p);
        c.parked_bytes += bytes;
        return;
      }
    }
    std::free(p);
  };
  return torch::from_blob(ptr, sizes, park, torch::TensorOptions().dtype(dtype));
}

// Frees the parked blocks; returns how many bytes were released.
int64_t empty_cache() {
  BlockCache& cache = block_cache();
  std::lock_guard<std::mutex> lock(cache.mu);
  const int64_t released = (int64_t)cache.parked_bytes;
  for (auto& kv : cache.parked) std::free(kv.second);
  cache.parked.clear();
  cache.parked_bytes = 0;
  return released;
}

// Which vector paths the kernels take: 0 the baseline (scalar) loops, 1 the AVX2 paths, 2 also
// the AVX-512 ones (the visibility backward's windows of 9-15 columns, a row per 16-lane vector;
// the binning's box scan), each level where both this build and the CPU have it. set_vector_level / set_vector_path force a lower
// level, for tests and comparisons: every level gives the same bits.
std::atomic<int> g_vector_level{2};
bool vector_path_available() {
#ifdef DSS_HAVE_AVX2
  static const bool has = __builtin_cpu_supports("avx2");
  return has;
#else
  return false;
#endif
}
bool avx512_available() {
#ifdef DSS_HAVE_AVX2
  static const bool has = vector_path_available() && __builtin_cpu_supports("avx512f") &&
                          __builtin_cpu_supports("avx512vl") && __builtin_cpu_supports("avx512dq") &&
                          __builtin_cpu_supports("avx512bw");
  return has;
#else
  return false;
#endif
}
// The highest level this build and CPU have.
int64_t max_vector_level() { return avx512_available() ? 2 : vector_path_available() ? 1 : 0; }
// The level the kernels take now.
int64_t vector_level() { return std::min<int64_t>(g_vector_level.load(), max_vector_level()); }
bool use_vector_path() { return vector_level() >= 1; }
bool use_avx512() { return vector_level() >= 2; }

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

// Inserts fragment (k, zk, rho) into pixel p's top-K list (sorted by (depth, index), c entries);
// the caller has checked that it belongs there (the list is not full, or k sorts before its
// last entry). Returns the new count.
inline int insert_fragment(int32_t* pi, float* pd, float* pr, int c, int64_t K, int32_t k, float zk, float r) {
  const int n = c == K ? (int)K : c + 1;
  int pos = c == K ? (int)K - 1 : c;
  while (pos > 0 && (zk < pd[pos - 1] || (zk == pd[pos - 1] && k < pi[pos - 1]))) {
    pi[pos] = pi[pos - 1];
    pd[pos] = pd[pos - 1];
    pr[pos] = pr[pos - 1];
    --pos;
  }
  pi[pos] = k;
  pd[pos] = zk;
  pr[pos] = r;
  return n;
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

#ifdef DSS_HAVE_AVX2
// Streaming (non-temporal) copy of n bytes from an aligned local buffer: 32-byte stores that
// bypass the caches where dst is 32-byte aligned, ordinary stores for the rest.
DSS_AVX2 void stream_bytes(void* dst, const void* src, size_t n) {
  char* d = static_cast<char*>(dst);
  const char* s = static_cast<const char*>(src);
  size_t head = (32 - (reinterpret_cast<uintptr_t>(d) & 31)) & 31;
  head = std::min(head, n);
  std::memcpy(d, s, head);
  size_t k = head;
  for (; k + 32 <= n; k += 32)
    _mm256_stream_si256(reinterpret_cast<__m256i*>(d + k), _mm256_loadu_si256(reinterpret_cast<const __m256i*>(s + k)));
  std::memcpy(d + k, s + k, n - k);
}
#endif

#ifdef DSS_HAVE_AVX2
// insert_fragment without its shifting loop, for K <= 8 (the caller's checks as there): the
// fragment's place is the number of the first n entries it does not sort before (n = c, or K - 1
// when the list is full: the last entry drops out), the entries from there on move one slot up
// through a lane permutation, and the K slots are written back. The same list as
// insert_fragment's, since a list is sorted and "sorts before" holds for a suffix of it; one
// mispredicted loop exit per insertion fewer (the loop ran 0-4 times, unpredictably).
// pi/pd: the pixel's K index and depth slots; pr/pn: two values carried along with each entry
// (r and nv for the new one; the tile loop's -q/2 and splat norm). Each is readable 8 values on
// (the tile lists' padding).
template <int64_t KC>
DSS_AVX2 inline int insert_fragment_avx2(int32_t* pi, float* pd, float* pr, float* pn, int c, int64_t Krt, int32_t k,
                                         float zk, float r, float nv) {
  const int K = KC > 0 ? (int)KC : (int)Krt;
  const int n = c == K ? K - 1 : c;
  const __m256 d = _mm256_loadu_ps(pd);
  const __m256i id = _mm256_loadu_si256((const __m256i*)pi);
  const __m256 vz = _mm256_set1_ps(zk);
  const __m256 before = _mm256_or_ps(
      _mm256_cmp_ps(vz, d, _CMP_LT_OQ),
      _mm256_and_ps(_mm256_cmp_ps(vz, d, _CMP_EQ_OQ), _mm256_castsi256_ps(_mm256_cmpgt_epi32(id, _mm256_set1_epi32(k)))));
  const unsigned first_n = (1u << n) - 1u;
  const int pos = n - __builtin_popcount((unsigned)_mm256_movemask_ps(before) & first_n);
  const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7), vpos = _mm256_set1_epi32(pos);
  // lane l takes l below pos, the new fragment at pos, l - 1 above
  const __m256i from = _mm256_add_epi32(lane, _mm256_cmpgt_epi32(lane, vpos));
  const __m256 at = _mm256_castsi256_ps(_mm256_cmpeq_epi32(lane, vpos));
  const __m256 nd = _mm256_blendv_ps(_mm256_permutevar8x32_ps(d, from), vz, at);
  const __m256 ni = _mm256_blendv_ps(_mm256_castsi256_ps(_mm256_permutevar8x32_epi32(id, from)),
                                     _mm256_castsi256_ps(_mm256_set1_epi32(k)), at);
  const __m256 nr = _mm256_blendv_ps(_mm256_permutevar8x32_ps(_mm256_loadu_ps(pr), from), _mm256_set1_ps(r), at);
  const __m256 nn = _mm256_blendv_ps(_mm256_permutevar8x32_ps(_mm256_loadu_ps(pn), from), _mm256_set1_ps(nv), at);
  if (K == 5) {
    // (four lanes and one: the slots after the fifth belong to the next pixel)
    _mm_storeu_ps(pd, _mm256_castps256_ps128(nd));
    _mm_storeu_ps((float*)pi, _mm256_castps256_ps128(ni));
    _mm_storeu_ps(pr, _mm256_castps256_ps128(nr));
    _mm_storeu_ps(pn, _mm256_castps256_ps128(nn));
    _mm_store_ss(pd + 4, _mm256_extractf128_ps(nd, 1));
    _mm_store_ss((float*)pi + 4, _mm256_extractf128_ps(ni, 1));
    _mm_store_ss(pr + 4, _mm256_extractf128_ps(nr, 1));
    _mm_store_ss(pn + 4, _mm256_extractf128_ps(nn, 1));
  } else {
    const __m256i keep = _mm256_cmpgt_epi32(_mm256_set1_epi32(K), lane);
    _mm256_maskstore_ps(pd, keep, nd);
    _mm256_maskstore_ps((float*)pi, keep, ni);
    _mm256_maskstore_ps(pr, keep, nr);
    _mm256_maskstore_ps(pn, keep, nn);
  }
  return c == K ? K : c + 1;
}

// Bit l: pixel l of 8 takes the fragment (depth z, index k, quadratic form q): inside the cutoff
// ellipse (0.5 q <= cutoff) and through the top-K gate (its list is open, i.e. not full, or the
// fragment sorts before the list's last entry (gd, gi)).
DSS_AVX2 inline unsigned fragment_gate(__m256 q, __m256 vcut, __m256 vz, __m256i vk, const float* gd,
                                       const int32_t* gi, const int32_t* gopen) {
  const __m256 in = _mm256_cmp_ps(_mm256_mul_ps(_mm256_set1_ps(0.5f), q), vcut, _CMP_LE_OQ);
  const __m256 d = _mm256_loadu_ps(gd);
  const __m256i id = _mm256_loadu_si256((const __m256i*)gi);
  const __m256 open = _mm256_castsi256_ps(_mm256_loadu_si256((const __m256i*)gopen));
  const __m256 before = _mm256_or_ps(
      _mm256_cmp_ps(vz, d, _CMP_LT_OQ),
      _mm256_and_ps(_mm256_cmp_ps(vz, d, _CMP_EQ_OQ), _mm256_castsi256_ps(_mm256_cmpgt_epi32(id, vk))));
  return (unsigned)_mm256_movemask_ps(_mm256_and_ps(in, _mm256_or_ps(before, open)));
}

// One tile's fragments, a tile row (16 pixels) per two AVX2 vectors, or per one vector of the 8
// columns from the box's first when the box is at most 8 columns wide: the cutoff test
// (0.5 q <= cutoff, q evaluated with the scalar loop's float32 operations in the same order) and
// the top-K gate (the pixel's list is not full, or the fragment sorts before its last entry) for
// 8 or 16 pixels at once, so only fragments that enter a list reach a branch. The gate is kept per
// pixel in three planes (open, the last entry's depth and index). The lists equal the scalar
// loop's bit for bit: a list's content does not depend on the order fragments arrive in, and rho
// comes from the scalar loop's operations (norm times splat_exp of -q/2), only later.
// li/ld/lr: (256, K) per-pixel lists, cnt: (256,) counts, all of the tile; lr holds -q/2 while
// the fragments are inserted and rho on return.
template <int64_t KC>
DSS_AVX2 void tile_fragments_avx2(const Frag* bin, int64_t n_bin, int ti0, int tj0, int tj1,
                                  int64_t Krt, float cutoff, int32_t* li, float* ld, float* lr, int* cnt) {
  const int64_t K = KC > 0 ? KC : Krt;
  // (8 values of padding: a window of 8 columns from column j0 > 8 of the last row reads past it)
  alignas(32) float gd[kTile * kTile + 8];
  alignas(32) int32_t gi[kTile * kTile + 8], gopen[kTile * kTile + 8];
  // -q/2 at the pixels of the fragment's rows (read only where its gate let it through), and the
  // norm of the splat in each list slot: the slots' rho = norm exp(-q/2) is evaluated once the
  // tile is done, 8 slots per vector, instead of one vector exp per tile row a fragment enters
  alignas(32) float xs[kTile * kTile + 8];
  alignas(32) float ln[kTile * kTile * 8];
  std::fill_n(ln, kTile * kTile * K, 0.f);
  // Columns beyond the image are never tested: closed, at -inf.
  const int nw = tj1 - tj0 + 1;
  for (int p = 0; p < kTile * kTile + 8; ++p) {
    const bool in = p < kTile * kTile && p % kTile < nw;
    gd[p] = in ? std::numeric_limits<float>::infinity() : -std::numeric_limits<float>::infinity();
    gi[p] = 0;
    gopen[p] = in ? -1 : 0;
  }
  const __m256 half = _mm256_set1_ps(0.5f), mhalf = _mm256_set1_ps(-0.5f), vcut = _mm256_set1_ps(cutoff);
  const __m256 col0 = _mm256_add_ps(_mm256_cvtepi32_ps(_mm256_setr_epi32(tj0, tj0 + 1, tj0 + 2, tj0 + 3, tj0 + 4,
                                                                          tj0 + 5, tj0 + 6, tj0 + 7)), half);
  const __m256 col1 = _mm256_add_ps(_mm256_cvtepi32_ps(_mm256_setr_epi32(tj0 + 8, tj0 + 9, tj0 + 10, tj0 + 11,
                                                                          tj0 + 12, tj0 + 13, tj0 + 14, tj0 + 15)), half);
  for (int64_t e = 0; e < n_bin; ++e) {
    const Frag& f = bin[e];
    const int32_t k = f.k;
    const float* s = &f.u;  // s[0..4]: u, v, a, b2, c as in the packed row
    const int r0 = f.i0, r1 = f.i1;  // the box's rows in the tile
    const float zk = f.z;
    const __m256 vz = _mm256_set1_ps(zk);
    const __m256i vk = _mm256_set1_epi32(k);
    // First every row's tests, into one bit per pixel of the tile (tile row r: bits 16 (r % 4) on
    // of word r / 4), with no branch on their outcome; then the pixels that took the fragment, in
    // one loop over the set bits. (Row by row, with a branch on each row's tests and a loop over
    // each row's bits, a fragment cost a mispredicted branch or two per row.) The rows' tests do
    // not depend on each other: the fragment enters distinct pixels.
    uint64_t take[4] = {0, 0, 0, 0};
    // q = ((a dx) dx + (b2 dx) dy) + (c dy) dy: the first term and b2 dx depend on the column only
    const __m256 va = _mm256_set1_ps(s[2]), vb = _mm256_set1_ps(s[3]), vu = _mm256_set1_ps(s[0]);
    if (f.j1 - f.j0 < 8) {
      // Columns j0 .. j1 fit in one vector of 8 from j0 (most boxes: 3.4 columns per tile row
      // at 20K points): one gate per row instead of two. The column centres are col0 + j0,
      // exact in float, so q has the same bits as in the two-vector path.
      const int j0 = f.j0;
      const unsigned colw = (2u << (f.j1 - j0)) - 1u;
      const __m256 dx = _mm256_sub_ps(_mm256_add_ps(col0, _mm256_set1_ps((float)j0)), vu);
      const __m256 t1 = _mm256_mul_ps(_mm256_mul_ps(va, dx), dx), bx = _mm256_mul_ps(vb, dx);
      for (int rr = r0; rr <= r1; ++rr) {
        const float dy = ((float)(ti0 + rr) + 0.5f) - s[1];
        const __m256 q = _mm256_add_ps(_mm256_add_ps(t1, _mm256_mul_ps(bx, _mm256_set1_ps(dy))),
                                       _mm256_set1_ps(s[4] * dy * dy));
        const int r = rr * kTile;
        const unsigned m = fragment_gate(q, vcut, vz, vk, gd + r + j0, gi + r + j0, gopen + r + j0) & colw;
        _mm256_storeu_ps(xs + r + j0, _mm256_mul_ps(mhalf, q));
        take[rr >> 2] |= (uint64_t)(m << j0) << ((rr & 3) * kTile);
      }
    } else {
      const unsigned cols = ((2u << f.j1) - 1u) & ~((1u << f.j0) - 1u);
      const __m256 dx0 = _mm256_sub_ps(col0, vu), dx1 = _mm256_sub_ps(col1, vu);
      const __m256 t10 = _mm256_mul_ps(_mm256_mul_ps(va, dx0), dx0), t11 = _mm256_mul_ps(_mm256_mul_ps(va, dx1), dx1);
      const __m256 bx0 = _mm256_mul_ps(vb, dx0), bx1 = _mm256_mul_ps(vb, dx1);
      for (int rr = r0; rr <= r1; ++rr) {
        const float dy = ((float)(ti0 + rr) + 0.5f) - s[1];
        const __m256 vdy = _mm256_set1_ps(dy), t3 = _mm256_set1_ps(s[4] * dy * dy);
        const __m256 q0 = _mm256_add_ps(_mm256_add_ps(t10, _mm256_mul_ps(bx0, vdy)), t3);
        const __m256 q1 = _mm256_add_ps(_mm256_add_ps(t11, _mm256_mul_ps(bx1, vdy)), t3);
        const int r = rr * kTile;
        const unsigned m = (fragment_gate(q0, vcut, vz, vk, gd + r, gi + r, gopen + r) |
                            (fragment_gate(q1, vcut, vz, vk, gd + r + 8, gi + r + 8, gopen + r + 8) << 8)) & cols;
        _mm256_store_ps(xs + r, _mm256_mul_ps(mhalf, q0));
        _mm256_store_ps(xs + r + 8, _mm256_mul_ps(mhalf, q1));
        take[rr >> 2] |= (uint64_t)m << ((rr & 3) * kTile);
      }
    }
    // The fragment enters pixel p's list; a list that fills closes its pixel's gate.
    for (int w = r0 >> 2; w <= (r1 >> 2); ++w) {
      for (uint64_t b = take[w]; b; b &= b - 1) {
        const int p = w * 64 + __builtin_ctzll(b);
        int32_t* pi = li + p * K;
        float* pd = ld + p * K;
        const int c = insert_fragment_avx2<KC>(pi, pd, lr + p * K, ln + p * K, cnt[p], K, k, zk, xs[p], f.norm);
        cnt[p] = c;
        if (c == K) {
          gopen[p] = 0;
          gd[p] = pd[K - 1];
          gi[p] = pi[K - 1];
        }
      }
    }
  }
  // rho = norm exp(-q/2) in every slot (empty ones: 0 exp(0) = 0), the scalar loop's operations
  for (int64_t e = 0; e < kTile * kTile * K; e += 8)
    _mm256_store_ps(lr + e, _mm256_mul_ps(_mm256_load_ps(ln + e), splat_exp_avx2(_mm256_load_ps(lr + e))));
}
#endif
}  // namespace

// Enables (every level the CPU has) / disables the vector paths; returns whether they were on.
bool set_vector_path(bool on) { return g_vector_level.exchange(on ? 2 : 0) > 0; }
// Sets the highest vector level the kernels may take (0-2, see g_vector_level); returns the
// previous setting.
int64_t set_vector_level(int64_t level) {
  TORCH_CHECK(level >= 0 && level <= 2, "vector level must be 0 (scalar), 1 (AVX2) or 2 (AVX-512), got ", level);
  return g_vector_level.exchange((int)level);
}

// Forward: top-K cache per pixel and (optionally) the blended image.
// packed (V,N,10) f32, attrs (V,N,C) f32 or empty, background (C) f32.
std::vector<torch::Tensor> rasterize_forward(torch::Tensor packed, torch::Tensor attrs, int64_t H, int64_t W,
                                             int64_t K, double cutoff_d, double merge_d, torch::Tensor background) {
  TORCH_CHECK(packed.dim() == 3 && packed.size(2) == kFields, "packed splats must be (V,N,10)");
  packed = packed.contiguous().to(torch::kFloat32);
  const int64_t V = packed.size(0), N = packed.size(1);
  TORCH_CHECK(K >= 1 && K <= 8, "K must be in [1, 8]");
  const bool do_blend = attrs.numel() > 0;
  const int64_t C = do_blend ? attrs.size(2) : 0;
  TORCH_CHECK(C <= 16, "at most 16 channels");
  if (do_blend) {
    TORCH_CHECK(attrs.size(0) == V && attrs.size(1) == N, "attrs must be (V,N,C)");
    attrs = attrs.contiguous().to(torch::kFloat32);
    background = background.contiguous().to(torch::kFloat32);
    TORCH_CHECK(background.numel() == C, "background must have C entries");
  }
  const float cutoff = (float)cutoff_d, merge = (float)merge_d;
  auto fopt = torch::TensorOptions().dtype(torch::kFloat32);
  // every entry is written below (empty slots: -1, inf, 0), so pooled buffers need no fill
  auto idx = pooled_empty({V, H, W, K}, torch::kInt32);
  auto depth = pooled_empty({V, H, W, K}, torch::kFloat32);
  auto rho = pooled_empty({V, H, W, K}, torch::kFloat32);
  auto images = do_blend ? pooled_empty({V, H, W, C}, torch::kFloat32) : torch::empty({0}, fopt);
  auto mask = pooled_empty({V, H, W}, torch::kBool);

  const float* P = packed.data_ptr<float>();
  const int64_t TX = (W + kTile - 1) / kTile, TY = (H + kTile - 1) / kTile, T = TX * TY;

  // Bin splats into tiles (CSR per view: offsets, bins of Frag records).
  // Scratch kept per calling thread between calls (fresh pages cost more than the binning).
  // (References: the worker lambdas must see the calling thread's instances, not their own.)
  static thread_local std::vector<std::vector<int64_t>> offsets_tl;
  static thread_local std::vector<std::vector<Frag>> bins_tl;
  static thread_local std::vector<std::vector<Drawn>> drawn_tl;
  auto& offsets = offsets_tl;
  auto& bins = bins_tl;
  auto& drawn = drawn_tl;
  offsets.resize(V);
  bins.resize(V);
  drawn.resize(V);
  const bool vec = use_vector_path(), v512 = use_avx512();
  for (int64_t v = 0; v < V; ++v) offsets[v].assign(T + 1, 0);
  dynamic_for(V, 1, [&](int64_t v) {
    auto& off = offsets[v];
    // One pass over the view's packed rows: the splats that are drawn (valid, box on screen),
    // each with its record and box, and the number of tiles' bins each box reaches.
    auto& dr = drawn[v];
    dr.clear();
    float zlo = std::numeric_limits<float>::infinity(), zhi = -zlo;
    ScanBlock sb;
    for (int64_t k0 = 0; k0 < N; k0 += kScanBlock) {
      const int nb = (int)std::min<int64_t>(kScanBlock, N - k0);
      const float* Pb = P + (v * N + k0) * kFields;
#ifdef DSS_HAVE_AVX2
      if (v512)
        scan_boxes_avx512(Pb, nb, (int)H, (int)W, cutoff, sb);
      else if (vec)
        scan_boxes_avx2(Pb, nb, (int)H, (int)W, cutoff, sb);
      else
#endif
        scan_boxes<false>(Pb, nb, (int)H, (int)W, cutoff, sb);
      // the drawn ones through a bit mask (about half the rows are drawn, in runs: a branch per
      // row would be mispredicted often)
      uint64_t bits = 0;
      for (int j = 0; j < nb; ++j) bits |= (uint64_t)(sb.drawn[j] != 0) << j;
      const size_t d0 = dr.size();
      dr.resize(d0 + (size_t)__builtin_popcountll(bits));
      Drawn* out = dr.data() + d0;
      for (; bits; bits &= bits - 1) {
        const int j = __builtin_ctzll(bits);
        const float* s = Pb + j * kFields;
        const Box b{sb.j0[j], sb.j1[j], sb.i0[j], sb.i1[j]};
        *out++ = {{s[0], s[1], s[2], s[3], s[4], s[5], s[6], (int32_t)(k0 + j), 0, 0, 0, 0}, b};
        zlo = std::min(zlo, s[6]);
        zhi = std::max(zhi, s[6]);
        const int ty0 = b.i0 / kTile, ty1 = b.i1 / kTile, tx0 = b.j0 / kTile, tx1 = b.j1 / kTile;
        if (ty0 == ty1 && tx0 == tx1) {  // most boxes: one tile
          off[ty0 * TX + tx0 + 1]++;
          continue;
        }
        for (int ty = ty0; ty <= ty1; ++ty)
          for (int tx = tx0; tx <= tx1; ++tx) off[ty * TX + tx + 1]++;
      }
    }
    for (int64_t t = 0; t < T; ++t) off[t + 1] += off[t];
    bins[v].resize(off[T]);
    // Bins filled roughly front to back (splats counting-sorted into kDepthBuckets depth slabs):
    // once a pixel's list is full, most later fragments fail its top-K gate at once. The lists
    // do not depend on this order.
    const int64_t n = (int64_t)dr.size();
    std::vector<int32_t> cnt_z(kDepthBuckets + 1, 0), order(n);
    std::vector<uint16_t> bucket(n);
    const float zscale = zhi > zlo ? (float)(kDepthBuckets - 1) / (zhi - zlo) : 0.f;
    for (int64_t d = 0; d < n; ++d) {
      bucket[d] = (uint16_t)std::min<int>(kDepthBuckets - 1, std::max<int>(0, (int)((dr[d].f.z - zlo) * zscale)));
      cnt_z[bucket[d] + 1]++;
    }
    for (int z = 0; z < kDepthBuckets; ++z) cnt_z[z + 1] += cnt_z[z];
    for (int64_t d = 0; d < n; ++d) order[cnt_z[bucket[d]]++] = (int32_t)d;
    std::vector<int64_t> fill(off.begin(), off.end() - 1);
    Frag* bin = bins[v].data();
    for (const int32_t d : order) {
      const Box& b = dr[d].b;
      Frag f = dr[d].f;
      for (int ty = b.i0 / kTile; ty <= b.i1 / kTile; ++ty) {
        // the box's rows in this tile (the box is clamped to the image, so within the tile's)
        f.i0 = (uint8_t)(std::max(b.i0, ty * kTile) - ty * kTile);
        f.i1 = (uint8_t)(std::min(b.i1, ty * kTile + kTile - 1) - ty * kTile);
        for (int tx = b.j0 / kTile; tx <= b.j1 / kTile; ++tx) {
          f.j0 = (uint8_t)(std::max(b.j0, tx * kTile) - tx * kTile);
          f.j1 = (uint8_t)(std::min(b.j1, tx * kTile + kTile - 1) - tx * kTile);
          bin[fill[ty * TX + tx]++] = f;
        }
      }
    }
  });

  int32_t* I = idx.data_ptr<int32_t>();
  float* D = depth.data_ptr<float>();
  float* Rh = rho.data_ptr<float>();
  bool* Mk = mask.data_ptr<bool>();
  float* IMG = do_blend ? images.data_ptr<float>() : nullptr;
  const float* A = do_blend ? attrs.data_ptr<float>() : nullptr;
  const float* BG = do_blend ? background.data_ptr<float>() : nullptr;

  // The tile loop, compiled for the common (K, C) = (5, 3) and (5, 1) with constant trip counts
  // and for any (K, C) at run time (C = 0: no blending).
  const int64_t Krt = K, Crt = C;
  // a tile row of the background colour, and of empty cache slots (-1, inf, 0)
  std::vector<float> empty_bg(kTile * C);
  for (int64_t e = 0; e < kTile * C; ++e) empty_bg[e] = BG[e % C];
  alignas(32) int32_t empty_i[kTile * 8];
  alignas(32) float empty_d[kTile * 8], empty_r[kTile * 8];
  std::fill_n(empty_i, kTile * 8, -1);
  std::fill_n(empty_d, kTile * 8, std::numeric_limits<float>::infinity());
  std::fill_n(empty_r, kTile * 8, 0.f);
  auto tile_task = [&](auto KT, auto CT, int64_t item) {
    constexpr int64_t KC = decltype(KT)::value, CC = decltype(CT)::value;
    const int64_t K = KC > 0 ? KC : Krt, C = CC > 0 ? CC : Crt;
    const int64_t v = item / T, t = item % T;
    const int ty = (int)(t / TX), tx = (int)(t % TX);
    const int ti0 = ty * kTile, tj0 = tx * kTile;
    const int ti1 = std::min<int>((int)H, ti0 + kTile) - 1, tj1 = std::min<int>((int)W, tj0 + kTile) - 1;
    const auto& off = offsets[v];
    const int nwrt = tj1 - tj0 + 1;  // the tile's columns on the image
    // One tile row (pixels from g0 on) out: cache slots from si/sd/sr (nwrt * K values each) and,
    // where simg is given, the image row; with streaming stores on the vector path (the 47 MB
    // cache is not read back before it leaves the caches, so writing around them saves reading
    // every line first), plain copies elsewhere.
    auto put_row = [&](int64_t g0, const int32_t* si, const float* sd, const float* sr, const float* simg) {
#ifdef DSS_HAVE_AVX2
      if (vec) {
        stream_bytes(I + g0 * K, si, sizeof(int32_t) * nwrt * K);
        stream_bytes(D + g0 * K, sd, sizeof(float) * nwrt * K);
        stream_bytes(Rh + g0 * K, sr, sizeof(float) * nwrt * K);
        if (simg) stream_bytes(IMG + g0 * C, simg, sizeof(float) * nwrt * C);
        return;
      }
#endif
      std::copy_n(si, nwrt * K, I + g0 * K);
      std::copy_n(sd, nwrt * K, D + g0 * K);
      std::copy_n(sr, nwrt * K, Rh + g0 * K);
      if (simg) std::copy_n(simg, nwrt * C, IMG + g0 * C);
    };
    if (off[t + 1] == off[t]) {
      // No splat reaches the tile (most tiles: 83% at 20K points, 12 views of 256x256): empty
      // slots, the background and a false mask, row by row, without the lists and the tile loop.
      for (int i = ti0; i <= ti1; ++i) {
        const int64_t g0 = (v * H + i) * W + tj0;
        std::fill_n(Mk + g0, nwrt, false);
        put_row(g0, empty_i, empty_d, empty_r, do_blend ? empty_bg.data() : nullptr);
      }
#ifdef DSS_HAVE_AVX2
      if (vec) _mm_sfence();  // this thread's streaming stores are weakly ordered: drain them
#endif
      return;
    }
    // Tile-local top-K lists in the cache's layout (K slots per pixel, a tile row's 16 pixels
    // side by side), their slots beyond a list's count holding the empty slot (-1, inf, 0): a
    // tile row of them is the cache's row as it is, written out without a copy.
    alignas(32) int32_t li[kTile * kTile * 8];
    alignas(32) float ld[kTile * kTile * 8], lr[kTile * kTile * 8];
    int cnt[kTile * kTile];
    std::fill(cnt, cnt + kTile * kTile, 0);
    std::fill_n(li, kTile * kTile * K, -1);
    std::fill_n(ld, kTile * kTile * K, std::numeric_limits<float>::infinity());
    std::fill_n(lr, kTile * kTile * K, 0.f);
    // The blend below reads the attributes of the splats that stay in the lists, rows scattered
    // over the view's (N, C) block: fetch those of the tile's splats now, so that they arrive
    // while the tile loop runs (a miss each otherwise: 0.9 of the rasteriser's 11.5 ms at 20K).
    if (do_blend)
      for (int64_t e = off[t]; e < off[t + 1]; ++e) __builtin_prefetch(A + (v * N + bins[v][e].k) * C);
#ifdef DSS_HAVE_AVX2
    if (vec) {
      tile_fragments_avx2<KC>(bins[v].data() + off[t], off[t + 1] - off[t], ti0, tj0, tj1, Krt,
                              cutoff, li, ld, lr, cnt);
    } else
#endif
    for (int64_t e = off[t]; e < off[t + 1]; ++e) {
      const Frag& f = bins[v][e];
      const int32_t k = f.k;
      const float* s = &f.u;  // s[0..4]: u, v, a, b2, c as in the packed row
      const int i0 = ti0 + f.i0, i1 = ti0 + f.i1, j0 = tj0 + f.j0, j1 = tj0 + f.j1;
      const float zk = f.z;
      for (int i = i0; i <= i1; ++i) {
        const float dy = ((float)i + 0.5f) - s[1];
        // The row's tests first, in a branch-free loop the compiler vectorises (same float
        // operations per pixel, so the same bits); then the accepted pixels one by one.
        float qrow[kTile];
        const int nj = j1 - j0 + 1;
        for (int t = 0; t < nj; ++t) {
          const float dx = ((float)(j0 + t) + 0.5f) - s[0];
          qrow[t] = quad(s, dx, dy);
        }
        for (int j = j0; j <= j1; ++j) {
          const float q = qrow[j - j0];
          if (!(0.5f * q <= cutoff)) continue;
          const int p = (i - ti0) * kTile + (j - tj0);
          const int c = cnt[p];
          int32_t* pi = li + p * K;
          float* pd = ld + p * K;
          float* pr = lr + p * K;
          // a full list takes the fragment only if it sorts before the last entry
          if (c == K && !(zk < pd[K - 1] || (zk == pd[K - 1] && k < pi[K - 1]))) continue;
          cnt[p] = insert_fragment(pi, pd, pr, c, K, k, zk, f.norm * dss_splat::splat_exp(-0.5f * q));
        }
      }
    }
    // Write out the cache and blend the visible entries (Eq. sumI), a tile row at a time. The
    // cache rows are the tile's lists as they are (put_row); images and mask are assembled per
    // row (empty pixels: the background, false), the image in a local row on the vector path.
    alignas(32) float bimg[kTile * 16];
    // (full tile rows with K compiled in have fixed sizes: the fills and copies inline)
    auto write_rows = [&](auto NW, auto VEC) {
      constexpr int64_t NWC = decltype(NW)::value;
      constexpr bool kStream = decltype(VEC)::value;
      const int nw = NWC > 0 ? (int)NWC : nwrt;
      for (int i = ti0; i <= ti1; ++i) {
        const int64_t g0 = (v * H + i) * W + tj0;
        const int r = (i - ti0) * kTile;
        float* rimg = kStream ? bimg : IMG + g0 * C;
        bool* rm = Mk + g0;
        std::fill_n(rm, nw, false);
        if (do_blend) std::copy_n(empty_bg.data(), nw * C, rimg);
        for (int jj = 0; jj < nwrt; ++jj) {
          const int p = r + jj;
          const int c = cnt[p];
          if (c == 0) continue;
          const int32_t* pi = li + p * K;
          const float* pd = ld + p * K;
          const float* pr = lr + p * K;
          const float lim = pd[0] + merge;
          float den = 0.f;
          float num[16] = {0};
          for (int e = 0; e < c; ++e) {
            if (!(pd[e] <= lim)) break;
            const float w = pr[e];
            den += w;
            if (do_blend) {
              const float* a = A + (v * N + pi[e]) * C;
              for (int64_t ch = 0; ch < C; ++ch) num[ch] += w * a[ch];
            }
          }
          rm[jj] = den > 0.f;
          if (do_blend && den > 0.f) {
            for (int64_t ch = 0; ch < C; ++ch) rimg[jj * C + ch] = num[ch] / den;
          }
        }
        // (the plain path assembled the image row in place)
        put_row(g0, li + r * K, ld + r * K, lr + r * K, kStream && do_blend ? bimg : nullptr);
      }
    };
    using Full = std::integral_constant<int64_t, kTile>;
    using Part = std::integral_constant<int64_t, 0>;
    using Stream = std::true_type;
    using Plain = std::false_type;
    const bool full = nwrt == kTile && KC > 0;
    if (vec)
      full ? write_rows(Full{}, Stream{}) : write_rows(Part{}, Stream{});
    else
      full ? write_rows(Full{}, Plain{}) : write_rows(Part{}, Plain{});
#ifdef DSS_HAVE_AVX2
    if (vec) _mm_sfence();  // this thread's streaming stores are weakly ordered: drain them
#endif
  };
  using K5 = std::integral_constant<int64_t, 5>;
  using Any = std::integral_constant<int64_t, 0>;
  if (Krt == 5 && Crt == 3)
    dynamic_for(V * T, 1, [&](int64_t t) { tile_task(K5{}, std::integral_constant<int64_t, 3>{}, t); });
  else if (Krt == 5 && Crt == 1)
    dynamic_for(V * T, 1, [&](int64_t t) { tile_task(K5{}, std::integral_constant<int64_t, 1>{}, t); });
  else
    dynamic_for(V * T, 1, [&](int64_t t) { tile_task(Any{}, Any{}, t); });
  return {idx, depth, rho, images, mask};
}

// ---------------------------------------------------------------------------------------------
// Visibility gradient (paper Eqs. gradcase, filteredG, cases (a), (b), (c)); see
// dss/visibility/reference.py for the rules written out in torch.
namespace {

// Everything a (point, pixel) evaluation reads about the pixel, for one view, as planes of H*W
// values (structure of arrays: a window row is a run of consecutive values in every plane, so the
// vector path loads 8 pixels with one instruction per plane). With g = dL/dI at the pixel only the
// projections g . w of the attributes matter (gd = g . I_new - g . I = (sum rho g.w) / (sum rho)
// - g . I), so an evaluation is channel-free. Float planes: nz (1 if g != 0; a pixel with nz = 0
// is never read further and its other planes are stale), d0 (front depth, inf if empty), den =
// sum rho and gn = sum rho g.w over the visible set, gi = g . I, gb = g . background, g (C
// planes), then per cache entry e its depth, rho and g.w (K planes each); int planes: the cache
// indices (K planes).
template <bool kSoA, int64_t KC = 0, int64_t CC = 0>
struct VisRecord {
  int64_t C_ = 0, K_ = 0;  // run-time values; KC, CC > 0 fix them at compile time (constant offsets)
  int64_t C() const { return CC > 0 ? CC : C_; }
  int64_t K() const { return KC > 0 ? KC : K_; }
  int64_t S = 0;  // planes: the plane stride (values); records: the record size (floats)
  float* f = nullptr;
  int32_t* ix = nullptr;  // planes: K index planes (stride S); records: the cache's idx (H*W, K)
  // field numbers
  static constexpr int64_t kNZ = 0, kD0 = 1, kDen = 2, kGn = 3, kGi = 4, kGb = 5;
  int64_t fG(int64_t ch) const { return 6 + ch; }
  int64_t fDep(int64_t e) const { return 6 + C() + e; }
  int64_t fRho(int64_t e) const { return 6 + C() + K() + e; }
  int64_t fGw(int64_t e) const { return 6 + C() + 2 * K() + e; }
  float& at(int64_t field, int64_t p) const { return kSoA ? f[field * S + p] : f[p * S + field]; }
  float& nz(int64_t p) const { return at(kNZ, p); }
  float& d0(int64_t p) const { return at(kD0, p); }
  float& den(int64_t p) const { return at(kDen, p); }
  float& gn(int64_t p) const { return at(kGn, p); }
  float& gi(int64_t p) const { return at(kGi, p); }
  float& gb(int64_t p) const { return at(kGb, p); }
  float& g(int64_t ch, int64_t p) const { return at(fG(ch), p); }
  float& dep(int64_t e, int64_t p) const { return at(fDep(e), p); }
  float& rho(int64_t e, int64_t p) const { return at(fRho(e), p); }
  float& gw(int64_t e, int64_t p) const { return at(fGw(e), p); }
  int32_t& idx(int64_t e, int64_t p) const { return kSoA ? ix[e * S + p] : ix[p * K() + e]; }
  // The same record with (K, C) fixed at compile time.
  template <int64_t K2, int64_t C2>
  VisRecord<kSoA, K2, C2> fixed() const {
    VisRecord<kSoA, K2, C2> r;
    r.C_ = C_, r.K_ = K_, r.S = S, r.f = f, r.ix = ix;
    return r;
  }
  // planes only: the start of a field's / an index plane
  const float* plane(int64_t field) const { return f + field * S; }
  const int32_t* idx_plane(int64_t e) const { return ix + e * S; }
  static int64_t fields(int64_t C, int64_t K) { return 6 + C + 3 * K; }
  // H*W rounded up to 16 values, plus 5 cache lines: planes a power of two apart (256 KB at
  // 256x256) would all map to the same few sets of the L1 and L2 caches and evict each other.
  // (The padding also holds the up to 7 values that the AVX-512 walk's full loads read past a
  // plane's last pixel, VisRow16.)
  static int64_t plane_stride(int64_t HW) { return (HW + 15) / 16 * 16 + 80; }
};

// What an evaluation needs about the point (one view).
struct VisPoint {
  const float* s;   // packed splat (kFields)
  const float* wk;  // the point's attributes (C)
  const float* pl;  // tangent plane: 1/z = pl[0] px + pl[1] py + pl[2]
  int32_t k;
  float u, v, z, nk;
  float z_f;    // camera units per pixel at the point's depth
  float X, Y;   // camera-frame x, y of the point
  float slope;  // plane-depth clamp per pixel of distance (kMaxSlope * z_f)
};

// The view's and the rule's constants.
struct VisConsts {
  float f, cx, cy, inv_f, cutoff, merge, eps;
};

// The visibility state after k's change at one pixel: the case, the loss change gd = g . I_new -
// g . I, k's (clamped) tangent-plane depth zp (cases (a)/(b) only) and the front depth d0.
struct VisState {
  int kase;  // 0: (a) invisible, nothing in front; 1: (b) occluded; 2: (c) visible
  float gd, zp, d0;
};

// Adds rho and rho g.w of the cache entries e0, e0 + 1, ... at pixel p to (den, gn) while they
// hold a point within depth lim: the visible set in front of lim (entries are depth-sorted).
template <class Rec>
inline void add_entries_within(const Rec& R, int64_t K, int64_t p, int e0, float lim, float& den, float& gn) {
  for (int e = e0; e < K && R.idx(e, p) >= 0 && R.dep(e, p) <= lim; ++e) {
    den += R.rho(e, p);
    gn += R.rho(e, p) * R.gw(e, p);
  }
}

template <int64_t KC, int64_t CC, class Rec>
DSS_INLINE VisState vis_state(const Rec& R, int64_t Krt, int64_t Crt, const VisPoint& P, const VisConsts& Q,
                          int64_t p, float px, float py) {
  const int64_t K = KC > 0 ? KC : Krt, C = CC > 0 ? CC : Crt;
  const float d0 = R.d0(p), merge = Q.merge;
  int ek = -1;  // position of k in the cache
  for (int e = 0; e < K && R.idx(e, p) >= 0; ++e)
    if (R.idx(e, p) == P.k) { ek = e; break; }
  const bool k_visible = ek >= 0 && R.dep(ek, p) <= d0 + merge;
  float zp = 0.f;  // only needed when k is not visible
  float den, gn;   // sum rho and sum rho g.w of the visible set after the change
  int kase;
  if (k_visible) {
    kase = 2;
    if (ek > 0) {  // the front stays: the visible set loses k only
      const float prk = R.rho(ek, p);
      den = R.den(p) - prk;
      gn = R.gn(p) - prk * R.gw(ek, p);
      if (!(den > 0.f)) den = 0.f;
    } else {  // k was the front: the next entry is the new front, may reveal others
      den = 0.f;
      gn = 0.f;
      if (K > 1 && R.idx(1, p) >= 0) add_entries_within(R, K, p, 1, R.dep(1, p) + merge, den, gn);
    }
  } else {
    // k's tangent-plane depth at the pixel, clamped to kMaxSlope (square root only if it applies)
    const float iz = P.pl[0] * px + P.pl[1] * py + P.pl[2];
    zp = iz > 0.f ? 1.f / iz : P.z;
    const float d2 = (px - P.u) * (px - P.u) + (py - P.v) * (py - P.v);
    const float dz = zp - P.z;
    if (dz * dz > P.slope * P.slope * d2) {
      const float dmax = P.slope * std::sqrt(d2);
      zp = std::min(std::max(zp, P.z - dmax), P.z + dmax);
    }
    const bool empty = R.idx(0, p) < 0;
    kase = (empty || zp <= d0 + merge) ? 0 : 1;
    float gw = 0.f;
    for (int64_t ch = 0; ch < C; ++ch) gw += R.g(ch, p) * P.wk[ch];
    den = P.nk;
    gn = P.nk * gw;
    if (kase == 1 || zp >= d0) {  // merges with the current visible set
      den += R.den(p);
      gn += R.gn(p);
    } else if (!empty) {  // k becomes the front: entries beyond zp + T drop out
      add_entries_within(R, K, p, 0, zp + merge, den, gn);
    }
  }
  const float gd = (den > 0.f ? gn / den : R.gb(p)) - R.gi(p);
  return {kase, gd, zp, d0};
}

// One (point, pixel) evaluation, scalar; adds to acc (double) in the order the window is walked.
// mode 0 (dss): the linearised step between the two visibility states; mode 1 (rbf): the
// derivative of a smooth Gaussian visibility h = exp(-q/2).
template <int64_t KC, int64_t CC, class Rec>
DSS_INLINE void eval_scalar(const Rec& R, int64_t Krt, int64_t Crt, const VisPoint& P, const VisConsts& Q,
                        int64_t mode, int64_t p, float px, float py, double acc[3]) {
  const VisState st = vis_state<KC, CC>(R, Krt, Crt, P, Q, p, px, py);
  const float gd = st.gd;
  const float ddx = px - P.u, ddy = py - P.v;
  if (mode == 1) {
    const float q = quad(P.s, ddx, ddy);
    const float h = dss_splat::splat_exp(-0.5f * q);
    const float sgn = st.kase == 2 ? -1.f : 1.f;  // Phi = I_without + h (I_with - I_without)
    const float gu = h * (P.s[2] * ddx + 0.5f * P.s[3] * ddy);  // dh/du_k = h Sigma^-1 d
    const float gv = h * (0.5f * P.s[3] * ddx + P.s[4] * ddy);
    const float c = sgn * gd, f = Q.f, z = P.z;
    acc[0] += c * (f / z) * gu;
    acc[1] += c * (f / z) * gv;
    acc[2] += c * (-f * P.X / (z * z) * gu - f * P.Y / (z * z) * gv);
    return;
  }
  if (!(gd < 0.f)) return;  // Eq. filteredG
  if (st.kase == 2) {       // (c): step out of the splat along the ray from its centre, both ways
    const float sd = std::sqrt(ddx * ddx + ddy * ddy);
    if (sd < 1e-6f) return;
    const float inv_sd = 1.f / sd;
    const float ux = ddx * inv_sd, uy = ddy * inv_sd;
    const float qu = quad(P.s, ux, uy);
    const float rr = std::sqrt(2.f * Q.cutoff / std::max(qu, 1e-20f));
    const float steps[2] = {-(std::max(rr - sd, 0.f)), rr + sd};
    for (int m = 0; m < 2; ++m) {
      const float mx = steps[m] * ux * P.z_f, my = steps[m] * uy * P.z_f;
      const float coef = gd / (mx * mx + my * my + Q.eps);
      acc[0] += coef * mx;
      acc[1] += coef * my;
    }
  } else {
    const float zt = st.kase == 1 ? st.d0 : st.zp;  // (b): forward to the front surface
    const float zt_f = zt * Q.inv_f;
    const float mx = (px - Q.cx) * zt_f - P.X, my = (py - Q.cy) * zt_f - P.Y, mz = zt - st.zp;
    const float coef = gd / (mx * mx + my * my + mz * mz + Q.eps);
    acc[0] += coef * mx;
    acc[1] += coef * my;
    acc[2] += coef * mz;
  }
}

// The dss rule over a point's stride-1 window, 8 pixels of a window row per AVX2 vector: every
// case is computed in every lane and the lane's own case selected by masks; the same float32
// operations in the same order as eval_scalar per lane, and lane l's contributions added to
// partial sum l (in double, two vectors of 4 per coordinate), the order that splat_math.h fixes
// for every path, so the result is bit for bit the scalar one (tests/test_render_backward.py
// checks). A row's pixels beyond its runs of 8 (the 9th of a 9-wide window) go through
// eval_scalar into their own partials, except in windows of 9 to 15 columns that lie wholly on
// the image: those are walked in chunks of 8 consecutive pixels in row-major order, across row
// ends (VisFlatPlan; 10 chunks and one pixel for 9 x 9 instead of 9 chunks and 9 pixels), with
// each lane's contributions moved to its column's partial. Windows narrower than 8 pixels,
// sparse (stride > 1) windows and the rbf rule take the scalar path.
#ifdef DSS_HAVE_AVX2
// One chunk's contributions, added per lane as acc += (x1, y1, 0); acc += (x2, y2, z): the two
// (c) steps (z = 0) or the (a)/(b) step (x2 = y2 = 0); lanes that do not contribute hold +0.
// Adding +0 leaves a sum that started at +0 unchanged, so this is the scalar path's sum without a
// branch on the case or the lane. any: some lane contributes.
struct VisChunkOut {
  __m256 x1, y1, x2, y2, z;
  bool any;
};

// Where a chunk's 8 pixels are: offsets p0 + l of a window row; masked: lanes outside oki (off
// the image) are not read. (AVX2 gathers, or vectors assembled from single loads, for pixels not
// in one row measured slower than evaluating those pixels one at a time.)
struct VisAddr {
  bool masked;
  int64_t p0;
  __m256i oki;
  DSS_AVX2 inline __m256 ld(const float* plane) const {
    return masked ? _mm256_maskload_ps(plane + p0, oki) : _mm256_loadu_ps(plane + p0);
  }
  DSS_AVX2 inline __m256i ldi(const int32_t* plane) const {
    return masked ? _mm256_maskload_epi32((const int*)(plane + p0), oki)
                  : _mm256_loadu_si256((const __m256i*)(plane + p0));
  }
};

// A chunk of 8 consecutive pixels of a window in row-major order, which may run over the end of
// one window row into the next: lanes below the split from offsets p0 + l (the end of row r),
// the others from p1 + l (the start of row r + 1), so a 9-wide window is 10 chunks and one pixel
// instead of 9 chunks and 9 single pixels. Every lane is on the image (the caller checks).
struct VisSplitAddr {
  int64_t p0, p1;
  __m256 hi;  // lanes taken from p1
  __m256i oki;
  DSS_AVX2 inline __m256 ld(const float* plane) const {
    return _mm256_blendv_ps(_mm256_loadu_ps(plane + p0), _mm256_loadu_ps(plane + p1), hi);
  }
  DSS_AVX2 inline __m256i ldi(const int32_t* plane) const {
    return _mm256_castps_si256(_mm256_blendv_ps(_mm256_loadu_ps((const float*)(plane + p0)),
                                                 _mm256_loadu_ps((const float*)(plane + p1)), hi));
  }
};

template <int64_t KC, int64_t CC>
struct VisLanes {
  using Rec = VisRecord<true, KC, CC>;
  const Rec* R;
  int64_t K, C;
  __m256i vk;
  __m256 vu, vv, vz, vnk, vzf, vX, vY, vslope, vslope2, pl0, pl1, pl2, s2, s3, s4;
  __m256 vmerge, veps, vcx, vcy, vinvf, v2cut;
  __m256 wk[16];

  DSS_AVX2 void init(const Rec& rec, int64_t Krt, int64_t Crt, const VisPoint& P, const VisConsts& Q) {
    R = &rec;
    K = KC > 0 ? KC : Krt;
    C = CC > 0 ? CC : Crt;
    vk = _mm256_set1_epi32(P.k);
    vu = _mm256_set1_ps(P.u), vv = _mm256_set1_ps(P.v), vz = _mm256_set1_ps(P.z), vnk = _mm256_set1_ps(P.nk);
    vzf = _mm256_set1_ps(P.z_f), vX = _mm256_set1_ps(P.X), vY = _mm256_set1_ps(P.Y);
    vslope = _mm256_set1_ps(P.slope), vslope2 = _mm256_set1_ps(P.slope * P.slope);
    pl0 = _mm256_set1_ps(P.pl[0]), pl1 = _mm256_set1_ps(P.pl[1]), pl2 = _mm256_set1_ps(P.pl[2]);
    s2 = _mm256_set1_ps(P.s[2]), s3 = _mm256_set1_ps(P.s[3]), s4 = _mm256_set1_ps(P.s[4]);
    vmerge = _mm256_set1_ps(Q.merge), veps = _mm256_set1_ps(Q.eps), vcx = _mm256_set1_ps(Q.cx);
    vcy = _mm256_set1_ps(Q.cy), vinvf = _mm256_set1_ps(Q.inv_f), v2cut = _mm256_set1_ps(2.f * Q.cutoff);
    for (int64_t ch = 0; ch < C; ++ch) wk[ch] = _mm256_set1_ps(P.wk[ch]);
  }

  // add_entries_within in lanes: the scalar loop's stop becomes a mask that stays off once off.
  DSS_AVX2 void add_entries_within(const __m256i* ie, const __m256* de, const __m256* re, const __m256* ge,
                                   int64_t e0, __m256 alive, __m256 lim, __m256& den, __m256& gn) const {
    const __m256i minus1 = _mm256_set1_epi32(-1);
    for (int64_t e = e0; e < K; ++e) {
      alive = _mm256_and_ps(alive, _mm256_and_ps(_mm256_castsi256_ps(_mm256_cmpgt_epi32(ie[e], minus1)),
                                                 _mm256_cmp_ps(de[e], lim, _CMP_LE_OQ)));
      den = _mm256_blendv_ps(den, _mm256_add_ps(den, re[e]), alive);
      gn = _mm256_blendv_ps(gn, _mm256_add_ps(gn, _mm256_mul_ps(re[e], ge[e])), alive);
    }
  }

  // Cases (a)/(b), vis_state: k's tangent-plane depth at the pixels, clamped to kMaxSlope (the
  // square root only where it applies); (dxp, dyp) = pixel centre - (u, v).
  DSS_AVX2 __m256 plane_depth(__m256 px, __m256 vpy, __m256 dxp, __m256 dyp) const {
    const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.f);
    const __m256 iz = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(pl0, px), _mm256_mul_ps(pl1, vpy)), pl2);
    __m256 zq = _mm256_blendv_ps(vz, _mm256_div_ps(one, iz), _mm256_cmp_ps(iz, zero, _CMP_GT_OQ));
    const __m256 d2 = _mm256_add_ps(_mm256_mul_ps(dxp, dxp), _mm256_mul_ps(dyp, dyp));
    const __m256 dz = _mm256_sub_ps(zq, vz);
    const __m256 cl = _mm256_cmp_ps(_mm256_mul_ps(dz, dz), _mm256_mul_ps(vslope2, d2), _CMP_GT_OQ);
    if (_mm256_movemask_ps(cl)) {
      const __m256 dmax = _mm256_mul_ps(vslope, _mm256_sqrt_ps(d2));
      const __m256 lo = _mm256_sub_ps(vz, dmax), hi = _mm256_add_ps(vz, dmax);
      const __m256 mx = _mm256_blendv_ps(zq, lo, _mm256_cmp_ps(zq, lo, _CMP_LT_OQ));  // std::max(zq, lo)
      const __m256 mn = _mm256_blendv_ps(mx, hi, _mm256_cmp_ps(hi, mx, _CMP_LT_OQ));  // std::min(mx, hi)
      zq = _mm256_blendv_ps(zq, mn, cl);
    }
    return zq;
  }

  // Cases (a)/(b): den, gn of the visible set with k added at plane depth zq, but for the cache
  // entries where k becomes the front: the lanes returned, whose entries within zq + T the caller
  // adds (add_entries_within); k1: the case (b) lanes.
  template <class Addr>
  DSS_AVX2 __m256 ab_sums(const Addr& a, __m256 zq, __m256 d0, __m256 d0m, __m256 r1, __m256 r2, __m256 empty,
                          __m256& k1, __m256& den, __m256& gn) const {
    k1 = _mm256_andnot_ps(empty, _mm256_cmp_ps(zq, d0m, _CMP_NLE_UQ));
    __m256 gw = _mm256_setzero_ps();
    for (int64_t ch = 0; ch < C; ++ch) gw = _mm256_add_ps(gw, _mm256_mul_ps(a.ld(R->plane(R->fG(ch))), wk[ch]));
    den = vnk, gn = _mm256_mul_ps(vnk, gw);
    const __m256 mall = _mm256_or_ps(k1, _mm256_cmp_ps(zq, d0, _CMP_GE_OQ));
    den = _mm256_blendv_ps(den, _mm256_add_ps(den, r1), mall);
    gn = _mm256_blendv_ps(gn, _mm256_add_ps(gn, r2), mall);
    return _mm256_andnot_ps(_mm256_or_ps(mall, empty), _mm256_castsi256_ps(_mm256_set1_epi32(-1)));
  }

  // Cases (a)/(b)'s step towards the pixel's ray ((b), lanes k1: onto the front surface d0), in
  // every lane: b = (x, y, z).
  DSS_AVX2 void ab_step(__m256 gd, __m256 k1, __m256 zp, __m256 d0, __m256 px, __m256 vpy, __m256 b[3]) const {
    const __m256 zt = _mm256_blendv_ps(zp, d0, k1);
    const __m256 zt_f = _mm256_mul_ps(zt, vinvf);
    const __m256 mx = _mm256_sub_ps(_mm256_mul_ps(_mm256_sub_ps(px, vcx), zt_f), vX);
    const __m256 my = _mm256_sub_ps(_mm256_mul_ps(_mm256_sub_ps(vpy, vcy), zt_f), vY);
    const __m256 mz = _mm256_sub_ps(zt, zp);
    const __m256 nrm = _mm256_add_ps(
        _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(mx, mx), _mm256_mul_ps(my, my)), _mm256_mul_ps(mz, mz)), veps);
    const __m256 coef = _mm256_div_ps(gd, nrm);
    b[0] = _mm256_mul_ps(coef, mx);
    b[1] = _mm256_mul_ps(coef, my);
    b[2] = _mm256_mul_ps(coef, mz);
  }

  // The 8 evaluations of one chunk; (px, py) the pixel centres.
  template <class Addr>
  DSS_AVX2 void eval(const Addr& a, __m256 px, __m256 vpy, VisChunkOut& out) const {
    const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.f);
    const __m256i minus1 = _mm256_set1_epi32(-1);
    out.any = false;
    const __m256 m = _mm256_and_ps(_mm256_castsi256_ps(a.oki), _mm256_cmp_ps(a.ld(R->plane(Rec::kNZ)), zero, _CMP_NEQ_UQ));
    if (_mm256_movemask_ps(m) == 0) return;
    const __m256 d0 = a.ld(R->plane(Rec::kD0)), r1 = a.ld(R->plane(Rec::kDen)), r2 = a.ld(R->plane(Rec::kGn));
    const __m256 d0m = _mm256_add_ps(d0, vmerge);
    __m256i ie[8];
    __m256 de[8], re[8], ge[8];
    __m256 found = zero, ek0 = zero, pdk = zero, prk = zero, pgk = zero;
    for (int64_t e = 0; e < K; ++e) {
      ie[e] = a.ldi(R->idx_plane(e));
      de[e] = a.ld(R->plane(R->fDep(e)));
      re[e] = a.ld(R->plane(R->fRho(e)));
      ge[e] = a.ld(R->plane(R->fGw(e)));
      const __m256 me = _mm256_castsi256_ps(_mm256_cmpeq_epi32(ie[e], vk));
      if (e == 0) ek0 = me;
      found = _mm256_or_ps(found, me);
      pdk = _mm256_blendv_ps(pdk, de[e], me);
      prk = _mm256_blendv_ps(prk, re[e], me);
      pgk = _mm256_blendv_ps(pgk, ge[e], me);
    }
    const __m256 kvis = _mm256_and_ps(found, _mm256_cmp_ps(pdk, d0m, _CMP_LE_OQ));
    const __m256 empty = _mm256_castsi256_ps(_mm256_cmpgt_epi32(_mm256_setzero_si256(), ie[0]));
    __m256 den = zero, gn = zero, zp = vz, kase1 = zero;
    const __m256 dxp = _mm256_sub_ps(px, vu), dyp = _mm256_sub_ps(vpy, vv);
    if (_mm256_movemask_ps(_mm256_and_ps(m, kvis))) {  // (c): without k the visible set loses it,
      __m256 den_a = _mm256_sub_ps(r1, prk);           // or the next entry becomes the front
      const __m256 gn_a = _mm256_sub_ps(r2, _mm256_mul_ps(prk, pgk));
      den_a = _mm256_blendv_ps(zero, den_a, _mm256_cmp_ps(den_a, zero, _CMP_GT_OQ));
      __m256 den_b = zero, gn_b = zero;
      if (K > 1)
        add_entries_within(ie, de, re, ge, 1, _mm256_castsi256_ps(minus1), _mm256_add_ps(de[1], vmerge), den_b, gn_b);
      den = _mm256_blendv_ps(den_a, den_b, ek0);
      gn = _mm256_blendv_ps(gn_a, gn_b, ek0);
    }
    if (_mm256_movemask_ps(_mm256_andnot_ps(kvis, m))) {  // (a)/(b): k's clamped plane depth decides
      const __m256 zq = plane_depth(px, vpy, dxp, dyp);
      __m256 k1, den_n, gn_n;
      const __m256 alive = ab_sums(a, zq, d0, d0m, r1, r2, empty, k1, den_n, gn_n);
      if (_mm256_movemask_ps(alive))  // k becomes the front: entries beyond zp + T drop out
        add_entries_within(ie, de, re, ge, 0, alive, _mm256_add_ps(zq, vmerge), den_n, gn_n);
      den = _mm256_blendv_ps(den_n, den, kvis);
      gn = _mm256_blendv_ps(gn_n, gn, kvis);
      zp = zq;
      kase1 = k1;
    }
    const __m256 gsel = _mm256_blendv_ps(a.ld(R->plane(Rec::kGb)), _mm256_div_ps(gn, den), _mm256_cmp_ps(den, zero, _CMP_GT_OQ));
    const __m256 gd = _mm256_sub_ps(gsel, a.ld(R->plane(Rec::kGi)));
    const __m256 act = _mm256_and_ps(m, _mm256_cmp_ps(gd, zero, _CMP_LT_OQ));  // Eq. filteredG
    __m256 act_v = _mm256_and_ps(act, kvis);
    const __m256 act_n = _mm256_andnot_ps(kvis, act);
    __m256 c[2][2] = {{zero, zero}, {zero, zero}}, b[3] = {zero, zero, zero};
    if (_mm256_movemask_ps(act_v)) {  // (c): step out of the splat along the ray, both ways
      const __m256 sd = _mm256_sqrt_ps(_mm256_add_ps(_mm256_mul_ps(dxp, dxp), _mm256_mul_ps(dyp, dyp)));
      act_v = _mm256_and_ps(act_v, _mm256_cmp_ps(sd, _mm256_set1_ps(1e-6f), _CMP_NLT_UQ));
      const __m256 inv_sd = _mm256_div_ps(one, sd);
      const __m256 ux = _mm256_mul_ps(dxp, inv_sd), uy = _mm256_mul_ps(dyp, inv_sd);
      const __m256 qu = _mm256_add_ps(
          _mm256_add_ps(_mm256_mul_ps(_mm256_mul_ps(s2, ux), ux), _mm256_mul_ps(_mm256_mul_ps(s3, ux), uy)),
          _mm256_mul_ps(_mm256_mul_ps(s4, uy), uy));
      const __m256 tiny = _mm256_set1_ps(1e-20f);
      const __m256 qm = _mm256_blendv_ps(qu, tiny, _mm256_cmp_ps(qu, tiny, _CMP_LT_OQ));  // std::max(qu, 1e-20f)
      const __m256 rr = _mm256_sqrt_ps(_mm256_div_ps(v2cut, qm));
      __m256 t = _mm256_sub_ps(rr, sd);
      t = _mm256_blendv_ps(t, zero, _mm256_cmp_ps(t, zero, _CMP_LT_OQ));  // std::max(rr - sd, 0.f)
      const __m256 steps[2] = {_mm256_xor_ps(t, _mm256_set1_ps(-0.f)), _mm256_add_ps(rr, sd)};
      for (int mm = 0; mm < 2; ++mm) {
        const __m256 mx = _mm256_mul_ps(_mm256_mul_ps(steps[mm], ux), vzf);
        const __m256 my = _mm256_mul_ps(_mm256_mul_ps(steps[mm], uy), vzf);
        const __m256 coef =
            _mm256_div_ps(gd, _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(mx, mx), _mm256_mul_ps(my, my)), veps));
        c[mm][0] = _mm256_mul_ps(coef, mx);
        c[mm][1] = _mm256_mul_ps(coef, my);
      }
    }
    if (_mm256_movemask_ps(act_n)) ab_step(gd, kase1, zp, d0, px, vpy, b);  // (a)/(b): towards the pixel's ray
    // a section's inactive lanes may hold anything (it ran for the others): keep the active ones
    const __m256 act_any = _mm256_or_ps(act_v, act_n);
    out.x1 = _mm256_and_ps(act_any, _mm256_blendv_ps(b[0], c[0][0], kvis));
    out.y1 = _mm256_and_ps(act_any, _mm256_blendv_ps(b[1], c[0][1], kvis));
    out.x2 = _mm256_and_ps(act_v, c[1][0]);
    out.y2 = _mm256_and_ps(act_v, c[1][1]);
    out.z = _mm256_and_ps(act_n, b[2]);
    out.any = _mm256_movemask_ps(act_any) != 0;
  }
  // eval for a chunk in none of whose pixels k is cached (VisLanes16::eval_nok in 8 lanes): every
  // lane takes case (a) or (b); eval's operations for such lanes, so the same bits.
  template <class Addr>
  DSS_AVX2 void eval_nok(const Addr& a, __m256 px, __m256 vpy, VisChunkOut& out) const {
    const __m256 zero = _mm256_setzero_ps();
    out.any = false;
    const __m256 m = _mm256_and_ps(_mm256_castsi256_ps(a.oki), _mm256_cmp_ps(a.ld(R->plane(Rec::kNZ)), zero, _CMP_NEQ_UQ));
    if (_mm256_movemask_ps(m) == 0) return;
    const __m256 d0 = a.ld(R->plane(Rec::kD0)), r1 = a.ld(R->plane(Rec::kDen)), r2 = a.ld(R->plane(Rec::kGn));
    const __m256 d0m = _mm256_add_ps(d0, vmerge);
    const __m256 empty = _mm256_castsi256_ps(_mm256_cmpgt_epi32(_mm256_setzero_si256(), a.ldi(R->idx_plane(0))));
    const __m256 dxp = _mm256_sub_ps(px, vu), dyp = _mm256_sub_ps(vpy, vv);
    const __m256 zq = plane_depth(px, vpy, dxp, dyp);
    __m256 k1, den, gn;
    const __m256 alive = ab_sums(a, zq, d0, d0m, r1, r2, empty, k1, den, gn);
    if (_mm256_movemask_ps(alive)) {  // k becomes the front: entries beyond zp + T drop out
      __m256i ie[8];
      __m256 de[8], re[8], ge[8];
      for (int64_t e = 0; e < K; ++e) {
        ie[e] = a.ldi(R->idx_plane(e));
        de[e] = a.ld(R->plane(R->fDep(e)));
        re[e] = a.ld(R->plane(R->fRho(e)));
        ge[e] = a.ld(R->plane(R->fGw(e)));
      }
      add_entries_within(ie, de, re, ge, 0, alive, _mm256_add_ps(zq, vmerge), den, gn);
    }
    const __m256 gsel = _mm256_blendv_ps(a.ld(R->plane(Rec::kGb)), _mm256_div_ps(gn, den), _mm256_cmp_ps(den, zero, _CMP_GT_OQ));
    const __m256 gd = _mm256_sub_ps(gsel, a.ld(R->plane(Rec::kGi)));
    const __m256 act = _mm256_and_ps(m, _mm256_cmp_ps(gd, zero, _CMP_LT_OQ));  // Eq. filteredG
    if (_mm256_movemask_ps(act) == 0) return;
    __m256 b[3];
    ab_step(gd, k1, zq, d0, px, vpy, b);
    out.x1 = _mm256_and_ps(act, b[0]);
    out.y1 = _mm256_and_ps(act, b[1]);
    out.x2 = zero;
    out.y2 = zero;
    out.z = _mm256_and_ps(act, b[2]);
    out.any = true;
  }
};

#endif

// Adds the window's partial sums to acc in partial order (dss_splat::vis_partial).
inline void add_partials(const double (*part)[3], int nq, double acc[3]) {
  for (int q = 0; q < nq; ++q)
    for (int a = 0; a < 3; ++a) acc[a] += part[q][a];
}

#ifdef DSS_HAVE_AVX2
// A lane's float contributions added to its double partial (lanes 0-3 in lo, 4-7 in hi).
DSS_AVX2 inline void add_lanes(__m256d& lo, __m256d& hi, __m256 x) {
  lo = _mm256_add_pd(lo, _mm256_cvtps_pd(_mm256_castps256_ps128(x)));
  hi = _mm256_add_pd(hi, _mm256_cvtps_pd(_mm256_extractf128_ps(x, 1)));
}

// A window of n = 2 w + 1 columns, 9 <= n <= 15, walked in row-major order in chunks of 8
// consecutive pixels (VisSplitAddr), n * n = 8 * nvec + 1 pixels: nvec chunks and the last pixel
// alone, where the row walk takes n - 8 single pixels per row. Lane l of chunk c is window pixel
// 8 c + l (row, column as below). For these widths a window column's partial sum
// (dss_splat::vis_partial) is its column number, so a chunk's contributions are moved by perm to
// the lane of their column (columns 0-7, present where pres is set: a chunk's columns are
// distinct, 8 < n) and added there, and those of columns 8 and beyond (extra lanes, all in the
// chunk's first row) go to their own partials: every partial gets its pixels in row-major order,
// as on the row walk, so the sums are the same bits.
struct VisFlatPlan {
  static constexpr int kMaxChunks = 28;  // 15 * 15 / 8
  int n = 0, nvec = 0;
  int64_t p0[kMaxChunks], p1[kMaxChunks];  // offsets from the window's first pixel
  alignas(32) int32_t col[kMaxChunks][8], row[kMaxChunks][8], perm[kMaxChunks][8], pres[kMaxChunks][8],
      hi[kMaxChunks][8];
  int nextra[kMaxChunks], extra[kMaxChunks][8];  // lanes in columns >= 8
  bool split[kMaxChunks];  // the chunk runs over a row end

  // Whether the chunked walk applies to windows of half size w (and builds it for image width W).
  bool build(int64_t w, int64_t W) {
    n = (int)(2 * w + 1);
    if (n < 9 || n > 15) return false;
    nvec = n * n / 8;
    for (int c = 0; c < nvec; ++c) {
      int split = 8;
      for (int l = 0; l < 8; ++l) {
        const int f = 8 * c + l;
        row[c][l] = f / n;
        col[c][l] = f % n;
        if (split == 8 && row[c][l] != row[c][0]) split = l;
        hi[c][l] = split < 8 ? -1 : 0;
      }
      p0[c] = (int64_t)row[c][0] * W + col[c][0];
      p1[c] = split < 8 ? (int64_t)(row[c][0] + 1) * W - split : p0[c];
      this->split[c] = split < 8;
      nextra[c] = 0;
      for (int k = 0; k < 8; ++k) perm[c][k] = 0, pres[c][k] = 0;
      for (int l = 0; l < 8; ++l) {
        if (col[c][l] < 8) {
          perm[c][col[c][l]] = l;
          pres[c][col[c][l]] = -1;
        } else {
          extra[c][nextra[c]++] = l;
        }
      }
    }
    return true;
  }
};

// The chunked walk of an interior window (every pixel on the image) by plan F: the same
// evaluations and partial sums as the row walk in window_dss_avx2.
template <int64_t KC, int64_t CC>
DSS_AVX2 void window_flat_avx2(const VisLanes<KC, CC>& L, const VisRecord<true, KC, CC>& rec, int64_t Krt,
                               int64_t Crt, const VisPoint& P, const VisConsts& Q, const VisFlatPlan& F, int64_t W,
                               int64_t window, int ic, int jc, const uint8_t* krows, __m256d* sx, __m256d* sy,
                               __m256d* sz, double (*part)[3]) {
  const int64_t corner = (int64_t)(ic - window) * W + (jc - window);
  const __m256i vj0 = _mm256_set1_epi32(jc - (int)window), vi0 = _mm256_set1_epi32(ic - (int)window);
  const __m256 half = _mm256_set1_ps(0.5f);
  VisSplitAddr a;
  a.oki = _mm256_set1_epi32(-1);
  VisAddr in_row;  // chunks within one row: one load per plane
  in_row.masked = false;
  in_row.oki = a.oki;
  VisChunkOut o;
  for (int c = 0; c < F.nvec; ++c) {
    const __m256 px = _mm256_add_ps(
        _mm256_cvtepi32_ps(_mm256_add_epi32(vj0, _mm256_load_si256((const __m256i*)F.col[c]))), half);
    const __m256 py = _mm256_add_ps(
        _mm256_cvtepi32_ps(_mm256_add_epi32(vi0, _mm256_load_si256((const __m256i*)F.row[c]))), half);
    // k cached in one of the chunk's rows (krows, window_rows_avx512), or no flags: eval
    const int r0 = F.row[c][0];
    const bool cached = !krows || krows[r0] || (F.split[c] && krows[r0 + 1]);
    if (F.split[c]) {
      a.p0 = corner + F.p0[c];
      a.p1 = corner + F.p1[c];
      a.hi = _mm256_castsi256_ps(_mm256_load_si256((const __m256i*)F.hi[c]));
      cached ? L.eval(a, px, py, o) : L.eval_nok(a, px, py, o);
    } else {
      in_row.p0 = corner + F.p0[c];
      cached ? L.eval(in_row, px, py, o) : L.eval_nok(in_row, px, py, o);
    }
    if (!o.any) continue;
    const __m256i pm = _mm256_load_si256((const __m256i*)F.perm[c]);
    const __m256 pr = _mm256_castsi256_ps(_mm256_load_si256((const __m256i*)F.pres[c]));
    add_lanes(sx[0], sx[1], _mm256_and_ps(_mm256_permutevar8x32_ps(o.x1, pm), pr));
    add_lanes(sy[0], sy[1], _mm256_and_ps(_mm256_permutevar8x32_ps(o.y1, pm), pr));
    add_lanes(sx[0], sx[1], _mm256_and_ps(_mm256_permutevar8x32_ps(o.x2, pm), pr));
    add_lanes(sy[0], sy[1], _mm256_and_ps(_mm256_permutevar8x32_ps(o.y2, pm), pr));
    add_lanes(sz[0], sz[1], _mm256_and_ps(_mm256_permutevar8x32_ps(o.z, pm), pr));
    if (F.nextra[c]) {
      alignas(32) float x1[8], y1[8], x2[8], y2[8], z[8];
      _mm256_store_ps(x1, o.x1), _mm256_store_ps(y1, o.y1), _mm256_store_ps(x2, o.x2);
      _mm256_store_ps(y2, o.y2), _mm256_store_ps(z, o.z);
      for (int e = 0; e < F.nextra[c]; ++e) {  // eval_scalar's order: (x1, y1), then (x2, y2, z)
        const int l = F.extra[c][e];
        double* q = part[F.col[c][l]];
        q[0] += x1[l];
        q[1] += y1[l];
        q[0] += x2[l];
        q[1] += y2[l];
        q[2] += z[l];
      }
    }
  }
  // the window's last pixel alone
  const int64_t p = corner + (int64_t)(F.n - 1) * W + (F.n - 1);
  if (rec.nz(p) != 0.f)
    eval_scalar<KC, CC>(rec, Krt, Crt, P, Q, 0, p, (float)(jc + window) + 0.5f, (float)(ic + window) + 0.5f,
                        part[F.n - 1]);
}

// The dss rule in 16 lanes (AVX-512, taken where the CPU has it) for windows of 9 to 15 columns:
// one window row per vector (lane l: column l of the window; the lanes beyond the row unused),
// for windows wholly on the image and at its border alike. VisLanes16::eval is VisLanes::eval
// with 16 lanes and mask registers: the same float32 operations in the same order per lane, every
// case computed in every lane and selected by masks, lanes that do not contribute holding +0. A
// lane's contributions go to its column's partial sum (vis_partial: the column number, for these
// widths), rows in order, so the result is the scalar walk's bit for bit
// (tests/test_render_backward.py compares every vector level with the scalar path). Against the
// 8-lane walk, 1.34x on the 20K position step's visibility backward (2 cores, Zen 5). (A walk
// that packed a window's pixels 16 at a time in row-major order, 5 vectors and one pixel per 9 x 9
// window instead of 9 vectors, was 1.07x slower: each vector read 2-3 row runs per plane and
// moved its lanes to their columns' partials.) A row costs about 80 cycles, bound by its chain
// of three divisions and the comparisons between them (session 37, docs/performance.md); rows
// where the point is not cached take eval_nok, about a third of eval.
struct VisRowOut16 {
  __m512 x1, y1, x2, y2, z;
  bool any;
  bool any_c;  // some lane contributes through case (c): x2, y2 are +0 in every lane otherwise
};

// One window row: lane l at offset p0 + l of every plane. Rows wholly on the image are read with
// full loads, which may read up to 7 values beyond the row's window (on the image or in a plane's
// padding, VisRecord::plane_stride; never used); rows at the border with loads masked to the
// lanes on the image.
struct VisRow16 {
  int64_t p0;
  bool masked;
  __mmask16 oki;
  DSS_AVX512 inline __m512 ld(const float* plane) const {
    return masked ? _mm512_maskz_loadu_ps(oki, plane + p0) : _mm512_loadu_ps(plane + p0);
  }
  DSS_AVX512 inline __m512i ldi(const int32_t* plane) const {
    return masked ? _mm512_maskz_loadu_epi32(oki, plane + p0) : _mm512_loadu_si512((const void*)(plane + p0));
  }
};

template <int64_t KC, int64_t CC>
struct VisLanes16 {
  using Rec = VisRecord<true, KC, CC>;
  const Rec* R;
  int64_t K, C;
  __m512i vk;
  __m512 vu, vv, vz, vnk, vzf, vX, vY, vslope, vslope2, pl0, pl1, pl2, s2, s3, s4;
  __m512 vmerge, veps, vcx, vcy, vinvf, v2cut;
  __m512 wk[16];

  DSS_AVX512 void init(const Rec& rec, int64_t Krt, int64_t Crt, const VisPoint& P, const VisConsts& Q) {
    R = &rec;
    K = KC > 0 ? KC : Krt;
    C = CC > 0 ? CC : Crt;
    vk = _mm512_set1_epi32(P.k);
    vu = _mm512_set1_ps(P.u), vv = _mm512_set1_ps(P.v), vz = _mm512_set1_ps(P.z), vnk = _mm512_set1_ps(P.nk);
    vzf = _mm512_set1_ps(P.z_f), vX = _mm512_set1_ps(P.X), vY = _mm512_set1_ps(P.Y);
    vslope = _mm512_set1_ps(P.slope), vslope2 = _mm512_set1_ps(P.slope * P.slope);
    pl0 = _mm512_set1_ps(P.pl[0]), pl1 = _mm512_set1_ps(P.pl[1]), pl2 = _mm512_set1_ps(P.pl[2]);
    s2 = _mm512_set1_ps(P.s[2]), s3 = _mm512_set1_ps(P.s[3]), s4 = _mm512_set1_ps(P.s[4]);
    vmerge = _mm512_set1_ps(Q.merge), veps = _mm512_set1_ps(Q.eps), vcx = _mm512_set1_ps(Q.cx);
    vcy = _mm512_set1_ps(Q.cy), vinvf = _mm512_set1_ps(Q.inv_f), v2cut = _mm512_set1_ps(2.f * Q.cutoff);
    for (int64_t ch = 0; ch < C; ++ch) wk[ch] = _mm512_set1_ps(P.wk[ch]);
  }

  // VisLanes::add_entries_within: a lane's sums stop growing at its first entry beyond lim.
  DSS_AVX512 void add_entries_within(const __m512i* ie, const __m512* de, const __m512* re, const __m512* ge,
                                     int64_t e0, __mmask16 alive, __m512 lim, __m512& den, __m512& gn) const {
    const __m512i minus1 = _mm512_set1_epi32(-1);
    for (int64_t e = e0; e < K; ++e) {
      alive = alive & _mm512_cmpgt_epi32_mask(ie[e], minus1) & _mm512_cmp_ps_mask(de[e], lim, _CMP_LE_OQ);
      den = _mm512_mask_add_ps(den, alive, den, re[e]);
      gn = _mm512_mask_add_ps(gn, alive, gn, _mm512_mul_ps(re[e], ge[e]));
    }
  }

  // Cases (a)/(b), vis_state: k's tangent-plane depth at the pixels, clamped to kMaxSlope (the
  // square root only where it applies); (dxp, dyp) = pixel centre - (u, v).
  DSS_AVX512 __m512 plane_depth(__m512 px, __m512 vpy, __m512 dxp, __m512 dyp) const {
    const __m512 zero = _mm512_setzero_ps(), one = _mm512_set1_ps(1.f);
    const __m512 iz = _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(pl0, px), _mm512_mul_ps(pl1, vpy)), pl2);
    __m512 zq = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(iz, zero, _CMP_GT_OQ), vz, _mm512_div_ps(one, iz));
    const __m512 d2 = _mm512_add_ps(_mm512_mul_ps(dxp, dxp), _mm512_mul_ps(dyp, dyp));
    const __m512 dz = _mm512_sub_ps(zq, vz);
    const __mmask16 cl = _mm512_cmp_ps_mask(_mm512_mul_ps(dz, dz), _mm512_mul_ps(vslope2, d2), _CMP_GT_OQ);
    if (cl) {
      const __m512 dmax = _mm512_mul_ps(vslope, _mm512_sqrt_ps(d2));
      const __m512 lo = _mm512_sub_ps(vz, dmax), hi = _mm512_add_ps(vz, dmax);
      const __m512 mx = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(zq, lo, _CMP_LT_OQ), zq, lo);
      const __m512 mn = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(hi, mx, _CMP_LT_OQ), mx, hi);
      zq = _mm512_mask_blend_ps(cl, zq, mn);
    }
    return zq;
  }

  // Cases (a)/(b): den, gn of the visible set with k added at plane depth zq, but for the cache
  // entries where k becomes the front: the lanes returned, whose entries within zq + T the caller
  // adds (add_entries_within); k1: the case (b) lanes.
  template <class Addr>
  DSS_AVX512 __mmask16 ab_sums(const Addr& a, __m512 zq, __m512 d0, __m512 d0m, __m512 r1, __m512 r2,
                               __mmask16 empty, __mmask16& k1, __m512& den, __m512& gn) const {
    k1 = ~empty & _mm512_cmp_ps_mask(zq, d0m, _CMP_NLE_UQ);
    __m512 gw = _mm512_setzero_ps();
    for (int64_t ch = 0; ch < C; ++ch) gw = _mm512_add_ps(gw, _mm512_mul_ps(a.ld(R->plane(R->fG(ch))), wk[ch]));
    den = vnk, gn = _mm512_mul_ps(vnk, gw);
    const __mmask16 mall = k1 | _mm512_cmp_ps_mask(zq, d0, _CMP_GE_OQ);
    den = _mm512_mask_add_ps(den, mall, den, r1);
    gn = _mm512_mask_add_ps(gn, mall, gn, r2);
    return ~(mall | empty);
  }

  // Cases (a)/(b)'s step towards the pixel's ray ((b), lanes k1: onto the front surface d0): b =
  // (x, y, z) in the lanes of keep, +0 in the others.
  DSS_AVX512 void ab_step(__m512 gd, __mmask16 k1, __m512 zp, __m512 d0, __m512 px, __m512 vpy, __mmask16 keep,
                          __m512 b[3]) const {
    const __m512 zt = _mm512_mask_blend_ps(k1, zp, d0);
    const __m512 zt_f = _mm512_mul_ps(zt, vinvf);
    const __m512 mx = _mm512_sub_ps(_mm512_mul_ps(_mm512_sub_ps(px, vcx), zt_f), vX);
    const __m512 my = _mm512_sub_ps(_mm512_mul_ps(_mm512_sub_ps(vpy, vcy), zt_f), vY);
    const __m512 mz = _mm512_sub_ps(zt, zp);
    const __m512 nrm = _mm512_add_ps(
        _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(mx, mx), _mm512_mul_ps(my, my)), _mm512_mul_ps(mz, mz)), veps);
    const __m512 coef = _mm512_div_ps(gd, nrm);
    b[0] = _mm512_maskz_mul_ps(keep, coef, mx);
    b[1] = _mm512_maskz_mul_ps(keep, coef, my);
    b[2] = _mm512_maskz_mul_ps(keep, coef, mz);
  }

  // The evaluations of one window row (lanes in oki); (px, py) the pixel centres. Comments on
  // the cases: VisLanes::eval and vis_state.
  template <class Addr>
  DSS_AVX512 void eval(const Addr& a, __mmask16 oki, __m512 px, __m512 vpy, VisRowOut16& out) const {
    const __m512 zero = _mm512_setzero_ps(), one = _mm512_set1_ps(1.f);
    out.any = false;
    const __mmask16 m = _mm512_mask_cmp_ps_mask(oki, a.ld(R->plane(Rec::kNZ)), zero, _CMP_NEQ_UQ);
    if (m == 0) return;
    const __m512 d0 = a.ld(R->plane(Rec::kD0)), r1 = a.ld(R->plane(Rec::kDen)), r2 = a.ld(R->plane(Rec::kGn));
    const __m512 d0m = _mm512_add_ps(d0, vmerge);
    __m512i ie[8];
    __m512 de[8], re[8], ge[8];
    __mmask16 found = 0, ek0 = 0;
    __m512 pdk = zero, prk = zero, pgk = zero;
    for (int64_t e = 0; e < K; ++e) {
      ie[e] = a.ldi(R->idx_plane(e));
      de[e] = a.ld(R->plane(R->fDep(e)));
      re[e] = a.ld(R->plane(R->fRho(e)));
      ge[e] = a.ld(R->plane(R->fGw(e)));
      const __mmask16 me = _mm512_cmpeq_epi32_mask(ie[e], vk);
      if (e == 0) ek0 = me;
      found |= me;
      pdk = _mm512_mask_blend_ps(me, pdk, de[e]);
      prk = _mm512_mask_blend_ps(me, prk, re[e]);
      pgk = _mm512_mask_blend_ps(me, pgk, ge[e]);
    }
    const __mmask16 kvis = found & _mm512_cmp_ps_mask(pdk, d0m, _CMP_LE_OQ);
    const __mmask16 empty = _mm512_cmplt_epi32_mask(ie[0], _mm512_setzero_si512());
    __m512 den = zero, gn = zero, zp = vz;
    __mmask16 kase1 = 0;
    const __m512 dxp = _mm512_sub_ps(px, vu), dyp = _mm512_sub_ps(vpy, vv);
    if (m & kvis) {
      __m512 den_a = _mm512_sub_ps(r1, prk);
      const __m512 gn_a = _mm512_sub_ps(r2, _mm512_mul_ps(prk, pgk));
      den_a = _mm512_maskz_mov_ps(_mm512_cmp_ps_mask(den_a, zero, _CMP_GT_OQ), den_a);
      __m512 den_b = zero, gn_b = zero;
      if (K > 1 && (ek0 & kvis & m))  // (only where k was the front)
        add_entries_within(ie, de, re, ge, 1, (__mmask16)0xFFFF, _mm512_add_ps(de[1], vmerge), den_b, gn_b);
      den = _mm512_mask_blend_ps(ek0, den_a, den_b);
      gn = _mm512_mask_blend_ps(ek0, gn_a, gn_b);
    }
    if (m & ~kvis) {
      const __m512 zq = plane_depth(px, vpy, dxp, dyp);
      __mmask16 k1;
      __m512 den_n, gn_n;
      const __mmask16 alive = ab_sums(a, zq, d0, d0m, r1, r2, empty, k1, den_n, gn_n);
      if (alive) add_entries_within(ie, de, re, ge, 0, alive, _mm512_add_ps(zq, vmerge), den_n, gn_n);
      den = _mm512_mask_blend_ps(kvis, den_n, den);
      gn = _mm512_mask_blend_ps(kvis, gn_n, gn);
      zp = zq;
      kase1 = k1;
    }
    const __m512 gsel = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(den, zero, _CMP_GT_OQ), a.ld(R->plane(Rec::kGb)),
                                             _mm512_div_ps(gn, den));
    const __m512 gd = _mm512_sub_ps(gsel, a.ld(R->plane(Rec::kGi)));
    const __mmask16 act = m & _mm512_cmp_ps_mask(gd, zero, _CMP_LT_OQ);
    __mmask16 act_v = act & kvis;
    const __mmask16 act_n = act & ~kvis;
    __m512 c[2][2] = {{zero, zero}, {zero, zero}}, b[3] = {zero, zero, zero};
    if (act_v) {
      const __m512 sd = _mm512_sqrt_ps(_mm512_add_ps(_mm512_mul_ps(dxp, dxp), _mm512_mul_ps(dyp, dyp)));
      act_v = act_v & _mm512_cmp_ps_mask(sd, _mm512_set1_ps(1e-6f), _CMP_NLT_UQ);
      const __m512 inv_sd = _mm512_div_ps(one, sd);
      const __m512 ux = _mm512_mul_ps(dxp, inv_sd), uy = _mm512_mul_ps(dyp, inv_sd);
      const __m512 qu = _mm512_add_ps(
          _mm512_add_ps(_mm512_mul_ps(_mm512_mul_ps(s2, ux), ux), _mm512_mul_ps(_mm512_mul_ps(s3, ux), uy)),
          _mm512_mul_ps(_mm512_mul_ps(s4, uy), uy));
      const __m512 tiny = _mm512_set1_ps(1e-20f);
      const __m512 qm = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(qu, tiny, _CMP_LT_OQ), qu, tiny);
      const __m512 rr = _mm512_sqrt_ps(_mm512_div_ps(v2cut, qm));
      __m512 t = _mm512_sub_ps(rr, sd);
      t = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(t, zero, _CMP_LT_OQ), t, zero);
      const __m512 steps[2] = {_mm512_xor_ps(t, _mm512_set1_ps(-0.f)), _mm512_add_ps(rr, sd)};
      for (int mm = 0; mm < 2; ++mm) {
        const __m512 mx = _mm512_mul_ps(_mm512_mul_ps(steps[mm], ux), vzf);
        const __m512 my = _mm512_mul_ps(_mm512_mul_ps(steps[mm], uy), vzf);
        const __m512 coef =
            _mm512_div_ps(gd, _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(mx, mx), _mm512_mul_ps(my, my)), veps));
        c[mm][0] = _mm512_mul_ps(coef, mx);
        c[mm][1] = _mm512_mul_ps(coef, my);
      }
    }
    if (act_n) ab_step(gd, kase1, zp, d0, px, vpy, act_n, b);
    const __mmask16 act_any = act_v | act_n;
    out.x1 = _mm512_maskz_mov_ps(act_any, _mm512_mask_blend_ps(kvis, b[0], c[0][0]));
    out.y1 = _mm512_maskz_mov_ps(act_any, _mm512_mask_blend_ps(kvis, b[1], c[0][1]));
    out.x2 = _mm512_maskz_mov_ps(act_v, c[1][0]);
    out.y2 = _mm512_maskz_mov_ps(act_v, c[1][1]);
    out.z = _mm512_maskz_mov_ps(act_n, b[2]);
    out.any = act_any != 0;
    out.any_c = act_v != 0;
  }
  // eval for a row in none of whose evaluated pixels k is cached (82% of the rows of a 20K-point
  // step: a point is cached at about 3 pixels around its centre; the record build flags the
  // others, visibility_backward's krows): found is 0 in every lane, so every lane takes case (a)
  // or (b), and the cache entries are read only where k becomes the front. The same operations
  // in the same order as eval's for such lanes, so the same bits (tests compare every level with
  // the scalar path). It costs about a third of eval (session 37: eval rows 6.6 ms, these 8.9 ms
  // for 4.5 times as many).
  template <class Addr>
  DSS_AVX512 void eval_nok(const Addr& a, __mmask16 oki, __m512 px, __m512 vpy, VisRowOut16& out) const {
    const __m512 zero = _mm512_setzero_ps();
    out.any = false;
    out.any_c = false;
    const __mmask16 m = _mm512_mask_cmp_ps_mask(oki, a.ld(R->plane(Rec::kNZ)), zero, _CMP_NEQ_UQ);
    if (m == 0) return;
    const __m512 d0 = a.ld(R->plane(Rec::kD0)), r1 = a.ld(R->plane(Rec::kDen)), r2 = a.ld(R->plane(Rec::kGn));
    const __m512 d0m = _mm512_add_ps(d0, vmerge);
    const __mmask16 empty = _mm512_cmplt_epi32_mask(a.ldi(R->idx_plane(0)), _mm512_setzero_si512());
    const __m512 dxp = _mm512_sub_ps(px, vu), dyp = _mm512_sub_ps(vpy, vv);
    const __m512 zq = plane_depth(px, vpy, dxp, dyp);
    __mmask16 k1;
    __m512 den, gn;
    const __mmask16 alive = ab_sums(a, zq, d0, d0m, r1, r2, empty, k1, den, gn);
    if (alive) {  // k becomes the front: entries beyond zp + T drop out
      __m512i ie[8];
      __m512 de[8], re[8], ge[8];
      for (int64_t e = 0; e < K; ++e) {
        ie[e] = a.ldi(R->idx_plane(e));
        de[e] = a.ld(R->plane(R->fDep(e)));
        re[e] = a.ld(R->plane(R->fRho(e)));
        ge[e] = a.ld(R->plane(R->fGw(e)));
      }
      add_entries_within(ie, de, re, ge, 0, alive, _mm512_add_ps(zq, vmerge), den, gn);
    }
    const __m512 gsel = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(den, zero, _CMP_GT_OQ), a.ld(R->plane(Rec::kGb)),
                                             _mm512_div_ps(gn, den));
    const __m512 gd = _mm512_sub_ps(gsel, a.ld(R->plane(Rec::kGi)));
    const __mmask16 act = m & _mm512_cmp_ps_mask(gd, zero, _CMP_LT_OQ);
    __m512 b[3];
    ab_step(gd, k1, zq, d0, px, vpy, act, b);
    out.x1 = b[0];
    out.y1 = b[1];
    out.z = b[2];
    out.any = true;  // (act may be 0: adding +0 changes no partial)
  }
};

// The window of half size w (9 <= 2 w + 1 <= 15 columns) of the point P centred on pixel (ic, jc),
// its rows on the image one vector each; adds the window's partial sums to acc in partial order.
// krows[r] (r = 0 .. 2 w): non-zero if P's point is cached at some evaluated pixel of window row
// r (VisLanes16::eval), zero if not (VisLanes16::eval_nok).
template <int64_t KC, int64_t CC>
DSS_AVX512 void window_rows_avx512(const VisRecord<true, KC, CC>& rec, int64_t Krt, int64_t Crt, const VisPoint& P,
                                   const VisConsts& Q, int64_t H, int64_t W, int64_t window, int ic, int jc,
                                   const uint8_t* krows, double acc[3]) {
  VisLanes16<KC, CC> L;
  L.init(rec, Krt, Crt, P, Q);
  const int n = (int)(2 * window + 1), j0 = jc - (int)window;
  const int nq = dss_splat::vis_partial_count(window);  // = n: partial q is column q
  const __m512i vj = _mm512_add_epi32(_mm512_set1_epi32(j0),
                                      _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15));
  const __m512 px = _mm512_add_ps(_mm512_cvtepi32_ps(vj), _mm512_set1_ps(0.5f));
  VisRow16 a;
  // the window's columns on the image
  a.oki = (__mmask16)((1u << n) - 1u) & _mm512_cmpgt_epi32_mask(vj, _mm512_set1_epi32(-1)) &
          _mm512_cmpgt_epi32_mask(_mm512_set1_epi32((int)W), vj);
  a.masked = !(j0 >= 0 && j0 + n <= W);
  // partials 0-7 and 8-15 as doubles, lane l = column l
  __m512d sx[2] = {_mm512_setzero_pd(), _mm512_setzero_pd()}, sy[2] = {sx[0], sx[0]}, sz[2] = {sx[0], sx[0]};
  auto add = [&](__m512d* sum, __m512 x) DSS_AVX512 {
    sum[0] = _mm512_add_pd(sum[0], _mm512_cvtps_pd(_mm512_castps512_ps256(x)));
    sum[1] = _mm512_add_pd(sum[1], _mm512_cvtps_pd(_mm512_extractf32x8_ps(x, 1)));
  };
  VisRowOut16 o;
  for (int i = std::max(ic - (int)window, 0); i <= std::min(ic + (int)window, (int)H - 1); ++i) {
    a.p0 = (int64_t)i * W + j0;
    if (krows[i - (ic - (int)window)])
      L.eval(a, a.oki, px, _mm512_set1_ps((float)i + 0.5f), o);
    else
      L.eval_nok(a, a.oki, px, _mm512_set1_ps((float)i + 0.5f), o);
    if (!o.any) continue;
    // eval_scalar's order per pixel: (x1, y1), then (x2, y2, z); x2 and y2 only where some lane
    // took case (c), a minority of the rows (the other lanes hold +0, and adding +0 to a
    // partial, which is never -0, leaves it unchanged)
    add(sx, o.x1);
    add(sy, o.y1);
    if (o.any_c) {
      add(sx, o.x2);
      add(sy, o.y2);
    }
    add(sz, o.z);
  }
  alignas(64) double lanes[3][16];
  _mm512_store_pd(lanes[0], sx[0]), _mm512_store_pd(lanes[0] + 8, sx[1]);
  _mm512_store_pd(lanes[1], sy[0]), _mm512_store_pd(lanes[1] + 8, sy[1]);
  _mm512_store_pd(lanes[2], sz[0]), _mm512_store_pd(lanes[2] + 8, sz[1]);
  for (int q = 0; q < nq; ++q)  // add_partials' order, read from the lanes in place
    for (int c = 0; c < 3; ++c) acc[c] += lanes[c][q];
}

template <int64_t KC, int64_t CC>
DSS_AVX2 void window_dss_avx2(const VisRecord<true, KC, CC>& rec, int64_t Krt, int64_t Crt, const VisPoint& P, const VisConsts& Q,
                              int64_t H, int64_t W, int64_t window, int ic, int jc, const VisFlatPlan* flat,
                              const uint8_t* krows, double acc[3]) {
  VisLanes<KC, CC> L;
  L.init(rec, Krt, Crt, P, Q);
  const int mw = dss_splat::vis_window_runs(window);  // a row's first mw pixels in runs of 8
  const int nq = dss_splat::vis_partial_count(window);
  const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
  const __m256i minus1 = _mm256_set1_epi32(-1), vW = _mm256_set1_epi32((int)W);
  const __m256 half = _mm256_set1_ps(0.5f);
  VisChunkOut o;
  // partials 0-7 in lanes (x, y, z; lanes 0-3 and 4-7), the rest (columns mw, mw + 1, ...) scalar
  __m256d sx[2] = {_mm256_setzero_pd(), _mm256_setzero_pd()}, sy[2] = {sx[0], sx[0]}, sz[2] = {sx[0], sx[0]};
  double part[dss_splat::kVisPartials][3] = {};
  // interior windows of 9 to 15 columns in chunks across rows; the others row by row
  if (flat && ic - window >= 0 && ic + window < H && jc - window >= 0 && jc + window < W) {
    window_flat_avx2<KC, CC>(L, rec, Krt, Crt, P, Q, *flat, W, window, ic, jc, krows, sx, sy, sz, part);
  } else {
    for (int64_t i = ic - window; i <= ic + window; ++i) {
      if (i < 0 || i >= H) continue;
      const float py = (float)i + 0.5f;
      for (int64_t j0 = jc - window; j0 < jc - window + mw; j0 += 8) {
        if (j0 + 7 < 0 || j0 >= W) continue;
        const __m256i vj = _mm256_add_epi32(_mm256_set1_epi32((int)j0), lane);
        VisAddr a;
        a.masked = !(j0 >= 0 && j0 + 8 <= W);
        a.p0 = i * W + j0;
        a.oki = _mm256_and_si256(_mm256_cmpgt_epi32(vj, minus1), _mm256_cmpgt_epi32(vW, vj));
        if (!krows || krows[i - (ic - window)])
          L.eval(a, _mm256_add_ps(_mm256_cvtepi32_ps(vj), half), _mm256_set1_ps(py), o);
        else
          L.eval_nok(a, _mm256_add_ps(_mm256_cvtepi32_ps(vj), half), _mm256_set1_ps(py), o);
        if (o.any) {
          add_lanes(sx[0], sx[1], o.x1);
          add_lanes(sy[0], sy[1], o.y1);
          add_lanes(sx[0], sx[1], o.x2);
          add_lanes(sy[0], sy[1], o.y2);
          add_lanes(sz[0], sz[1], o.z);
        }
      }
      // the row's last 2 w + 1 - mw pixels one at a time (a vector with one lane in use costs 3 scalar ones)
      for (int64_t j = std::max<int64_t>(jc - window + mw, 0); j <= std::min<int64_t>(jc + window, W - 1); ++j) {
        const int64_t p = i * W + j;
        if (rec.nz(p) == 0.f) continue;
        eval_scalar<KC, CC>(rec, Krt, Crt, P, Q, 0, p, (float)j + 0.5f, py, part[8 + (j - (jc - window) - mw)]);
      }
    }
  }
  alignas(32) double lanes[3][8];
  _mm256_store_pd(lanes[0], sx[0]), _mm256_store_pd(lanes[0] + 4, sx[1]);
  _mm256_store_pd(lanes[1], sy[0]), _mm256_store_pd(lanes[1] + 4, sy[1]);
  _mm256_store_pd(lanes[2], sz[0]), _mm256_store_pd(lanes[2] + 4, sz[1]);
  for (int l = 0; l < 8; ++l)
    for (int c = 0; c < 3; ++c) part[l][c] = lanes[c][l];
  add_partials(part, nq, acc);
}
#endif

}  // namespace

torch::Tensor visibility_backward(torch::Tensor packed, torch::Tensor attrs, torch::Tensor idx, torch::Tensor depth,
                                  torch::Tensor rho, torch::Tensor images, torch::Tensor grad, torch::Tensor R,
                                  torch::Tensor focal, torch::Tensor principal, torch::Tensor background,
                                  torch::Tensor planes, int64_t window, int64_t stride, double cutoff_d,
                                  double merge_d, double eps_d, int64_t mode) {
  packed = packed.contiguous().to(torch::kFloat32);
  planes = planes.contiguous().to(torch::kFloat32);
  attrs = attrs.contiguous().to(torch::kFloat32);
  idx = idx.contiguous();
  depth = depth.contiguous();
  rho = rho.contiguous();
  images = images.contiguous().to(torch::kFloat32);
  grad = grad.contiguous().to(torch::kFloat32);
  R = R.contiguous().to(torch::kFloat32);
  focal = focal.contiguous().to(torch::kFloat32);
  principal = principal.contiguous().to(torch::kFloat32);
  background = background.contiguous().to(torch::kFloat32);
  const int64_t V = packed.size(0), N = packed.size(1), H = idx.size(1), W = idx.size(2), K = idx.size(3);
  const int64_t C = attrs.size(2);
  TORCH_CHECK(C <= 16, "at most 16 channels");
  TORCH_CHECK(K >= 1 && K <= 8, "K must be in [1, 8]");
  TORCH_CHECK(stride >= 1, "window stride must be >= 1");
  TORCH_CHECK(planes.numel() == V * N * 3, "planes must be (V,N,3)");
  const float cutoff = (float)cutoff_d, merge = (float)merge_d, eps = (float)eps_d;
  auto out = torch::zeros({N, 3}, torch::TensorOptions().dtype(torch::kFloat32));
  const float* PL = planes.data_ptr<float>();
  float* G = out.data_ptr<float>();
  const float* P = packed.data_ptr<float>();
  const float* A = attrs.data_ptr<float>();
  const int32_t* I = idx.data_ptr<int32_t>();
  const float* D = depth.data_ptr<float>();
  const float* Rh = rho.data_ptr<float>();
  const float* IMG = images.data_ptr<float>();
  const float* GR = grad.data_ptr<float>();
  const float* Rm = R.data_ptr<float>();
  const float* F = focal.data_ptr<float>();
  const float* PP = principal.data_ptr<float>();
  const float* BG = background.data_ptr<float>();

  // The pixel record (VisRecord) of one view at a time: a few MB, cache-resident while that
  // view's points read it; planes (structure of arrays) for the vector path, one record per
  // pixel otherwise (a scalar evaluation then reads 2 cache lines, not one per field). Kept
  // between calls (no fresh pages per call).
  const int64_t HW = H * W;
  // The vector path needs window rows of at least 8 pixels (window >= 4); narrower windows would
  // only run eval_scalar on planes, slower than on per-pixel records.
  const bool vec = mode == 0 && stride == 1 && 2 * window + 1 >= 8 && use_vector_path();
  std::vector<double> gsum((size_t)(N * 3), 0.0);  // world gradient, summed over views in view order
  const int64_t Krt = K, Crt = C;  // run-time values; the evaluation loop may fix them at compile time
  const int64_t kChunk = 64;
  const float inf = std::numeric_limits<float>::infinity();
#ifdef DSS_HAVE_AVX2
  // windows of 9 to 15 columns in 16 lanes, a row per vector, where the CPU has AVX-512; the
  // 8-lane walk's chunk plan otherwise
  const bool rows16 = vec && use_avx512() && window >= 4 && window <= 7;
  VisFlatPlan flat_plan;
  const VisFlatPlan* flat = vec && !rows16 && flat_plan.build(window, W) ? &flat_plan : nullptr;
#endif
  static thread_local std::vector<float> rec_f;
  static thread_local std::vector<int32_t> rec_i;
#ifdef DSS_HAVE_AVX2
  // Per point, a flag per window row (kFlagRows bytes; windows of 9 to 15 rows): non-zero where k is
  // cached at some evaluated pixel of that row; the vector walks' rows (chunks) without it skip
  // the cache scan (VisLanes16::eval_nok, VisLanes::eval_nok). Flags, not a bit mask: the record
  // build sets them from both threads, and plain byte stores of 1 need no atomic
  // read-modify-write (which cost a fifth of the build).
  const bool kf = vec && window >= 4 && 2 * window + 1 <= kFlagRows;
  static thread_local std::vector<uint8_t> krows;
  if (kf) krows.resize((size_t)(N * kFlagRows));
  uint8_t* const kr = krows.data();  // (the vector is this thread's: the tasks use the pointer)
#endif
  auto run = [&](auto layout) {
    constexpr bool kSoA = decltype(layout)::value;
    VisRecord<kSoA> rec;
    rec.C_ = C;
    rec.K_ = K;
    if (kSoA) {
      rec.S = VisRecord<kSoA>::plane_stride(HW);
      rec_f.resize((size_t)(rec.S * VisRecord<kSoA>::fields(C, K)));
      rec_i.resize((size_t)(rec.S * K));
      rec.ix = rec_i.data();
    } else {
      rec.S = VisRecord<kSoA>::fields(C, K);
      rec_f.resize((size_t)(rec.S * HW));
    }
    rec.f = rec_f.data();
    for (int64_t v = 0; v < V; ++v) {
      if (!kSoA) rec.ix = const_cast<int32_t*>(I + v * HW * K);  // read only
#ifdef DSS_HAVE_AVX2
      if (kf) std::memset(kr, 0, (size_t)(N * kFlagRows));
#endif
      dynamic_for(H, 4, [&](int64_t i) {
        // the row's pixels with a non-zero loss gradient (the only ones an evaluation reads
        // further), found in one pass over the gradient row
        static thread_local std::vector<int32_t> col_list;  // (this worker thread's)
        if ((int64_t)col_list.size() < W) col_list.resize((size_t)W);
        int32_t* const cols = col_list.data();
        int ncols = 0;
        for (int64_t j = 0; j < W; ++j) {
          const float* gp = GR + (v * HW + i * W + j) * C;
          bool nz = false;
          for (int64_t ch = 0; ch < C; ++ch) nz |= (gp[ch] != 0.f);
          rec.nz(i * W + j) = nz ? 1.f : 0.f;
          cols[ncols] = (int32_t)j;
          ncols += nz;
        }
        for (int c = 0; c < ncols; ++c) {
          const int64_t j = cols[c], p = i * W + j, g = v * HW + p;
          if (c + kPixelsAhead < ncols) {
            // the cached splats' attributes are scattered rows (a miss each): fetch those of the
            // pixel kPixelsAhead on while this one is built (as the blend backward does)
            const int32_t* qi = I + (v * HW + i * W + cols[c + kPixelsAhead]) * K;
            for (int e = 0; e < K && qi[e] >= 0; ++e) {
              __builtin_prefetch(A + (v * N + qi[e]) * C);
#ifdef DSS_HAVE_AVX2
              if (kf) __builtin_prefetch(P + (v * N + qi[e]) * kFields);
#endif
            }
          }
          const float* gp = GR + g * C;
          const int32_t* pi = I + g * K;
          const float* pd = D + g * K;
          const float* pr = Rh + g * K;
          const float* ip = IMG + g * C;
          float gi = 0.f, gb = 0.f;
          for (int64_t ch = 0; ch < C; ++ch) {
            rec.g(ch, p) = gp[ch];
            gi += gp[ch] * ip[ch];
            gb += gp[ch] * BG[ch];
          }
          rec.gi(p) = gi;
          rec.gb(p) = gb;
          const float d0 = pi[0] >= 0 ? pd[0] : inf;
#ifdef DSS_HAVE_AVX2
          if (kf) {
            // mark row i of the window of every point cached here, if this pixel is in it (the
            // window's centre pixel as the point loop computes it)
            for (int e = 0; e < K && pi[e] >= 0; ++e) {
              const float* sk = P + (v * N + pi[e]) * kFields;
              const int64_t r = i - ((int64_t)std::floor(sk[1]) - window), c = j - ((int64_t)std::floor(sk[0]) - window);
              if (r >= 0 && r <= 2 * window && c >= 0 && c <= 2 * window)
                __atomic_store_n(&kr[pi[e] * kFlagRows + r], (uint8_t)1, __ATOMIC_RELAXED);
            }
          }
#endif
          float gwe[8];
          for (int64_t e = 0; e < K; ++e) {
            if (kSoA) rec.idx(e, p) = pi[e];
            rec.dep(e, p) = pd[e];
            rec.rho(e, p) = pr[e];
            float ga = 0.f;
            if (pi[e] >= 0) {
              const float* a = A + (v * N + pi[e]) * C;
              for (int64_t ch = 0; ch < C; ++ch) ga += gp[ch] * a[ch];
            }
            rec.gw(e, p) = gwe[e] = ga;
          }
          float den = 0.f, gnum = 0.f;
          for (int64_t e = 0; e < K && pi[e] >= 0 && pd[e] <= d0 + merge; ++e) {
            den += pr[e];
            gnum += pr[e] * gwe[e];
          }
          rec.d0(p) = d0;
          rec.den(p) = den;
          rec.gn(p) = gnum;
        }
      });
      const VisConsts Q{F[v], PP[v * 2], PP[v * 2 + 1], 1.f / F[v], cutoff, merge, eps};
      const float* Rv = Rm + v * 9;
      const float* PLv = PL + v * N * 3;
      // A task is a run of consecutive (spatially sorted) points: their windows overlap in the
      // record. Each point is one task's, so it owns its gsum row (no race; views added in view
      // order). (Ordering the points by screen tile first measured no faster.)
      const int64_t nchunks = (N + kChunk - 1) / kChunk;
      // The evaluation, compiled for the common (K, C) = (5, 3) and (5, 1) with constant trip
      // counts (the cache scans and channel dots unroll) and for any (K, C) at run time.
      auto points_task = [&](auto KT, auto CT, int64_t task) {
        constexpr int64_t KC = decltype(KT)::value, CC = decltype(CT)::value;
        const auto R = rec.template fixed<KC, CC>();
        const int64_t k_begin = task * kChunk, k_end = std::min(N, k_begin + kChunk);
        for (int64_t k = k_begin; k < k_end; ++k) {
          const float* s = P + (v * N + k) * kFields;
          if (!(s[9] > 0.f)) continue;
          VisPoint pt;
          pt.s = s;
          pt.wk = A + (v * N + k) * Crt;
          pt.pl = PLv + k * 3;
          pt.k = (int32_t)k;
          pt.u = s[0];
          pt.v = s[1];
          pt.z = s[6];
          pt.nk = s[5];
          pt.z_f = pt.z * Q.inv_f;
          pt.X = (pt.u - Q.cx) * pt.z_f;
          pt.Y = (pt.v - Q.cy) * pt.z_f;
          pt.slope = kMaxSlope * pt.z_f;
          const int ic = (int)std::floor(pt.v), jc = (int)std::floor(pt.u);
          double acc[3] = {0, 0, 0};
          bool done = false;
#ifdef DSS_HAVE_AVX2
          if constexpr (kSoA) {
            if (rows16) {
              window_rows_avx512<KC, CC>(R, Krt, Crt, pt, Q, H, W, window, ic, jc, kr + k * kFlagRows, acc);
              done = true;
            } else if (vec) {
              window_dss_avx2<KC, CC>(R, Krt, Crt, pt, Q, H, W, window, ic, jc, flat, kf ? kr + k * kFlagRows : nullptr,
                                      acc);
              done = true;
            }
          }
#endif
          if (!done) {  // partial sums in the order of dss_splat::vis_partial, as the vector path
            double part[dss_splat::kVisPartials][3] = {};
            const int mw = dss_splat::vis_window_runs(window);
            for (int64_t dy = -window; dy <= window; dy += stride) {
              const int64_t i = ic + dy;
              if (i < 0 || i >= H) continue;
              const float py = (float)i + 0.5f;
              for (int64_t dx = -window; dx <= window; dx += stride) {
                const int64_t j = jc + dx;
                if (j < 0 || j >= W) continue;
                const int64_t p = i * W + j;
                if (R.nz(p) == 0.f) continue;
                eval_scalar<KC, CC>(R, Krt, Crt, pt, Q, mode, p, (float)j + 0.5f, py,
                                    part[dss_splat::vis_partial(dx + window, mw)]);
              }
            }
            add_partials(part, dss_splat::vis_partial_count(window), acc);
          }
          double* gk = gsum.data() + k * 3;  // world gradient = R^T acc
          for (int a = 0; a < 3; ++a)
            gk[a] += Rv[0 * 3 + a] * acc[0] + Rv[1 * 3 + a] * acc[1] + Rv[2 * 3 + a] * acc[2];
        }
      };
      using K5 = std::integral_constant<int64_t, 5>;
      using Any = std::integral_constant<int64_t, 0>;
      if (Krt == 5 && Crt == 3)
        dynamic_for(nchunks, 1, [&](int64_t t) { points_task(K5{}, std::integral_constant<int64_t, 3>{}, t); });
      else if (Krt == 5 && Crt == 1)
        dynamic_for(nchunks, 1, [&](int64_t t) { points_task(K5{}, std::integral_constant<int64_t, 1>{}, t); });
      else
        dynamic_for(nchunks, 1, [&](int64_t t) { points_task(Any{}, Any{}, t); });
    }
  };
  if (vec)
    run(std::true_type{});
  else
    run(std::false_type{});
  for (int64_t e = 0; e < N * 3; ++e) G[e] = (float)gsum[e];
  return out;
}

// ---------------------------------------------------------------------------------------------
// Backward of Eq. sumI for the smooth terms (Eqs. gradN, gradP without the visibility term):
// I = sum_f rho_f w_f / sum_f rho_f over the visible cached fragments, rho_f = norm exp(-q/2),
// q = a dx^2 + b2 dx dy + c dy^2 with d = pixel centre - (u, v). Returns dL/dpacked (V,N,10)
// (u, v, conic a, b2, c, norm; zero for the other fields) and dL/dattrs (V,N,C).
// Parallel over views, each view scanning its own fragments once in row-major pixel order: a view
// owns its (v, k) accumulators (no race, a fixed sum order per point), and the work is the
// number of cached fragments, not (splat box area x K) per point as a point-parallel loop over
// each splat's box would be (2-4x slower at 20K points, 256 px).
// mask (optional): the rasteriser's (V,H,W) bool mask (den > 0: the pixels this loop visits, the
// same sum in the same order); without it, every pixel's cache row is read to find them.
std::vector<torch::Tensor> blend_backward(torch::Tensor packed, torch::Tensor attrs, torch::Tensor idx,
                                          torch::Tensor depth, torch::Tensor rho, torch::Tensor images,
                                          torch::Tensor grad, double merge_d, std::optional<torch::Tensor> mask_opt) {
  packed = packed.contiguous().to(torch::kFloat32);
  attrs = attrs.contiguous().to(torch::kFloat32);
  idx = idx.contiguous();
  depth = depth.contiguous();
  rho = rho.contiguous();
  images = images.contiguous().to(torch::kFloat32);
  grad = grad.contiguous().to(torch::kFloat32);
  const int64_t V = packed.size(0), N = packed.size(1), H = idx.size(1), W = idx.size(2), K = idx.size(3);
  const int64_t C = attrs.size(2);
  TORCH_CHECK(C <= 16, "at most 16 channels");
  torch::Tensor mask = mask_opt.has_value() ? *mask_opt : torch::Tensor();
  const bool has_mask = mask.defined() && mask.numel() > 0;
  if (has_mask) {
    TORCH_CHECK(mask.dim() == 3 && mask.size(0) == V && mask.size(1) == H && mask.size(2) == W,
                "mask must be (V,H,W) like the cache");
    mask = mask.contiguous().to(torch::kBool);
  }
  const float merge = (float)merge_d;
  auto gpk = pooled_empty({V, N, kFields}, torch::kFloat32);  // every entry written below
  auto gat = pooled_empty({V, N, C}, torch::kFloat32);
  const float* P = packed.data_ptr<float>();
  const float* A = attrs.data_ptr<float>();
  const int32_t* I = idx.data_ptr<int32_t>();
  const float* D = depth.data_ptr<float>();
  const float* Rh = rho.data_ptr<float>();
  const float* IMG = images.data_ptr<float>();
  const float* GR = grad.data_ptr<float>();
  const bool* MK = has_mask ? mask.data_ptr<bool>() : nullptr;
  float* GP = gpk.data_ptr<float>();
  float* GA = gat.data_ptr<float>();
  const int64_t S = 6 + C;  // per point: du, dv, da, db, dc, dnorm, then dL/dattr per channel
  const int64_t HW = H * W;
  dynamic_for(V, 1, [&](int64_t v) {
    static thread_local std::vector<double> acc;  // double sums, as the per-point loop had
    static thread_local std::vector<int32_t> pix;
    acc.assign((size_t)(N * S), 0.0);
    // The pixels to visit, in raster order. With the mask: 8 of its bytes at a time (9% of the
    // pixels hold a visible fragment at 20K points, 12 views of 256x256), so the 16 MB of index
    // rows of empty pixels are never read; without it, each pixel's first index.
    pix.resize((size_t)HW);
    int64_t np = 0;
    if (MK) {
      const bool* m = MK + v * HW;
      int64_t g = 0;
      for (; g + 8 <= HW; g += 8) {
        uint64_t word;
        std::memcpy(&word, m + g, 8);
        if (!word) continue;
        for (int b = 0; b < 8; ++b) {
          pix[np] = (int32_t)(g + b);
          np += m[g + b] ? 1 : 0;
        }
      }
      for (; g < HW; ++g) {
        pix[np] = (int32_t)g;
        np += m[g] ? 1 : 0;
      }
    } else {
      for (int64_t g = 0; g < HW; ++g) {
        pix[np] = (int32_t)g;
        np += I[(v * HW + g) * K] >= 0 ? 1 : 0;
      }
    }
    const float* Pv = P + v * N * kFields;
    const float* Av = A + v * N * C;
    for (int64_t q = 0; q < np; ++q) {
      if (q + 2 * kPixelsAhead < np) {
        // the cache rows, gradient and image of the pixel 2 kPixelsAhead visits on
        const int64_t g2 = v * HW + pix[q + 2 * kPixelsAhead];
        __builtin_prefetch(I + g2 * K);
        __builtin_prefetch(D + g2 * K);
        __builtin_prefetch(Rh + g2 * K);
        __builtin_prefetch(GR + g2 * C);
        __builtin_prefetch(IMG + g2 * C);
      }
      if (q + kPixelsAhead < np) {
        // Most cached splats cover only a few pixels of a view, so their rows (splat, attributes,
        // accumulators) are first touched here and miss the caches: fetch those of the pixel
        // kPixelsAhead visits on (its index row fetched above) while this one is processed.
        const int32_t* qi = I + (v * HW + pix[q + kPixelsAhead]) * K;
        for (int e = 0; e < K && qi[e] >= 0; ++e) {
          __builtin_prefetch(Pv + qi[e] * kFields);
          __builtin_prefetch(Av + qi[e] * C);
          __builtin_prefetch(acc.data() + qi[e] * S, 1);
        }
      }
      const int64_t gv = pix[q], g = v * HW + gv;
      const int64_t i = gv / W, j = gv % W;
      const int32_t* pi = I + g * K;
      const float* pd = D + g * K;
      const float* pr = Rh + g * K;
      // (every listed pixel has an entry; a mask true at an empty pixel finds den = 0 below)
      const float lim = pd[0] + merge;
      int nvis = 0;
      float den = 0.f;
      for (int e = 0; e < K && pi[e] >= 0 && pd[e] <= lim; ++e) {
        den += pr[e];
        ++nvis;
      }
      if (!(den > 0.f)) continue;
      const float* gp = GR + g * C;
      const float* ip = IMG + g * C;
      const double rden = 1.0 / (double)den;  // one division per pixel, not 2C per fragment
      const float py = (float)i + 0.5f;
      for (int e = 0; e < nvis; ++e) {
        const int64_t k = pi[e];
        const float* s = Pv + k * kFields;
        if (!(s[9] > 0.f)) continue;
        const float dx = ((float)j + 0.5f) - s[0], dy = py - s[1];
        dss_splat::blend_entry_grad(s, Av + k * C, gp, ip, C, pr[e], rden, dx, dy, acc.data() + k * S);
      }
    }
    for (int64_t k = 0; k < N; ++k) {
      const double* a = acc.data() + k * S;
      float* o = GP + (v * N + k) * kFields;
      for (int f = 0; f < 6; ++f) o[f] = (float)a[f];
      for (int f = 6; f < kFields; ++f) o[f] = 0.f;
      float* oa = GA + (v * N + k) * C;
      for (int64_t c = 0; c < C; ++c) oa[c] = (float)a[6 + c];
    }
  });
  return {gpk, gat};
}

// ---------------------------------------------------------------------------------------------
// The projection of one splat, forward and backward: splat_math.h (shared with the CUDA kernel).
using dss_splat::project_backward_one;
using dss_splat::project_forward_one;

// One view's points [k0, k1) of project_splats_forward: straight-line code (the branches are
// selects) so that the compiler vectorises the loop; every lane does the scalar loop's float32
// operations in the same order (no contraction: -ffp-contract=off), so both give the same bits.
struct ProjectView {
  const float *Pp, *Nn, *Rv, *tv, *Sg;
  float f, cx, cy, fv, C2, zn;
  bool culling;
};

DSS_INLINE void project_forward_range(const ProjectView& a, int64_t k0, int64_t k1, float* O) {
  // (the view's values in locals: stores through o could alias a's fields otherwise)
  const float *Pp = a.Pp, *Nn = a.Nn, *Rv = a.Rv, *tv = a.tv, *Sg = a.Sg;
  const float f = a.f, cx = a.cx, cy = a.cy, fv = a.fv, C2 = a.C2, zn = a.zn;
  const bool culling = a.culling;
#pragma omp simd
  for (int64_t k = k0; k < k1; ++k)
    project_forward_one(Pp + k * 3, Nn + k * 3, Rv, tv, f, cx, cy, Sg[k], fv, C2, zn, culling, O + k * kFields);
}

#ifdef DSS_HAVE_AVX2
DSS_AVX2 void project_forward_avx2(const ProjectView& a, int64_t k0, int64_t k1, float* O) {
  project_forward_range(a, k0, k1, O);
}
#endif

// The point and camera inputs of the projection and tangent-plane kernels as contiguous float32
// (in place; no copy where they already are).
inline void points_cameras_f32(torch::Tensor& points, torch::Tensor& normals, torch::Tensor& R, torch::Tensor& t,
                               torch::Tensor& focal, torch::Tensor& principal) {
  for (torch::Tensor* x : {&points, &normals, &R, &t, &focal, &principal}) *x = x->contiguous().to(torch::kFloat32);
}

// Forward-only fused version of dss/splats.py project_splats (same formulas; used when no
// gradient is needed, where the torch version's many (V, N) temporaries dominate at 100K points).
torch::Tensor project_splats_forward(torch::Tensor points, torch::Tensor normals, torch::Tensor R, torch::Tensor t,
                                     torch::Tensor focal, torch::Tensor principal, torch::Tensor sigma,
                                     double cutoff, bool culling, double znear, double filter_variance) {
  points_cameras_f32(points, normals, R, t, focal, principal);
  const int64_t N = points.size(0), V = R.size(0);
  sigma = sigma.to(torch::kFloat32).expand({N}).contiguous();
  auto out = pooled_empty({V, N, kFields}, torch::kFloat32);
  const float* Rr = R.data_ptr<float>();
  const float* Tt = t.data_ptr<float>();
  const float* Ff = focal.data_ptr<float>();
  const float* Cc = principal.data_ptr<float>();
  float* O = out.data_ptr<float>();
  const bool vec = use_vector_path();
  const int64_t nb = (N + 1023) / 1024;
  dynamic_for(V * nb, 1, [&](int64_t item) {
    const int64_t v = item / nb, k0 = (item % nb) * 1024, k1 = std::min(N, k0 + 1024);
    const ProjectView a{points.data_ptr<float>(), normals.data_ptr<float>(), Rr + v * 9, Tt + v * 3,
                        sigma.data_ptr<float>(), Ff[v], Cc[v * 2], Cc[v * 2 + 1], (float)filter_variance,
                        2.f * (float)cutoff, (float)znear, culling};
#ifdef DSS_HAVE_AVX2
    if (vec) {
      project_forward_avx2(a, k0, k1, O + v * N * kFields);
      return;
    }
#endif
    project_forward_range(a, k0, k1, O + v * N * kFields);  // the baseline build
  });
  return out;
}

// One view's gradients of the points [b0, b0 + n), n <= 64, of project_splats_backward added to
// acc: dL/dp and dL/dn (world frame) as six planes (acc[c][j]: dL/dp_c of point b0 + j for c < 3,
// dL/dn_(c-3) after). Straight-line like project_forward_range (culled splats compute values that
// a select replaces with zeros), so the loop vectorises with the scalar bits; it runs only on
// groups of 8 splats of which one at least is valid with a gradient row that is not all zeros
// (49% of the groups in a 20K-point step, where 35% of the (view, point) pairs are such: half the
// splats face away, and many valid ones reach no pixel's visible set). The other groups add
// nothing: their splats' terms are +-0, which leave a sum that started at +0 unchanged.
// (Packing the active splats side by side first measured slower: 1.92 -> 2.49 ms at 20K points,
// the packing's scalar moves.)
struct ProjectGradView {
  const float *Pp, *Nn, *Rv, *tv, *Sg, *PK, *GK;
  float f, fv, C;
};
constexpr int kProjectBlock = 64;

template <bool kVec>
DSS_INLINE void project_backward_block(const ProjectGradView& a, int64_t b0, int n, float (*acc)[kProjectBlock]) {
  // (the view's values in locals: stores through acc could alias a's fields otherwise)
  const float *Pp = a.Pp, *Nn = a.Nn, *Rv = a.Rv, *tv = a.tv, *Sg = a.Sg, *PK = a.PK, *GK = a.GK;
  const float f = a.f, fv = a.fv, C = a.C;
  static_assert(kProjectBlock == 64, "rows_to_planes writes planes of 64");
  // The gradient's fields 0-8 and the packed rows' 7-9 transposed to planes first: the vectoriser
  // takes no strided loads from rows of 10 with gaps.
  // (fields 2-9 of the packed rows: rows_to_planes moves at least 8; 7-9 are pk[5..7])
  alignas(32) float gk[9][kProjectBlock], pk[8][kProjectBlock];
  rows_to_planes<kVec>(GK + b0 * kFields, n, 0, 9, gk);
  rows_to_planes<kVec>(PK + b0 * kFields, n, 2, 8, pk);
  alignas(32) int act[kProjectBlock];
  for (int j = 0; j < n; ++j) {
    bool nz = false;
    for (int c = 0; c < 9; ++c) nz |= gk[c][j] != 0.f;
    act[j] = (pk[7][j] > 0.f) & nz;
  }
  for (int g0 = 0; g0 < n; g0 += 8) {
    const int g1 = std::min(n, g0 + 8);
    int any = 0;
    for (int j = g0; j < g1; ++j) any |= act[j];
    if (!any) continue;
#pragma omp simd
    for (int j = g0; j < g1; ++j) {
      const int64_t k = b0 + j;
      // culled splats get no gradient (the renderer never reads them)
      const dss_splat::SplatGrad sg =
          project_backward_one(Pp + k * 3, Nn + k * 3, Rv, tv, f, Sg[k], fv, C, gk[0][j], gk[1][j], gk[2][j],
                               gk[3][j], gk[4][j], gk[5][j], gk[6][j], gk[7][j], gk[8][j], pk[5][j], pk[6][j],
                               pk[7][j] > 0.f);
      for (int c = 0; c < 3; ++c) {
        acc[c][j] += sg.gp[c];
        acc[3 + c][j] += sg.gn[c];
      }
    }
  }
}

#ifdef DSS_HAVE_AVX2
DSS_AVX2 void project_backward_avx2(const ProjectGradView& a, int64_t b0, int n, float (*acc)[kProjectBlock]) {
  project_backward_block<true>(a, b0, n, acc);
}
#endif

// Inverse-depth tangent planes (V, N, 3) for the visibility gradient's occlusion test
// (dss/splats.py tangent_planes, its torch twin; splat_math.h tangent_plane_one): one pass over
// (view, point) instead of ~20 torch operators on (V, N) tensors (20K points, 12 views, 2
// threads: 3.2-4.0 ms in torch, 1.0-1.2 ms here). center: (0, 0, 1 / z) for every point.
torch::Tensor tangent_planes_forward(torch::Tensor points, torch::Tensor normals, torch::Tensor R, torch::Tensor t,
                                     torch::Tensor focal, torch::Tensor principal, bool center) {
  TORCH_CHECK(points.dim() == 2 && points.size(1) == 3 && normals.sizes() == points.sizes(),
              "points and normals must be (N, 3)");
  TORCH_CHECK(R.dim() == 3 && R.size(1) == 3 && R.size(2) == 3, "R must be (V, 3, 3)");
  points_cameras_f32(points, normals, R, t, focal, principal);
  const int64_t N = points.size(0), V = R.size(0);
  TORCH_CHECK(t.numel() == V * 3 && focal.numel() == V && principal.numel() == V * 2, "one camera per view");
  auto out = pooled_empty({V, N, 3}, torch::kFloat32);  // every entry is written below
  const float *Pp = points.data_ptr<float>(), *Nn = normals.data_ptr<float>(), *Rr = R.data_ptr<float>();
  const float *Tt = t.data_ptr<float>(), *Ff = focal.data_ptr<float>(), *Cc = principal.data_ptr<float>();
  float* O = out.data_ptr<float>();
  const int64_t nb = (N + 4095) / 4096;
  dynamic_for(V * nb, 1, [&](int64_t item) {
    const int64_t v = item / nb, k0 = (item % nb) * 4096, k1 = std::min(N, k0 + 4096);
    for (int64_t k = k0; k < k1; ++k)
      dss_splat::tangent_plane_one(Pp + k * 3, Nn + k * 3, Rr + v * 9, Tt + v * 3, Ff[v], Cc[v * 2], Cc[v * 2 + 1],
                                   center, O + (v * N + k) * 3);
  });
  return out;
}

// Backward of project_splats_forward (the same formulas as dss/splats.py project_splats): given
// dL/dpacked (V,N,10), returns dL/dpoints and dL/dnormals (N,3) with sigma, cameras and the
// filter held fixed. Fields 0-8 (u, v, conic a, b2, c, norm, depth, rx, ry) carry gradients; the
// valid flag is a step function. Culled splats (valid = 0) get none, as the renderer never reads
// them. Per-view gradients are summed over views in view order (deterministic at any thread count).
std::vector<torch::Tensor> project_splats_backward(torch::Tensor points, torch::Tensor normals, torch::Tensor R,
                                                   torch::Tensor t, torch::Tensor focal, torch::Tensor principal,
                                                   torch::Tensor sigma, torch::Tensor packed, torch::Tensor grad,
                                                   double cutoff, double filter_variance) {
  points_cameras_f32(points, normals, R, t, focal, principal);
  packed = packed.contiguous().to(torch::kFloat32);
  grad = grad.contiguous().to(torch::kFloat32);
  const int64_t N = points.size(0), V = R.size(0);
  TORCH_CHECK(packed.size(0) == V && packed.size(1) == N && packed.size(2) == kFields, "packed must be (V,N,10)");
  TORCH_CHECK(grad.sizes() == packed.sizes(), "grad must be shaped like packed");
  sigma = sigma.to(torch::kFloat32).expand({N}).contiguous();
  const float* Rr = R.data_ptr<float>();
  const float* Tt = t.data_ptr<float>();
  const float* Ff = focal.data_ptr<float>();
  const float* PK = packed.data_ptr<float>();
  const float* GK = grad.data_ptr<float>();
  auto gp = torch::empty({N, 3}, torch::TensorOptions().dtype(torch::kFloat32));
  auto gn = torch::empty({N, 3}, torch::TensorOptions().dtype(torch::kFloat32));
  float* GP = gp.data_ptr<float>();
  float* GN = gn.data_ptr<float>();
  const bool vec = use_vector_path();
  // A work item is a run of points; each block of them goes through the views in view order,
  // adding to its own sums (the same order at any thread count, and no per-view planes to write
  // and read back).
  constexpr int kItemBlocks = 16;  // a view's rows of an item in one sequential run (40 KB each)
  constexpr int64_t kItem = kItemBlocks * kProjectBlock;
  dynamic_for((N + kItem - 1) / kItem, 1, [&](int64_t item) {
    const int64_t k0 = item * kItem, k1 = std::min(N, k0 + kItem);
    alignas(32) float acc[kItemBlocks][6][kProjectBlock] = {};
    for (int64_t v = 0; v < V; ++v) {
      const ProjectGradView a{points.data_ptr<float>(), normals.data_ptr<float>(), Rr + v * 9, Tt + v * 3,
                              sigma.data_ptr<float>(), PK + v * N * kFields, GK + v * N * kFields, Ff[v],
                              (float)filter_variance, (float)cutoff};
      for (int64_t b0 = k0; b0 < k1; b0 += kProjectBlock) {
        const int n = (int)std::min<int64_t>(kProjectBlock, k1 - b0);
        auto* ab = acc[(b0 - k0) / kProjectBlock];
#ifdef DSS_HAVE_AVX2
        if (vec) {
          project_backward_avx2(a, b0, n, ab);
          continue;
        }
#endif
        project_backward_block<false>(a, b0, n, ab);  // the baseline build
      }
    }
    for (int64_t k = k0; k < k1; ++k)
      for (int c = 0; c < 3; ++c) {
        const auto* ab = acc[(k - k0) / kProjectBlock];
        GP[k * 3 + c] = ab[c][(k - k0) % kProjectBlock];
        GN[k * 3 + c] = ab[3 + c][(k - k0) % kProjectBlock];
      }
  });
  return {gp, gn};
}

// SMAPE (paper Eq. smape) in one pass: sum over all elements of |x - y| / (|x| + |y| + eps), and
// when asked its derivative with respect to x times grad_scale, (sign(x - y) / s - |x - y|
// sign(x) / s^2) grad_scale with s = |x| + |y| + eps (sign(0) = 0, as torch's abs backward).
// dss/losses.py scales both to the loss's mean; the torch expression there is the reference.
// Runs of 8 elements are computed side by side (the compiler vectorises them) into 8 double
// partial sums per block of 2^16 elements; blocks are added in block order, so the sum has the
// same bits at any thread count.
namespace {
template <bool kGrad>
DSS_INLINE double smape_block(const float* X, const float* Y, float* G, int64_t n, float eps, float gscale) {
  double acc[8] = {0, 0, 0, 0, 0, 0, 0, 0};
  auto one = [&](int64_t e, float& r) {
    const float x = X[e], y = Y[e];
    const float d = x - y, ad = std::fabs(d);
    const float s = std::fabs(x) + std::fabs(y) + eps;
    const float inv = 1.f / s;  // one division, not three (with the AVX2 build 1.04 -> 0.74 ms, 12 views)
    r = ad * inv;
    if constexpr (kGrad) {
      const float sd = (float)((d > 0.f) - (d < 0.f)), sx = (float)((x > 0.f) - (x < 0.f));
      G[e] = (sd * inv - ad * sx * inv * inv) * gscale;
    }
  };
  int64_t e = 0;
  for (; e + 8 <= n; e += 8) {
    float r[8];
    for (int l = 0; l < 8; ++l) one(e + l, r[l]);
    for (int l = 0; l < 8; ++l) acc[l] += r[l];
  }
  for (; e < n; ++e) {
    float r;
    one(e, r);
    acc[0] += r;
  }
  return ((acc[0] + acc[1]) + (acc[2] + acc[3])) + ((acc[4] + acc[5]) + (acc[6] + acc[7]));
}

// smape_block compiled for AVX2 and (inlined below) for the baseline: the same operations, bits
#ifdef DSS_HAVE_AVX2
template <bool kGrad>
DSS_AVX2 double smape_block_avx2(const float* X, const float* Y, float* G, int64_t n, float eps, float gscale) {
  return smape_block<kGrad>(X, Y, G, n, eps, gscale);
}
#endif
template <bool kGrad>
double smape_block_any(bool vec, const float* X, const float* Y, float* G, int64_t n, float eps, float gscale) {
#ifdef DSS_HAVE_AVX2
  if (vec) return smape_block_avx2<kGrad>(X, Y, G, n, eps, gscale);
#endif
  return smape_block<kGrad>(X, Y, G, n, eps, gscale);
}
}  // namespace

std::vector<torch::Tensor> smape_sum(torch::Tensor pred, torch::Tensor target, double eps_d, double grad_scale,
                                     bool with_grad) {
  TORCH_CHECK(pred.sizes() == target.sizes(), "pred and target must have the same shape");
  pred = pred.contiguous().to(torch::kFloat32);
  target = target.contiguous().to(torch::kFloat32);
  const int64_t n = pred.numel();
  const float eps = (float)eps_d, gscale = (float)grad_scale;
  auto grad = with_grad ? pooled_empty(pred.sizes(), torch::kFloat32) : torch::empty({0}, pred.options());
  const float* X = pred.data_ptr<float>();
  const float* Y = target.data_ptr<float>();
  float* Gd = with_grad ? grad.data_ptr<float>() : nullptr;
  constexpr int64_t kBlock = 1 << 16;
  const int64_t nblocks = (n + kBlock - 1) / kBlock;
  std::vector<double> part((size_t)nblocks, 0.0);
  const bool vec = use_vector_path();
  at::parallel_for(0, nblocks, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t b = b0; b < b1; ++b) {
      const int64_t e0 = b * kBlock, m = std::min(n, e0 + kBlock) - e0;
      part[b] = Gd ? smape_block_any<true>(vec, X + e0, Y + e0, Gd + e0, m, eps, gscale)
                   : smape_block_any<false>(vec, X + e0, Y + e0, nullptr, m, eps, gscale);
    }
  });
  double total = 0.0;
  for (double p : part) total += p;
  return {torch::full({}, total, torch::TensorOptions().dtype(torch::kFloat64)), grad};
}

// Sun shading (dss/shading.py SunLights with its default colours: light l lights channel l, three
// lights): w[v,k,l] = (max(0, n_k . d_vl) + ambient) * albedo[k,l] (albedo 1 when not given),
// d_vl the world-space direction towards light l of view v. The torch version's (N, 3V) product,
// clamp, permute and the contiguous copy the kernels need, and their autograd graph, become one
// pass each way. normals (N,3), albedo (N,3) or empty, dirs (V,3,3), all float32.
namespace {
struct SunArgs {
  const float* n;
  const float* alb;  // nullptr: no albedo
  const float* d;
  int64_t V, N;
  float ambient;
};
SunArgs sun_args(torch::Tensor& normals, torch::Tensor& albedo, torch::Tensor& dirs, double ambient) {
  normals = normals.contiguous().to(torch::kFloat32);
  dirs = dirs.contiguous().to(torch::kFloat32);
  TORCH_CHECK(normals.dim() == 2 && normals.size(1) == 3, "normals must be (N, 3)");
  TORCH_CHECK(dirs.dim() == 3 && dirs.size(1) == 3 && dirs.size(2) == 3, "dirs must be (V, 3, 3)");
  const bool has_alb = albedo.numel() > 0;
  if (has_alb) {
    albedo = albedo.contiguous().to(torch::kFloat32);
    TORCH_CHECK(albedo.dim() == 2 && albedo.size(0) == normals.size(0) && albedo.size(1) == 3,
                "albedo must be (N, 3)");
  }
  return {normals.data_ptr<float>(), has_alb ? albedo.data_ptr<float>() : nullptr, dirs.data_ptr<float>(),
          dirs.size(0), normals.size(0), (float)ambient};
}
// n . d summed left to right, as torch's float32 product does here (a BLAS may differ in the last bit)
DSS_INLINE float sun_dot(const float* n, const float* d) { return n[0] * d[0] + n[1] * d[1] + n[2] * d[2]; }
constexpr int64_t kSunChunk = 2048;  // points per work item

template <bool ALB>
void sun_forward_range(const SunArgs a, int64_t k0, int64_t k1, float* __restrict__ O) {
  const float* __restrict__ n = a.n;
  const float* __restrict__ alb = a.alb;
  const float amb = a.ambient;
  for (int64_t v = 0; v < a.V; ++v) {
    float d[9];
    for (int i = 0; i < 9; ++i) d[i] = a.d[v * 9 + i];
    float* __restrict__ o = O + v * a.N * 3;
    for (int64_t k = k0; k < k1; ++k)
      for (int l = 0; l < 3; ++l) {
        const float w = std::max(sun_dot(n + k * 3, d + l * 3), 0.f) + amb;
        o[k * 3 + l] = ALB ? w * alb[k * 3 + l] : w;
      }
  }
}

// Points in blocks of kSunBlock, the views and lights outermost, so the loop over points (with
// the per-point sums in local arrays) vectorises; each point's sums still run in (view, light)
// order. The block's normals, albedo and each view's gradient rows are first split into planes
// (x, y, z), so that the vector loop reads them with unit stride (with rows of 3 floats GCC left
// it at a few lanes); sun_backward_block_avx2 compiles the same body for AVX2 (1.83x, the same
// bits: no contraction, the same operations per lane).
constexpr int64_t kSunBlock = 256;
template <bool ALB, bool GRAD_ALB>
DSS_INLINE void sun_backward_block(const SunArgs& a, const float* __restrict__ G, int64_t b0, int64_t m,
                                   float* __restrict__ GN, float* __restrict__ GA) {
  const float amb = a.ambient;
  alignas(32) float np[3][kSunBlock], ap[3][kSunBlock], gp[3][kSunBlock];
  alignas(32) float s0[kSunBlock] = {}, s1[kSunBlock] = {}, s2[kSunBlock] = {}, sa[3][kSunBlock] = {};
  for (int64_t i = 0; i < m; ++i)
    for (int c = 0; c < 3; ++c) {
      np[c][i] = a.n[(b0 + i) * 3 + c];
      if (ALB) ap[c][i] = a.alb[(b0 + i) * 3 + c];
    }
  for (int64_t v = 0; v < a.V; ++v) {
    const float* __restrict__ g = G + (v * a.N + b0) * 3;
    for (int64_t i = 0; i < m; ++i)
      for (int c = 0; c < 3; ++c) gp[c][i] = g[i * 3 + c];
    for (int l = 0; l < 3; ++l) {
      const float d0 = a.d[v * 9 + l * 3], d1 = a.d[v * 9 + l * 3 + 1], d2 = a.d[v * 9 + l * 3 + 2];
      for (int64_t i = 0; i < m; ++i) {
        const float dot = np[0][i] * d0 + np[1][i] * d1 + np[2][i] * d2;  // as sun_dot
        const float gv = gp[l][i];
        if (GRAD_ALB) sa[l][i] += gv * (std::max(dot, 0.f) + amb);
        // torch's clamp_min passes the gradient where its input >= the bound
        const float gl = dot >= 0.f ? (ALB ? gv * ap[l][i] : gv) : 0.f;
        s0[i] += gl * d0;
        s1[i] += gl * d1;
        s2[i] += gl * d2;
      }
    }
  }
  for (int64_t i = 0; i < m; ++i) {
    GN[(b0 + i) * 3] = s0[i];
    GN[(b0 + i) * 3 + 1] = s1[i];
    GN[(b0 + i) * 3 + 2] = s2[i];
    if (GRAD_ALB)
      for (int l = 0; l < 3; ++l) GA[(b0 + i) * 3 + l] = sa[l][i];
  }
}

#ifdef DSS_HAVE_AVX2
template <bool ALB, bool GRAD_ALB>
DSS_AVX2 void sun_backward_block_avx2(const SunArgs& a, const float* G, int64_t b0, int64_t m, float* GN, float* GA) {
  sun_backward_block<ALB, GRAD_ALB>(a, G, b0, m, GN, GA);
}
#endif

template <bool ALB, bool GRAD_ALB>
void sun_backward_range(const SunArgs a, const float* __restrict__ G, int64_t k0, int64_t k1, float* __restrict__ GN,
                        float* __restrict__ GA, bool vec) {
  for (int64_t b0 = k0; b0 < k1; b0 += kSunBlock) {
    const int64_t m = std::min(k1 - b0, kSunBlock);
#ifdef DSS_HAVE_AVX2
    if (vec) {
      sun_backward_block_avx2<ALB, GRAD_ALB>(a, G, b0, m, GN, GA);
      continue;
    }
#endif
    sun_backward_block<ALB, GRAD_ALB>(a, G, b0, m, GN, GA);
  }
}
}  // namespace

// -> (V,N,3) float32
torch::Tensor sun_shade_forward(torch::Tensor normals, torch::Tensor albedo, torch::Tensor dirs, double ambient) {
  const SunArgs a = sun_args(normals, albedo, dirs, ambient);
  auto out = pooled_empty({a.V, a.N, 3}, torch::kFloat32);  // every entry written below
  float* O = out.data_ptr<float>();
  dynamic_for((a.N + kSunChunk - 1) / kSunChunk, 1, [&](int64_t c) {
    const int64_t k0 = c * kSunChunk, k1 = std::min(a.N, k0 + kSunChunk);
    if (a.alb)
      sun_forward_range<true>(a, k0, k1, O);
    else
      sun_forward_range<false>(a, k0, k1, O);
  });
  return out;
}

// Backward of sun_shade_forward for grad = dL/dw (V,N,3): dL/dnormals (N,3) and, when albedo is
// given and need_albedo, dL/dalbedo (N,3) (else an empty tensor). Sums per point in view order
// (the same bits on any number of threads).
std::vector<torch::Tensor> sun_shade_backward(torch::Tensor normals, torch::Tensor albedo, torch::Tensor dirs,
                                              double ambient, torch::Tensor grad, bool need_albedo) {
  const SunArgs a = sun_args(normals, albedo, dirs, ambient);
  grad = grad.contiguous().to(torch::kFloat32);
  TORCH_CHECK(grad.dim() == 3 && grad.size(0) == a.V && grad.size(1) == a.N && grad.size(2) == 3,
              "grad must be (V, N, 3)");
  need_albedo = need_albedo && a.alb;
  auto gn = torch::empty({a.N, 3}, torch::TensorOptions().dtype(torch::kFloat32));
  auto ga = need_albedo ? torch::empty({a.N, 3}, gn.options()) : torch::empty({0}, gn.options());
  const float* G = grad.data_ptr<float>();
  float* GN = gn.data_ptr<float>();
  float* GA = need_albedo ? ga.data_ptr<float>() : nullptr;
  const bool vec = use_vector_path();
  dynamic_for((a.N + kSunChunk - 1) / kSunChunk, 1, [&](int64_t c) {
    const int64_t k0 = c * kSunChunk, k1 = std::min(a.N, k0 + kSunChunk);
    if (GA)
      sun_backward_range<true, true>(a, G, k0, k1, GN, GA, vec);
    else if (a.alb)
      sun_backward_range<true, false>(a, G, k0, k1, GN, GA, vec);
    else
      sun_backward_range<false, false>(a, G, k0, k1, GN, GA, vec);
  });
  return {gn, ga};
}

// Z-order permutation of N points (dss/ordering.py spatial_order is the reference): codes on a
// 1024^3 grid over the bounding box with the same float32 operations as morton_codes, sorted by
// a stable LSD radix sort (three 10-bit digits), so equal codes keep their index order as in
// torch.argsort(stable=True). points (N, 3) float32 -> (N,) int64.
namespace {
inline uint32_t spread3(uint32_t x) {
  x = (x | (x << 16)) & 0x030000FFu;
  x = (x | (x << 8)) & 0x0300F00Fu;
  x = (x | (x << 4)) & 0x030C30C3u;
  return (x | (x << 2)) & 0x09249249u;
}
}  // namespace

// dss_splat::splat_exp element-wise over float32 x (any shape), on the vector path (AVX2, 8 at a
// time) where it is enabled: for the tests, which hold both paths to the same bits and to float64.
torch::Tensor splat_exp(torch::Tensor x) {
  TORCH_CHECK(x.scalar_type() == torch::kFloat32, "x must be float32");
  x = x.contiguous();
  auto out = torch::empty_like(x);
  const float* X = x.data_ptr<float>();
  float* O = out.data_ptr<float>();
  const int64_t n = x.numel();
  int64_t i = 0;
#ifdef DSS_HAVE_AVX2
  if (use_vector_path()) {
    auto run = [&]() __attribute__((target("avx2"))) {
      for (; i + 8 <= n; i += 8) _mm256_storeu_ps(O + i, splat_exp_avx2(_mm256_loadu_ps(X + i)));
    };
    run();
  }
#endif
  for (; i < n; ++i) O[i] = dss_splat::splat_exp(X[i]);
  return out;
}

torch::Tensor morton_order(torch::Tensor points) {
  TORCH_CHECK(points.dim() == 2 && points.size(1) == 3 && points.scalar_type() == torch::kFloat32,
              "points must be (N, 3) float32");
  points = points.contiguous();
  const int64_t N = points.size(0);
  auto order = torch::empty({N}, torch::TensorOptions().dtype(torch::kInt64));
  if (N == 0) return order;
  const float* p = points.data_ptr<float>();
  float lo[3], hi[3];
  for (int a = 0; a < 3; ++a) lo[a] = hi[a] = p[a];
  for (int64_t n = 1; n < N; ++n)
    for (int a = 0; a < 3; ++a) {
      lo[a] = std::min(lo[a], p[n * 3 + a]);
      hi[a] = std::max(hi[a], p[n * 3 + a]);
    }
  float scale[3];
  // torch evaluates 1023.0 / ext as ext.reciprocal() * 1023.0 (two roundings)
  for (int a = 0; a < 3; ++a) scale[a] = (1.f / std::max(hi[a] - lo[a], 1e-30f)) * 1023.f;
  std::vector<uint32_t> code((size_t)N), code2((size_t)N);
  std::vector<int64_t> idx2((size_t)N);
  int64_t* idx = order.data_ptr<int64_t>();
  for (int64_t n = 0; n < N; ++n) {
    uint32_t c = 0;
    for (int a = 0; a < 3; ++a) {
      // float -> int64 truncation, then the clamp to the grid, as the torch expression
      const int64_t q = std::min<int64_t>(1023, std::max<int64_t>(0, (int64_t)((p[n * 3 + a] - lo[a]) * scale[a])));
      c |= spread3((uint32_t)q) << a;
    }
    code[n] = c;
    idx[n] = n;
  }
  int64_t* src_i = idx;
  int64_t* dst_i = idx2.data();
  uint32_t* src_c = code.data();
  uint32_t* dst_c = code2.data();
  std::vector<int64_t> count(1025);
  for (int shift = 0; shift < 30; shift += 10) {
    std::fill(count.begin(), count.end(), 0);
    for (int64_t n = 0; n < N; ++n) count[((src_c[n] >> shift) & 1023u) + 1]++;
    for (int d = 0; d < 1024; ++d) count[d + 1] += count[d];
    for (int64_t n = 0; n < N; ++n) {
      const int64_t at = count[(src_c[n] >> shift) & 1023u]++;
      dst_c[at] = src_c[n];
      dst_i[at] = src_i[n];
    }
    std::swap(src_c, dst_c);
    std::swap(src_i, dst_i);
  }
  // three passes: the sorted permutation is in the scratch buffer
  std::copy(src_i, src_i + N, idx);
  return order;
}

// the other sources compiled into this module: dss/csrc/frames_cpu.cpp (the regularisers' weighted PCA)
std::vector<torch::Tensor> local_frames_forward(torch::Tensor points, torch::Tensor idx, torch::Tensor normals,
                                                torch::Tensor occlusion, double lim2, double inv_d2,
                                                int64_t min_neighbors, double inv_sharp, bool squared);
torch::Tensor neighbor_diff_forward(torch::Tensor points, torch::Tensor idx, torch::Tensor valid);
torch::Tensor neighbor_diff_backward(torch::Tensor grad, torch::Tensor idx, torch::Tensor valid);
// dss/csrc/knn_cpu.cpp
std::vector<torch::Tensor> knn_grid(torch::Tensor ref, torch::Tensor query, int64_t k, double radius);

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("rasterize_forward", &rasterize_forward, "DSS forward rasterisation (CPU)");
  m.def("visibility_backward", &visibility_backward, "DSS visibility gradient (CPU)");
  m.def("set_vector_path", &set_vector_path,
        "enable/disable the vector paths (AVX2: rasterize_forward's tile loop and write-out, visibility_backward's "
        "dss rule, the projection's forward and backward loops, smape_sum, the sun shader's backward; AVX-512: "
        "visibility_backward's windows of 9-15 columns, the binning's box scan); returns whether they were enabled");
  m.def("vector_path_available", &vector_path_available, "whether this build and CPU have the AVX2 paths");
  m.def("set_vector_level", &set_vector_level,
        "the highest vector level the kernels may take: 0 scalar, 1 AVX2, 2 AVX-512; returns the previous setting");
  m.def("vector_level", &vector_level, "the vector level the kernels take now (0 scalar, 1 AVX2, 2 AVX-512)");
  m.def("max_vector_level", &max_vector_level, "the highest vector level this build and CPU have");
  m.def("project_splats_forward", &project_splats_forward, "EWA splat projection, forward only (CPU)");
  m.def("project_splats_backward", &project_splats_backward, "EWA splat projection, backward (CPU)");
  m.def("tangent_planes_forward", &tangent_planes_forward, "inverse-depth tangent planes (V,N,3) (CPU)");
  m.def("splat_exp", &splat_exp, "the kernels' float32 exp, element-wise (tests)");
  m.def("morton_order", &morton_order, "stable Z-order permutation of (N, 3) float32 points (CPU)");
  m.def("smape_sum", &smape_sum, "SMAPE sum and its derivative in one pass (CPU)");
  m.def("empty_cache", &empty_cache, "free the parked output blocks; returns the bytes released");
  m.def("blend_backward", &blend_backward, "DSS smooth-term backward of the normalised sum (CPU)", py::arg("packed"),
        py::arg("attrs"), py::arg("idx"), py::arg("depth"), py::arg("rho"), py::arg("images"), py::arg("grad"),
        py::arg("merge"), py::arg("mask") = py::none());
  m.def("sun_shade_forward", &sun_shade_forward, "sun-light shading (V,N,3) of (N,3) normals (CPU)");
  m.def("sun_shade_backward", &sun_shade_backward, "backward of sun_shade_forward (CPU)");
  m.def("local_frames_forward", &local_frames_forward, "the regularisers' weighted PCA frames, detached (CPU)");
  m.def("neighbor_diff_forward", &neighbor_diff_forward, "(p_i - p_k) over valid neighbours, (N,K,3) (CPU)");
  m.def("neighbor_diff_backward", &neighbor_diff_backward, "backward of neighbor_diff_forward (CPU)");
  m.def("knn_grid", &knn_grid, "exact k nearest 3D neighbours on a uniform grid (CPU)");
}
