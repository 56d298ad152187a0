// The rasteriser's AVX2 and AVX-512 code (rasterize_cpu.cpp takes it where the CPU has the
// instructions, vector level 1 or 2): the binning's box scan, the tile loop's fragment gate and
// top-K insertion for 8 or 16 pixels at once, and the cache's streaming write-out. Every function
// gives the scalar loop's bits (tests/test_render_forward.py compares every vector level).
#pragma once

#include "cpu_common.h"
#include "rasterize_cpu.h"

namespace dss_cpu {
namespace {

#ifdef DSS_HAVE_AVX2
DSS_AVX2 void scan_boxes_avx2(const float* P, int n, int H, int W, float cutoff, ScanBlock& o) {
  scan_boxes<true>(P, n, H, W, cutoff, o);
}
DSS_AVX512 void scan_boxes_avx512(const float* P, int n, int H, int W, float cutoff, ScanBlock& o) {
  scan_boxes<true>(P, n, H, W, cutoff, o);
}
#endif

#ifdef DSS_HAVE_AVX2
// Streaming (non-temporal) copy of n bytes from an aligned local buffer: 32-byte stores that
// bypass the caches where dst is 32-byte aligned, ordinary stores for the rest.
DSS_AVX2 void stream_bytes(void* dst, const void* src, size_t n) {
  char* d = static_cast<char*>(dst);
  const char* s = static_cast<const char*>(src);
  size_t head = (32 - (reinterpret_cast<uintptr_t>(d) & 31)) & 31;
  head = std::min(head, n);
  std::memcpy(d, s, head);
  size_t k = head;
  for (; k + 32 <= n; k += 32)
    _mm256_stream_si256(reinterpret_cast<__m256i*>(d + k), _mm256_loadu_si256(reinterpret_cast<const __m256i*>(s + k)));
  std::memcpy(d + k, s + k, n - k);
}
#endif

#ifdef DSS_HAVE_AVX2
// insert_fragment without its shifting loop, for K <= 8 (the caller's checks as there): the
// fragment's place is the number of the first n entries it does not sort before (n = c, or K - 1
// when the list is full: the last entry drops out), the entries from there on move one slot up
// through a lane permutation, and the K slots are written back. The same list as
// insert_fragment's, since a list is sorted and "sorts before" holds for a suffix of it; one
// mispredicted loop exit per insertion fewer (the loop ran 0-4 times, unpredictably).
// pi/pd: the pixel's K index and depth slots; pr/pn: two values carried along with each entry
// (r and nv for the new one; the tile loop's -q/2 and splat norm). Each is readable 8 values on
// (the tile lists' padding).
template <int64_t KC>
DSS_AVX2 inline int insert_fragment_avx2(int32_t* pi, float* pd, float* pr, float* pn, int c, int64_t Krt, int32_t k,
                                         float zk, float r, float nv) {
  const int K = KC > 0 ? (int)KC : (int)Krt;
  const int n = c == K ? K - 1 : c;
  const __m256 d = _mm256_loadu_ps(pd);
  const __m256i id = _mm256_loadu_si256((const __m256i*)pi);
  const __m256 vz = _mm256_set1_ps(zk);
  const __m256 before = _mm256_or_ps(
      _mm256_cmp_ps(vz, d, _CMP_LT_OQ),
      _mm256_and_ps(_mm256_cmp_ps(vz, d, _CMP_EQ_OQ), _mm256_castsi256_ps(_mm256_cmpgt_epi32(id, _mm256_set1_epi32(k)))));
  const unsigned first_n = (1u << n) - 1u;
  const int pos = n - __builtin_popcount((unsigned)_mm256_movemask_ps(before) & first_n);
  const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7), vpos = _mm256_set1_epi32(pos);
  // lane l takes l below pos, the new fragment at pos, l - 1 above
  const __m256i from = _mm256_add_epi32(lane, _mm256_cmpgt_epi32(lane, vpos));
  const __m256 at = _mm256_castsi256_ps(_mm256_cmpeq_epi32(lane, vpos));
  const __m256 nd = _mm256_blendv_ps(_mm256_permutevar8x32_ps(d, from), vz, at);
  const __m256 ni = _mm256_blendv_ps(_mm256_castsi256_ps(_mm256_permutevar8x32_epi32(id, from)),
                                     _mm256_castsi256_ps(_mm256_set1_epi32(k)), at);
  const __m256 nr = _mm256_blendv_ps(_mm256_permutevar8x32_ps(_mm256_loadu_ps(pr), from), _mm256_set1_ps(r), at);
  const __m256 nn = _mm256_blendv_ps(_mm256_permutevar8x32_ps(_mm256_loadu_ps(pn), from), _mm256_set1_ps(nv), at);
  if (K == 5) {
    // (four lanes and one: the slots after the fifth belong to the next pixel)
    _mm_storeu_ps(pd, _mm256_castps256_ps128(nd));
    _mm_storeu_ps((float*)pi, _mm256_castps256_ps128(ni));
    _mm_storeu_ps(pr, _mm256_castps256_ps128(nr));
    _mm_storeu_ps(pn, _mm256_castps256_ps128(nn));
    _mm_store_ss(pd + 4, _mm256_extractf128_ps(nd, 1));
    _mm_store_ss((float*)pi + 4, _mm256_extractf128_ps(ni, 1));
    _mm_store_ss(pr + 4, _mm256_extractf128_ps(nr, 1));
    _mm_store_ss(pn + 4, _mm256_extractf128_ps(nn, 1));
  } else {
    const __m256i keep = _mm256_cmpgt_epi32(_mm256_set1_epi32(K), lane);
    _mm256_maskstore_ps(pd, keep, nd);
    _mm256_maskstore_ps((float*)pi, keep, ni);
    _mm256_maskstore_ps(pr, keep, nr);
    _mm256_maskstore_ps(pn, keep, nn);
  }
  return c == K ? K : c + 1;
}

// Bit l: pixel l of 8 takes the fragment (depth z, index k, quadratic form q): inside the cutoff
// ellipse (0.5 q <= cutoff) and through the top-K gate (its list is open, i.e. not full, or the
// fragment sorts before the list's last entry (gd, gi)).
DSS_AVX2 inline unsigned fragment_gate(__m256 q, __m256 vcut, __m256 vz, __m256i vk, const float* gd,
                                       const int32_t* gi, const int32_t* gopen) {
  const __m256 in = _mm256_cmp_ps(_mm256_mul_ps(_mm256_set1_ps(0.5f), q), vcut, _CMP_LE_OQ);
  const __m256 d = _mm256_loadu_ps(gd);
  const __m256i id = _mm256_loadu_si256((const __m256i*)gi);
  const __m256 open = _mm256_castsi256_ps(_mm256_loadu_si256((const __m256i*)gopen));
  const __m256 before = _mm256_or_ps(
      _mm256_cmp_ps(vz, d, _CMP_LT_OQ),
      _mm256_and_ps(_mm256_cmp_ps(vz, d, _CMP_EQ_OQ), _mm256_castsi256_ps(_mm256_cmpgt_epi32(id, vk))));
  return (unsigned)_mm256_movemask_ps(_mm256_and_ps(in, _mm256_or_ps(before, open)));
}

// One tile's fragments, a tile row (16 pixels) per two AVX2 vectors, or per one vector of the 8
// columns from the box's first when the box is at most 8 columns wide: the cutoff test
// (0.5 q <= cutoff, q evaluated with the scalar loop's float32 operations in the same order) and
// the top-K gate (the pixel's list is not full, or the fragment sorts before its last entry) for
// 8 or 16 pixels at once, so only fragments that enter a list reach a branch. The gate is kept per
// pixel in three planes (open, the last entry's depth and index). The lists equal the scalar
// loop's bit for bit: a list's content does not depend on the order fragments arrive in, and rho
// comes from the scalar loop's operations (norm times splat_exp of -q/2), only later.
// li/ld/lr: (256, K) per-pixel lists, cnt: (256,) counts, all of the tile; lr holds -q/2 while
// the fragments are inserted and rho on return.
template <int64_t KC>
DSS_AVX2 void tile_fragments_avx2(const Frag* bin, int64_t n_bin, int ti0, int tj0, int tj1,
                                  int64_t Krt, float cutoff, int32_t* li, float* ld, float* lr, int* cnt) {
  const int64_t K = KC > 0 ? KC : Krt;
  // (8 values of padding: a window of 8 columns from column j0 > 8 of the last row reads past it)
  alignas(32) float gd[kTile * kTile + 8];
  alignas(32) int32_t gi[kTile * kTile + 8], gopen[kTile * kTile + 8];
  // -q/2 at the pixels of the fragment's rows (read only where its gate let it through), and the
  // norm of the splat in each list slot: the slots' rho = norm exp(-q/2) is evaluated once the
  // tile is done, 8 slots per vector, instead of one vector exp per tile row a fragment enters
  alignas(32) float xs[kTile * kTile + 8];
  alignas(32) float ln[kTile * kTile * 8];
  std::fill_n(ln, kTile * kTile * K, 0.f);
  // Columns beyond the image are never tested: closed, at -inf.
  const int nw = tj1 - tj0 + 1;
  for (int p = 0; p < kTile * kTile + 8; ++p) {
    const bool in = p < kTile * kTile && p % kTile < nw;
    gd[p] = in ? std::numeric_limits<float>::infinity() : -std::numeric_limits<float>::infinity();
    gi[p] = 0;
    gopen[p] = in ? -1 : 0;
  }
  const __m256 half = _mm256_set1_ps(0.5f), mhalf = _mm256_set1_ps(-0.5f), vcut = _mm256_set1_ps(cutoff);
  const __m256 col0 = _mm256_add_ps(_mm256_cvtepi32_ps(_mm256_setr_epi32(tj0, tj0 + 1, tj0 + 2, tj0 + 3, tj0 + 4,
                                                                          tj0 + 5, tj0 + 6, tj0 + 7)), half);
  const __m256 col1 = _mm256_add_ps(_mm256_cvtepi32_ps(_mm256_setr_epi32(tj0 + 8, tj0 + 9, tj0 + 10, tj0 + 11,
                                                                          tj0 + 12, tj0 + 13, tj0 + 14, tj0 + 15)), half);
  for (int64_t e = 0; e < n_bin; ++e) {
    const Frag& f = bin[e];
    const int32_t k = f.k;
    const float* s = &f.u;  // s[0..4]: u, v, a, b2, c as in the packed row
    const int r0 = f.i0, r1 = f.i1;  // the box's rows in the tile
    const float zk = f.z;
    const __m256 vz = _mm256_set1_ps(zk);
    const __m256i vk = _mm256_set1_epi32(k);
    // First every row's tests, into one bit per pixel of the tile (tile row r: bits 16 (r % 4) on
    // of word r / 4), with no branch on their outcome; then the pixels that took the fragment, in
    // one loop over the set bits. (Row by row, with a branch on each row's tests and a loop over
    // each row's bits, a fragment cost a mispredicted branch or two per row.) The rows' tests do
    // not depend on each other: the fragment enters distinct pixels.
    uint64_t take[4] = {0, 0, 0, 0};
    // q = ((a dx) dx + (b2 dx) dy) + (c dy) dy: the first term and b2 dx depend on the column only
    const __m256 va = _mm256_set1_ps(s[2]), vb = _mm256_set1_ps(s[3]), vu = _mm256_set1_ps(s[0]);
    if (f.j1 - f.j0 < 8) {
      // Columns j0 .. j1 fit in one vector of 8 from j0 (most boxes: 3.4 columns per tile row
      // at 20K points): one gate per row instead of two. The column centres are col0 + j0,
      // exact in float, so q has the same bits as in the two-vector path.
      const int j0 = f.j0;
      const unsigned colw = (2u << (f.j1 - j0)) - 1u;
      const __m256 dx = _mm256_sub_ps(_mm256_add_ps(col0, _mm256_set1_ps((float)j0)), vu);
      const __m256 t1 = _mm256_mul_ps(_mm256_mul_ps(va, dx), dx), bx = _mm256_mul_ps(vb, dx);
      for (int rr = r0; rr <= r1; ++rr) {
        const float dy = ((float)(ti0 + rr) + 0.5f) - s[1];
        const __m256 q = _mm256_add_ps(_mm256_add_ps(t1, _mm256_mul_ps(bx, _mm256_set1_ps(dy))),
                                       _mm256_set1_ps(s[4] * dy * dy));
        const int r = rr * kTile;
        const unsigned m = fragment_gate(q, vcut, vz, vk, gd + r + j0, gi + r + j0, gopen + r + j0) & colw;
        _mm256_storeu_ps(xs + r + j0, _mm256_mul_ps(mhalf, q));
        take[rr >> 2] |= (uint64_t)(m << j0) << ((rr & 3) * kTile);
      }
    } else {
      const unsigned cols = ((2u << f.j1) - 1u) & ~((1u << f.j0) - 1u);
      const __m256 dx0 = _mm256_sub_ps(col0, vu), dx1 = _mm256_sub_ps(col1, vu);
      const __m256 t10 = _mm256_mul_ps(_mm256_mul_ps(va, dx0), dx0), t11 = _mm256_mul_ps(_mm256_mul_ps(va, dx1), dx1);
      const __m256 bx0 = _mm256_mul_ps(vb, dx0), bx1 = _mm256_mul_ps(vb, dx1);
      for (int rr = r0; rr <= r1; ++rr) {
        const float dy = ((float)(ti0 + rr) + 0.5f) - s[1];
        const __m256 vdy = _mm256_set1_ps(dy), t3 = _mm256_set1_ps(s[4] * dy * dy);
        const __m256 q0 = _mm256_add_ps(_mm256_add_ps(t10, _mm256_mul_ps(bx0, vdy)), t3);
        const __m256 q1 = _mm256_add_ps(_mm256_add_ps(t11, _mm256_mul_ps(bx1, vdy)), t3);
        const int r = rr * kTile;
        const unsigned m = (fragment_gate(q0, vcut, vz, vk, gd + r, gi + r, gopen + r) |
                            (fragment_gate(q1, vcut, vz, vk, gd + r + 8, gi + r + 8, gopen + r + 8) << 8)) & cols;
        _mm256_store_ps(xs + r, _mm256_mul_ps(mhalf, q0));
        _mm256_store_ps(xs + r + 8, _mm256_mul_ps(mhalf, q1));
        take[rr >> 2] |= (uint64_t)m << ((rr & 3) * kTile);
      }
    }
    // The fragment enters pixel p's list; a list that fills closes its pixel's gate.
    for (int w = r0 >> 2; w <= (r1 >> 2); ++w) {
      for (uint64_t b = take[w]; b; b &= b - 1) {
        const int p = w * 64 + __builtin_ctzll(b);
        int32_t* pi = li + p * K;
        float* pd = ld + p * K;
        const int c = insert_fragment_avx2<KC>(pi, pd, lr + p * K, ln + p * K, cnt[p], K, k, zk, xs[p], f.norm);
        cnt[p] = c;
        if (c == K) {
          gopen[p] = 0;
          gd[p] = pd[K - 1];
          gi[p] = pi[K - 1];
        }
      }
    }
  }
  // rho = norm exp(-q/2) in every slot (empty ones: 0 exp(0) = 0), the scalar loop's operations
  for (int64_t e = 0; e < kTile * kTile * K; e += 8)
    _mm256_store_ps(lr + e, _mm256_mul_ps(_mm256_load_ps(ln + e), splat_exp_avx2(_mm256_load_ps(lr + e))));
}
#endif

}  // namespace
}  // namespace dss_cpu
