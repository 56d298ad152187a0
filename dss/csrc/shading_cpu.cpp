// Sun shading on the CPU (dss/shading.py SunLights), forward and backward.
#include "cpu_common.h"
#include "dss_cpu.h"

using namespace dss_cpu;

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
