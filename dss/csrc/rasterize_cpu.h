// The rasteriser's tile records and the binning's first pass (rasterize_cpu.cpp; the AVX2 and
// AVX-512 builds of the pass are in rasterize_cpu_avx2.h).
#pragma once

#include "cpu_common.h"

namespace dss_cpu {
namespace {

constexpr int kTile = 16;
constexpr int kDepthBuckets = 1024;

// One splat in one tile's bin: what the tile loop reads of it, in one record so that a tile
// streams through its bin instead of gathering each splat's row of the packed array and its box
// (scattered over ~1 MB per view: an L2 miss each). u..c are the packed fields 0-4 in their
// order (quad() reads them), norm and z the fields 5 and 6, k the splat index; the rows and
// columns the splat's box covers in this tile, relative to the tile's corner.
struct Frag {
  float u, v, a, b2, c, norm, z;
  int32_t k;
  uint8_t i0, i1, j0, j1;
};

// A splat the binning draws: its record (tile fields unset) and its box.
struct Drawn {
  Frag f;
  Box b;
};

using dss_splat::splat_box;  // shared with the CUDA kernel

// The binning's first pass over one view's splats, kScanBlock at a time: each splat's box
// (splat_box, then tighten_box) and whether it is drawn (valid, centre and extent not NaN, a box
// left on screen), in straight-line code that the compiler vectorises; the caller then takes the
// drawn ones. (One splat at a time, with branches, the pass took about 2.2 of the rasteriser's
// 11.6 ms at 20K points.) A NaN row's fields are replaced by zeros first, so that no float-to-int
// conversion sees a NaN; it is not drawn.
constexpr int kScanBlock = 64;
struct ScanBlock {
  alignas(32) int j0[kScanBlock], j1[kScanBlock], i0[kScanBlock], i1[kScanBlock], drawn[kScanBlock];
};

template <bool kVec>
DSS_INLINE void scan_boxes(const float* P, int n, int H, int W, float cutoff, ScanBlock& o) {
  static_assert(kScanBlock == 64, "rows_to_planes writes planes of 64");
  alignas(32) float f[kFields][kScanBlock];  // the rows transposed: the vector loop reads planes
  rows_to_planes<kVec>(P, n, 0, kFields, f);
  // (no "omp simd" here: with it GCC 12 finds no vector type for the planes' loads and leaves the
  // loop scalar; without it the loop vectorises, for AVX2 with vroundps for floor and ceil)
  for (int j = 0; j < n; ++j) {
    const bool fin = !std::isnan(f[0][j] + f[1][j] + f[7][j] + f[8][j]);
    const float u = fin ? f[0][j] : 0.f, v = fin ? f[1][j] : 0.f;
    Box b = splat_box(u, v, fin ? f[7][j] : 0.f, fin ? f[8][j] : 0.f, H, W);
    const bool on = (b.j0 <= b.j1) & (b.i0 <= b.i1);
    const bool left = dss_splat::tighten_box(u, v, f[2][j], f[3][j], f[4][j], cutoff, b.j0, b.j1, b.i0, b.i1);
    o.j0[j] = b.j0;
    o.j1[j] = b.j1;
    o.i0[j] = b.i0;
    o.i1[j] = b.i1;
    o.drawn[j] = (f[9][j] > 0.f) & fin & on & left;
  }
}

// Inserts fragment (k, zk, rho) into pixel p's top-K list (sorted by (depth, index), c entries);
// the caller has checked that it belongs there (the list is not full, or k sorts before its
// last entry). Returns the new count.
inline int insert_fragment(int32_t* pi, float* pd, float* pr, int c, int64_t K, int32_t k, float zk, float r) {
  const int n = c == K ? (int)K : c + 1;
  int pos = c == K ? (int)K - 1 : c;
  while (pos > 0 && (zk < pd[pos - 1] || (zk == pd[pos - 1] && k < pi[pos - 1]))) {
    pi[pos] = pi[pos - 1];
    pd[pos] = pd[pos - 1];
    pr[pos] = pr[pos - 1];
    --pos;
  }
  pi[pos] = k;
  pd[pos] = zk;
  pr[pos] = r;
  return n;
}

}  // namespace
}  // namespace dss_cpu
