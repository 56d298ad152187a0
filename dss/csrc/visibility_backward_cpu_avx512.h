// The visibility gradient's AVX-512 walk (vector level 2): a window row of 9-15 pixels per
// 16-lane vector, in the scalar evaluation's float32 operations and partial-sum order
// (visibility_backward_cpu.h), so the same bits.
#pragma once

#include "cpu_common.h"
#include "visibility_backward_cpu.h"

namespace dss_cpu {
namespace {

#ifdef DSS_HAVE_AVX2
// The dss rule in 16 lanes (AVX-512, taken where the CPU has it) for windows of 9 to 15 columns:
// one window row per vector (lane l: column l of the window; the lanes beyond the row unused),
// for windows wholly on the image and at its border alike. VisLanes16::eval is VisLanes::eval
// with 16 lanes and mask registers: the same float32 operations in the same order per lane, every
// case computed in every lane and selected by masks, lanes that do not contribute holding +0. A
// lane's contributions go to its column's partial sum (vis_partial: the column number, for these
// widths), rows in order, so the result is the scalar walk's bit for bit
// (tests/test_render_backward.py compares every vector level with the scalar path). Against the
// 8-lane walk, 1.34x on the 20K position step's visibility backward (2 cores, Zen 5). (A walk
// that packed a window's pixels 16 at a time in row-major order, 5 vectors and one pixel per 9 x 9
// window instead of 9 vectors, was 1.07x slower: each vector read 2-3 row runs per plane and
// moved its lanes to their columns' partials.) A row costs about 80 cycles, bound by its chain
// of three divisions and the comparisons between them (docs/performance.md); rows
// where the point is not cached take eval_nok, about a third of eval.
struct VisRowOut16 {
  __m512 x1, y1, x2, y2, z;
  bool any;
  bool any_c;  // some lane contributes through case (c): x2, y2 are +0 in every lane otherwise
};

// One window row: lane l at offset p0 + l of every plane. Rows wholly on the image are read with
// full loads, which may read up to 7 values beyond the row's window (on the image or in a plane's
// padding, VisRecord::plane_stride; never used); rows at the border with loads masked to the
// lanes on the image.
struct VisRow16 {
  int64_t p0;
  bool masked;
  __mmask16 oki;
  DSS_AVX512 inline __m512 ld(const float* plane) const {
    return masked ? _mm512_maskz_loadu_ps(oki, plane + p0) : _mm512_loadu_ps(plane + p0);
  }
  DSS_AVX512 inline __m512i ldi(const int32_t* plane) const {
    return masked ? _mm512_maskz_loadu_epi32(oki, plane + p0) : _mm512_loadu_si512((const void*)(plane + p0));
  }
};

template <int64_t KC, int64_t CC>
struct VisLanes16 {
  using Rec = VisRecord<true, KC, CC>;
  const Rec* R;
  int64_t K, C;
  __m512i vk;
  __m512 vu, vv, vz, vnk, vzf, vX, vY, vslope, vslope2, pl0, pl1, pl2, s2, s3, s4;
  __m512 vmerge, veps, vcx, vcy, vinvf, v2cut;
  __m512 wk[16];

  DSS_AVX512 void init(const Rec& rec, int64_t Krt, int64_t Crt, const VisPoint& P, const VisConsts& Q) {
    R = &rec;
    K = KC > 0 ? KC : Krt;
    C = CC > 0 ? CC : Crt;
    vk = _mm512_set1_epi32(P.k);
    vu = _mm512_set1_ps(P.u), vv = _mm512_set1_ps(P.v), vz = _mm512_set1_ps(P.z), vnk = _mm512_set1_ps(P.nk);
    vzf = _mm512_set1_ps(P.z_f), vX = _mm512_set1_ps(P.X), vY = _mm512_set1_ps(P.Y);
    vslope = _mm512_set1_ps(P.slope), vslope2 = _mm512_set1_ps(P.slope * P.slope);
    pl0 = _mm512_set1_ps(P.pl[0]), pl1 = _mm512_set1_ps(P.pl[1]), pl2 = _mm512_set1_ps(P.pl[2]);
    s2 = _mm512_set1_ps(P.s[2]), s3 = _mm512_set1_ps(P.s[3]), s4 = _mm512_set1_ps(P.s[4]);
    vmerge = _mm512_set1_ps(Q.merge), veps = _mm512_set1_ps(Q.eps), vcx = _mm512_set1_ps(Q.cx);
    vcy = _mm512_set1_ps(Q.cy), vinvf = _mm512_set1_ps(Q.inv_f), v2cut = _mm512_set1_ps(2.f * Q.cutoff);
    for (int64_t ch = 0; ch < C; ++ch) wk[ch] = _mm512_set1_ps(P.wk[ch]);
  }

  // VisLanes::add_entries_within: a lane's sums stop growing at its first entry beyond lim.
  DSS_AVX512 void add_entries_within(const __m512i* ie, const __m512* de, const __m512* re, const __m512* ge,
                                     int64_t e0, __mmask16 alive, __m512 lim, __m512& den, __m512& gn) const {
    const __m512i minus1 = _mm512_set1_epi32(-1);
    for (int64_t e = e0; e < K; ++e) {
      alive = alive & _mm512_cmpgt_epi32_mask(ie[e], minus1) & _mm512_cmp_ps_mask(de[e], lim, _CMP_LE_OQ);
      den = _mm512_mask_add_ps(den, alive, den, re[e]);
      gn = _mm512_mask_add_ps(gn, alive, gn, _mm512_mul_ps(re[e], ge[e]));
    }
  }

  // Cases (a)/(b), vis_state: k's tangent-plane depth at the pixels, clamped to kMaxSlope (the
  // square root only where it applies); (dxp, dyp) = pixel centre - (u, v).
  DSS_AVX512 __m512 plane_depth(__m512 px, __m512 vpy, __m512 dxp, __m512 dyp) const {
    const __m512 zero = _mm512_setzero_ps(), one = _mm512_set1_ps(1.f);
    const __m512 iz = _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(pl0, px), _mm512_mul_ps(pl1, vpy)), pl2);
    __m512 zq = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(iz, zero, _CMP_GT_OQ), vz, _mm512_div_ps(one, iz));
    const __m512 d2 = _mm512_add_ps(_mm512_mul_ps(dxp, dxp), _mm512_mul_ps(dyp, dyp));
    const __m512 dz = _mm512_sub_ps(zq, vz);
    const __mmask16 cl = _mm512_cmp_ps_mask(_mm512_mul_ps(dz, dz), _mm512_mul_ps(vslope2, d2), _CMP_GT_OQ);
    if (cl) {
      const __m512 dmax = _mm512_mul_ps(vslope, _mm512_sqrt_ps(d2));
      const __m512 lo = _mm512_sub_ps(vz, dmax), hi = _mm512_add_ps(vz, dmax);
      const __m512 mx = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(zq, lo, _CMP_LT_OQ), zq, lo);
      const __m512 mn = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(hi, mx, _CMP_LT_OQ), mx, hi);
      zq = _mm512_mask_blend_ps(cl, zq, mn);
    }
    return zq;
  }

  // Cases (a)/(b): den, gn of the visible set with k added at plane depth zq, but for the cache
  // entries where k becomes the front: the lanes returned, whose entries within zq + T the caller
  // adds (add_entries_within); k1: the case (b) lanes.
  template <class Addr>
  DSS_AVX512 __mmask16 ab_sums(const Addr& a, __m512 zq, __m512 d0, __m512 d0m, __m512 r1, __m512 r2,
                               __mmask16 empty, __mmask16& k1, __m512& den, __m512& gn) const {
    k1 = ~empty & _mm512_cmp_ps_mask(zq, d0m, _CMP_NLE_UQ);
    __m512 gw = _mm512_setzero_ps();
    for (int64_t ch = 0; ch < C; ++ch) gw = _mm512_add_ps(gw, _mm512_mul_ps(a.ld(R->plane(R->fG(ch))), wk[ch]));
    den = vnk, gn = _mm512_mul_ps(vnk, gw);
    const __mmask16 mall = k1 | _mm512_cmp_ps_mask(zq, d0, _CMP_GE_OQ);
    den = _mm512_mask_add_ps(den, mall, den, r1);
    gn = _mm512_mask_add_ps(gn, mall, gn, r2);
    return ~(mall | empty);
  }

  // Cases (a)/(b)'s step towards the pixel's ray ((b), lanes k1: onto the front surface d0): b =
  // (x, y, z) in the lanes of keep, +0 in the others.
  DSS_AVX512 void ab_step(__m512 gd, __mmask16 k1, __m512 zp, __m512 d0, __m512 px, __m512 vpy, __mmask16 keep,
                          __m512 b[3]) const {
    const __m512 zt = _mm512_mask_blend_ps(k1, zp, d0);
    const __m512 zt_f = _mm512_mul_ps(zt, vinvf);
    const __m512 mx = _mm512_sub_ps(_mm512_mul_ps(_mm512_sub_ps(px, vcx), zt_f), vX);
    const __m512 my = _mm512_sub_ps(_mm512_mul_ps(_mm512_sub_ps(vpy, vcy), zt_f), vY);
    const __m512 mz = _mm512_sub_ps(zt, zp);
    const __m512 nrm = _mm512_add_ps(
        _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(mx, mx), _mm512_mul_ps(my, my)), _mm512_mul_ps(mz, mz)), veps);
    const __m512 coef = _mm512_div_ps(gd, nrm);
    b[0] = _mm512_maskz_mul_ps(keep, coef, mx);
    b[1] = _mm512_maskz_mul_ps(keep, coef, my);
    b[2] = _mm512_maskz_mul_ps(keep, coef, mz);
  }

  // The evaluations of one window row (lanes in oki); (px, py) the pixel centres. Comments on
  // the cases: VisLanes::eval and vis_state.
  template <class Addr>
  DSS_AVX512 void eval(const Addr& a, __mmask16 oki, __m512 px, __m512 vpy, VisRowOut16& out) const {
    const __m512 zero = _mm512_setzero_ps(), one = _mm512_set1_ps(1.f);
    out.any = false;
    const __mmask16 m = _mm512_mask_cmp_ps_mask(oki, a.ld(R->plane(Rec::kNZ)), zero, _CMP_NEQ_UQ);
    if (m == 0) return;
    const __m512 d0 = a.ld(R->plane(Rec::kD0)), r1 = a.ld(R->plane(Rec::kDen)), r2 = a.ld(R->plane(Rec::kGn));
    const __m512 d0m = _mm512_add_ps(d0, vmerge);
    __m512i ie[8];
    __m512 de[8], re[8], ge[8];
    __mmask16 found = 0, ek0 = 0;
    __m512 pdk = zero, prk = zero, pgk = zero;
    for (int64_t e = 0; e < K; ++e) {
      ie[e] = a.ldi(R->idx_plane(e));
      de[e] = a.ld(R->plane(R->fDep(e)));
      re[e] = a.ld(R->plane(R->fRho(e)));
      ge[e] = a.ld(R->plane(R->fGw(e)));
      const __mmask16 me = _mm512_cmpeq_epi32_mask(ie[e], vk);
      if (e == 0) ek0 = me;
      found |= me;
      pdk = _mm512_mask_blend_ps(me, pdk, de[e]);
      prk = _mm512_mask_blend_ps(me, prk, re[e]);
      pgk = _mm512_mask_blend_ps(me, pgk, ge[e]);
    }
    const __mmask16 kvis = found & _mm512_cmp_ps_mask(pdk, d0m, _CMP_LE_OQ);
    const __mmask16 empty = _mm512_cmplt_epi32_mask(ie[0], _mm512_setzero_si512());
    __m512 den = zero, gn = zero, zp = vz;
    __mmask16 kase1 = 0;
    const __m512 dxp = _mm512_sub_ps(px, vu), dyp = _mm512_sub_ps(vpy, vv);
    if (m & kvis) {
      __m512 den_a = _mm512_sub_ps(r1, prk);
      const __m512 gn_a = _mm512_sub_ps(r2, _mm512_mul_ps(prk, pgk));
      den_a = _mm512_maskz_mov_ps(_mm512_cmp_ps_mask(den_a, zero, _CMP_GT_OQ), den_a);
      __m512 den_b = zero, gn_b = zero;
      if (K > 1 && (ek0 & kvis & m))  // (only where k was the front)
        add_entries_within(ie, de, re, ge, 1, (__mmask16)0xFFFF, _mm512_add_ps(de[1], vmerge), den_b, gn_b);
      den = _mm512_mask_blend_ps(ek0, den_a, den_b);
      gn = _mm512_mask_blend_ps(ek0, gn_a, gn_b);
    }
    if (m & ~kvis) {
      const __m512 zq = plane_depth(px, vpy, dxp, dyp);
      __mmask16 k1;
      __m512 den_n, gn_n;
      const __mmask16 alive = ab_sums(a, zq, d0, d0m, r1, r2, empty, k1, den_n, gn_n);
      if (alive) add_entries_within(ie, de, re, ge, 0, alive, _mm512_add_ps(zq, vmerge), den_n, gn_n);
      den = _mm512_mask_blend_ps(kvis, den_n, den);
      gn = _mm512_mask_blend_ps(kvis, gn_n, gn);
      zp = zq;
      kase1 = k1;
    }
    const __m512 gsel = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(den, zero, _CMP_GT_OQ), a.ld(R->plane(Rec::kGb)),
                                             _mm512_div_ps(gn, den));
    const __m512 gd = _mm512_sub_ps(gsel, a.ld(R->plane(Rec::kGi)));
    const __mmask16 act = m & _mm512_cmp_ps_mask(gd, zero, _CMP_LT_OQ);
    __mmask16 act_v = act & kvis;
    const __mmask16 act_n = act & ~kvis;
    __m512 c[2][2] = {{zero, zero}, {zero, zero}}, b[3] = {zero, zero, zero};
    if (act_v) {
      const __m512 sd = _mm512_sqrt_ps(_mm512_add_ps(_mm512_mul_ps(dxp, dxp), _mm512_mul_ps(dyp, dyp)));
      act_v = act_v & _mm512_cmp_ps_mask(sd, _mm512_set1_ps(1e-6f), _CMP_NLT_UQ);
      const __m512 inv_sd = _mm512_div_ps(one, sd);
      const __m512 ux = _mm512_mul_ps(dxp, inv_sd), uy = _mm512_mul_ps(dyp, inv_sd);
      const __m512 qu = _mm512_add_ps(
          _mm512_add_ps(_mm512_mul_ps(_mm512_mul_ps(s2, ux), ux), _mm512_mul_ps(_mm512_mul_ps(s3, ux), uy)),
          _mm512_mul_ps(_mm512_mul_ps(s4, uy), uy));
      const __m512 tiny = _mm512_set1_ps(1e-20f);
      const __m512 qm = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(qu, tiny, _CMP_LT_OQ), qu, tiny);
      const __m512 rr = _mm512_sqrt_ps(_mm512_div_ps(v2cut, qm));
      __m512 t = _mm512_sub_ps(rr, sd);
      t = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(t, zero, _CMP_LT_OQ), t, zero);
      const __m512 steps[2] = {_mm512_xor_ps(t, _mm512_set1_ps(-0.f)), _mm512_add_ps(rr, sd)};
      for (int mm = 0; mm < 2; ++mm) {
        const __m512 mx = _mm512_mul_ps(_mm512_mul_ps(steps[mm], ux), vzf);
        const __m512 my = _mm512_mul_ps(_mm512_mul_ps(steps[mm], uy), vzf);
        const __m512 coef =
            _mm512_div_ps(gd, _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(mx, mx), _mm512_mul_ps(my, my)), veps));
        c[mm][0] = _mm512_mul_ps(coef, mx);
        c[mm][1] = _mm512_mul_ps(coef, my);
      }
    }
    if (act_n) ab_step(gd, kase1, zp, d0, px, vpy, act_n, b);
    const __mmask16 act_any = act_v | act_n;
    out.x1 = _mm512_maskz_mov_ps(act_any, _mm512_mask_blend_ps(kvis, b[0], c[0][0]));
    out.y1 = _mm512_maskz_mov_ps(act_any, _mm512_mask_blend_ps(kvis, b[1], c[0][1]));
    out.x2 = _mm512_maskz_mov_ps(act_v, c[1][0]);
    out.y2 = _mm512_maskz_mov_ps(act_v, c[1][1]);
    out.z = _mm512_maskz_mov_ps(act_n, b[2]);
    out.any = act_any != 0;
    out.any_c = act_v != 0;
  }
  // eval for a row in none of whose evaluated pixels k is cached (82% of the rows of a 20K-point
  // step: a point is cached at about 3 pixels around its centre; the record build flags the
  // others, visibility_backward's krows): found is 0 in every lane, so every lane takes case (a)
  // or (b), and the cache entries are read only where k becomes the front. The same operations
  // in the same order as eval's for such lanes, so the same bits (tests compare every level with
  // the scalar path). It costs about a third of eval (eval rows 6.6 ms, these 8.9 ms for 4.5
  // times as many, at 20K points).
  template <class Addr>
  DSS_AVX512 void eval_nok(const Addr& a, __mmask16 oki, __m512 px, __m512 vpy, VisRowOut16& out) const {
    const __m512 zero = _mm512_setzero_ps();
    out.any = false;
    out.any_c = false;
    const __mmask16 m = _mm512_mask_cmp_ps_mask(oki, a.ld(R->plane(Rec::kNZ)), zero, _CMP_NEQ_UQ);
    if (m == 0) return;
    const __m512 d0 = a.ld(R->plane(Rec::kD0)), r1 = a.ld(R->plane(Rec::kDen)), r2 = a.ld(R->plane(Rec::kGn));
    const __m512 d0m = _mm512_add_ps(d0, vmerge);
    const __mmask16 empty = _mm512_cmplt_epi32_mask(a.ldi(R->idx_plane(0)), _mm512_setzero_si512());
    const __m512 dxp = _mm512_sub_ps(px, vu), dyp = _mm512_sub_ps(vpy, vv);
    const __m512 zq = plane_depth(px, vpy, dxp, dyp);
    __mmask16 k1;
    __m512 den, gn;
    const __mmask16 alive = ab_sums(a, zq, d0, d0m, r1, r2, empty, k1, den, gn);
    if (alive) {  // k becomes the front: entries beyond zp + T drop out
      __m512i ie[8];
      __m512 de[8], re[8], ge[8];
      for (int64_t e = 0; e < K; ++e) {
        ie[e] = a.ldi(R->idx_plane(e));
        de[e] = a.ld(R->plane(R->fDep(e)));
        re[e] = a.ld(R->plane(R->fRho(e)));
        ge[e] = a.ld(R->plane(R->fGw(e)));
      }
      add_entries_within(ie, de, re, ge, 0, alive, _mm512_add_ps(zq, vmerge), den, gn);
    }
    const __m512 gsel = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(den, zero, _CMP_GT_OQ), a.ld(R->plane(Rec::kGb)),
                                             _mm512_div_ps(gn, den));
    const __m512 gd = _mm512_sub_ps(gsel, a.ld(R->plane(Rec::kGi)));
    const __mmask16 act = m & _mm512_cmp_ps_mask(gd, zero, _CMP_LT_OQ);
    __m512 b[3];
    ab_step(gd, k1, zq, d0, px, vpy, act, b);
    out.x1 = b[0];
    out.y1 = b[1];
    out.z = b[2];
    out.any = true;  // (act may be 0: adding +0 changes no partial)
  }
};

// The window of half size w (9 <= 2 w + 1 <= 15 columns) of the point P centred on pixel (ic, jc),
// its rows on the image one vector each; adds the window's partial sums to acc in partial order.
// krows[r] (r = 0 .. 2 w): non-zero if P's point is cached at some evaluated pixel of window row
// r (VisLanes16::eval), zero if not (VisLanes16::eval_nok).
template <int64_t KC, int64_t CC>
DSS_AVX512 void window_rows_avx512(const VisRecord<true, KC, CC>& rec, int64_t Krt, int64_t Crt, const VisPoint& P,
                                   const VisConsts& Q, int64_t H, int64_t W, int64_t window, int ic, int jc,
                                   const uint8_t* krows, double acc[3]) {
  VisLanes16<KC, CC> L;
  L.init(rec, Krt, Crt, P, Q);
  const int n = (int)(2 * window + 1), j0 = jc - (int)window;
  const int nq = dss_splat::vis_partial_count(window);  // = n: partial q is column q
  const __m512i vj = _mm512_add_epi32(_mm512_set1_epi32(j0),
                                      _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15));
  const __m512 px = _mm512_add_ps(_mm512_cvtepi32_ps(vj), _mm512_set1_ps(0.5f));
  VisRow16 a;
  // the window's columns on the image
  a.oki = (__mmask16)((1u << n) - 1u) & _mm512_cmpgt_epi32_mask(vj, _mm512_set1_epi32(-1)) &
          _mm512_cmpgt_epi32_mask(_mm512_set1_epi32((int)W), vj);
  a.masked = !(j0 >= 0 && j0 + n <= W);
  // partials 0-7 and 8-15 as doubles, lane l = column l
  __m512d sx[2] = {_mm512_setzero_pd(), _mm512_setzero_pd()}, sy[2] = {sx[0], sx[0]}, sz[2] = {sx[0], sx[0]};
  auto add = [&](__m512d* sum, __m512 x) DSS_AVX512 {
    sum[0] = _mm512_add_pd(sum[0], _mm512_cvtps_pd(_mm512_castps512_ps256(x)));
    sum[1] = _mm512_add_pd(sum[1], _mm512_cvtps_pd(_mm512_extractf32x8_ps(x, 1)));
  };
  VisRowOut16 o;
  for (int i = std::max(ic - (int)window, 0); i <= std::min(ic + (int)window, (int)H - 1); ++i) {
    a.p0 = (int64_t)i * W + j0;
    if (krows[i - (ic - (int)window)])
      L.eval(a, a.oki, px, _mm512_set1_ps((float)i + 0.5f), o);
    else
      L.eval_nok(a, a.oki, px, _mm512_set1_ps((float)i + 0.5f), o);
    if (!o.any) continue;
    // eval_scalar's order per pixel: (x1, y1), then (x2, y2, z); x2 and y2 only where some lane
    // took case (c), a minority of the rows (the other lanes hold +0, and adding +0 to a
    // partial, which is never -0, leaves it unchanged)
    add(sx, o.x1);
    add(sy, o.y1);
    if (o.any_c) {
      add(sx, o.x2);
      add(sy, o.y2);
    }
    add(sz, o.z);
  }
  alignas(64) double lanes[3][16];
  _mm512_store_pd(lanes[0], sx[0]), _mm512_store_pd(lanes[0] + 8, sx[1]);
  _mm512_store_pd(lanes[1], sy[0]), _mm512_store_pd(lanes[1] + 8, sy[1]);
  _mm512_store_pd(lanes[2], sz[0]), _mm512_store_pd(lanes[2] + 8, sz[1]);
  for (int q = 0; q < nq; ++q)  // add_partials' order, read from the lanes in place
    for (int c = 0; c < 3; ++c) acc[c] += lanes[c][q];
}
#endif

}  // namespace
}  // namespace dss_cpu
