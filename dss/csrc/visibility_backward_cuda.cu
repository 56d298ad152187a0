// The visibility gradient on a CUDA GPU: one thread per (view, pixel) builds the pixel records of
// the CPU kernel (visibility_backward_cpu.h: the loss gradient's projections g . w of the cached
// attributes, so an evaluation is channel-free); then one thread per (view, point) evaluates the
// window around the point exactly as the CPU kernel's scalar path does and writes its world-space
// contribution (double); a third kernel sums the views of every point in view order. No atomics:
// deterministic.
#include "cuda_common.cuh"

namespace dss_cuda {
namespace {

// Per (view, pixel): the pixel record of the CPU kernel (visibility_backward_cpu.h) (one record per pixel,
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

// One (point, pixel) evaluation of visibility_kernel: vis_state and eval_scalar of visibility_backward_cpu.h,
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

// Per (view, point): the window loop of visibility_backward_cpu.cpp over the pixel records,
// its contributions added in the same partial sums (dss_splat::vis_partial) in the same order.
// Two walks keep that order (each partial's contributions arrive in row-major order in both; the
// tests compare the float32 outputs, which a reordered double sum rarely changes, so the order
// itself is kept by construction):
// kRows = false, partial by partial, each over its columns (one column of a
// 9-wide window at a time, so a window's records are read 9 times, a column apart); kRows = true,
// one row-major pass with every partial's sum open at once (t in local memory). On an H100 this
// kernel is 1.34x slower at 100K points than a row-major walk that summed in another order;
// launch_visibility takes the row walk when DSS_CUDA_VIS_ORDER=rows, so that
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

}  // namespace
}  // namespace dss_cuda

// Launchers: qualified definitions, so a signature that drifts from dss_cuda.h fails to compile.

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
