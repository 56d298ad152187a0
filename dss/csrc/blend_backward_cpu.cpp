// The blend's backward on the CPU: the smooth terms of Eq. sumI (paper Eqs. gradN, gradP without
// the visibility term).
#include "cpu_common.h"
#include "dss_cpu.h"

using namespace dss_cpu;

// Backward of Eq. sumI for the smooth terms (Eqs. gradN, gradP without the visibility term):
// I = sum_f rho_f w_f / sum_f rho_f over the visible cached fragments, rho_f = norm exp(-q/2),
// q = a dx^2 + b2 dx dy + c dy^2 with d = pixel centre - (u, v). Returns dL/dpacked (V,N,10)
// (u, v, conic a, b2, c, norm; zero for the other fields) and dL/dattrs (V,N,C).
// Parallel over views, each view scanning its own fragments once in row-major pixel order: a view
// owns its (v, k) accumulators (no race, a fixed sum order per point), and the work is the
// number of cached fragments, not (splat box area x K) per point as a point-parallel loop over
// each splat's box would be (2-4x slower at 20K points, 256 px).
// mask (optional): the rasteriser's (V,H,W) bool mask (den > 0: the pixels this loop visits, the
// same sum in the same order); without it, every pixel's cache row is read to find them.
std::vector<torch::Tensor> blend_backward(torch::Tensor packed, torch::Tensor attrs, torch::Tensor idx,
                                          torch::Tensor depth, torch::Tensor rho, torch::Tensor images,
                                          torch::Tensor grad, double merge_d, std::optional<torch::Tensor> mask_opt) {
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
  torch::Tensor mask = mask_opt.has_value() ? *mask_opt : torch::Tensor();
  const bool has_mask = mask.defined() && mask.numel() > 0;
  if (has_mask) {
    TORCH_CHECK(mask.dim() == 3 && mask.size(0) == V && mask.size(1) == H && mask.size(2) == W,
                "mask must be (V,H,W) like the cache");
    mask = mask.contiguous().to(torch::kBool);
  }
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
  const bool* MK = has_mask ? mask.data_ptr<bool>() : nullptr;
  float* GP = gpk.data_ptr<float>();
  float* GA = gat.data_ptr<float>();
  const int64_t S = 6 + C;  // per point: du, dv, da, db, dc, dnorm, then dL/dattr per channel
  const int64_t HW = H * W;
  dynamic_for(V, 1, [&](int64_t v) {
    static thread_local std::vector<double> acc;  // double sums, as the per-point loop had
    static thread_local std::vector<int32_t> pix;
    acc.assign((size_t)(N * S), 0.0);
    // The pixels to visit, in raster order. With the mask: 8 of its bytes at a time (9% of the
    // pixels hold a visible fragment at 20K points, 12 views of 256x256), so the 16 MB of index
    // rows of empty pixels are never read; without it, each pixel's first index.
    pix.resize((size_t)HW);
    int64_t np = 0;
    if (MK) {
      const bool* m = MK + v * HW;
      int64_t g = 0;
      for (; g + 8 <= HW; g += 8) {
        uint64_t word;
        std::memcpy(&word, m + g, 8);
        if (!word) continue;
        for (int b = 0; b < 8; ++b) {
          pix[np] = (int32_t)(g + b);
          np += m[g + b] ? 1 : 0;
        }
      }
      for (; g < HW; ++g) {
        pix[np] = (int32_t)g;
        np += m[g] ? 1 : 0;
      }
    } else {
      for (int64_t g = 0; g < HW; ++g) {
        pix[np] = (int32_t)g;
        np += I[(v * HW + g) * K] >= 0 ? 1 : 0;
      }
    }
    const float* Pv = P + v * N * kFields;
    const float* Av = A + v * N * C;
    for (int64_t q = 0; q < np; ++q) {
      if (q + 2 * kPixelsAhead < np) {
        // the cache rows, gradient and image of the pixel 2 kPixelsAhead visits on
        const int64_t g2 = v * HW + pix[q + 2 * kPixelsAhead];
        __builtin_prefetch(I + g2 * K);
        __builtin_prefetch(D + g2 * K);
        __builtin_prefetch(Rh + g2 * K);
        __builtin_prefetch(GR + g2 * C);
        __builtin_prefetch(IMG + g2 * C);
      }
      if (q + kPixelsAhead < np) {
        // Most cached splats cover only a few pixels of a view, so their rows (splat, attributes,
        // accumulators) are first touched here and miss the caches: fetch those of the pixel
        // kPixelsAhead visits on (its index row fetched above) while this one is processed.
        const int32_t* qi = I + (v * HW + pix[q + kPixelsAhead]) * K;
        for (int e = 0; e < K && qi[e] >= 0; ++e) {
          __builtin_prefetch(Pv + qi[e] * kFields);
          __builtin_prefetch(Av + qi[e] * C);
          __builtin_prefetch(acc.data() + qi[e] * S, 1);
        }
      }
      const int64_t gv = pix[q], g = v * HW + gv;
      const int64_t i = gv / W, j = gv % W;
      const int32_t* pi = I + g * K;
      const float* pd = D + g * K;
      const float* pr = Rh + g * K;
      // (every listed pixel has an entry; a mask true at an empty pixel finds den = 0 below)
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
      const double rden = 1.0 / (double)den;  // one division per pixel, not 2C per fragment
      const float py = (float)i + 0.5f;
      for (int e = 0; e < nvis; ++e) {
        const int64_t k = pi[e];
        const float* s = Pv + k * kFields;
        if (!(s[9] > 0.f)) continue;
        const float dx = ((float)j + 0.5f) - s[0], dy = py - s[1];
        dss_splat::blend_entry_grad(s, Av + k * C, gp, ip, C, pr[e], rden, dx, dy, acc.data() + k * S);
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
