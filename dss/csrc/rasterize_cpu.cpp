// The rasteriser on the CPU (paper Eqs. rk, rho, sumI): splats binned into 16x16 screen tiles,
// each tile's per-pixel top-K lists, the cache written out and the visible entries blended.
#include "cpu_common.h"
#include "dss_cpu.h"
#include "rasterize_cpu_avx2.h"
#include "rasterize_cpu.h"

using namespace dss_cpu;

// Forward: top-K cache per pixel and (optionally) the blended image.
// packed (V,N,10) f32, attrs (V,N,C) f32 or empty, background (C) f32.
std::vector<torch::Tensor> rasterize_forward(torch::Tensor packed, torch::Tensor attrs, int64_t H, int64_t W,
                                             int64_t K, double cutoff_d, double merge_d, torch::Tensor background) {
  TORCH_CHECK(packed.dim() == 3 && packed.size(2) == kFields, "packed splats must be (V,N,10)");
  packed = packed.contiguous().to(torch::kFloat32);
  const int64_t V = packed.size(0), N = packed.size(1);
  TORCH_CHECK(K >= 1 && K <= 8, "K must be in [1, 8]");
  const bool do_blend = attrs.numel() > 0;
  const int64_t C = do_blend ? attrs.size(2) : 0;
  TORCH_CHECK(C <= 16, "at most 16 channels");
  if (do_blend) {
    TORCH_CHECK(attrs.size(0) == V && attrs.size(1) == N, "attrs must be (V,N,C)");
    attrs = attrs.contiguous().to(torch::kFloat32);
    background = background.contiguous().to(torch::kFloat32);
    TORCH_CHECK(background.numel() == C, "background must have C entries");
  }
  const float cutoff = (float)cutoff_d, merge = (float)merge_d;
  auto fopt = torch::TensorOptions().dtype(torch::kFloat32);
  // every entry is written below (empty slots: -1, inf, 0), so pooled buffers need no fill
  auto idx = pooled_empty({V, H, W, K}, torch::kInt32);
  auto depth = pooled_empty({V, H, W, K}, torch::kFloat32);
  auto rho = pooled_empty({V, H, W, K}, torch::kFloat32);
  auto images = do_blend ? pooled_empty({V, H, W, C}, torch::kFloat32) : torch::empty({0}, fopt);
  auto mask = pooled_empty({V, H, W}, torch::kBool);

  const float* P = packed.data_ptr<float>();
  const int64_t TX = (W + kTile - 1) / kTile, TY = (H + kTile - 1) / kTile, T = TX * TY;

  // Bin splats into tiles (CSR per view: offsets, bins of Frag records).
  // Scratch kept per calling thread between calls (fresh pages cost more than the binning).
  // (References: the worker lambdas must see the calling thread's instances, not their own.)
  static thread_local std::vector<std::vector<int64_t>> offsets_tl;
  static thread_local std::vector<std::vector<Frag>> bins_tl;
  static thread_local std::vector<std::vector<Drawn>> drawn_tl;
  auto& offsets = offsets_tl;
  auto& bins = bins_tl;
  auto& drawn = drawn_tl;
  offsets.resize(V);
  bins.resize(V);
  drawn.resize(V);
  const bool vec = use_vector_path(), v512 = use_avx512();
  for (int64_t v = 0; v < V; ++v) offsets[v].assign(T + 1, 0);
  dynamic_for(V, 1, [&](int64_t v) {
    auto& off = offsets[v];
    // One pass over the view's packed rows: the splats that are drawn (valid, box on screen),
    // each with its record and box, and the number of tiles' bins each box reaches.
    auto& dr = drawn[v];
    dr.clear();
    float zlo = std::numeric_limits<float>::infinity(), zhi = -zlo;
    ScanBlock sb;
    for (int64_t k0 = 0; k0 < N; k0 += kScanBlock) {
      const int nb = (int)std::min<int64_t>(kScanBlock, N - k0);
      const float* Pb = P + (v * N + k0) * kFields;
#ifdef DSS_HAVE_AVX2
      if (v512)
        scan_boxes_avx512(Pb, nb, (int)H, (int)W, cutoff, sb);
      else if (vec)
        scan_boxes_avx2(Pb, nb, (int)H, (int)W, cutoff, sb);
      else
#endif
        scan_boxes<false>(Pb, nb, (int)H, (int)W, cutoff, sb);
      // the drawn ones through a bit mask (about half the rows are drawn, in runs: a branch per
      // row would be mispredicted often)
      uint64_t bits = 0;
      for (int j = 0; j < nb; ++j) bits |= (uint64_t)(sb.drawn[j] != 0) << j;
      const size_t d0 = dr.size();
      dr.resize(d0 + (size_t)__builtin_popcountll(bits));
      Drawn* out = dr.data() + d0;
      for (; bits; bits &= bits - 1) {
        const int j = __builtin_ctzll(bits);
        const float* s = Pb + j * kFields;
        const Box b{sb.j0[j], sb.j1[j], sb.i0[j], sb.i1[j]};
        *out++ = {{s[0], s[1], s[2], s[3], s[4], s[5], s[6], (int32_t)(k0 + j), 0, 0, 0, 0}, b};
        zlo = std::min(zlo, s[6]);
        zhi = std::max(zhi, s[6]);
        const int ty0 = b.i0 / kTile, ty1 = b.i1 / kTile, tx0 = b.j0 / kTile, tx1 = b.j1 / kTile;
        if (ty0 == ty1 && tx0 == tx1) {  // most boxes: one tile
          off[ty0 * TX + tx0 + 1]++;
          continue;
        }
        for (int ty = ty0; ty <= ty1; ++ty)
          for (int tx = tx0; tx <= tx1; ++tx) off[ty * TX + tx + 1]++;
      }
    }
    for (int64_t t = 0; t < T; ++t) off[t + 1] += off[t];
    bins[v].resize(off[T]);
    // Bins filled roughly front to back (splats counting-sorted into kDepthBuckets depth slabs):
    // once a pixel's list is full, most later fragments fail its top-K gate at once. The lists
    // do not depend on this order.
    const int64_t n = (int64_t)dr.size();
    std::vector<int32_t> cnt_z(kDepthBuckets + 1, 0), order(n);
    std::vector<uint16_t> bucket(n);
    const float zscale = zhi > zlo ? (float)(kDepthBuckets - 1) / (zhi - zlo) : 0.f;
    for (int64_t d = 0; d < n; ++d) {
      bucket[d] = (uint16_t)std::min<int>(kDepthBuckets - 1, std::max<int>(0, (int)((dr[d].f.z - zlo) * zscale)));
      cnt_z[bucket[d] + 1]++;
    }
    for (int z = 0; z < kDepthBuckets; ++z) cnt_z[z + 1] += cnt_z[z];
    for (int64_t d = 0; d < n; ++d) order[cnt_z[bucket[d]]++] = (int32_t)d;
    std::vector<int64_t> fill(off.begin(), off.end() - 1);
    Frag* bin = bins[v].data();
    for (const int32_t d : order) {
      const Box& b = dr[d].b;
      Frag f = dr[d].f;
      for (int ty = b.i0 / kTile; ty <= b.i1 / kTile; ++ty) {
        // the box's rows in this tile (the box is clamped to the image, so within the tile's)
        f.i0 = (uint8_t)(std::max(b.i0, ty * kTile) - ty * kTile);
        f.i1 = (uint8_t)(std::min(b.i1, ty * kTile + kTile - 1) - ty * kTile);
        for (int tx = b.j0 / kTile; tx <= b.j1 / kTile; ++tx) {
          f.j0 = (uint8_t)(std::max(b.j0, tx * kTile) - tx * kTile);
          f.j1 = (uint8_t)(std::min(b.j1, tx * kTile + kTile - 1) - tx * kTile);
          bin[fill[ty * TX + tx]++] = f;
        }
      }
    }
  });

  int32_t* I = idx.data_ptr<int32_t>();
  float* D = depth.data_ptr<float>();
  float* Rh = rho.data_ptr<float>();
  bool* Mk = mask.data_ptr<bool>();
  float* IMG = do_blend ? images.data_ptr<float>() : nullptr;
  const float* A = do_blend ? attrs.data_ptr<float>() : nullptr;
  const float* BG = do_blend ? background.data_ptr<float>() : nullptr;

  // The tile loop, compiled for the common (K, C) = (5, 3) and (5, 1) with constant trip counts
  // and for any (K, C) at run time (C = 0: no blending).
  const int64_t Krt = K, Crt = C;
  // a tile row of the background colour, and of empty cache slots (-1, inf, 0)
  std::vector<float> empty_bg(kTile * C);
  for (int64_t e = 0; e < kTile * C; ++e) empty_bg[e] = BG[e % C];
  alignas(32) int32_t empty_i[kTile * 8];
  alignas(32) float empty_d[kTile * 8], empty_r[kTile * 8];
  std::fill_n(empty_i, kTile * 8, -1);
  std::fill_n(empty_d, kTile * 8, std::numeric_limits<float>::infinity());
  std::fill_n(empty_r, kTile * 8, 0.f);
  auto tile_task = [&](auto KT, auto CT, int64_t item) {
    constexpr int64_t KC = decltype(KT)::value, CC = decltype(CT)::value;
    const int64_t K = KC > 0 ? KC : Krt, C = CC > 0 ? CC : Crt;
    const int64_t v = item / T, t = item % T;
    const int ty = (int)(t / TX), tx = (int)(t % TX);
    const int ti0 = ty * kTile, tj0 = tx * kTile;
    const int ti1 = std::min<int>((int)H, ti0 + kTile) - 1, tj1 = std::min<int>((int)W, tj0 + kTile) - 1;
    const auto& off = offsets[v];
    const int nwrt = tj1 - tj0 + 1;  // the tile's columns on the image
    // One tile row (pixels from g0 on) out: cache slots from si/sd/sr (nwrt * K values each) and,
    // where simg is given, the image row; with streaming stores on the vector path (the 47 MB
    // cache is not read back before it leaves the caches, so writing around them saves reading
    // every line first), plain copies elsewhere.
    auto put_row = [&](int64_t g0, const int32_t* si, const float* sd, const float* sr, const float* simg) {
#ifdef DSS_HAVE_AVX2
      if (vec) {
        stream_bytes(I + g0 * K, si, sizeof(int32_t) * nwrt * K);
        stream_bytes(D + g0 * K, sd, sizeof(float) * nwrt * K);
        stream_bytes(Rh + g0 * K, sr, sizeof(float) * nwrt * K);
        if (simg) stream_bytes(IMG + g0 * C, simg, sizeof(float) * nwrt * C);
        return;
      }
#endif
      std::copy_n(si, nwrt * K, I + g0 * K);
      std::copy_n(sd, nwrt * K, D + g0 * K);
      std::copy_n(sr, nwrt * K, Rh + g0 * K);
      if (simg) std::copy_n(simg, nwrt * C, IMG + g0 * C);
    };
    if (off[t + 1] == off[t]) {
      // No splat reaches the tile (most tiles: 83% at 20K points, 12 views of 256x256): empty
      // slots, the background and a false mask, row by row, without the lists and the tile loop.
      for (int i = ti0; i <= ti1; ++i) {
        const int64_t g0 = (v * H + i) * W + tj0;
        std::fill_n(Mk + g0, nwrt, false);
        put_row(g0, empty_i, empty_d, empty_r, do_blend ? empty_bg.data() : nullptr);
      }
#ifdef DSS_HAVE_AVX2
      if (vec) _mm_sfence();  // this thread's streaming stores are weakly ordered: drain them
#endif
      return;
    }
    // Tile-local top-K lists in the cache's layout (K slots per pixel, a tile row's 16 pixels
    // side by side), their slots beyond a list's count holding the empty slot (-1, inf, 0): a
    // tile row of them is the cache's row as it is, written out without a copy.
    alignas(32) int32_t li[kTile * kTile * 8];
    alignas(32) float ld[kTile * kTile * 8], lr[kTile * kTile * 8];
    int cnt[kTile * kTile];
    std::fill(cnt, cnt + kTile * kTile, 0);
    std::fill_n(li, kTile * kTile * K, -1);
    std::fill_n(ld, kTile * kTile * K, std::numeric_limits<float>::infinity());
    std::fill_n(lr, kTile * kTile * K, 0.f);
    // The blend below reads the attributes of the splats that stay in the lists, rows scattered
    // over the view's (N, C) block: fetch those of the tile's splats now, so that they arrive
    // while the tile loop runs (a miss each otherwise: 0.9 of the rasteriser's 11.5 ms at 20K).
    if (do_blend)
      for (int64_t e = off[t]; e < off[t + 1]; ++e) __builtin_prefetch(A + (v * N + bins[v][e].k) * C);
#ifdef DSS_HAVE_AVX2
    if (vec) {
      tile_fragments_avx2<KC>(bins[v].data() + off[t], off[t + 1] - off[t], ti0, tj0, tj1, Krt,
                              cutoff, li, ld, lr, cnt);
    } else
#endif
    for (int64_t e = off[t]; e < off[t + 1]; ++e) {
      const Frag& f = bins[v][e];
      const int32_t k = f.k;
      const float* s = &f.u;  // s[0..4]: u, v, a, b2, c as in the packed row
      const int i0 = ti0 + f.i0, i1 = ti0 + f.i1, j0 = tj0 + f.j0, j1 = tj0 + f.j1;
      const float zk = f.z;
      for (int i = i0; i <= i1; ++i) {
        const float dy = ((float)i + 0.5f) - s[1];
        // The row's tests first, in a branch-free loop the compiler vectorises (same float
        // operations per pixel, so the same bits); then the accepted pixels one by one.
        float qrow[kTile];
        const int nj = j1 - j0 + 1;
        for (int t = 0; t < nj; ++t) {
          const float dx = ((float)(j0 + t) + 0.5f) - s[0];
          qrow[t] = quad(s, dx, dy);
        }
        for (int j = j0; j <= j1; ++j) {
          const float q = qrow[j - j0];
          if (!(0.5f * q <= cutoff)) continue;
          const int p = (i - ti0) * kTile + (j - tj0);
          const int c = cnt[p];
          int32_t* pi = li + p * K;
          float* pd = ld + p * K;
          float* pr = lr + p * K;
          // a full list takes the fragment only if it sorts before the last entry
          if (c == K && !(zk < pd[K - 1] || (zk == pd[K - 1] && k < pi[K - 1]))) continue;
          cnt[p] = insert_fragment(pi, pd, pr, c, K, k, zk, f.norm * dss_splat::splat_exp(-0.5f * q));
        }
      }
    }
    // Write out the cache and blend the visible entries (Eq. sumI), a tile row at a time. The
    // cache rows are the tile's lists as they are (put_row); images and mask are assembled per
    // row (empty pixels: the background, false), the image in a local row on the vector path.
    alignas(32) float bimg[kTile * 16];
    // (full tile rows with K compiled in have fixed sizes: the fills and copies inline)
    auto write_rows = [&](auto NW, auto VEC) {
      constexpr int64_t NWC = decltype(NW)::value;
      constexpr bool kStream = decltype(VEC)::value;
      const int nw = NWC > 0 ? (int)NWC : nwrt;
      for (int i = ti0; i <= ti1; ++i) {
        const int64_t g0 = (v * H + i) * W + tj0;
        const int r = (i - ti0) * kTile;
        float* rimg = kStream ? bimg : IMG + g0 * C;
        bool* rm = Mk + g0;
        std::fill_n(rm, nw, false);
        if (do_blend) std::copy_n(empty_bg.data(), nw * C, rimg);
        for (int jj = 0; jj < nwrt; ++jj) {
          const int p = r + jj;
          const int c = cnt[p];
          if (c == 0) continue;
          const int32_t* pi = li + p * K;
          const float* pd = ld + p * K;
          const float* pr = lr + p * K;
          const float lim = pd[0] + merge;
          float den = 0.f;
          float num[16] = {0};
          for (int e = 0; e < c; ++e) {
            if (!(pd[e] <= lim)) break;
            const float w = pr[e];
            den += w;
            if (do_blend) {
              const float* a = A + (v * N + pi[e]) * C;
              for (int64_t ch = 0; ch < C; ++ch) num[ch] += w * a[ch];
            }
          }
          rm[jj] = den > 0.f;
          if (do_blend && den > 0.f) {
            for (int64_t ch = 0; ch < C; ++ch) rimg[jj * C + ch] = num[ch] / den;
          }
        }
        // (the plain path assembled the image row in place)
        put_row(g0, li + r * K, ld + r * K, lr + r * K, kStream && do_blend ? bimg : nullptr);
      }
    };
    using Full = std::integral_constant<int64_t, kTile>;
    using Part = std::integral_constant<int64_t, 0>;
    using Stream = std::true_type;
    using Plain = std::false_type;
    const bool full = nwrt == kTile && KC > 0;
    if (vec)
      full ? write_rows(Full{}, Stream{}) : write_rows(Part{}, Stream{});
    else
      full ? write_rows(Full{}, Plain{}) : write_rows(Part{}, Plain{});
#ifdef DSS_HAVE_AVX2
    if (vec) _mm_sfence();  // this thread's streaming stores are weakly ordered: drain them
#endif
  };
  using K5 = std::integral_constant<int64_t, 5>;
  using Any = std::integral_constant<int64_t, 0>;
  if (Krt == 5 && Crt == 3)
    dynamic_for(V * T, 1, [&](int64_t t) { tile_task(K5{}, std::integral_constant<int64_t, 3>{}, t); });
  else if (Krt == 5 && Crt == 1)
    dynamic_for(V * T, 1, [&](int64_t t) { tile_task(K5{}, std::integral_constant<int64_t, 1>{}, t); });
  else
    dynamic_for(V * T, 1, [&](int64_t t) { tile_task(Any{}, Any{}, t); });
  return {idx, depth, rho, images, mask};
}
