// DSS rasteriser and visibility gradient on the CPU.
//
// One contract with the pure-torch reference (dss/rasterizer/reference.py,
// dss/visibility/reference.py): same inputs (packed screen-space splats, see dss/splats.py),
// same per-pixel tests in the same float32 operation order (compiled with -ffp-contract=off so
// no fused multiply-add changes a rounding), same (depth, index) ordering of the top-K cache.
//
// Work is split over screen tiles (forward) and over points (backward) and handed out
// dynamically from an atomic counter inside at::parallel_for, so one view still uses every core
// and the object's uneven screen coverage does not leave a thread idle.
#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdlib>
#include <limits>
#include <map>
#include <mutex>
#include <type_traits>
#include <vector>

namespace {

constexpr int kFields = 10;  // u v conic_a conic_b2 conic_c norm depth rx ry valid
constexpr int kTile = 16;

struct Box {
  int j0, j1, i0, i1;
};

// Same arithmetic as reference.bbox(): float32 floor/ceil, then clamps.
inline Box splat_box(const float* s, int H, int W) {
  auto clampf = [](float x, float lo, float hi) { return std::min(std::max(x, lo), hi); };
  float j0 = clampf(std::floor(s[0] - s[7] - 0.5f), -1.f, (float)W) - 1.f;
  float j1 = clampf(std::ceil(s[0] + s[7] - 0.5f), -1.f, (float)W) + 1.f;
  float i0 = clampf(std::floor(s[1] - s[8] - 0.5f), -1.f, (float)H) - 1.f;
  float i1 = clampf(std::ceil(s[1] + s[8] - 0.5f), -1.f, (float)H) + 1.f;
  Box b;
  b.j0 = (int)clampf(j0, 0.f, (float)(W - 1));
  b.j1 = (int)clampf(j1, 0.f, (float)(W - 1));
  b.i0 = (int)clampf(i0, 0.f, (float)(H - 1));
  b.i1 = (int)clampf(i1, 0.f, (float)(H - 1));
  return b;
}

inline float quad(const float* s, float dx, float dy) {
  // (a*dx)*dx + (b2*dx)*dy + (c*dy)*dy, left to right, as torch evaluates it.
  float t1 = s[2] * dx * dx;
  float t2 = s[3] * dx * dy;
  float t3 = s[4] * dy * dy;
  return (t1 + t2) + t3;
}

// Depth of point k's tangent plane at the pixel centre (px, py), the depth its splat would have
// there (the backward pass's occlusion test, cases (a)/(b)). For a plane 1/z is affine in screen
// space: 1/z = pl[0] px + pl[1] py + pl[2] (computed in dss/render.py; (0, 0, 1/z) reproduces
// the centre depth). Grazing planes are clamped to a slope of kMaxSlope: |zp - z| <= kMaxSlope *
// (pixel distance) * z / f.
// (visibility_backward evaluates it inline, with the square root only where the clamp applies.)
constexpr float kMaxSlope = 3.f;

// Large outputs (the top-K cache is 47 MB at 12 views of 256x256) come from a block cache: a
// fresh allocation of that size is a fresh mmap, whose page faults and kernel zeroing cost more
// than filling it (14 vs 2 ms for the cache at 20K points on 2 cores, every render). A tensor
// made here owns a block; when its storage dies (no tensor, view or saved variable refers to it
// any more) the deleter parks the block for the next request of the same byte size, up to
// kPoolBytes parked in all (beyond that blocks are freed). Contents are undefined, as with
// torch::empty. empty_cache() frees the parked blocks.
constexpr size_t kPoolBytes = size_t(512) << 20;
struct BlockCache {
  std::mutex mu;
  std::multimap<size_t, void*> parked;
  size_t parked_bytes = 0;
};
BlockCache& block_cache() {
  static BlockCache* cache = new BlockCache();  // never destroyed: tensors may outlive static destructors
  return *cache;
}

torch::Tensor pooled_empty(at::IntArrayRef sizes, at::ScalarType dtype) {
  int64_t numel = 1;
  for (int64_t d : sizes) numel *= d;
  const size_t bytes = (size_t)numel * c10::elementSize(dtype);
  if (bytes == 0) return torch::empty(sizes, torch::TensorOptions().dtype(dtype));
  BlockCache& cache = block_cache();
  void* ptr = nullptr;
  {
    std::lock_guard<std::mutex> lock(cache.mu);
    auto it = cache.parked.find(bytes);
    if (it != cache.parked.end()) {
      ptr = it->second;
      cache.parked.erase(it);
      cache.parked_bytes -= bytes;
    }
  }
  if (ptr == nullptr) {
    ptr = std::aligned_alloc(64, (bytes + 63) / 64 * 64);
    TORCH_CHECK(ptr != nullptr, "dss: out of memory allocating ", bytes, " bytes");
  }
  auto park = [bytes](void* p) {
    BlockCache& c = block_cache();
    {
      std::lock_guard<std::mutex> lock(c.mu);
      if (c.parked_bytes + bytes <= kPoolBytes) {
        c.parked.emplace(bytes, p);
        c.parked_bytes += bytes;
        return;
      }
    }
    std::free(p);
  };
  return torch::from_blob(ptr, sizes, park, torch::TensorOptions().dtype(dtype));
}

// Frees the parked blocks; returns how many bytes were released.
int64_t empty_cache() {
  BlockCache& cache = block_cache();
  std::lock_guard<std::mutex> lock(cache.mu);
  const int64_t released = (int64_t)cache.parked_bytes;
  for (auto& kv : cache.parked) std::free(kv.second);
  cache.parked.clear();
  cache.parked_bytes = 0;
  return released;
}

// Run fn(item) for item in [0, n) on all intra-op threads, items handed out dynamically.
template <typename F>
void dynamic_for(int64_t n, int64_t chunk, const F& fn) {
  std::atomic<int64_t> next(0);
  int nthreads = std::max<int>(1, at::get_num_threads());
  at::parallel_for(0, nthreads, 1, [&](int64_t, int64_t) {
    while (true) {
      int64_t start = next.fetch_add(chunk);
      if (start >= n) break;
      int64_t end = std::min(n, start + chunk);
      for (int64_t it = start; it < end; ++it) fn(it);
    }
  });
}

}  // namespace

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

  // Bin splats into tiles (CSR per view), splats in index order inside each bin.
  // Scratch kept per calling thread between calls (fresh pages cost more than the binning).
  // (References: the worker lambdas must see the calling thread's instances, not their own.)
  static thread_local std::vector<std::vector<int64_t>> offsets_tl;
  static thread_local std::vector<std::vector<int32_t>> lists_tl;
  static thread_local std::vector<std::vector<Box>> boxes_tl;
  auto& offsets = offsets_tl;
  auto& lists = lists_tl;
  auto& boxes = boxes_tl;
  offsets.resize(V);
  lists.resize(V);
  boxes.resize(V);
  for (int64_t v = 0; v < V; ++v) {
    offsets[v].assign(T + 1, 0);
    boxes[v].resize(N);
  }
  dynamic_for(V, 1, [&](int64_t v) {
    auto& off = offsets[v];
    auto& bx = boxes[v];
    for (int64_t k = 0; k < N; ++k) {
      const float* s = P + (v * N + k) * kFields;
      if (!(s[9] > 0.f)) { bx[k].j0 = 1; bx[k].j1 = 0; continue; }
      Box b = splat_box(s, (int)H, (int)W);
      bx[k] = b;
      if (b.j1 < b.j0 || b.i1 < b.i0) continue;
      for (int ty = b.i0 / kTile; ty <= b.i1 / kTile; ++ty)
        for (int tx = b.j0 / kTile; tx <= b.j1 / kTile; ++tx) off[ty * TX + tx + 1]++;
    }
    for (int64_t t = 0; t < T; ++t) off[t + 1] += off[t];
    lists[v].resize(off[T]);
    std::vector<int64_t> fill(off.begin(), off.end() - 1);
    for (int64_t k = 0; k < N; ++k) {
      const Box& b = bx[k];
      if (b.j1 < b.j0 || b.i1 < b.i0) continue;
      for (int ty = b.i0 / kTile; ty <= b.i1 / kTile; ++ty)
        for (int tx = b.j0 / kTile; tx <= b.j1 / kTile; ++tx) lists[v][fill[ty * TX + tx]++] = (int32_t)k;
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
  auto tile_task = [&](auto KT, auto CT, int64_t item) {
    constexpr int64_t KC = decltype(KT)::value, CC = decltype(CT)::value;
    const int64_t K = KC > 0 ? KC : Krt, C = CC > 0 ? CC : Crt;
    const int64_t v = item / T, t = item % T;
    const int ty = (int)(t / TX), tx = (int)(t % TX);
    const int ti0 = ty * kTile, tj0 = tx * kTile;
    const int ti1 = std::min<int>((int)H, ti0 + kTile) - 1, tj1 = std::min<int>((int)W, tj0 + kTile) - 1;
    // Tile-local top-K buffers (contiguous per pixel).
    int32_t li[kTile * kTile * 8];
    float ld[kTile * kTile * 8], lr[kTile * kTile * 8];
    int cnt[kTile * kTile];
    std::fill(cnt, cnt + kTile * kTile, 0);
    const auto& off = offsets[v];
    for (int64_t e = off[t]; e < off[t + 1]; ++e) {
      const int32_t k = lists[v][e];
      const float* s = P + (v * N + k) * kFields;
      const Box& b = boxes[v][k];
      const int i0 = std::max(b.i0, ti0), i1 = std::min(b.i1, ti1);
      const int j0 = std::max(b.j0, tj0), j1 = std::min(b.j1, tj1);
      const float zk = s[6];
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
          int c = cnt[p];
          int32_t* pi = li + p * 8;
          float* pd = ld + p * 8;
          float* pr = lr + p * 8;
          // Insertion into the sorted (depth, index) list.
          if (c == K) {
            if (!(zk < pd[K - 1] || (zk == pd[K - 1] && k < pi[K - 1]))) continue;
            c = (int)K - 1;
          }
          int pos = c;
          while (pos > 0 && (zk < pd[pos - 1] || (zk == pd[pos - 1] && k < pi[pos - 1]))) {
            pi[pos] = pi[pos - 1];
            pd[pos] = pd[pos - 1];
            pr[pos] = pr[pos - 1];
            --pos;
          }
          pi[pos] = k;
          pd[pos] = zk;
          pr[pos] = s[5] * std::exp(-0.5f * q);
          cnt[p] = c + 1;
        }
      }
    }
    // Write out the cache and blend the visible entries (Eq. sumI).
    for (int i = ti0; i <= ti1; ++i) {
      for (int j = tj0; j <= tj1; ++j) {
        const int p = (i - ti0) * kTile + (j - tj0);
        const int c = cnt[p];
        const int64_t g = ((v * H + i) * W + j);
        for (int e = 0; e < c; ++e) {
          I[g * K + e] = li[p * 8 + e];
          D[g * K + e] = ld[p * 8 + e];
          Rh[g * K + e] = lr[p * 8 + e];
        }
        for (int e = c; e < K; ++e) {
          I[g * K + e] = -1;
          D[g * K + e] = std::numeric_limits<float>::infinity();
          Rh[g * K + e] = 0.f;
        }
        Mk[g] = false;
        if (c == 0) {
          if (do_blend)
            for (int64_t ch = 0; ch < C; ++ch) IMG[g * C + ch] = BG[ch];
          continue;
        }
        const float lim = ld[p * 8] + merge;
        float den = 0.f;
        float num[16] = {0};
        for (int e = 0; e < c; ++e) {
          if (!(ld[p * 8 + e] <= lim)) break;
          const float w = lr[p * 8 + e];
          den += w;
          if (do_blend) {
            const float* a = A + (v * N + li[p * 8 + e]) * C;
            for (int64_t ch = 0; ch < C; ++ch) num[ch] += w * a[ch];
          }
        }
        Mk[g] = den > 0.f;
        if (do_blend) {
          for (int64_t ch = 0; ch < C; ++ch) IMG[g * C + ch] = den > 0.f ? num[ch] / den : BG[ch];
        }
      }
    }
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

// ---------------------------------------------------------------------------------------------
// Visibility gradient (paper Eqs. gradcase, filteredG, cases (a), (b), (c)); see
// dss/visibility/reference.py for the rules written out in torch.
torch::Tensor visibility_backward(torch::Tensor packed, torch::Tensor attrs, torch::Tensor idx, torch::Tensor depth,
                                  torch::Tensor rho, torch::Tensor images, torch::Tensor grad, torch::Tensor R,
                                  torch::Tensor focal, torch::Tensor principal, torch::Tensor background,
                                  torch::Tensor planes, int64_t window, int64_t stride, double cutoff_d,
                                  double merge_d, double eps_d, int64_t mode) {
  packed = packed.contiguous().to(torch::kFloat32);
  planes = planes.contiguous().to(torch::kFloat32);
  attrs = attrs.contiguous().to(torch::kFloat32);
  idx = idx.contiguous();
  depth = depth.contiguous();
  rho = rho.contiguous();
  images = images.contiguous().to(torch::kFloat32);
  grad = grad.contiguous().to(torch::kFloat32);
  R = R.contiguous().to(torch::kFloat32);
  focal = focal.contiguous().to(torch::kFloat32);
  principal = principal.contiguous().to(torch::kFloat32);
  background = background.contiguous().to(torch::kFloat32);
  const int64_t V = packed.size(0), N = packed.size(1), H = idx.size(1), W = idx.size(2), K = idx.size(3);
  const int64_t C = attrs.size(2);
  TORCH_CHECK(C <= 16, "at most 16 channels");
  TORCH_CHECK(stride >= 1, "window stride must be >= 1");
  TORCH_CHECK(planes.numel() == V * N * 3, "planes must be (V,N,3)");
  const float cutoff = (float)cutoff_d, merge = (float)merge_d, eps = (float)eps_d;
  auto out = torch::zeros({N, 3}, torch::TensorOptions().dtype(torch::kFloat32));
  const float* PL = planes.data_ptr<float>();
  float* G = out.data_ptr<float>();
  const float* P = packed.data_ptr<float>();
  const float* A = attrs.data_ptr<float>();
  const int32_t* I = idx.data_ptr<int32_t>();
  const float* D = depth.data_ptr<float>();
  const float* Rh = rho.data_ptr<float>();
  const float* IMG = images.data_ptr<float>();
  const float* GR = grad.data_ptr<float>();
  const float* Rm = R.data_ptr<float>();
  const float* F = focal.data_ptr<float>();
  const float* PP = principal.data_ptr<float>();
  const float* BG = background.data_ptr<float>();

  // Everything a (point, pixel) evaluation reads about the pixel, in one record per pixel, so an
  // evaluation is channel-free: with g = dL/dI at the pixel, only the projections g . w of the
  // attributes matter (gd = g . I_new - g . I = (sum rho g.w) / (sum rho) - g . I). Record layout
  // (floats): [0] front depth d0 (inf if empty), [1] sum rho and [2] sum rho g.w over the visible
  // set, [3] g . I, [4] g . background, [5] 1 if g != 0, [6, 6+C) g, then per cache entry depth,
  // rho and g.w (K each). Built for one view at a time (a few MB, cache-resident while that
  // view's points read it); the cache indices are read from idx directly.
  const int64_t HW = H * W;
  const int64_t RS = 6 + C + 3 * K;
  const int64_t oD = 6 + C, oR = oD + K, oG = oR + K;
  static thread_local std::vector<float> rec;  // kept between calls: no fresh pages per call
  rec.resize((size_t)(HW * RS));
  float* REC = rec.data();
  std::vector<double> gsum((size_t)(N * 3), 0.0);  // world gradient, summed over views in view order
  const int64_t Krt = K, Crt = C;  // run-time values; the evaluation loop may fix them at compile time
  const int64_t kChunk = 64, nchunks = (N + kChunk - 1) / kChunk;
  const float inf = std::numeric_limits<float>::infinity();
  for (int64_t v = 0; v < V; ++v) {
    dynamic_for(H, 4, [&](int64_t i) {
      for (int64_t j = 0; j < W; ++j) {
        const int64_t g = (v * H + i) * W + j;
        float* r = REC + (i * W + j) * RS;
        const float* gp = GR + g * C;
        bool nz = false;
        for (int64_t ch = 0; ch < C; ++ch) nz |= (gp[ch] != 0.f);
        r[5] = nz ? 1.f : 0.f;
        if (!nz) continue;  // no evaluation reads this record
        const int32_t* pi = I + g * K;
        const float* pd = D + g * K;
        const float* pr = Rh + g * K;
        const float* ip = IMG + g * C;
        float gi = 0.f, gb = 0.f;
        for (int64_t ch = 0; ch < C; ++ch) {
          r[6 + ch] = gp[ch];
          gi += gp[ch] * ip[ch];
          gb += gp[ch] * BG[ch];
        }
        r[3] = gi;
        r[4] = gb;
        const float d0 = pi[0] >= 0 ? pd[0] : inf;
        float den = 0.f, gnum = 0.f;
        for (int64_t e = 0; e < K; ++e) {
          r[oD + e] = pd[e];
          r[oR + e] = pr[e];
          float ga = 0.f;
          if (pi[e] >= 0) {
            const float* a = A + (v * N + pi[e]) * C;
            for (int64_t ch = 0; ch < C; ++ch) ga += gp[ch] * a[ch];
          }
          r[oG + e] = ga;
        }
        for (int64_t e = 0; e < K && pi[e] >= 0 && pd[e] <= d0 + merge; ++e) {
          den += pr[e];
          gnum += pr[e] * r[oG + e];
        }
        r[0] = d0;
        r[1] = den;
        r[2] = gnum;
      }
    });
    const float f = F[v], cx = PP[v * 2], cy = PP[v * 2 + 1], inv_f = 1.f / f;
    const float* Rv = Rm + v * 9;
    const float* PLv = PL + v * N * 3;
    const int32_t* Iv = I + v * HW * K;
    // A task is a run of consecutive (spatially sorted) points: their windows overlap in the
    // record buffer. Each point is one task's, so it owns its gsum row (no race, view order kept).
    // The evaluation loop, compiled for the common (K, C) = (5, 3) and (5, 1) with constant
    // trip counts (the cache scans and channel dots unroll) and for any (K, C) at run time.
    auto points_task = [&](auto KT, auto CT, int64_t task) {
      constexpr int64_t KC = decltype(KT)::value, CC = decltype(CT)::value;
      const int64_t K = KC > 0 ? KC : Krt, C = CC > 0 ? CC : Crt;
      const int64_t RS = 6 + C + 3 * K, oD = 6 + C, oR = oD + K, oG = oR + K;
      const int64_t k_begin = task * kChunk, k_end = std::min(N, k_begin + kChunk);
      for (int64_t k = k_begin; k < k_end; ++k) {
        const float* s = P + (v * N + k) * kFields;
        if (!(s[9] > 0.f)) continue;
        const float u = s[0], vv = s[1], z = s[6], nk = s[5];
        const float z_f = z * inv_f;  // camera units per pixel at the point's depth
        const float X = (u - cx) * z_f, Y = (vv - cy) * z_f;
        const float* wk = A + (v * N + k) * C;
        const float* pl = PLv + k * 3;
        const float slope = kMaxSlope * z_f;  // plane-depth clamp per pixel of distance
        const int ic = (int)std::floor(vv), jc = (int)std::floor(u);
        double acc[3] = {0, 0, 0};
        for (int64_t dy = -window; dy <= window; dy += stride) {
          const int64_t i = ic + dy;
          if (i < 0 || i >= H) continue;
          const float py = (float)i + 0.5f;
          for (int64_t dx = -window; dx <= window; dx += stride) {
            const int64_t j = jc + dx;
            if (j < 0 || j >= W) continue;
            const float* r = REC + (i * W + j) * RS;
            if (r[5] == 0.f) continue;
            const int32_t* pi = Iv + (i * W + j) * K;
            const float* pd = r + oD;
            const float* pr = r + oR;
            const float* pg = r + oG;
            const float d0 = r[0];
            int ek = -1;  // position of k in the cache
            for (int e = 0; e < K && pi[e] >= 0; ++e)
              if (pi[e] == (int32_t)k) { ek = e; break; }
            const bool k_visible = ek >= 0 && pd[ek] <= d0 + merge;
            const float px = (float)j + 0.5f;
            float zp = 0.f;  // k's tangent-plane depth at the pixel: only needed when k is not visible
            float den, gn;   // sum rho and sum rho g.w of the visible set after the change
            int kase;        // 0: (a) invisible, nothing in front; 1: (b) occluded; 2: (c) visible
            if (k_visible) {
              kase = 2;
              if (ek > 0) {  // the front stays: the visible set loses k only
                den = r[1] - pr[ek];
                gn = r[2] - pr[ek] * pg[ek];
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
                const float dmax = slope * std::sqrt(d2);
                zp = std::min(std::max(zp, z - dmax), z + dmax);
              }
              kase = (pi[0] < 0 || zp <= d0 + merge) ? 0 : 1;
              float gw = 0.f;
              for (int64_t ch = 0; ch < C; ++ch) gw += r[6 + ch] * wk[ch];
              den = nk;
              gn = nk * gw;
              if (kase == 1 || zp >= d0) {  // merges with the current visible set
                den += r[1];
                gn += r[2];
              } else if (pi[0] >= 0) {  // k becomes the front: entries beyond zp + T drop out
                const float lim = zp + merge;
                for (int e = 0; e < K && pi[e] >= 0 && pd[e] <= lim; ++e) {
                  den += pr[e];
                  gn += pr[e] * pg[e];
                }
              }
            }
            const float gd = (den > 0.f ? gn / den : r[4]) - r[3];
            if (mode == 0) {  // dss: linearised step between the two visibility states
              if (!(gd < 0.f)) continue;  // Eq. filteredG
              if (kase == 2) {
                const float ddx = px - u, ddy = py - vv;
                const float sd = std::sqrt(ddx * ddx + ddy * ddy);
                if (sd < 1e-6f) continue;
                const float inv_sd = 1.f / sd;
                const float ux = ddx * inv_sd, uy = ddy * inv_sd;
                const float qu = quad(s, ux, uy);
                const float rr = std::sqrt(2.f * cutoff / std::max(qu, 1e-20f));
                const float steps[2] = {-(std::max(rr - sd, 0.f)), rr + sd};
                for (int m = 0; m < 2; ++m) {
                  const float mx = steps[m] * ux * z_f, my = steps[m] * uy * z_f;
                  const float coef = gd / (mx * mx + my * my + eps);
                  acc[0] += coef * mx;
                  acc[1] += coef * my;
                }
              } else {
                const float zt = kase == 1 ? d0 : zp;  // (b): forward to the front surface
                const float zt_f = zt * inv_f;
                const float mx = (px - cx) * zt_f - X, my = (py - cy) * zt_f - Y, mz = zt - zp;
                const float coef = gd / (mx * mx + my * my + mz * mz + eps);
                acc[0] += coef * mx;
                acc[1] += coef * my;
                acc[2] += coef * mz;
              }
            } else {  // rbf: derivative of a smooth Gaussian visibility h = exp(-q/2)
              const float ddx = px - u, ddy = py - vv;
              const float q = quad(s, ddx, ddy);
              const float h = std::exp(-0.5f * q);
              const float sgn = kase == 2 ? -1.f : 1.f;  // Phi = I_without + h (I_with - I_without)
              const float gu = h * (s[2] * ddx + 0.5f * s[3] * ddy);  // dh/du_k = h Sigma^-1 d
              const float gv = h * (0.5f * s[3] * ddx + s[4] * ddy);
              const float c = sgn * gd;
              acc[0] += c * (f / z) * gu;
              acc[1] += c * (f / z) * gv;
              acc[2] += c * (-f * X / (z * z) * gu - f * Y / (z * z) * gv);
            }
          }
        }
        double* gk = gsum.data() + k * 3;  // world gradient = R^T acc
        for (int a = 0; a < 3; ++a) gk[a] += Rv[0 * 3 + a] * acc[0] + Rv[1 * 3 + a] * acc[1] + Rv[2 * 3 + a] * acc[2];
      }
    };
    using K5 = std::integral_constant<int64_t, 5>;
    using Any = std::integral_constant<int64_t, 0>;
    if (Krt == 5 && Crt == 3)
      dynamic_for(nchunks, 1, [&](int64_t t) { points_task(K5{}, std::integral_constant<int64_t, 3>{}, t); });
    else if (Krt == 5 && Crt == 1)
      dynamic_for(nchunks, 1, [&](int64_t t) { points_task(K5{}, std::integral_constant<int64_t, 1>{}, t); });
    else
      dynamic_for(nchunks, 1, [&](int64_t t) { points_task(Any{}, Any{}, t); });
  }
  for (int64_t e = 0; e < N * 3; ++e) G[e] = (float)gsum[e];
  return out;
}

// ---------------------------------------------------------------------------------------------
// Backward of Eq. sumI for the smooth terms (Eqs. gradN, gradP without the visibility term):
// I = sum_f rho_f w_f / sum_f rho_f over the visible cached fragments, rho_f = norm exp(-q/2),
// q = a dx^2 + b2 dx dy + c dy^2 with d = pixel centre - (u, v). Returns dL/dpacked (V,N,10)
// (u, v, conic a, b2, c, norm; zero for the other fields) and dL/dattrs (V,N,C).
// Parallel over views, each view scanning its own fragments once in row-major pixel order: a view
// owns its (v, k) accumulators (no race, a fixed sum order per point), and the work is the
// number of cached fragments, not (splat box area x K) per point as a point-parallel loop over
// each splat's box would be (2-4x slower at 20K points, 256 px).
std::vector<torch::Tensor> blend_backward(torch::Tensor packed, torch::Tensor attrs, torch::Tensor idx,
                                          torch::Tensor depth, torch::Tensor rho, torch::Tensor images,
                                          torch::Tensor grad, double merge_d) {
  packed = packed.contiguous().to(torch::kFloat32);
  attrs = attrs.contiguous().to(torch::kFloat32);
  idx = idx.contiguous();
  depth = depth.contiguous();
  rho = rho.contiguous();
  images = images.contiguous().to(torch::kFloat32);
  grad = grad.contiguous().to(torch::kFloat32);
  const int64_t V = packed.size(0), N = packed.size(1), H = idx.size(1), W = idx.size(2), K = idx.size(3);
  const int64_t C = attrs.size(2);
  TORCH_CHECK(C <= 16, "at most 16 channels");
  const float merge = (float)merge_d;
  auto gpk = pooled_empty({V, N, kFields}, torch::kFloat32);  // every entry written below
  auto gat = pooled_empty({V, N, C}, torch::kFloat32);
  const float* P = packed.data_ptr<float>();
  const float* A = attrs.data_ptr<float>();
  const int32_t* I = idx.data_ptr<int32_t>();
  const float* D = depth.data_ptr<float>();
  const float* Rh = rho.data_ptr<float>();
  const float* IMG = images.data_ptr<float>();
  const float* GR = grad.data_ptr<float>();
  float* GP = gpk.data_ptr<float>();
  float* GA = gat.data_ptr<float>();
  const int64_t S = 6 + C;  // per point: du, dv, da, db, dc, dnorm, then dL/dattr per channel
  dynamic_for(V, 1, [&](int64_t v) {
    static thread_local std::vector<double> acc;  // double sums, as the per-point loop had
    acc.assign((size_t)(N * S), 0.0);
    for (int64_t i = 0; i < H; ++i) {
      const float py = (float)i + 0.5f;
      for (int64_t j = 0; j < W; ++j) {
        const int64_t g = (v * H + i) * W + j;
        const int32_t* pi = I + g * K;
        const float* pd = D + g * K;
        const float* pr = Rh + g * K;
        if (pi[0] < 0) continue;
        const float lim = pd[0] + merge;
        int nvis = 0;
        float den = 0.f;
        for (int e = 0; e < K && pi[e] >= 0 && pd[e] <= lim; ++e) {
          den += pr[e];
          ++nvis;
        }
        if (!(den > 0.f)) continue;
        const float* gp = GR + g * C;
        const float* ip = IMG + g * C;
        for (int e = 0; e < nvis; ++e) {
          const int64_t k = pi[e];
          const float* s = P + (v * N + k) * kFields;
          if (!(s[9] > 0.f)) continue;
          const float* wk = A + (v * N + k) * C;
          double* a = acc.data() + k * S;
          const float rf = pr[e];
          double drho = 0;
          for (int64_t c = 0; c < C; ++c) {
            drho += (double)gp[c] * (wk[c] - ip[c]) / den;
            a[6 + c] += (double)gp[c] * rf / den;
          }
          const float dx = ((float)j + 0.5f) - s[0], dy = py - s[1];
          const float q = quad(s, dx, dy);
          const double ex = std::exp(-0.5 * (double)q);
          a[5] += drho * ex;
          const double dq = -0.5 * drho * (double)s[5] * ex;
          a[2] += dq * dx * dx;
          a[3] += dq * dx * dy;
          a[4] += dq * dy * dy;
          a[0] += -dq * (2.0 * s[2] * dx + s[3] * dy);
          a[1] += -dq * (s[3] * dx + 2.0 * s[4] * dy);
        }
      }
    }
    for (int64_t k = 0; k < N; ++k) {
      const double* a = acc.data() + k * S;
      float* o = GP + (v * N + k) * kFields;
      for (int f = 0; f < 6; ++f) o[f] = (float)a[f];
      for (int f = 6; f < kFields; ++f) o[f] = 0.f;
      float* oa = GA + (v * N + k) * C;
      for (int64_t c = 0; c < C; ++c) oa[c] = (float)a[6 + c];
    }
  });
  return {gpk, gat};
}

// ---------------------------------------------------------------------------------------------
// The camera-frame geometry of one splat (dss/splats.py project_splats, same formulas), shared by
// the projection's forward and backward: camera-space point and normal, the unit normal, the rows
// m1, m2 of the projection's derivative, A = M P M^T, |det J| and Sigma = s^2 A + fv I.
// Zs = Z in front of the near plane, else 1 (culled splats stay finite).
constexpr float kInf = std::numeric_limits<float>::infinity();
struct SplatGeometry {
  float X, Y, Z, Zs, nc[3], inv, nh[3], m1[3], m2[3], m1n, m2n, A11, A12, A22, w, detJ, s2, S11, S12, S22, detS;
};

inline SplatGeometry splat_geometry(const float* p, const float* n, const float* Rv, const float* tv, float f,
                                    float sigma, float fv, float zn) {
  SplatGeometry g;
  float pc[3];
  for (int a = 0; a < 3; ++a) {
    pc[a] = Rv[a * 3] * p[0] + Rv[a * 3 + 1] * p[1] + Rv[a * 3 + 2] * p[2] + tv[a];
    g.nc[a] = Rv[a * 3] * n[0] + Rv[a * 3 + 1] * n[1] + Rv[a * 3 + 2] * n[2];
  }
  g.X = pc[0], g.Y = pc[1], g.Z = pc[2];
  const float Zs = g.Z > zn ? g.Z : 1.f;
  g.Zs = Zs;
  const float nl2 = g.nc[0] * g.nc[0] + g.nc[1] * g.nc[1] + g.nc[2] * g.nc[2];
  g.inv = 1.f / std::sqrt(nl2 + 1e-20f);
  for (int a = 0; a < 3; ++a) g.nh[a] = g.nc[a] * g.inv;
  g.m1[0] = f / Zs, g.m1[1] = 0.f, g.m1[2] = -f * g.X / (Zs * Zs);
  g.m2[0] = 0.f, g.m2[1] = f / Zs, g.m2[2] = -f * g.Y / (Zs * Zs);
  g.m1n = g.m1[0] * g.nh[0] + g.m1[2] * g.nh[2];
  g.m2n = g.m2[1] * g.nh[1] + g.m2[2] * g.nh[2];
  g.A11 = g.m1[0] * g.m1[0] + g.m1[2] * g.m1[2] - g.m1n * g.m1n;
  g.A12 = g.m1[2] * g.m2[2] - g.m1n * g.m2n;
  g.A22 = g.m2[1] * g.m2[1] + g.m2[2] * g.m2[2] - g.m2n * g.m2n;
  g.w = g.nh[0] * g.X + g.nh[1] * g.Y + g.nh[2] * Zs;
  g.detJ = f * f * std::fabs(g.w) / (Zs * Zs * Zs);
  g.s2 = sigma * sigma;
  g.S11 = g.s2 * g.A11 + fv, g.S12 = g.s2 * g.A12, g.S22 = g.s2 * g.A22 + fv;
  g.detS = g.s2 * g.s2 * (g.detJ * g.detJ) + g.s2 * fv * (g.A11 + g.A22) + fv * fv;
  return g;
}

// Forward-only fused version of dss/splats.py project_splats (same formulas; used when no
// gradient is needed, where the torch version's many (V, N) temporaries dominate at 100K points).
torch::Tensor project_splats_forward(torch::Tensor points, torch::Tensor normals, torch::Tensor R, torch::Tensor t,
                                     torch::Tensor focal, torch::Tensor principal, torch::Tensor sigma,
                                     double cutoff, bool culling, double znear, double filter_variance) {
  points = points.contiguous().to(torch::kFloat32);
  normals = normals.contiguous().to(torch::kFloat32);
  R = R.contiguous().to(torch::kFloat32);
  t = t.contiguous().to(torch::kFloat32);
  focal = focal.contiguous().to(torch::kFloat32);
  principal = principal.contiguous().to(torch::kFloat32);
  const int64_t N = points.size(0), V = R.size(0);
  sigma = sigma.to(torch::kFloat32).expand({N}).contiguous();
  auto out = pooled_empty({V, N, kFields}, torch::kFloat32);
  const float* Pp = points.data_ptr<float>();
  const float* Nn = normals.data_ptr<float>();
  const float* Rr = R.data_ptr<float>();
  const float* Tt = t.data_ptr<float>();
  const float* Ff = focal.data_ptr<float>();
  const float* Cc = principal.data_ptr<float>();
  const float* Sg = sigma.data_ptr<float>();
  float* O = out.data_ptr<float>();
  const float fv = (float)filter_variance, C2 = 2.f * (float)cutoff, zn = (float)znear;
  dynamic_for(V * ((N + 1023) / 1024), 1, [&](int64_t item) {
    const int64_t nb = (N + 1023) / 1024;
    const int64_t v = item / nb, k0 = (item % nb) * 1024, k1 = std::min(N, k0 + 1024);
    const float* Rv = Rr + v * 9;
    const float f = Ff[v], cx = Cc[v * 2], cy = Cc[v * 2 + 1];
    for (int64_t k = k0; k < k1; ++k) {
      const SplatGeometry g = splat_geometry(Pp + k * 3, Nn + k * 3, Rv, Tt + v * 3, f, Sg[k], fv, zn);
      const float X = g.X, Y = g.Y, Z = g.Z, Zs = g.Zs, S11 = g.S11, S12 = g.S12, S22 = g.S22, detS = g.detS;
      const float* nc = g.nc;
      float* o = O + (v * N + k) * kFields;
      o[0] = f * X / Zs + cx;
      o[1] = f * Y / Zs + cy;
      o[2] = S22 / detS;
      o[3] = -2.f * S12 / detS;
      o[4] = S11 / detS;
      o[5] = g.detJ / (2.f * 3.14159265358979f * std::sqrt(detS));
      o[6] = Z;
      o[7] = std::sqrt(C2 * S11);
      o[8] = std::sqrt(C2 * S22);
      bool valid = Z > zn;
      if (culling) valid = valid && (nc[0] * X + nc[1] * Y + nc[2] * Z) < 0.f;
      o[9] = valid ? 1.f : 0.f;
    }
  });
  return out;
}

// Backward of project_splats_forward (the same formulas as dss/splats.py project_splats): given
// dL/dpacked (V,N,10), returns dL/dpoints and dL/dnormals (N,3) with sigma, cameras and the
// filter held fixed. Fields 0-8 (u, v, conic a, b2, c, norm, depth, rx, ry) carry gradients; the
// valid flag is a step function. Culled splats (valid = 0) get none, as the renderer never reads
// them. Per-view gradients are summed over views in view order (deterministic at any thread count).
std::vector<torch::Tensor> project_splats_backward(torch::Tensor points, torch::Tensor normals, torch::Tensor R,
                                                   torch::Tensor t, torch::Tensor focal, torch::Tensor principal,
                                                   torch::Tensor sigma, torch::Tensor packed, torch::Tensor grad,
                                                   double cutoff, double filter_variance) {
  points = points.contiguous().to(torch::kFloat32);
  normals = normals.contiguous().to(torch::kFloat32);
  R = R.contiguous().to(torch::kFloat32);
  t = t.contiguous().to(torch::kFloat32);
  focal = focal.contiguous().to(torch::kFloat32);
  packed = packed.contiguous().to(torch::kFloat32);
  grad = grad.contiguous().to(torch::kFloat32);
  const int64_t N = points.size(0), V = R.size(0);
  TORCH_CHECK(packed.size(0) == V && packed.size(1) == N && packed.size(2) == kFields, "packed must be (V,N,10)");
  TORCH_CHECK(grad.sizes() == packed.sizes(), "grad must be shaped like packed");
  sigma = sigma.to(torch::kFloat32).expand({N}).contiguous();
  const float* Pp = points.data_ptr<float>();
  const float* Nn = normals.data_ptr<float>();
  const float* Rr = R.data_ptr<float>();
  const float* Tt = t.data_ptr<float>();
  const float* Ff = focal.data_ptr<float>();
  const float* Sg = sigma.data_ptr<float>();
  const float* PK = packed.data_ptr<float>();
  const float* GK = grad.data_ptr<float>();
  const float fv = (float)filter_variance, C = (float)cutoff;
  static thread_local std::vector<float> gview_tl;  // per view: dL/dp (3), dL/dn (3), world frame
  auto& gview = gview_tl;  // the calling thread's instance, also inside the worker lambdas
  gview.resize((size_t)(V * N * 6));
  const int64_t nb = (N + 1023) / 1024;
  dynamic_for(V * nb, 1, [&](int64_t item) {
    const int64_t v = item / nb, k0 = (item % nb) * 1024, k1 = std::min(N, k0 + 1024);
    const float* Rv = Rr + v * 9;
    const float f = Ff[v];
    for (int64_t k = k0; k < k1; ++k) {
      float* out = gview.data() + (v * N + k) * 6;
      const float* pk = PK + (v * N + k) * kFields;
      const float* gk = GK + (v * N + k) * kFields;
      if (!(pk[9] > 0.f)) {
        for (int a = 0; a < 6; ++a) out[a] = 0.f;
        continue;
      }
      // valid splats only (Z > znear): no near-plane substitute for Z
      const SplatGeometry g = splat_geometry(Pp + k * 3, Nn + k * 3, Rv, Tt + v * 3, f, Sg[k], fv, -kInf);
      const float X = g.X, Y = g.Y, Z = g.Z, iZ = 1.f / Z, inv = g.inv, w = g.w, detJ = g.detJ, s2 = g.s2;
      const float m1n = g.m1n, m2n = g.m2n, S11 = g.S11, S12 = g.S12, S22 = g.S22, detS = g.detS;
      const float *nc = g.nc, *nh = g.nh, *m1 = g.m1, *m2 = g.m2;
      const float iS = 1.f / detS;
      const float sqS = std::sqrt(detS);
      // outputs: u v a b2 c norm depth rx ry
      const float gu = gk[0], gv = gk[1], ga = gk[2], gb2 = gk[3], gc = gk[4], gnorm = gk[5], gz = gk[6];
      const float grx = gk[7], gry = gk[8];
      const float k2pi = 1.f / (2.f * 3.14159265358979f);
      float gS11 = gc * iS, gS22 = ga * iS, gS12 = -2.f * gb2 * iS;
      // rx = sqrt(2 C S11), ry = sqrt(2 C S22)
      if (pk[7] > 0.f) gS11 += grx * C / pk[7];
      if (pk[8] > 0.f) gS22 += gry * C / pk[8];
      const float gdetS = -(ga * S22 - 2.f * gb2 * S12 + gc * S11) * iS * iS - 0.5f * gnorm * detJ * k2pi * iS / sqS;
      const float gdetJ = gnorm * k2pi / sqS + gdetS * s2 * s2 * 2.f * detJ;
      const float gA11 = s2 * gS11 + gdetS * s2 * fv, gA22 = s2 * gS22 + gdetS * s2 * fv, gA12 = s2 * gS12;
      float gm1[3], gm2[3];
      for (int a = 0; a < 3; ++a) {
        gm1[a] = 2.f * gA11 * m1[a] + gA12 * m2[a];
        gm2[a] = 2.f * gA22 * m2[a] + gA12 * m1[a];
      }
      const float gm1n = -2.f * gA11 * m1n - gA12 * m2n;
      const float gm2n = -2.f * gA22 * m2n - gA12 * m1n;
      float gnh[3];
      for (int a = 0; a < 3; ++a) {
        gm1[a] += gm1n * nh[a];
        gm2[a] += gm2n * nh[a];
        gnh[a] = gm1n * m1[a] + gm2n * m2[a];
      }
      // detJ = f^2 |w| / Z^3
      const float gw = gdetJ * f * f * (w > 0.f ? 1.f : (w < 0.f ? -1.f : 0.f)) * iZ * iZ * iZ;
      gnh[0] += gw * X;
      gnh[1] += gw * Y;
      gnh[2] += gw * Z;
      float gX = gw * nh[0], gY = gw * nh[1];
      float gZ = gw * nh[2] - 3.f * gdetJ * detJ * iZ + gz;
      // m1 = f (1/Z, 0, -X/Z^2), m2 = f (0, 1/Z, -Y/Z^2)
      gZ += -(gm1[0] + gm2[1]) * f * iZ * iZ + 2.f * f * (gm1[2] * X + gm2[2] * Y) * iZ * iZ * iZ;
      gX += -gm1[2] * f * iZ * iZ;
      gY += -gm2[2] * f * iZ * iZ;
      // u = f X / Z + cx, v = f Y / Z + cy
      gX += gu * f * iZ;
      gY += gv * f * iZ;
      gZ += -(gu * X + gv * Y) * f * iZ * iZ;
      // nh = nc / sqrt(|nc|^2 + 1e-20)
      const float dn = gnh[0] * nc[0] + gnh[1] * nc[1] + gnh[2] * nc[2];
      float gnc[3];
      for (int a = 0; a < 3; ++a) gnc[a] = inv * gnh[a] - inv * inv * inv * dn * nc[a];
      const float gpc[3] = {gX, gY, gZ};
      for (int a = 0; a < 3; ++a) {  // world = R^T camera
        out[a] = Rv[0 * 3 + a] * gpc[0] + Rv[1 * 3 + a] * gpc[1] + Rv[2 * 3 + a] * gpc[2];
        out[3 + a] = Rv[0 * 3 + a] * gnc[0] + Rv[1 * 3 + a] * gnc[1] + Rv[2 * 3 + a] * gnc[2];
      }
    }
  });
  auto gp = torch::empty({N, 3}, torch::TensorOptions().dtype(torch::kFloat32));
  auto gn = torch::empty({N, 3}, torch::TensorOptions().dtype(torch::kFloat32));
  float* GP = gp.data_ptr<float>();
  float* GN = gn.data_ptr<float>();
  at::parallel_for(0, N, 1024, [&](int64_t k0, int64_t k1) {
    for (int64_t k = k0; k < k1; ++k) {
      float s[6] = {0, 0, 0, 0, 0, 0};
      for (int64_t v = 0; v < V; ++v)
        for (int a = 0; a < 6; ++a) s[a] += gview[(v * N + k) * 6 + a];
      for (int a = 0; a < 3; ++a) {
        GP[k * 3 + a] = s[a];
        GN[k * 3 + a] = s[3 + a];
      }
    }
  });
  return {gp, gn};
}

// SMAPE (paper Eq. smape) in one pass: sum over all elements of |x - y| / (|x| + |y| + eps), and
// when asked its derivative with respect to x, sign(x - y) / s - |x - y| sign(x) / s^2 with
// s = |x| + |y| + eps (sign(0) = 0, as torch's abs backward). dss/losses.py scales both to the
// loss's mean; the torch expression there is the reference. Partial sums per block of 2^16
// elements in double, added in block order: the same bits at any thread count.
std::vector<torch::Tensor> smape_sum(torch::Tensor pred, torch::Tensor target, double eps_d, bool with_grad) {
  TORCH_CHECK(pred.sizes() == target.sizes(), "pred and target must have the same shape");
  pred = pred.contiguous().to(torch::kFloat32);
  target = target.contiguous().to(torch::kFloat32);
  const int64_t n = pred.numel();
  const float eps = (float)eps_d;
  auto grad = with_grad ? torch::empty_like(pred) : torch::empty({0}, pred.options());
  const float* X = pred.data_ptr<float>();
  const float* Y = target.data_ptr<float>();
  float* Gd = with_grad ? grad.data_ptr<float>() : nullptr;
  constexpr int64_t kBlock = 1 << 16;
  const int64_t nblocks = (n + kBlock - 1) / kBlock;
  std::vector<double> part((size_t)nblocks, 0.0);
  at::parallel_for(0, nblocks, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t b = b0; b < b1; ++b) {
      const int64_t e0 = b * kBlock, e1 = std::min(n, e0 + kBlock);
      double acc = 0.0;
      for (int64_t e = e0; e < e1; ++e) {
        const float x = X[e], y = Y[e];
        const float d = x - y, ad = std::fabs(d);
        const float s = std::fabs(x) + std::fabs(y) + eps;
        acc += ad / s;
        if (Gd) {
          const float sd = (d > 0.f) - (d < 0.f), sx = (x > 0.f) - (x < 0.f);
          Gd[e] = sd / s - ad * sx / (s * s);
        }
      }
      part[b] = acc;
    }
  });
  double total = 0.0;
  for (double p : part) total += p;
  return {torch::full({}, total, torch::TensorOptions().dtype(torch::kFloat64)), grad};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("rasterize_forward", &rasterize_forward, "DSS forward rasterisation (CPU)");
  m.def("visibility_backward", &visibility_backward, "DSS visibility gradient (CPU)");
  m.def("project_splats_forward", &project_splats_forward, "EWA splat projection, forward only (CPU)");
  m.def("project_splats_backward", &project_splats_backward, "EWA splat projection, backward (CPU)");
  m.def("smape_sum", &smape_sum, "SMAPE sum and its derivative in one pass (CPU)");
  m.def("empty_cache", &empty_cache, "free the parked output blocks; returns the bytes released");
  m.def("blend_backward", &blend_backward, "DSS smooth-term backward of the normalised sum (CPU)");
}
