// The visibility gradient's pixel records and its scalar evaluation (paper Eqs. gradcase,
// filteredG, cases (a), (b), (c); dss/visibility/reference.py has the rules written out in torch),
// shared by visibility_backward_cpu.cpp and its vector walks (visibility_backward_cpu_avx2.h,
// visibility_backward_cpu_avx512.h).
#pragma once

#include "cpu_common.h"

namespace dss_cpu {
namespace {

// The visibility backward's per-point row flags: one byte per window row, windows of up to 15 rows.
constexpr int64_t kFlagRows = 16;

// Depth of point k's tangent plane at the pixel centre (px, py), the depth its splat would have
// there (the backward pass's occlusion test, cases (a)/(b)). For a plane 1/z is affine in screen
// space: 1/z = pl[0] px + pl[1] py + pl[2] (computed in dss/render.py; (0, 0, 1/z) reproduces
// the centre depth). Grazing planes are clamped to a slope of kMaxSlope: |zp - z| <= kMaxSlope *
// (pixel distance) * z / f.
// (vis_state evaluates it inline, with the square root only where the clamp applies.)
constexpr float kMaxSlope = 3.f;

// Everything a (point, pixel) evaluation reads about the pixel, for one view, as planes of H*W
// values (structure of arrays: a window row is a run of consecutive values in every plane, so the
// vector path loads 8 pixels with one instruction per plane). With g = dL/dI at the pixel only the
// projections g . w of the attributes matter (gd = g . I_new - g . I = (sum rho g.w) / (sum rho)
// - g . I), so an evaluation is channel-free. Float planes: nz (1 if g != 0; a pixel with nz = 0
// is never read further and its other planes are stale), d0 (front depth, inf if empty), den =
// sum rho and gn = sum rho g.w over the visible set, gi = g . I, gb = g . background, g (C
// planes), then per cache entry e its depth, rho and g.w (K planes each); int planes: the cache
// indices (K planes).
template <bool kSoA, int64_t KC = 0, int64_t CC = 0>
struct VisRecord {
  int64_t C_ = 0, K_ = 0;  // run-time values; KC, CC > 0 fix them at compile time (constant offsets)
  int64_t C() const { return CC > 0 ? CC : C_; }
  int64_t K() const { return KC > 0 ? KC : K_; }
  int64_t S = 0;  // planes: the plane stride (values); records: the record size (floats)
  float* f = nullptr;
  int32_t* ix = nullptr;  // planes: K index planes (stride S); records: the cache's idx (H*W, K)
  // field numbers
  static constexpr int64_t kNZ = 0, kD0 = 1, kDen = 2, kGn = 3, kGi = 4, kGb = 5;
  int64_t fG(int64_t ch) const { return 6 + ch; }
  int64_t fDep(int64_t e) const { return 6 + C() + e; }
  int64_t fRho(int64_t e) const { return 6 + C() + K() + e; }
  int64_t fGw(int64_t e) const { return 6 + C() + 2 * K() + e; }
  float& at(int64_t field, int64_t p) const { return kSoA ? f[field * S + p] : f[p * S + field]; }
  float& nz(int64_t p) const { return at(kNZ, p); }
  float& d0(int64_t p) const { return at(kD0, p); }
  float& den(int64_t p) const { return at(kDen, p); }
  float& gn(int64_t p) const { return at(kGn, p); }
  float& gi(int64_t p) const { return at(kGi, p); }
  float& gb(int64_t p) const { return at(kGb, p); }
  float& g(int64_t ch, int64_t p) const { return at(fG(ch), p); }
  float& dep(int64_t e, int64_t p) const { return at(fDep(e), p); }
  float& rho(int64_t e, int64_t p) const { return at(fRho(e), p); }
  float& gw(int64_t e, int64_t p) const { return at(fGw(e), p); }
  int32_t& idx(int64_t e, int64_t p) const { return kSoA ? ix[e * S + p] : ix[p * K() + e]; }
  // The same record with (K, C) fixed at compile time.
  template <int64_t K2, int64_t C2>
  VisRecord<kSoA, K2, C2> fixed() const {
    VisRecord<kSoA, K2, C2> r;
    r.C_ = C_, r.K_ = K_, r.S = S, r.f = f, r.ix = ix;
    return r;
  }
  // planes only: the start of a field's / an index plane
  const float* plane(int64_t field) const { return f + field * S; }
  const int32_t* idx_plane(int64_t e) const { return ix + e * S; }
  static int64_t fields(int64_t C, int64_t K) { return 6 + C + 3 * K; }
  // H*W rounded up to 16 values, plus 5 cache lines: planes a power of two apart (256 KB at
  // 256x256) would all map to the same few sets of the L1 and L2 caches and evict each other.
  // (The padding also holds the up to 7 values that the AVX-512 walk's full loads read past a
  // plane's last pixel, VisRow16.)
  static int64_t plane_stride(int64_t HW) { return (HW + 15) / 16 * 16 + 80; }
};

// What an evaluation needs about the point (one view).
struct VisPoint {
  const float* s;   // packed splat (kFields)
  const float* wk;  // the point's attributes (C)
  const float* pl;  // tangent plane: 1/z = pl[0] px + pl[1] py + pl[2]
  int32_t k;
  float u, v, z, nk;
  float z_f;    // camera units per pixel at the point's depth
  float X, Y;   // camera-frame x, y of the point
  float slope;  // plane-depth clamp per pixel of distance (kMaxSlope * z_f)
};

// The view's and the rule's constants.
struct VisConsts {
  float f, cx, cy, inv_f, cutoff, merge, eps;
};

// The visibility state after k's change at one pixel: the case, the loss change gd = g . I_new -
// g . I, k's (clamped) tangent-plane depth zp (cases (a)/(b) only) and the front depth d0.
struct VisState {
  int kase;  // 0: (a) invisible, nothing in front; 1: (b) occluded; 2: (c) visible
  float gd, zp, d0;
};

// Adds rho and rho g.w of the cache entries e0, e0 + 1, ... at pixel p to (den, gn) while they
// hold a point within depth lim: the visible set in front of lim (entries are depth-sorted).
template <class Rec>
inline void add_entries_within(const Rec& R, int64_t K, int64_t p, int e0, float lim, float& den, float& gn) {
  for (int e = e0; e < K && R.idx(e, p) >= 0 && R.dep(e, p) <= lim; ++e) {
    den += R.rho(e, p);
    gn += R.rho(e, p) * R.gw(e, p);
  }
}

template <int64_t KC, int64_t CC, class Rec>
DSS_INLINE VisState vis_state(const Rec& R, int64_t Krt, int64_t Crt, const VisPoint& P, const VisConsts& Q,
                          int64_t p, float px, float py) {
  const int64_t K = KC > 0 ? KC : Krt, C = CC > 0 ? CC : Crt;
  const float d0 = R.d0(p), merge = Q.merge;
  int ek = -1;  // position of k in the cache
  for (int e = 0; e < K && R.idx(e, p) >= 0; ++e)
    if (R.idx(e, p) == P.k) { ek = e; break; }
  const bool k_visible = ek >= 0 && R.dep(ek, p) <= d0 + merge;
  float zp = 0.f;  // only needed when k is not visible
  float den, gn;   // sum rho and sum rho g.w of the visible set after the change
  int kase;
  if (k_visible) {
    kase = 2;
    if (ek > 0) {  // the front stays: the visible set loses k only
      const float prk = R.rho(ek, p);
      den = R.den(p) - prk;
      gn = R.gn(p) - prk * R.gw(ek, p);
      if (!(den > 0.f)) den = 0.f;
    } else {  // k was the front: the next entry is the new front, may reveal others
      den = 0.f;
      gn = 0.f;
      if (K > 1 && R.idx(1, p) >= 0) add_entries_within(R, K, p, 1, R.dep(1, p) + merge, den, gn);
    }
  } else {
    // k's tangent-plane depth at the pixel, clamped to kMaxSlope (square root only if it applies)
    const float iz = P.pl[0] * px + P.pl[1] * py + P.pl[2];
    zp = iz > 0.f ? 1.f / iz : P.z;
    const float d2 = (px - P.u) * (px - P.u) + (py - P.v) * (py - P.v);
    const float dz = zp - P.z;
    if (dz * dz > P.slope * P.slope * d2) {
      const float dmax = P.slope * std::sqrt(d2);
      zp = std::min(std::max(zp, P.z - dmax), P.z + dmax);
    }
    const bool empty = R.idx(0, p) < 0;
    kase = (empty || zp <= d0 + merge) ? 0 : 1;
    float gw = 0.f;
    for (int64_t ch = 0; ch < C; ++ch) gw += R.g(ch, p) * P.wk[ch];
    den = P.nk;
    gn = P.nk * gw;
    if (kase == 1 || zp >= d0) {  // merges with the current visible set
      den += R.den(p);
      gn += R.gn(p);
    } else if (!empty) {  // k becomes the front: entries beyond zp + T drop out
      add_entries_within(R, K, p, 0, zp + merge, den, gn);
    }
  }
  const float gd = (den > 0.f ? gn / den : R.gb(p)) - R.gi(p);
  return {kase, gd, zp, d0};
}

// One (point, pixel) evaluation, scalar; adds to acc (double) in the order the window is walked.
// mode 0 (dss): the linearised step between the two visibility states; mode 1 (rbf): the
// derivative of a smooth Gaussian visibility h = exp(-q/2).
template <int64_t KC, int64_t CC, class Rec>
DSS_INLINE void eval_scalar(const Rec& R, int64_t Krt, int64_t Crt, const VisPoint& P, const VisConsts& Q,
                        int64_t mode, int64_t p, float px, float py, double acc[3]) {
  const VisState st = vis_state<KC, CC>(R, Krt, Crt, P, Q, p, px, py);
  const float gd = st.gd;
  const float ddx = px - P.u, ddy = py - P.v;
  if (mode == 1) {
    const float q = quad(P.s, ddx, ddy);
    const float h = dss_splat::splat_exp(-0.5f * q);
    const float sgn = st.kase == 2 ? -1.f : 1.f;  // Phi = I_without + h (I_with - I_without)
    const float gu = h * (P.s[2] * ddx + 0.5f * P.s[3] * ddy);  // dh/du_k = h Sigma^-1 d
    const float gv = h * (0.5f * P.s[3] * ddx + P.s[4] * ddy);
    const float c = sgn * gd, f = Q.f, z = P.z;
    acc[0] += c * (f / z) * gu;
    acc[1] += c * (f / z) * gv;
    acc[2] += c * (-f * P.X / (z * z) * gu - f * P.Y / (z * z) * gv);
    return;
  }
  if (!(gd < 0.f)) return;  // Eq. filteredG
  if (st.kase == 2) {       // (c): step out of the splat along the ray from its centre, both ways
    const float sd = std::sqrt(ddx * ddx + ddy * ddy);
    if (sd < 1e-6f) return;
    const float inv_sd = 1.f / sd;
    const float ux = ddx * inv_sd, uy = ddy * inv_sd;
    const float qu = quad(P.s, ux, uy);
    const float rr = std::sqrt(2.f * Q.cutoff / std::max(qu, 1e-20f));
    const float steps[2] = {-(std::max(rr - sd, 0.f)), rr + sd};
    for (int m = 0; m < 2; ++m) {
      const float mx = steps[m] * ux * P.z_f, my = steps[m] * uy * P.z_f;
      const float coef = gd / (mx * mx + my * my + Q.eps);
      acc[0] += coef * mx;
      acc[1] += coef * my;
    }
  } else {
    const float zt = st.kase == 1 ? st.d0 : st.zp;  // (b): forward to the front surface
    const float zt_f = zt * Q.inv_f;
    const float mx = (px - Q.cx) * zt_f - P.X, my = (py - Q.cy) * zt_f - P.Y, mz = zt - st.zp;
    const float coef = gd / (mx * mx + my * my + mz * mz + Q.eps);
    acc[0] += coef * mx;
    acc[1] += coef * my;
    acc[2] += coef * mz;
  }
}

// Adds the window's partial sums to acc in partial order (dss_splat::vis_partial).
inline void add_partials(const double (*part)[3], int nq, double acc[3]) {
  for (int q = 0; q < nq; ++q)
    for (int a = 0; a < 3; ++a) acc[a] += part[q][a];
}

}  // namespace
}  // namespace dss_cpu
