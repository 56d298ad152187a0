// Host launchers of the DSS CUDA kernels (one *_cuda.cu file per stage), called by the torch glue
// (dss_cuda_bind.cpp). Raw pointers and the CUDA runtime only, so the kernels compile with
// plain nvcc, without torch headers (tests/test_cuda_build.py does exactly that).
//
// Layouts (all row-major, contiguous):
//   packed  (V, N, 10) f32  u v conic_a conic_b2 conic_c norm depth rx ry valid (dss/splats.py)
//   attrs   (V, N, C)  f32  per-view point attributes, C <= 16
//   cache   (V, H, W, K)    idx i32 (-1 empty), depth f32 (+inf empty), rho f32 (0 empty); K <= 8
//   images  (V, H, W, C) f32, mask (V, H, W) bool (1 byte)
// Every launcher returns the launch status (cudaGetLastError()); a zero-sized launch is a no-op.
#pragma once

#include <cuda_runtime_api.h>

#include <cstdint>

namespace dss_cuda {

constexpr int kFields = 10;
constexpr int kTile = 16;     // screen tiles are kTile x kTile pixels, one CUDA block each
constexpr int kMaxK = 8;
constexpr int kMaxC = 16;

// EWA splat projection (dss/splats.py project_splats; splat_math.h, the CPU kernel's code):
// packed (V, N, 10) from points, normals (N, 3), R (V, 3, 3), t (V, 3), focal (V), principal
// (V, 2), sigma (N).
cudaError_t launch_project_forward(const float* points, const float* normals, const float* R, const float* t,
                                   const float* focal, const float* principal, const float* sigma, int64_t V,
                                   int64_t N, float cutoff, bool culling, float znear, float filter_variance,
                                   float* packed, cudaStream_t stream);

// Its backward: grad_points, grad_normals (N, 3) from grad = dL/dpacked (V, N, 10), each point's
// views summed in view order (float, as the CPU kernel); sigma and the cameras held fixed.
cudaError_t launch_project_backward(const float* points, const float* normals, const float* R, const float* t,
                                    const float* focal, const float* sigma, const float* packed, const float* grad,
                                    int64_t V, int64_t N, float cutoff, float filter_variance, float* grad_points,
                                    float* grad_normals, cudaStream_t stream);

// Sun shading, one light per channel (dss/shading.py SunLights): out (V, N, 3) from normals (N, 3),
// albedo (N, 3) or null, dirs (V, 3, 3) (light l of view v in world space, row l).
cudaError_t launch_sun_forward(const float* normals, const float* albedo, const float* dirs, int64_t V, int64_t N,
                               float ambient, float* out, cudaStream_t stream);

// Its backward: grad_normals (N, 3) and, unless null, grad_albedo (N, 3) from grad (V, N, 3).
cudaError_t launch_sun_backward(const float* normals, const float* albedo, const float* dirs, const float* grad,
                                int64_t V, int64_t N, float ambient, float* grad_normals, float* grad_albedo,
                                cudaStream_t stream);

// Binning pass 1: counts[v * T + t] += 1 for every tile t touched by the box of splat (v, k)
// (splat_box() shrunk by dss_splat::tighten_box for the cutoff, as the CPU kernel bins).
// counts (V * T) i32 must be zeroed; T = ceil(H / kTile) * ceil(W / kTile).
cudaError_t launch_bin_count(const float* packed, int64_t V, int64_t N, int H, int W, float cutoff, int32_t* counts,
                             cudaStream_t stream);

// Binning pass 2: list[cursor[v * T + t]++] = k. cursor (V * T) i64 starts as the exclusive
// prefix sum of counts; list holds sum(counts) entries. The order inside a bin does not matter:
// the per-pixel top-K is a strict (depth, index) order, so the result is order-independent.
cudaError_t launch_bin_fill(const float* packed, int64_t V, int64_t N, int H, int W, float cutoff, int64_t* cursor,
                            int32_t* list, cudaStream_t stream);

// One block per (view, tile), one thread per pixel: top-K insertion over the tile's bin, then the
// cache write-out and the blend of the visible entries (Eq. sumI). bin_start / bin_end (V * T) i64.
// attrs / background / images may be null (C = 0): only the cache and the mask are written.
cudaError_t launch_rasterize_tiles(const float* packed, int64_t V, int64_t N, int H, int W, int K,
                                   const int64_t* bin_start, const int64_t* bin_end, const int32_t* list,
                                   float cutoff, float merge, const float* attrs, int C, const float* background,
                                   int32_t* idx, float* depth, float* rho, float* images, bool* mask,
                                   cudaStream_t stream);

// Floats in one pixel record of the visibility gradient (the layout of visibility_backward_cpu.h's records);
// used by the kernels (device) and by the callers that allocate the workspace (host).
#ifdef __CUDACC__
__host__ __device__
#endif
constexpr int64_t vis_record_floats(int K, int C) { return 6 + C + 3 * (int64_t)K; }

// Backward of Eq. sumI for the smooth terms (blend_backward_cpu.cpp): grad_packed (V, N, 10)
// (fields 0-5; 6-9 zero) and grad_attrs (V, N, C) from grad = dL/dimages (V, H, W, C) and the
// forward's cache and images. One thread per (view, splat) over the pixels of its box.
cudaError_t launch_blend_backward(const float* packed, const float* attrs, const int32_t* idx, const float* depth,
                                  const float* rho, const float* images, const float* grad, int64_t V, int64_t N,
                                  int H, int W, int K, int C, float merge, float* grad_packed, float* grad_attrs,
                                  cudaStream_t stream);

// Visibility gradient: one thread per (view, pixel) fills records (V * H * W *
// vis_record_floats(K, C) f32, workspace: the pixel records of visibility_backward_cpu.h), then one thread per (view, point): partial
// (V, N, 3) f64 receives R_v^T acc_v, the world-space contribution of view v (zero where the
// splat is not valid). mode 0: dss, 1: rbf.
// The visibility kernel's walk over a window (both give the same bits; see visibility_kernel in
// visibility_backward_cuda.cu), from the environment variable DSS_CUDA_VIS_ORDER: 0 for "partials" (or unset, the
// default), 1 for "rows", -1 for any other value (launch_visibility then returns
// cudaErrorInvalidValue).
int visibility_order();
// The most partial sums a window has (dss_splat::vis_partial_count <= 8 + 7).
constexpr int kMaxVisPartials = 15;

cudaError_t launch_visibility(const float* packed, const float* attrs, const int32_t* idx, const float* depth,
                              const float* rho, const float* images, const float* grad, const float* R,
                              const float* focal, const float* principal, const float* background,
                              const float* planes, int64_t V, int64_t N, int H, int W, int K, int C, int window,
                              int stride, float cutoff, float merge, float eps, int mode, float* records,
                              double* partial, cudaStream_t stream);

// out (N, 3) f32 = sum over views v = 0..V-1 in order (double) of partial[v, k], skipping views
// where splat (v, k) is not valid: the CPU kernel's summation order, hence deterministic.
cudaError_t launch_reduce_views(const float* packed, const double* partial, int64_t V, int64_t N, float* out,
                                cudaStream_t stream);

}  // namespace dss_cuda
