// What every CUDA stage shares (dss_cuda.h lists the launchers, one source file per stage):
// the includes, the launch macro (tests/cuda_emu runs the kernels on CPU threads through it), the
// launch sizes, the splat's pixel box and the cache's entry order.
//
// Same contract as the CPU kernels (dss_cpu.h) and the torch reference: same packed splats, the
// same per-pixel tests written as the same float32 expressions in the same order (build with
// --fmad=false so no fused multiply-add changes a rounding), the same (depth, index) order of the
// top-K cache, and exp as dss_splat::splat_exp (float32 operations only, not CUDA's expf, whose
// last bit differs from the host's). The caches, images, visibility gradients and blend backward
// therefore match the CPU kernels' bit for bit, in the CPU emulation of these files and on the
// device (the gpu tests of tests/test_cuda_build.py assert torch.equal).
//
// Only the CUDA runtime is needed here; the torch glue is dss_cuda_bind.cpp.
#pragma once

#include "dss_cuda.h"
#include "splat_math.h"

#include <cuda_runtime.h>

#include <climits>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>

// Kernel launch, as a macro so that tests/cuda_emu can run these kernels on CPU threads.
#ifndef DSS_LAUNCH
#define DSS_LAUNCH(kernel, grid, block, stream) kernel<<<grid, block, 0, stream>>>
#endif

namespace dss_cuda {
namespace {

constexpr int kBlockPixels = kTile * kTile;  // threads per tile block, also the batch size
constexpr int kThreads1D = 256;

using dss_splat::Box;  // a splat's pixel box (splat_math.h)

// dss_splat::splat_box (the CPU kernel's, reference.bbox()'s arithmetic) of a packed splat row.
__device__ __forceinline__ Box splat_box(const float* __restrict__ s, int H, int W) {
  Box b = dss_splat::splat_box(s[0], s[1], s[7], s[8], H, W);
  // A NaN centre converts to 0 on the GPU (undefined on the CPU, whose binning zeroes NaN rows
  // first); keep the box in the image anyway.
  b.j0 = max(0, min(b.j0, W - 1));
  b.j1 = max(0, min(b.j1, W - 1));
  b.i0 = max(0, min(b.i0, H - 1));
  b.i1 = max(0, min(b.i1, H - 1));
  return b;
}

using dss_splat::quad;  // the CPU kernel's quadratic form (splat_math.h)

// The tangent-plane depth clamp's slope (the rule at kMaxSlope in visibility_backward_cpu.h).
constexpr float kMaxSlope = 3.f;

// Strict total order of cache entries: depth, then point index.
__device__ __forceinline__ bool before(float za, int ia, float zb, int ib) {
  return za < zb || (za == zb && ia < ib);
}

inline unsigned int blocks_for(int64_t n, int threads) { return (unsigned int)((n + threads - 1) / threads); }

inline int tiles_x(int W) { return (W + kTile - 1) / kTile; }
inline int tiles_y(int H) { return (H + kTile - 1) / kTile; }

}  // namespace
}  // namespace dss_cuda
