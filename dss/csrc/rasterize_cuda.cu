// The rasteriser on a CUDA GPU, with tile binning (no pixel loops over all points):
//   1. bin_count: one thread per (view, splat) counts the 16x16 tiles its cutoff box touches;
//   2. exclusive scan of the counts (done by the caller, torch.cumsum);
//   3. bin_fill: one thread per (view, splat) writes its index into each touched tile's bin;
//   4. rasterize_tiles: a block per (view, tile), a thread per pixel; the bin is streamed through
//      shared memory in batches of 256 splats and each pixel keeps its top-K (depth, index) list
//      in registers (K is a template parameter so the insertion unrolls); then the cache is
//      written and the visible entries are blended (Eq. sumI).
#include "cuda_common.cuh"

namespace dss_cuda {
namespace {

__global__ void bin_count_kernel(const float* __restrict__ P, int64_t V, int64_t N, int H, int W, int TX, int T,
                                 float cutoff, int32_t* __restrict__ counts) {
  const int64_t item = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (item >= V * N) return;
  const float* s = P + item * kFields;
  if (!(s[9] > 0.f)) return;
  Box b = splat_box(s, H, W);
  if (b.j1 < b.j0 || b.i1 < b.i0 || !dss_splat::tighten_box(s, cutoff, b.j0, b.j1, b.i0, b.i1)) return;
  const int64_t v = item / N;
  int32_t* c = counts + v * T;
  for (int ty = b.i0 / kTile; ty <= b.i1 / kTile; ++ty)
    for (int tx = b.j0 / kTile; tx <= b.j1 / kTile; ++tx) atomicAdd(c + ty * TX + tx, 1);
}

__global__ void bin_fill_kernel(const float* __restrict__ P, int64_t V, int64_t N, int H, int W, int TX, int T,
                                float cutoff, int64_t* __restrict__ cursor, int32_t* __restrict__ list) {
  const int64_t item = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (item >= V * N) return;
  const float* s = P + item * kFields;
  if (!(s[9] > 0.f)) return;
  Box b = splat_box(s, H, W);
  if (b.j1 < b.j0 || b.i1 < b.i0 || !dss_splat::tighten_box(s, cutoff, b.j0, b.j1, b.i0, b.i1)) return;
  const int64_t v = item / N;
  const int32_t k = (int32_t)(item - v * N);
  unsigned long long* cur = reinterpret_cast<unsigned long long*>(cursor + v * T);
  for (int ty = b.i0 / kTile; ty <= b.i1 / kTile; ++ty)
    for (int tx = b.j0 / kTile; tx <= b.j1 / kTile; ++tx) {
      const unsigned long long pos = atomicAdd(cur + ty * TX + tx, 1ULL);
      list[pos] = k;
    }
}

template <int K>
__global__ void __launch_bounds__(kBlockPixels)
    rasterize_tiles_kernel(const float* __restrict__ P, int64_t N, int H, int W, int TX, int T,
                           const int64_t* __restrict__ bin_start, const int64_t* __restrict__ bin_end,
                           const int32_t* __restrict__ list, float cutoff, float merge, const float* __restrict__ A,
                           int C, const float* __restrict__ BG, int32_t* __restrict__ I, float* __restrict__ D,
                           float* __restrict__ Rh, float* __restrict__ IMG, bool* __restrict__ Mk) {
  // Splat batch in shared memory, structure of arrays (every thread reads the same entry: broadcast).
  __shared__ float s_u[kBlockPixels], s_v[kBlockPixels], s_a[kBlockPixels], s_b2[kBlockPixels],
      s_c[kBlockPixels], s_norm[kBlockPixels], s_z[kBlockPixels];
  __shared__ int s_j0[kBlockPixels], s_j1[kBlockPixels], s_i0[kBlockPixels], s_i1[kBlockPixels],
      s_k[kBlockPixels];

  const int64_t item = blockIdx.x;  // v * T + t
  const int64_t v = item / T;
  const int t = (int)(item - v * T);
  const int ty = t / TX, tx = t - (t / TX) * TX;
  const int i = ty * kTile + (int)threadIdx.y;
  const int j = tx * kTile + (int)threadIdx.x;
  const int tid = (int)threadIdx.y * kTile + (int)threadIdx.x;
  const bool inside = i < H && j < W;
  const float px = (float)j + 0.5f, py = (float)i + 0.5f;

  // Sorted top-K; empty slots are (+inf, INT_MAX), which every real entry precedes.
  float kd[K], kr[K];
  int ki[K];
#pragma unroll
  for (int e = 0; e < K; ++e) {
    kd[e] = INFINITY;
    ki[e] = INT_MAX;
    kr[e] = 0.f;
  }

  const float* Pv = P + v * N * kFields;
  const int64_t b_start = bin_start[item], b_end = bin_end[item];
  for (int64_t base = b_start; base < b_end; base += kBlockPixels) {
    const int n = (int)min((int64_t)kBlockPixels, b_end - base);
    if (tid < n) {
      const int k = list[base + tid];
      const float* s = Pv + (int64_t)k * kFields;
      Box b = splat_box(s, H, W);
      dss_splat::tighten_box(s, cutoff, b.j0, b.j1, b.i0, b.i1);  // the box the binning used
      s_u[tid] = s[0];
      s_v[tid] = s[1];
      s_a[tid] = s[2];
      s_b2[tid] = s[3];
      s_c[tid] = s[4];
      s_norm[tid] = s[5];
      s_z[tid] = s[6];
      s_j0[tid] = b.j0;
      s_j1[tid] = b.j1;
      s_i0[tid] = b.i0;
      s_i1[tid] = b.i1;
      s_k[tid] = k;
    }
    __syncthreads();
    if (inside) {
      for (int m = 0; m < n; ++m) {
        // The CPU kernel tests exactly the pixels of the box; so do we.
        if (i < s_i0[m] || i > s_i1[m] || j < s_j0[m] || j > s_j1[m]) continue;
        const float dy = py - s_v[m];
        const float dx = px - s_u[m];
        const float q = quad(s_a[m], s_b2[m], s_c[m], dx, dy);
        if (!(0.5f * q <= cutoff)) continue;
        float cz = s_z[m];
        int ck = s_k[m];
        if (!before(cz, ck, kd[K - 1], ki[K - 1])) continue;  // full and behind the last entry
        float cr = s_norm[m] * dss_splat::splat_exp(-0.5f * q);
        // One pass of compare-and-swap inserts the candidate; the last entry falls off.
#pragma unroll
        for (int e = 0; e < K; ++e) {
          if (before(cz, ck, kd[e], ki[e])) {
            const float td = kd[e], tr = kr[e];
            const int ti = ki[e];
            kd[e] = cz;
            ki[e] = ck;
            kr[e] = cr;
            cz = td;
            ck = ti;
            cr = tr;
          }
        }
      }
    }
    __syncthreads();  // the batch is overwritten next
  }
  if (!inside) return;

  const int64_t g = (v * H + i) * (int64_t)W + j;
  int c = 0;
#pragma unroll
  for (int e = 0; e < K; ++e) {
    const bool real = ki[e] != INT_MAX;
    c += real ? 1 : 0;
    I[g * K + e] = real ? ki[e] : -1;
    D[g * K + e] = real ? kd[e] : INFINITY;
    Rh[g * K + e] = real ? kr[e] : 0.f;
  }
  if (c == 0) {
    Mk[g] = false;
    for (int ch = 0; ch < C; ++ch) IMG[g * C + ch] = BG[ch];
    return;
  }
  const float lim = kd[0] + merge;
  float den = 0.f;
  float num[kMaxC];
#pragma unroll
  for (int ch = 0; ch < kMaxC; ++ch) num[ch] = 0.f;
  bool go = true;  // entries are visible up to the first one deeper than lim (CPU: break)
#pragma unroll
  for (int e = 0; e < K; ++e) {
    go = go && (e < c) && (kd[e] <= lim);
    if (go) {
      const float w = kr[e];
      den += w;
      if (C > 0) {
        const float* a = A + ((int64_t)v * N + ki[e]) * C;
#pragma unroll
        for (int ch = 0; ch < kMaxC; ++ch)
          if (ch < C) num[ch] += w * a[ch];
      }
    }
  }
  Mk[g] = den > 0.f;
#pragma unroll
  for (int ch = 0; ch < kMaxC; ++ch)
    if (ch < C) IMG[g * C + ch] = den > 0.f ? num[ch] / den : BG[ch];
}

}  // namespace
}  // namespace dss_cuda

// Launchers: qualified definitions, so a signature that drifts from dss_cuda.h fails to compile.

// Launchers: qualified definitions, so a signature that drifts from dss_cuda.h fails to compile.

cudaError_t dss_cuda::launch_bin_count(const float* packed, int64_t V, int64_t N, int H, int W, float cutoff,
                                       int32_t* counts, cudaStream_t stream) {
  const int TX = tiles_x(W), T = TX * tiles_y(H);
  if (V * N == 0 || T == 0) return cudaSuccess;
  const unsigned int blocks = blocks_for(V * N, kThreads1D);
  DSS_LAUNCH(bin_count_kernel, blocks, kThreads1D, stream)(packed, V, N, H, W, TX, T, cutoff, counts);
  return cudaGetLastError();
}

cudaError_t dss_cuda::launch_bin_fill(const float* packed, int64_t V, int64_t N, int H, int W, float cutoff,
                                      int64_t* cursor, int32_t* list, cudaStream_t stream) {
  const int TX = tiles_x(W), T = TX * tiles_y(H);
  if (V * N == 0 || T == 0) return cudaSuccess;
  const unsigned int blocks = blocks_for(V * N, kThreads1D);
  DSS_LAUNCH(bin_fill_kernel, blocks, kThreads1D, stream)(packed, V, N, H, W, TX, T, cutoff, cursor, list);
  return cudaGetLastError();
}

cudaError_t dss_cuda::launch_rasterize_tiles(const float* packed, int64_t V, int64_t N, int H, int W, int K,
                                             const int64_t* bin_start, const int64_t* bin_end,
                                             const int32_t* list, float cutoff, float merge, const float* attrs,
                                             int C, const float* background, int32_t* idx, float* depth,
                                             float* rho, float* images, bool* mask, cudaStream_t stream) {
  const int TX = tiles_x(W), T = TX * tiles_y(H);
  if (V == 0 || T == 0) return cudaSuccess;
  if (K < 1 || K > kMaxK || C < 0 || C > kMaxC) return cudaErrorInvalidValue;
  const dim3 grid((unsigned int)(V * T)), block(kTile, kTile);
#define DSS_TILES(KK)                                                                                 \
  case KK:                                                                                            \
    DSS_LAUNCH(rasterize_tiles_kernel<KK>, grid, block, stream)(packed, N, H, W, TX, T, bin_start,     \
                                                                bin_end, list, cutoff, merge, attrs, C, \
                                                                background, idx, depth, rho, images,    \
                                                                mask);                                  \
    break;
  switch (K) {
    DSS_TILES(1)
    DSS_TILES(2)
    DSS_TILES(3)
    DSS_TILES(4)
    DSS_TILES(5)
    DSS_TILES(6)
    DSS_TILES(7)
    DSS_TILES(8)
  }
#undef DSS_TILES
  return cudaGetLastError();
}
