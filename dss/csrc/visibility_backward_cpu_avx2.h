// The visibility gradient's AVX2 walk (vector level 1): 8 window pixels per vector, in the scalar
// evaluation's float32 operations and partial-sum order (visibility_backward_cpu.h), so the same bits.
#pragma once

#include "cpu_common.h"
#include "visibility_backward_cpu.h"

namespace dss_cpu {
namespace {

// The dss rule over a point's stride-1 window, 8 pixels of a window row per AVX2 vector: every
// case is computed in every lane and the lane's own case selected by masks; the same float32
// operations in the same order as eval_scalar per lane, and lane l's contributions added to
// partial sum l (in double, two vectors of 4 per coordinate), the order that splat_math.h fixes
// for every path, so the result is bit for bit the scalar one (tests/test_render_backward.py
// checks). A row's pixels beyond its runs of 8 (the 9th of a 9-wide window) go through
// eval_scalar into their own partials, except in windows of 9 to 15 columns that lie wholly on
// the image: those are walked in chunks of 8 consecutive pixels in row-major order, across row
// ends (VisFlatPlan; 10 chunks and one pixel for 9 x 9 instead of 9 chunks and 9 pixels), with
// each lane's contributions moved to its column's partial. Windows narrower than 8 pixels,
// sparse (stride > 1) windows and the rbf rule take the scalar path.
#ifdef DSS_HAVE_AVX2
// One chunk's contributions, added per lane as acc += (x1, y1, 0); acc += (x2, y2, z): the two
// (c) steps (z = 0) or the (a)/(b) step (x2 = y2 = 0); lanes that do not contribute hold +0.
// Adding +0 leaves a sum that started at +0 unchanged, so this is the scalar path's sum without a
// branch on the case or the lane. any: some lane contributes.
struct VisChunkOut {
  __m256 x1, y1, x2, y2, z;
  bool any;
};

// Where a chunk's 8 pixels are: offsets p0 + l of a window row; masked: lanes outside oki (off
// the image) are not read. (AVX2 gathers, or vectors assembled from single loads, for pixels not
// in one row measured slower than evaluating those pixels one at a time.)
struct VisAddr {
  bool masked;
  int64_t p0;
  __m256i oki;
  DSS_AVX2 inline __m256 ld(const float* plane) const {
    return masked ? _mm256_maskload_ps(plane + p0, oki) : _mm256_loadu_ps(plane + p0);
  }
  DSS_AVX2 inline __m256i ldi(const int32_t* plane) const {
    return masked ? _mm256_maskload_epi32((const int*)(plane + p0), oki)
                  : _mm256_loadu_si256((const __m256i*)(plane + p0));
  }
};

// A chunk of 8 consecutive pixels of a window in row-major order, which may run over the end of
// one window row into the next: lanes below the split from offsets p0 + l (the end of row r),
// the others from p1 + l (the start of row r + 1), so a 9-wide window is 10 chunks and one pixel
// instead of 9 chunks and 9 single pixels. Every lane is on the image (the caller checks).
struct VisSplitAddr {
  int64_t p0, p1;
  __m256 hi;  // lanes taken from p1
  __m256i oki;
  DSS_AVX2 inline __m256 ld(const float* plane) const {
    return _mm256_blendv_ps(_mm256_loadu_ps(plane + p0), _mm256_loadu_ps(plane + p1), hi);
  }
  DSS_AVX2 inline __m256i ldi(const int32_t* plane) const {
    return _mm256_castps_si256(_mm256_blendv_ps(_mm256_loadu_ps((const float*)(plane + p0)),
                                                 _mm256_loadu_ps((const float*)(plane + p1)), hi));
  }
};

template <int64_t KC, int64_t CC>
struct VisLanes {
  using Rec = VisRecord<true, KC, CC>;
  const Rec* R;
  int64_t K, C;
  __m256i vk;
  __m256 vu, vv, vz, vnk, vzf, vX, vY, vslope, vslope2, pl0, pl1, pl2, s2, s3, s4;
  __m256 vmerge, veps, vcx, vcy, vinvf, v2cut;
  __m256 wk[16];

  DSS_AVX2 void init(const Rec& rec, int64_t Krt, int64_t Crt, const VisPoint& P, const VisConsts& Q) {
    R = &rec;
    K = KC > 0 ? KC : Krt;
    C = CC > 0 ? CC : Crt;
    vk = _mm256_set1_epi32(P.k);
    vu = _mm256_set1_ps(P.u), vv = _mm256_set1_ps(P.v), vz = _mm256_set1_ps(P.z), vnk = _mm256_set1_ps(P.nk);
    vzf = _mm256_set1_ps(P.z_f), vX = _mm256_set1_ps(P.X), vY = _mm256_set1_ps(P.Y);
    vslope = _mm256_set1_ps(P.slope), vslope2 = _mm256_set1_ps(P.slope * P.slope);
    pl0 = _mm256_set1_ps(P.pl[0]), pl1 = _mm256_set1_ps(P.pl[1]), pl2 = _mm256_set1_ps(P.pl[2]);
    s2 = _mm256_set1_ps(P.s[2]), s3 = _mm256_set1_ps(P.s[3]), s4 = _mm256_set1_ps(P.s[4]);
    vmerge = _mm256_set1_ps(Q.merge), veps = _mm256_set1_ps(Q.eps), vcx = _mm256_set1_ps(Q.cx);
    vcy = _mm256_set1_ps(Q.cy), vinvf = _mm256_set1_ps(Q.inv_f), v2cut = _mm256_set1_ps(2.f * Q.cutoff);
    for (int64_t ch = 0; ch < C; ++ch) wk[ch] = _mm256_set1_ps(P.wk[ch]);
  }

  // add_entries_within in lanes: the scalar loop's stop becomes a mask that stays off once off.
  DSS_AVX2 void add_entries_within(const __m256i* ie, const __m256* de, const __m256* re, const __m256* ge,
                                   int64_t e0, __m256 alive, __m256 lim, __m256& den, __m256& gn) const {
    const __m256i minus1 = _mm256_set1_epi32(-1);
    for (int64_t e = e0; e < K; ++e) {
      alive = _mm256_and_ps(alive, _mm256_and_ps(_mm256_castsi256_ps(_mm256_cmpgt_epi32(ie[e], minus1)),
                                                 _mm256_cmp_ps(de[e], lim, _CMP_LE_OQ)));
      den = _mm256_blendv_ps(den, _mm256_add_ps(den, re[e]), alive);
      gn = _mm256_blendv_ps(gn, _mm256_add_ps(gn, _mm256_mul_ps(re[e], ge[e])), alive);
    }
  }

  // Cases (a)/(b), vis_state: k's tangent-plane depth at the pixels, clamped to kMaxSlope (the
  // square root only where it applies); (dxp, dyp) = pixel centre - (u, v).
  DSS_AVX2 __m256 plane_depth(__m256 px, __m256 vpy, __m256 dxp, __m256 dyp) const {
    const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.f);
    const __m256 iz = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(pl0, px), _mm256_mul_ps(pl1, vpy)), pl2);
    __m256 zq = _mm256_blendv_ps(vz, _mm256_div_ps(one, iz), _mm256_cmp_ps(iz, zero, _CMP_GT_OQ));
    const __m256 d2 = _mm256_add_ps(_mm256_mul_ps(dxp, dxp), _mm256_mul_ps(dyp, dyp));
    const __m256 dz = _mm256_sub_ps(zq, vz);
    const __m256 cl = _mm256_cmp_ps(_mm256_mul_ps(dz, dz), _mm256_mul_ps(vslope2, d2), _CMP_GT_OQ);
    if (_mm256_movemask_ps(cl)) {
      const __m256 dmax = _mm256_mul_ps(vslope, _mm256_sqrt_ps(d2));
      const __m256 lo = _mm256_sub_ps(vz, dmax), hi = _mm256_add_ps(vz, dmax);
      const __m256 mx = _mm256_blendv_ps(zq, lo, _mm256_cmp_ps(zq, lo, _CMP_LT_OQ));  // std::max(zq, lo)
      const __m256 mn = _mm256_blendv_ps(mx, hi, _mm256_cmp_ps(hi, mx, _CMP_LT_OQ));  // std::min(mx, hi)
      zq = _mm256_blendv_ps(zq, mn, cl);
    }
    return zq;
  }

  // Cases (a)/(b): den, gn of the visible set with k added at plane depth zq, but for the cache
  // entries where k becomes the front: the lanes returned, whose entries within zq + T the caller
  // adds (add_entries_within); k1: the case (b) lanes.
  template <class Addr>
  DSS_AVX2 __m256 ab_sums(const Addr& a, __m256 zq, __m256 d0, __m256 d0m, __m256 r1, __m256 r2, __m256 empty,
                          __m256& k1, __m256& den, __m256& gn) const {
    k1 = _mm256_andnot_ps(empty, _mm256_cmp_ps(zq, d0m, _CMP_NLE_UQ));
    __m256 gw = _mm256_setzero_ps();
    for (int64_t ch = 0; ch < C; ++ch) gw = _mm256_add_ps(gw, _mm256_mul_ps(a.ld(R->plane(R->fG(ch))), wk[ch]));
    den = vnk, gn = _mm256_mul_ps(vnk, gw);
    const __m256 mall = _mm256_or_ps(k1, _mm256_cmp_ps(zq, d0, _CMP_GE_OQ));
    den = _mm256_blendv_ps(den, _mm256_add_ps(den, r1), mall);
    gn = _mm256_blendv_ps(gn, _mm256_add_ps(gn, r2), mall);
    return _mm256_andnot_ps(_mm256_or_ps(mall, empty), _mm256_castsi256_ps(_mm256_set1_epi32(-1)));
  }

  // Cases (a)/(b)'s step towards the pixel's ray ((b), lanes k1: onto the front surface d0), in
  // every lane: b = (x, y, z).
  DSS_AVX2 void ab_step(__m256 gd, __m256 k1, __m256 zp, __m256 d0, __m256 px, __m256 vpy, __m256 b[3]) const {
    const __m256 zt = _mm256_blendv_ps(zp, d0, k1);
    const __m256 zt_f = _mm256_mul_ps(zt, vinvf);
    const __m256 mx = _mm256_sub_ps(_mm256_mul_ps(_mm256_sub_ps(px, vcx), zt_f), vX);
    const __m256 my = _mm256_sub_ps(_mm256_mul_ps(_mm256_sub_ps(vpy, vcy), zt_f), vY);
    const __m256 mz = _mm256_sub_ps(zt, zp);
    const __m256 nrm = _mm256_add_ps(
        _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(mx, mx), _mm256_mul_ps(my, my)), _mm256_mul_ps(mz, mz)), veps);
    const __m256 coef = _mm256_div_ps(gd, nrm);
    b[0] = _mm256_mul_ps(coef, mx);
    b[1] = _mm256_mul_ps(coef, my);
    b[2] = _mm256_mul_ps(coef, mz);
  }

  // The 8 evaluations of one chunk; (px, py) the pixel centres.
  template <class Addr>
  DSS_AVX2 void eval(const Addr& a, __m256 px, __m256 vpy, VisChunkOut& out) const {
    const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.f);
    const __m256i minus1 = _mm256_set1_epi32(-1);
    out.any = false;
    const __m256 m = _mm256_and_ps(_mm256_castsi256_ps(a.oki), _mm256_cmp_ps(a.ld(R->plane(Rec::kNZ)), zero, _CMP_NEQ_UQ));
    if (_mm256_movemask_ps(m) == 0) return;
    const __m256 d0 = a.ld(R->plane(Rec::kD0)), r1 = a.ld(R->plane(Rec::kDen)), r2 = a.ld(R->plane(Rec::kGn));
    const __m256 d0m = _mm256_add_ps(d0, vmerge);
    __m256i ie[8];
    __m256 de[8], re[8], ge[8];
    __m256 found = zero, ek0 = zero, pdk = zero, prk = zero, pgk = zero;
    for (int64_t e = 0; e < K; ++e) {
      ie[e] = a.ldi(R->idx_plane(e));
      de[e] = a.ld(R->plane(R->fDep(e)));
      re[e] = a.ld(R->plane(R->fRho(e)));
      ge[e] = a.ld(R->plane(R->fGw(e)));
      const __m256 me = _mm256_castsi256_ps(_mm256_cmpeq_epi32(ie[e], vk));
      if (e == 0) ek0 = me;
      found = _mm256_or_ps(found, me);
      pdk = _mm256_blendv_ps(pdk, de[e], me);
      prk = _mm256_blendv_ps(prk, re[e], me);
      pgk = _mm256_blendv_ps(pgk, ge[e], me);
    }
    const __m256 kvis = _mm256_and_ps(found, _mm256_cmp_ps(pdk, d0m, _CMP_LE_OQ));
    const __m256 empty = _mm256_castsi256_ps(_mm256_cmpgt_epi32(_mm256_setzero_si256(), ie[0]));
    __m256 den = zero, gn = zero, zp = vz, kase1 = zero;
    const __m256 dxp = _mm256_sub_ps(px, vu), dyp = _mm256_sub_ps(vpy, vv);
    if (_mm256_movemask_ps(_mm256_and_ps(m, kvis))) {  // (c): without k the visible set loses it,
      __m256 den_a = _mm256_sub_ps(r1, prk);           // or the next entry becomes the front
      const __m256 gn_a = _mm256_sub_ps(r2, _mm256_mul_ps(prk, pgk));
      den_a = _mm256_blendv_ps(zero, den_a, _mm256_cmp_ps(den_a, zero, _CMP_GT_OQ));
      __m256 den_b = zero, gn_b = zero;
      if (K > 1)
        add_entries_within(ie, de, re, ge, 1, _mm256_castsi256_ps(minus1), _mm256_add_ps(de[1], vmerge), den_b, gn_b);
      den = _mm256_blendv_ps(den_a, den_b, ek0);
      gn = _mm256_blendv_ps(gn_a, gn_b, ek0);
    }
    if (_mm256_movemask_ps(_mm256_andnot_ps(kvis, m))) {  // (a)/(b): k's clamped plane depth decides
      const __m256 zq = plane_depth(px, vpy, dxp, dyp);
      __m256 k1, den_n, gn_n;
      const __m256 alive = ab_sums(a, zq, d0, d0m, r1, r2, empty, k1, den_n, gn_n);
      if (_mm256_movemask_ps(alive))  // k becomes the front: entries beyond zp + T drop out
        add_entries_within(ie, de, re, ge, 0, alive, _mm256_add_ps(zq, vmerge), den_n, gn_n);
      den = _mm256_blendv_ps(den_n, den, kvis);
      gn = _mm256_blendv_ps(gn_n, gn, kvis);
      zp = zq;
      kase1 = k1;
    }
    const __m256 gsel = _mm256_blendv_ps(a.ld(R->plane(Rec::kGb)), _mm256_div_ps(gn, den), _mm256_cmp_ps(den, zero, _CMP_GT_OQ));
    const __m256 gd = _mm256_sub_ps(gsel, a.ld(R->plane(Rec::kGi)));
    const __m256 act = _mm256_and_ps(m, _mm256_cmp_ps(gd, zero, _CMP_LT_OQ));  // Eq. filteredG
    __m256 act_v = _mm256_and_ps(act, kvis);
    const __m256 act_n = _mm256_andnot_ps(kvis, act);
    __m256 c[2][2] = {{zero, zero}, {zero, zero}}, b[3] = {zero, zero, zero};
    if (_mm256_movemask_ps(act_v)) {  // (c): step out of the splat along the ray, both ways
      const __m256 sd = _mm256_sqrt_ps(_mm256_add_ps(_mm256_mul_ps(dxp, dxp), _mm256_mul_ps(dyp, dyp)));
      act_v = _mm256_and_ps(act_v, _mm256_cmp_ps(sd, _mm256_set1_ps(1e-6f), _CMP_NLT_UQ));
      const __m256 inv_sd = _mm256_div_ps(one, sd);
      const __m256 ux = _mm256_mul_ps(dxp, inv_sd), uy = _mm256_mul_ps(dyp, inv_sd);
      const __m256 qu = _mm256_add_ps(
          _mm256_add_ps(_mm256_mul_ps(_mm256_mul_ps(s2, ux), ux), _mm256_mul_ps(_mm256_mul_ps(s3, ux), uy)),
          _mm256_mul_ps(_mm256_mul_ps(s4, uy), uy));
      const __m256 tiny = _mm256_set1_ps(1e-20f);
      const __m256 qm = _mm256_blendv_ps(qu, tiny, _mm256_cmp_ps(qu, tiny, _CMP_LT_OQ));  // std::max(qu, 1e-20f)
      const __m256 rr = _mm256_sqrt_ps(_mm256_div_ps(v2cut, qm));
      __m256 t = _mm256_sub_ps(rr, sd);
      t = _mm256_blendv_ps(t, zero, _mm256_cmp_ps(t, zero, _CMP_LT_OQ));  // std::max(rr - sd, 0.f)
      const __m256 steps[2] = {_mm256_xor_ps(t, _mm256_set1_ps(-0.f)), _mm256_add_ps(rr, sd)};
      for (int mm = 0; mm < 2; ++mm) {
        const __m256 mx = _mm256_mul_ps(_mm256_mul_ps(steps[mm], ux), vzf);
        const __m256 my = _mm256_mul_ps(_mm256_mul_ps(steps[mm], uy), vzf);
        const __m256 coef =
            _mm256_div_ps(gd, _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(mx, mx), _mm256_mul_ps(my, my)), veps));
        c[mm][0] = _mm256_mul_ps(coef, mx);
        c[mm][1] = _mm256_mul_ps(coef, my);
      }
    }
    if (_mm256_movemask_ps(act_n)) ab_step(gd, kase1, zp, d0, px, vpy, b);  // (a)/(b): towards the pixel's ray
    // a section's inactive lanes may hold anything (it ran for the others): keep the active ones
    const __m256 act_any = _mm256_or_ps(act_v, act_n);
    out.x1 = _mm256_and_ps(act_any, _mm256_blendv_ps(b[0], c[0][0], kvis));
    out.y1 = _mm256_and_ps(act_any, _mm256_blendv_ps(b[1], c[0][1], kvis));
    out.x2 = _mm256_and_ps(act_v, c[1][0]);
    out.y2 = _mm256_and_ps(act_v, c[1][1]);
    out.z = _mm256_and_ps(act_n, b[2]);
    out.any = _mm256_movemask_ps(act_any) != 0;
  }
  // eval for a chunk in none of whose pixels k is cached (VisLanes16::eval_nok in 8 lanes): every
  // lane takes case (a) or (b); eval's operations for such lanes, so the same bits.
  template <class Addr>
  DSS_AVX2 void eval_nok(const Addr& a, __m256 px, __m256 vpy, VisChunkOut& out) const {
    const __m256 zero = _mm256_setzero_ps();
    out.any = false;
    const __m256 m = _mm256_and_ps(_mm256_castsi256_ps(a.oki), _mm256_cmp_ps(a.ld(R->plane(Rec::kNZ)), zero, _CMP_NEQ_UQ));
    if (_mm256_movemask_ps(m) == 0) return;
    const __m256 d0 = a.ld(R->plane(Rec::kD0)), r1 = a.ld(R->plane(Rec::kDen)), r2 = a.ld(R->plane(Rec::kGn));
    const __m256 d0m = _mm256_add_ps(d0, vmerge);
    const __m256 empty = _mm256_castsi256_ps(_mm256_cmpgt_epi32(_mm256_setzero_si256(), a.ldi(R->idx_plane(0))));
    const __m256 dxp = _mm256_sub_ps(px, vu), dyp = _mm256_sub_ps(vpy, vv);
    const __m256 zq = plane_depth(px, vpy, dxp, dyp);
    __m256 k1, den, gn;
    const __m256 alive = ab_sums(a, zq, d0, d0m, r1, r2, empty, k1, den, gn);
    if (_mm256_movemask_ps(alive)) {  // k becomes the front: entries beyond zp + T drop out
      __m256i ie[8];
      __m256 de[8], re[8], ge[8];
      for (int64_t e = 0; e < K; ++e) {
        ie[e] = a.ldi(R->idx_plane(e));
        de[e] = a.ld(R->plane(R->fDep(e)));
        re[e] = a.ld(R->plane(R->fRho(e)));
        ge[e] = a.ld(R->plane(R->fGw(e)));
      }
      add_entries_within(ie, de, re, ge, 0, alive, _mm256_add_ps(zq, vmerge), den, gn);
    }
    const __m256 gsel = _mm256_blendv_ps(a.ld(R->plane(Rec::kGb)), _mm256_div_ps(gn, den), _mm256_cmp_ps(den, zero, _CMP_GT_OQ));
    const __m256 gd = _mm256_sub_ps(gsel, a.ld(R->plane(Rec::kGi)));
    const __m256 act = _mm256_and_ps(m, _mm256_cmp_ps(gd, zero, _CMP_LT_OQ));  // Eq. filteredG
    if (_mm256_movemask_ps(act) == 0) return;
    __m256 b[3];
    ab_step(gd, k1, zq, d0, px, vpy, b);
    out.x1 = _mm256_and_ps(act, b[0]);
    out.y1 = _mm256_and_ps(act, b[1]);
    out.x2 = zero;
    out.y2 = zero;
    out.z = _mm256_and_ps(act, b[2]);
    out.any = true;
  }
};

#endif

#ifdef DSS_HAVE_AVX2
// A lane's float contributions added to its double partial (lanes 0-3 in lo, 4-7 in hi).
DSS_AVX2 inline void add_lanes(__m256d& lo, __m256d& hi, __m256 x) {
  lo = _mm256_add_pd(lo, _mm256_cvtps_pd(_mm256_castps256_ps128(x)));
  hi = _mm256_add_pd(hi, _mm256_cvtps_pd(_mm256_extractf128_ps(x, 1)));
}

// A window of n = 2 w + 1 columns, 9 <= n <= 15, walked in row-major order in chunks of 8
// consecutive pixels (VisSplitAddr), n * n = 8 * nvec + 1 pixels: nvec chunks and the last pixel
// alone, where the row walk takes n - 8 single pixels per row. Lane l of chunk c is window pixel
// 8 c + l (row, column as below). For these widths a window column's partial sum
// (dss_splat::vis_partial) is its column number, so a chunk's contributions are moved by perm to
// the lane of their column (columns 0-7, present where pres is set: a chunk's columns are
// distinct, 8 < n) and added there, and those of columns 8 and beyond (extra lanes, all in the
// chunk's first row) go to their own partials: every partial gets its pixels in row-major order,
// as on the row walk, so the sums are the same bits.
struct VisFlatPlan {
  static constexpr int kMaxChunks = 28;  // 15 * 15 / 8
  int n = 0, nvec = 0;
  int64_t p0[kMaxChunks], p1[kMaxChunks];  // offsets from the window's first pixel
  alignas(32) int32_t col[kMaxChunks][8], row[kMaxChunks][8], perm[kMaxChunks][8], pres[kMaxChunks][8],
      hi[kMaxChunks][8];
  int nextra[kMaxChunks], extra[kMaxChunks][8];  // lanes in columns >= 8
  bool split[kMaxChunks];  // the chunk runs over a row end

  // Whether the chunked walk applies to windows of half size w (and builds it for image width W).
  bool build(int64_t w, int64_t W) {
    n = (int)(2 * w + 1);
    if (n < 9 || n > 15) return false;
    nvec = n * n / 8;
    for (int c = 0; c < nvec; ++c) {
      int split = 8;
      for (int l = 0; l < 8; ++l) {
        const int f = 8 * c + l;
        row[c][l] = f / n;
        col[c][l] = f % n;
        if (split == 8 && row[c][l] != row[c][0]) split = l;
        hi[c][l] = split < 8 ? -1 : 0;
      }
      p0[c] = (int64_t)row[c][0] * W + col[c][0];
      p1[c] = split < 8 ? (int64_t)(row[c][0] + 1) * W - split : p0[c];
      this->split[c] = split < 8;
      nextra[c] = 0;
      for (int k = 0; k < 8; ++k) perm[c][k] = 0, pres[c][k] = 0;
      for (int l = 0; l < 8; ++l) {
        if (col[c][l] < 8) {
          perm[c][col[c][l]] = l;
          pres[c][col[c][l]] = -1;
        } else {
          extra[c][nextra[c]++] = l;
        }
      }
    }
    return true;
  }
};

// The chunked walk of an interior window (every pixel on the image) by plan F: the same
// evaluations and partial sums as the row walk in window_dss_avx2.
template <int64_t KC, int64_t CC>
DSS_AVX2 void window_flat_avx2(const VisLanes<KC, CC>& L, const VisRecord<true, KC, CC>& rec, int64_t Krt,
                               int64_t Crt, const VisPoint& P, const VisConsts& Q, const VisFlatPlan& F, int64_t W,
                               int64_t window, int ic, int jc, const uint8_t* krows, __m256d* sx, __m256d* sy,
                               __m256d* sz, double (*part)[3]) {
  const int64_t corner = (int64_t)(ic - window) * W + (jc - window);
  const __m256i vj0 = _mm256_set1_epi32(jc - (int)window), vi0 = _mm256_set1_epi32(ic - (int)window);
  const __m256 half = _mm256_set1_ps(0.5f);
  VisSplitAddr a;
  a.oki = _mm256_set1_epi32(-1);
  VisAddr in_row;  // chunks within one row: one load per plane
  in_row.masked = false;
  in_row.oki = a.oki;
  VisChunkOut o;
  for (int c = 0; c < F.nvec; ++c) {
    const __m256 px = _mm256_add_ps(
        _mm256_cvtepi32_ps(_mm256_add_epi32(vj0, _mm256_load_si256((const __m256i*)F.col[c]))), half);
    const __m256 py = _mm256_add_ps(
        _mm256_cvtepi32_ps(_mm256_add_epi32(vi0, _mm256_load_si256((const __m256i*)F.row[c]))), half);
    // k cached in one of the chunk's rows (krows, window_rows_avx512), or no flags: eval
    const int r0 = F.row[c][0];
    const bool cached = !krows || krows[r0] || (F.split[c] && krows[r0 + 1]);
    if (F.split[c]) {
      a.p0 = corner + F.p0[c];
      a.p1 = corner + F.p1[c];
      a.hi = _mm256_castsi256_ps(_mm256_load_si256((const __m256i*)F.hi[c]));
      cached ? L.eval(a, px, py, o) : L.eval_nok(a, px, py, o);
    } else {
      in_row.p0 = corner + F.p0[c];
      cached ? L.eval(in_row, px, py, o) : L.eval_nok(in_row, px, py, o);
    }
    if (!o.any) continue;
    const __m256i pm = _mm256_load_si256((const __m256i*)F.perm[c]);
    const __m256 pr = _mm256_castsi256_ps(_mm256_load_si256((const __m256i*)F.pres[c]));
    add_lanes(sx[0], sx[1], _mm256_and_ps(_mm256_permutevar8x32_ps(o.x1, pm), pr));
    add_lanes(sy[0], sy[1], _mm256_and_ps(_mm256_permutevar8x32_ps(o.y1, pm), pr));
    add_lanes(sx[0], sx[1], _mm256_and_ps(_mm256_permutevar8x32_ps(o.x2, pm), pr));
    add_lanes(sy[0], sy[1], _mm256_and_ps(_mm256_permutevar8x32_ps(o.y2, pm), pr));
    add_lanes(sz[0], sz[1], _mm256_and_ps(_mm256_permutevar8x32_ps(o.z, pm), pr));
    if (F.nextra[c]) {
      alignas(32) float x1[8], y1[8], x2[8], y2[8], z[8];
      _mm256_store_ps(x1, o.x1), _mm256_store_ps(y1, o.y1), _mm256_store_ps(x2, o.x2);
      _mm256_store_ps(y2, o.y2), _mm256_store_ps(z, o.z);
      for (int e = 0; e < F.nextra[c]; ++e) {  // eval_scalar's order: (x1, y1), then (x2, y2, z)
        const int l = F.extra[c][e];
        double* q = part[F.col[c][l]];
        q[0] += x1[l];
        q[1] += y1[l];
        q[0] += x2[l];
        q[1] += y2[l];
        q[2] += z[l];
      }
    }
  }
  // the window's last pixel alone
  const int64_t p = corner + (int64_t)(F.n - 1) * W + (F.n - 1);
  if (rec.nz(p) != 0.f)
    eval_scalar<KC, CC>(rec, Krt, Crt, P, Q, 0, p, (float)(jc + window) + 0.5f, (float)(ic + window) + 0.5f,
                        part[F.n - 1]);
}

template <int64_t KC, int64_t CC>
DSS_AVX2 void window_dss_avx2(const VisRecord<true, KC, CC>& rec, int64_t Krt, int64_t Crt, const VisPoint& P, const VisConsts& Q,
                              int64_t H, int64_t W, int64_t window, int ic, int jc, const VisFlatPlan* flat,
                              const uint8_t* krows, double acc[3]) {
  VisLanes<KC, CC> L;
  L.init(rec, Krt, Crt, P, Q);
  const int mw = dss_splat::vis_window_runs(window);  // a row's first mw pixels in runs of 8
  const int nq = dss_splat::vis_partial_count(window);
  const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
  const __m256i minus1 = _mm256_set1_epi32(-1), vW = _mm256_set1_epi32((int)W);
  const __m256 half = _mm256_set1_ps(0.5f);
  VisChunkOut o;
  // partials 0-7 in lanes (x, y, z; lanes 0-3 and 4-7), the rest (columns mw, mw + 1, ...) scalar
  __m256d sx[2] = {_mm256_setzero_pd(), _mm256_setzero_pd()}, sy[2] = {sx[0], sx[0]}, sz[2] = {sx[0], sx[0]};
  double part[dss_splat::kVisPartials][3] = {};
  // interior windows of 9 to 15 columns in chunks across rows; the others row by row
  if (flat && ic - window >= 0 && ic + window < H && jc - window >= 0 && jc + window < W) {
    window_flat_avx2<KC, CC>(L, rec, Krt, Crt, P, Q, *flat, W, window, ic, jc, krows, sx, sy, sz, part);
  } else {
    for (int64_t i = ic - window; i <= ic + window; ++i) {
      if (i < 0 || i >= H) continue;
      const float py = (float)i + 0.5f;
      for (int64_t j0 = jc - window; j0 < jc - window + mw; j0 += 8) {
        if (j0 + 7 < 0 || j0 >= W) continue;
        const __m256i vj = _mm256_add_epi32(_mm256_set1_epi32((int)j0), lane);
        VisAddr a;
        a.masked = !(j0 >= 0 && j0 + 8 <= W);
        a.p0 = i * W + j0;
        a.oki = _mm256_and_si256(_mm256_cmpgt_epi32(vj, minus1), _mm256_cmpgt_epi32(vW, vj));
        if (!krows || krows[i - (ic - window)])
          L.eval(a, _mm256_add_ps(_mm256_cvtepi32_ps(vj), half), _mm256_set1_ps(py), o);
        else
          L.eval_nok(a, _mm256_add_ps(_mm256_cvtepi32_ps(vj), half), _mm256_set1_ps(py), o);
        if (o.any) {
          add_lanes(sx[0], sx[1], o.x1);
          add_lanes(sy[0], sy[1], o.y1);
          add_lanes(sx[0], sx[1], o.x2);
          add_lanes(sy[0], sy[1], o.y2);
          add_lanes(sz[0], sz[1], o.z);
        }
      }
      // the row's last 2 w + 1 - mw pixels one at a time (a vector with one lane in use costs 3 scalar ones)
      for (int64_t j = std::max<int64_t>(jc - window + mw, 0); j <= std::min<int64_t>(jc + window, W - 1); ++j) {
        const int64_t p = i * W + j;
        if (rec.nz(p) == 0.f) continue;
        eval_scalar<KC, CC>(rec, Krt, Crt, P, Q, 0, p, (float)j + 0.5f, py, part[8 + (j - (jc - window) - mw)]);
      }
    }
  }
  alignas(32) double lanes[3][8];
  _mm256_store_pd(lanes[0], sx[0]), _mm256_store_pd(lanes[0] + 4, sx[1]);
  _mm256_store_pd(lanes[1], sy[0]), _mm256_store_pd(lanes[1] + 4, sy[1]);
  _mm256_store_pd(lanes[2], sz[0]), _mm256_store_pd(lanes[2] + 4, sz[1]);
  for (int l = 0; l < 8; ++l)
    for (int c = 0; c < 3; ++c) part[l][c] = lanes[c][l];
  add_partials(part, nq, acc);
}
#endif

}  // namespace
}  // namespace dss_cpu
