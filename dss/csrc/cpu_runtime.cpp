// The CPU module's shared run-time state: the block cache behind the large outputs
// (pooled_empty, empty_cache), the vector-level switch the kernels read (set_vector_level), and
// the kernels' float32 exp over a tensor (splat_exp, for the tests).
#include "cpu_common.h"
#include "dss_cpu.h"

namespace dss_cpu {
namespace {

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

}  // namespace

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

namespace {
// Which vector paths the kernels take: 0 the baseline (scalar) loops, 1 the AVX2 paths, 2 also
// the AVX-512 ones (the visibility backward's windows of 9-15 columns, a row per 16-lane vector;
// the binning's box scan), each level where both this build and the CPU have it. set_vector_level / set_vector_path force a lower
// level, for tests and comparisons: every level gives the same bits.
std::atomic<int> g_vector_level{2};
}  // namespace

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

}  // namespace dss_cpu

using namespace dss_cpu;

// Enables (every level the CPU has) / disables the vector paths; returns whether they were on.
bool set_vector_path(bool on) { return g_vector_level.exchange(on ? 2 : 0) > 0; }
// Sets the highest vector level the kernels may take (0-2, see g_vector_level); returns the
// previous setting.
int64_t set_vector_level(int64_t level) {
  TORCH_CHECK(level >= 0 && level <= 2, "vector level must be 0 (scalar), 1 (AVX2) or 2 (AVX-512), got ", level);
  return g_vector_level.exchange((int)level);
}

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
