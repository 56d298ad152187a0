// The blend's backward on a CUDA GPU (the smooth terms of Eqs. gradN, gradP): one thread per
// (view, splat) gathers the cache entries that hold it over its box, in the CPU kernel's pixel
// order (no atomics).
#include "cuda_common.cuh"

namespace dss_cuda {
namespace {

// Backward of Eq. sumI for the smooth terms (blend_backward_cpu.cpp: the same formulas and,
// per splat, the same row-major pixel order of the double sums). One thread per (view, splat)
// gathers over the pixels of its cutoff box (the only pixels whose cache can hold it: the
// rasteriser tests exactly those) the visible cache entries that are this splat. No atomics.
// Writes dL/dpacked fields 0-5 (u, v, conic a, b2, c, norm; 6-9 zero) and dL/dattrs.
__global__ void blend_backward_kernel(const float* __restrict__ P, const float* __restrict__ A,
                                      const int32_t* __restrict__ I, const float* __restrict__ D,
                                      const float* __restrict__ Rh, const float* __restrict__ IMG,
                                      const float* __restrict__ GR, int64_t V, int64_t N, int H, int W, int K, int C,
                                      float merge, float* __restrict__ GP, float* __restrict__ GA) {
  const int64_t item = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (item >= V * N) return;
  const int64_t v = item / N;
  const int32_t k = (int32_t)(item - v * N);
  const float* s = P + item * kFields;
  const float* wk = A + item * C;
  double a[6 + kMaxC];
  for (int f = 0; f < 6 + C; ++f) a[f] = 0.0;
  if (s[9] > 0.f) {
    const Box b = splat_box(s, H, W);
    for (int i = b.i0; i <= b.i1; ++i) {
      const float py = (float)i + 0.5f;
      for (int j = b.j0; j <= b.j1; ++j) {
        const int64_t g = ((int64_t)v * H + i) * W + j;
        const int32_t* pi = I + g * K;
        const float* pd = D + g * K;
        const float* pr = Rh + g * K;
        if (pi[0] < 0) continue;
        const float lim = pd[0] + merge;
        int mine = -1;
        float den = 0.f;
        for (int e = 0; e < K && pi[e] >= 0 && pd[e] <= lim; ++e) {
          den += pr[e];
          if (pi[e] == k) mine = e;
        }
        if (mine < 0 || !(den > 0.f)) continue;
        const float dx = ((float)j + 0.5f) - s[0], dy = py - s[1];
        dss_splat::blend_entry_grad(s, wk, GR + g * C, IMG + g * C, C, pr[mine], 1.0 / (double)den, dx, dy, a);
      }
    }
  }
  float* o = GP + item * kFields;
  for (int f = 0; f < 6; ++f) o[f] = (float)a[f];
  for (int f = 6; f < kFields; ++f) o[f] = 0.f;
  for (int c = 0; c < C; ++c) GA[item * C + c] = (float)a[6 + c];
}

}  // namespace
}  // namespace dss_cuda

// Launchers: qualified definitions, so a signature that drifts from dss_cuda.h fails to compile.

cudaError_t dss_cuda::launch_blend_backward(const float* packed, const float* attrs, const int32_t* idx,
                                            const float* depth, const float* rho, const float* images,
                                            const float* grad, int64_t V, int64_t N, int H, int W, int K, int C,
                                            float merge, float* grad_packed, float* grad_attrs, cudaStream_t stream) {
  if (V * N == 0) return cudaSuccess;
  if (K < 1 || K > kMaxK || C < 1 || C > kMaxC) return cudaErrorInvalidValue;
  DSS_LAUNCH(blend_backward_kernel, blocks_for(V * N, 128), 128, stream)(packed, attrs, idx, depth, rho, images, grad,
                                                                         V, N, H, W, K, C, merge, grad_packed,
                                                                         grad_attrs);
  return cudaGetLastError();
}
