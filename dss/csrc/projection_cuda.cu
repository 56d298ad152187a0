// The EWA splat projection on a CUDA GPU (dss/splats.py project_splats): forward, one thread per
// (view, point), and backward, one thread per point summing its views in view order; the
// per-splat formulas are splat_math.h's, the CPU kernel's code.
#include "cuda_common.cuh"

namespace dss_cuda {
namespace {

__global__ void project_forward_kernel(const float* __restrict__ P, const float* __restrict__ Nrm,
                                       const float* __restrict__ R, const float* __restrict__ T,
                                       const float* __restrict__ F, const float* __restrict__ Cc,
                                       const float* __restrict__ S, int64_t V, int64_t N, float fv, float C2, float zn,
                                       int culling, float* __restrict__ out) {
  const int64_t item = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (item >= V * N) return;
  const int64_t v = item / N, k = item - v * N;
  dss_splat::project_forward_one(P + k * 3, Nrm + k * 3, R + v * 9, T + v * 3, F[v], Cc[v * 2], Cc[v * 2 + 1], S[k],
                                 fv, C2, zn, culling != 0, out + item * kFields);
}

__global__ void project_backward_kernel(const float* __restrict__ P, const float* __restrict__ Nrm,
                                        const float* __restrict__ R, const float* __restrict__ T,
                                        const float* __restrict__ F, const float* __restrict__ S,
                                        const float* __restrict__ PK, const float* __restrict__ GK, int64_t V,
                                        int64_t N, float fv, float C, float* __restrict__ gp, float* __restrict__ gn) {
  const int64_t k = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (k >= N) return;
  // float sums from 0 in view order: the CPU kernel's order, so the same bits
  float ap[3] = {0.f, 0.f, 0.f}, an[3] = {0.f, 0.f, 0.f};
  for (int64_t v = 0; v < V; ++v) {
    const float* g = GK + (v * N + k) * kFields;
    const float* pk = PK + (v * N + k) * kFields;
    const dss_splat::SplatGrad sg = dss_splat::project_backward_one(
        P + k * 3, Nrm + k * 3, R + v * 9, T + v * 3, F[v], S[k], fv, C, g[0], g[1], g[2], g[3], g[4], g[5], g[6],
        g[7], g[8], pk[7], pk[8], pk[9] > 0.f);
    for (int a = 0; a < 3; ++a) {
      ap[a] += sg.gp[a];
      an[a] += sg.gn[a];
    }
  }
  for (int a = 0; a < 3; ++a) {
    gp[k * 3 + a] = ap[a];
    gn[k * 3 + a] = an[a];
  }
}

}  // namespace
}  // namespace dss_cuda

// Launchers: qualified definitions, so a signature that drifts from dss_cuda.h fails to compile.

cudaError_t dss_cuda::launch_project_forward(const float* points, const float* normals, const float* R, const float* t,
                                             const float* focal, const float* principal, const float* sigma,
                                             int64_t V, int64_t N, float cutoff, bool culling, float znear,
                                             float filter_variance, float* packed, cudaStream_t stream) {
  if (V * N == 0) return cudaSuccess;
  DSS_LAUNCH(project_forward_kernel, blocks_for(V * N, kThreads1D), kThreads1D, stream)(
      points, normals, R, t, focal, principal, sigma, V, N, filter_variance, 2.f * cutoff, znear, culling ? 1 : 0,
      packed);
  return cudaGetLastError();
}

cudaError_t dss_cuda::launch_project_backward(const float* points, const float* normals, const float* R,
                                              const float* t, const float* focal, const float* sigma,
                                              const float* packed, const float* grad, int64_t V, int64_t N,
                                              float cutoff, float filter_variance, float* grad_points,
                                              float* grad_normals, cudaStream_t stream) {
  if (N == 0) return cudaSuccess;
  DSS_LAUNCH(project_backward_kernel, blocks_for(N, 128), 128, stream)(points, normals, R, t, focal, sigma, packed,
                                                                       grad, V, N, filter_variance, cutoff,
                                                                       grad_points, grad_normals);
  return cudaGetLastError();
}
