// The Z-order (Morton) permutation of a cloud on the CPU (dss/ordering.py spatial_order).
#include "cpu_common.h"
#include "dss_cpu.h"

using namespace dss_cpu;

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
