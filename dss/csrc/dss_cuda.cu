// DSS rasteriser and visibility gradient on a CUDA GPU.
//
// Same contract as the CPU kernel (dss_cpu.cpp) and the torch reference: same packed splats, the
// same per-pixel tests written as the same float32 expressions in the same order (build with
// --fmad=false so no fused multiply-add changes a rounding), the same (depth, index) order of the
// top-K cache, and exp as dss_splat::splat_exp (float32 operations only, not CUDA's expf, whose
// last bit differs from the host's). The caches, images, visibility gradients and blend backward
// therefore match the CPU kernel's bit for bit, in the CPU emulation of this file and on the
// device (the gpu tests of tests/test_cuda_build.py assert torch.equal; first run on an H100 in
// session 40).
//
// Forward, with tile binning (no pixel loops over all points):
//   1. bin_count: one thread per (view, splat) counts the 16x16 tiles its cutoff box touches;
//   2. exclusive scan of the counts (done by the caller, torch.cumsum);
//   3. bin_fill: one thread per (view, splat) writes its index into each touched tile's bin;
//   4. rasterize_tiles: a block per (view, tile), a thread per pixel; the bin is streamed through
//      shared memory in batches of 256 splats and each pixel keeps its top-K (depth, index) list
//      in registers (K is a template parameter so the insertion unrolls); then the cache is
//      written and the visible entries are blended (Eq. sumI).
// Blend backward (the smooth terms of Eqs. gradN, gradP): one thread per (view, splat) gathers the
// cache entries that hold it over its box, in the CPU kernel's pixel order (no atomics).
// Projection (dss/splats.py project_splats) forward, one thread per (view, point), and backward,
// one thread per point summing its views in view order: splat_math.h, the CPU kernel's code.
// Backward: one thread per (view, pixel) builds the pixel records of dss_cpu.cpp
// visibility_backward (the loss gradient's projections g . w of the cached attributes, so an
// evaluation is channel-free); then one thread per (view, point) evaluates the window around the
// point exactly as the CPU kernel's scalar path does and writes its world-space contribution
// (double); a third kernel sums the views of every point in view order. No atomics:
// deterministic.
//
// Only the CUDA runtime is needed here; the torch glue is dss_cuda_bind.cpp.
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

// The tangent-plane depth clamp's slope (the rule at kMaxSlope in dss_cpu.cpp).
constexpr float kMaxSlope = 3.f;

// Strict total order of cache entries: depth, then point index.
__device__ __forceinline__ bool before(float za, int ia, float zb, int ib) {
  return za < zb || (za == zb && ia < ib);
}

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

// Per (view, pixel): the pixel record of dss_cpu.cpp visibility_backward (one record per pixel,
// RS = 6 + C + 3K floats): [0] 1 if the loss gradient g != 0 (else nothing more is written or
// read), [1] front depth d0 (inf if empty), [2] sum rho and [3] sum rho g.w over the visible set,
// [4] g . I, [5] g . background, [6, 6+C) g, then per cache entry its depth, rho and g . w (K
// each). Same expressions in the same order as the CPU builder.
__global__ void vis_records_kernel(const float* __restrict__ A, const int32_t* __restrict__ I,
                                   const float* __restrict__ D, const float* __restrict__ Rh,
                                   const float* __restrict__ IMG, const float* __restrict__ GR,
                                   const float* __restrict__ BG, int64_t V, int64_t N, int H, int W, int K, int C,
                                   float merge, float* __restrict__ REC) {
  const int64_t g = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  const int64_t HW = (int64_t)H * W;
  if (g >= V * HW) return;
  const int64_t v = g / HW;
  const int64_t RS = vis_record_floats(K, C);
  float* r = REC + g * RS;
  const float* gp = GR + g * C;
  bool nz = false;
  for (int ch = 0; ch < C; ++ch) nz |= (gp[ch] != 0.f);
  r[0] = nz ? 1.f : 0.f;
  if (!nz) return;
  const int32_t* pi = I + g * K;
  const float* pd = D + g * K;
  const float* pr = Rh + g * K;
  const float* ip = IMG + g * C;
  float gi = 0.f, gb = 0.f;
  for (int ch = 0; ch < C; ++ch) {
    r[6 + ch] = gp[ch];
    gi += gp[ch] * ip[ch];
    gb += gp[ch] * BG[ch];
  }
  r[4] = gi;
  r[5] = gb;
  const float d0 = pi[0] >= 0 ? pd[0] : INFINITY;
  float* rd = r + 6 + C;
  float* rr = rd + K;
  float* rg = rr + K;
  for (int e = 0; e < K; ++e) {
    rd[e] = pd[e];
    rr[e] = pr[e];
    float ga = 0.f;
    if (pi[e] >= 0) {
      const float* a = A + (v * N + pi[e]) * C;
      for (int ch = 0; ch < C; ++ch) ga += gp[ch] * a[ch];
    }
    rg[e] = ga;
  }
  float den = 0.f, gnum = 0.f;
  for (int e = 0; e < K && pi[e] >= 0 && pd[e] <= d0 + merge; ++e) {
    den += pr[e];
    gnum += pr[e] * rg[e];
  }
  r[1] = d0;
  r[2] = den;
  r[3] = gnum;
}

// One (point, pixel) evaluation of visibility_kernel: vis_state and eval_scalar of dss_cpu.cpp,
// expression for expression; adds the contribution to t (double).
__device__ __forceinline__ void vis_eval_pixel(const float* __restrict__ s, const float* __restrict__ wk,
                                               const float* __restrict__ pl, const int32_t* __restrict__ I,
                                               const float* __restrict__ REC, int64_t RS, int32_t k, int64_t p,
                                               float px, float py, int K, int C, float f, float cx, float cy,
                                               float inv_f, float u, float vv, float z, float nk, float z_f, float X,
                                               float Y, float slope, float cutoff, float merge, float eps, int mode,
                                               double t[3]) {
  const float* r = REC + p * RS;
  if (r[0] == 0.f) return;
  const int32_t* pi = I + p * K;
  const float* pd = r + 6 + C;
  const float* pr = pd + K;
  const float* pg = pr + K;
  const float d0 = r[1];
  int ek = -1;  // position of k in the cache
  for (int e = 0; e < K && pi[e] >= 0; ++e)
    if (pi[e] == k) {
      ek = e;
      break;
    }
  const bool k_visible = ek >= 0 && pd[ek] <= d0 + merge;
  float zp = 0.f, den, gn;
  int kase;  // 0: (a) invisible, nothing in front; 1: (b) occluded; 2: (c) visible
  if (k_visible) {
    kase = 2;
    if (ek > 0) {  // the front stays: the visible set loses k only
      const float prk = pr[ek];
      den = r[2] - prk;
      gn = r[3] - prk * pg[ek];
      if (!(den > 0.f)) den = 0.f;
    } else {  // k was the front: the next entry is the new front, may reveal others
      den = 0.f;
      gn = 0.f;
      if (K > 1 && pi[1] >= 0) {
        const float lim = pd[1] + merge;
        for (int e = 1; e < K && pi[e] >= 0 && pd[e] <= lim; ++e) {
          den += pr[e];
          gn += pr[e] * pg[e];
        }
      }
    }
  } else {
    // k's tangent-plane depth at the pixel, clamped to kMaxSlope (square root only if it applies)
    const float iz = pl[0] * px + pl[1] * py + pl[2];
    zp = iz > 0.f ? 1.f / iz : z;
    const float d2 = (px - u) * (px - u) + (py - vv) * (py - vv);
    const float dz = zp - z;
    if (dz * dz > slope * slope * d2) {
      const float dmax = slope * sqrtf(d2);
      const float lo = z - dmax, hi = z + dmax;
      zp = (zp < lo) ? lo : zp;  // std::max(zp, lo)
      zp = (hi < zp) ? hi : zp;  // std::min(zp, hi)
    }
    const bool empty = pi[0] < 0;
    kase = (empty || zp <= d0 + merge) ? 0 : 1;
    float gw = 0.f;
    for (int ch = 0; ch < C; ++ch) gw += r[6 + ch] * wk[ch];
    den = nk;
    gn = nk * gw;
    if (kase == 1 || zp >= d0) {  // merges with the current visible set
      den += r[2];
      gn += r[3];
    } else if (!empty) {  // k becomes the front: entries beyond zp + T drop out
      const float lim = zp + merge;
      for (int e = 0; e < K && pi[e] >= 0 && pd[e] <= lim; ++e) {
        den += pr[e];
        gn += pr[e] * pg[e];
      }
    }
  }
  const float gd = (den > 0.f ? gn / den : r[5]) - r[4];
  const float ddx = px - u, ddy = py - vv;
  if (mode == 1) {  // rbf: derivative of a smooth Gaussian visibility h = exp(-q/2)
    const float q = quad(s[2], s[3], s[4], ddx, ddy);
    const float h = dss_splat::splat_exp(-0.5f * q);
    const float sgn = kase == 2 ? -1.f : 1.f;  // Phi = I_without + h (I_with - I_without)
    const float gu = h * (s[2] * ddx + 0.5f * s[3] * ddy);
    const float gv = h * (0.5f * s[3] * ddx + s[4] * ddy);
    const float c = sgn * gd;
    t[0] += c * (f / z) * gu;
    t[1] += c * (f / z) * gv;
    t[2] += c * (-f * X / (z * z) * gu - f * Y / (z * z) * gv);
    return;
  }
  if (!(gd < 0.f)) return;  // Eq. filteredG
  if (kase == 2) {  // (c): step out of the splat along the ray from its centre, both ways
    const float sd = sqrtf(ddx * ddx + ddy * ddy);
    if (sd < 1e-6f) return;
    const float inv_sd = 1.f / sd;
    const float ux = ddx * inv_sd, uy = ddy * inv_sd;
    const float qu = quad(s[2], s[3], s[4], ux, uy);
    const float rr = sqrtf(2.f * cutoff / ((qu < 1e-20f) ? 1e-20f : qu));  // std::max(qu, 1e-20f)
    const float rs = rr - sd;
    const float steps[2] = {-((rs < 0.f) ? 0.f : rs), rr + sd};  // -(std::max(rr - sd, 0.f))
#pragma unroll
    for (int m = 0; m < 2; ++m) {
      const float mx = steps[m] * ux * z_f, my = steps[m] * uy * z_f;
      const float coef = gd / (mx * mx + my * my + eps);
      t[0] += coef * mx;
      t[1] += coef * my;
    }
  } else {
    const float zt = kase == 1 ? d0 : zp;  // (b): forward to the front surface
    const float zt_f = zt * inv_f;
    const float mx = (px - cx) * zt_f - X, my = (py - cy) * zt_f - Y, mz = zt - zp;
    const float coef = gd / (mx * mx + my * my + mz * mz + eps);
    t[0] += coef * mx;
    t[1] += coef * my;
    t[2] += coef * mz;
  }
}

// Per (view, point): the window loop of dss_cpu.cpp visibility_backward over the pixel records,
// its contributions added in the same partial sums (dss_splat::vis_partial) in the same order.
// Two walks keep that order (each partial's contributions arrive in row-major order in both; the
// tests compare the float32 outputs, which a reordered double sum rarely changes, so the order
// itself is kept by construction):
// kRows = false, partial by partial, each over its columns (since session 28: one column of a
// 9-wide window at a time, so a window's records are read 9 times, a column apart); kRows = true,
// one row-major pass with every partial's sum open at once (t in local memory). Session 40 found
// this kernel 1.34x slower at 100K points than session 27's row-major walk (which summed in
// another order); launch_visibility takes the row walk when DSS_CUDA_VIS_ORDER=rows, so that
// both can be timed on one GPU (not yet run on one).
template <bool kRows>
__global__ void visibility_kernel(const float* __restrict__ P, const float* __restrict__ A,
                                  const int32_t* __restrict__ I, const float* __restrict__ REC,
                                  const float* __restrict__ Rm, const float* __restrict__ F,
                                  const float* __restrict__ PP, const float* __restrict__ PL, int64_t V, int64_t N,
                                  int H, int W, int K, int C, int window, int stride, float cutoff, float merge,
                                  float eps, int mode, double* __restrict__ partial) {
  const int64_t item = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (item >= V * N) return;
  const int64_t v = item / N;
  const int32_t k = (int32_t)(item - v * N);
  double* out = partial + item * 3;
  const float* s = P + item * kFields;
  if (!(s[9] > 0.f)) {
    out[0] = 0.0;
    out[1] = 0.0;
    out[2] = 0.0;
    return;
  }
  const int64_t RS = vis_record_floats(K, C);
  const float f = F[v], cx = PP[v * 2], cy = PP[v * 2 + 1], inv_f = 1.f / f;
  const float u = s[0], vv = s[1], z = s[6], nk = s[5];
  const float z_f = z * inv_f;  // camera units per pixel at the point's depth
  const float X = (u - cx) * z_f, Y = (vv - cy) * z_f;
  const float slope = kMaxSlope * z_f;
  const float* wk = A + item * C;
  const float* pl = PL + item * 3;
  const int ic = (int)floorf(vv), jc = (int)floorf(u);
  const int64_t HW = (int64_t)H * W;
  // the window's partial sums in the order of dss_splat::vis_partial (the CPU kernel's): each
  // partial over its columns in row-major order
  const int mw = dss_splat::vis_window_runs(window), nq = dss_splat::vis_partial_count(window);
  // pixel (i, j) of the window (on the image), its contribution added to t
  auto eval = [&](int64_t i, int64_t j, float py, double* t) {
    vis_eval_pixel(s, wk, pl, I, REC, RS, k, v * HW + i * W + j, (float)j + 0.5f, py, K, C, f, cx, cy, inv_f, u, vv,
                   z, nk, z_f, X, Y, slope, cutoff, merge, eps, mode, t);
  };
  double acc[3] = {0, 0, 0};
  if constexpr (kRows) {
    double t[kMaxVisPartials][3];
    for (int q = 0; q < nq; ++q) t[q][0] = t[q][1] = t[q][2] = 0.0;
    for (int64_t dy = -window; dy <= window; dy += stride) {
      const int64_t i = ic + dy;
      if (i < 0 || i >= H) continue;
      const float py = (float)i + 0.5f;
      for (int c = 0; c <= 2 * window; c += stride) {  // stride-th columns from the first: c % stride == 0
        const int64_t j = jc + c - window;
        if (j < 0 || j >= W) continue;
        eval(i, j, py, t[dss_splat::vis_partial(c, mw)]);
      }
    }
    for (int q = 0; q < nq; ++q)
      for (int a = 0; a < 3; ++a) acc[a] += t[q][a];
  } else {
    for (int q = 0; q < nq; ++q) {
      const int c0 = q < 8 ? q : mw + q - 8, c1 = q < 8 ? mw : c0 + 1, cstep = q < 8 ? 8 : 1;
      double t[3] = {0, 0, 0};
      for (int64_t dy = -window; dy <= window; dy += stride) {
        const int64_t i = ic + dy;
        if (i < 0 || i >= H) continue;
        const float py = (float)i + 0.5f;
        for (int c = c0; c < c1; c += cstep) {
          if (c % stride) continue;  // sparse windows visit every stride-th column
          const int64_t j = jc + c - window;
          if (j < 0 || j >= W) continue;
          eval(i, j, py, t);
        }
      }
      for (int a = 0; a < 3; ++a) acc[a] += t[a];
    }
  }
  const float* Rv = Rm + v * 9;  // world contribution = R^T acc
#pragma unroll
  for (int a = 0; a < 3; ++a) out[a] = Rv[0 * 3 + a] * acc[0] + Rv[1 * 3 + a] * acc[1] + Rv[2 * 3 + a] * acc[2];
}

__global__ void reduce_views_kernel(const float* __restrict__ P, const double* __restrict__ partial, int64_t V,
                                    int64_t N, float* __restrict__ out) {
  const int64_t k = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (k >= N) return;
  double gw[3] = {0, 0, 0};
  for (int64_t v = 0; v < V; ++v) {
    const int64_t item = v * N + k;
    if (!(P[item * kFields + 9] > 0.f)) continue;
    for (int a = 0; a < 3; ++a) gw[a] += partial[item * 3 + a];
  }
  for (int a = 0; a < 3; ++a) out[k * 3 + a] = (float)gw[a];
}

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

// Backward of Eq. sumI for the smooth terms (dss_cpu.cpp blend_backward: the same formulas and,
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

// Sun shading with one light per channel (dss/shading.py SunLights; dss_cpu.cpp sun_shade_*):
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

inline unsigned int blocks_for(int64_t n, int threads) { return (unsigned int)((n + threads - 1) / threads); }

inline int tiles_x(int W) { return (W + kTile - 1) / kTile; }
inline int tiles_y(int H) { return (H + kTile - 1) / kTile; }

}  // namespace
}  // namespace dss_cuda

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

int dss_cuda::visibility_order() {
  const char* e = std::getenv("DSS_CUDA_VIS_ORDER");
  if (e == nullptr || *e == '\0' || std::strcmp(e, "partials") == 0) return 0;
  return std::strcmp(e, "rows") == 0 ? 1 : -1;
}

cudaError_t dss_cuda::launch_visibility(const float* packed, const float* attrs, const int32_t* idx,
                                        const float* depth, const float* rho, const float* images,
                                        const float* grad, const float* R, const float* focal,
                                        const float* principal, const float* background, const float* planes,
                                        int64_t V, int64_t N, int H, int W, int K, int C, int window, int stride,
                                        float cutoff, float merge, float eps, int mode, float* records,
                                        double* partial, cudaStream_t stream) {
  const int order = visibility_order();
  if (order < 0) return cudaErrorInvalidValue;
  if (V * N == 0) return cudaSuccess;
  if (K < 1 || K > kMaxK || C < 1 || C > kMaxC || stride < 1 || window < 0) return cudaErrorInvalidValue;
  const int64_t pixels = V * (int64_t)H * W;
  if (pixels > 0) {
    DSS_LAUNCH(vis_records_kernel, blocks_for(pixels, kThreads1D), kThreads1D, stream)(
        attrs, idx, depth, rho, images, grad, background, V, N, H, W, K, C, merge, records);
  }
#define DSS_VIS(ROWS)                                                                                        \
  DSS_LAUNCH(visibility_kernel<ROWS>, blocks_for(V * N, 128), 128, stream)(packed, attrs, idx, records, R, focal, \
                                                                           principal, planes, V, N, H, W, K, C,  \
                                                                           window, stride, cutoff, merge, eps,   \
                                                                           mode, partial)
  if (order == 1)
    DSS_VIS(true);
  else
    DSS_VIS(false);
#undef DSS_VIS
  return cudaGetLastError();
}

cudaError_t dss_cuda::launch_reduce_views(const float* packed, const double* partial, int64_t V, int64_t N,
                                          float* out, cudaStream_t stream) {
  if (N == 0) return cudaSuccess;
  const unsigned int blocks = blocks_for(N, kThreads1D);
  DSS_LAUNCH(reduce_views_kernel, blocks, kThreads1D, stream)(packed, partial, V, N, out);
  return cudaGetLastError();
}

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
