// Sun shading on a CUDA GPU (dss/shading.py SunLights), forward and backward.
#include "cuda_common.cuh"

namespace dss_cuda {
namespace {

// Sun shading with one light per channel (dss/shading.py SunLights; shading_cpu.cpp sun_shade_*):
// w[v, k, l] = (max(n_k . d_vl, 0) + ambient) (x albedo[k, l]); d (V, 3, 3): light l's direction in
// world space for view v. The CPU kernel's expressions and summation order: the same bits.
__device__ __forceinline__ float sun_dot(const float* n, const float* d) { return n[0] * d[0] + n[1] * d[1] + n[2] * d[2]; }
__device__ __forceinline__ float relu_as_std_max(float x) { return x < 0.f ? 0.f : x; }  // std::max(x, 0.f)

__global__ void sun_forward_kernel(const float* __restrict__ Nrm, const float* __restrict__ alb,
                                   const float* __restrict__ D, int64_t V, int64_t N, float amb,
                                   float* __restrict__ out) {
  const int64_t item = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (item >= V * N) return;
  const int64_t v = item / N, k = item - v * N;
  for (int l = 0; l < 3; ++l) {
    const float w = relu_as_std_max(sun_dot(Nrm + k * 3, D + v * 9 + l * 3)) + amb;
    out[item * 3 + l] = alb ? w * alb[k * 3 + l] : w;
  }
}

// One thread per point, views then lights in order (the CPU kernel's per-point order).
__global__ void sun_backward_kernel(const float* __restrict__ Nrm, const float* __restrict__ alb,
                                    const float* __restrict__ D, const float* __restrict__ G, int64_t V, int64_t N,
                                    float amb, float* __restrict__ gn, float* __restrict__ ga) {
  const int64_t k = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (k >= N) return;
  float s[3] = {0.f, 0.f, 0.f}, sa[3] = {0.f, 0.f, 0.f};
  for (int64_t v = 0; v < V; ++v)
    for (int l = 0; l < 3; ++l) {
      const float* d = D + v * 9 + l * 3;
      const float dot = sun_dot(Nrm + k * 3, d);
      const float gv = G[(v * N + k) * 3 + l];
      if (ga) sa[l] += gv * (relu_as_std_max(dot) + amb);
      // torch's clamp_min passes the gradient where its input >= the bound
      const float gl = dot >= 0.f ? (alb ? gv * alb[k * 3 + l] : gv) : 0.f;
      for (int a = 0; a < 3; ++a) s[a] += gl * d[a];
    }
  for (int a = 0; a < 3; ++a) {
    gn[k * 3 + a] = s[a];
    if (ga) ga[k * 3 + a] = sa[a];
  }
}

}  // namespace
}  // namespace dss_cuda

// Launchers: qualified definitions, so a signature that drifts from dss_cuda.h fails to compile.

cudaError_t dss_cuda::launch_sun_forward(const float* normals, const float* albedo, const float* dirs, int64_t V,
                                         int64_t N, float ambient, float* out, cudaStream_t stream) {
  if (V * N == 0) return cudaSuccess;
  DSS_LAUNCH(sun_forward_kernel, blocks_for(V * N, kThreads1D), kThreads1D, stream)(normals, albedo, dirs, V, N,
                                                                                     ambient, out);
  return cudaGetLastError();
}

cudaError_t dss_cuda::launch_sun_backward(const float* normals, const float* albedo, const float* dirs,
                                          const float* grad, int64_t V, int64_t N, float ambient,
                                          float* grad_normals, float* grad_albedo, cudaStream_t stream) {
  if (N == 0) return cudaSuccess;
  DSS_LAUNCH(sun_backward_kernel, blocks_for(N, kThreads1D), kThreads1D, stream)(normals, albedo, dirs, grad, V, N,
                                                                                  ambient, grad_normals, grad_albedo);
  return cudaGetLastError();
}
