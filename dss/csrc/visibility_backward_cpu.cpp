// The visibility gradient on the CPU (paper Eqs. gradcase, filteredG, cases (a), (b), (c)): per
// view, the pixel records (visibility_backward_cpu.h), then each point's screen window, on the scalar path
// or a vector walk (visibility_backward_cpu_avx2.h, visibility_backward_cpu_avx512.h) with the same bits.
#include "cpu_common.h"
#include "dss_cpu.h"
#include "visibility_backward_cpu.h"
#include "visibility_backward_cpu_avx2.h"
#include "visibility_backward_cpu_avx512.h"

using namespace dss_cpu;

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
  TORCH_CHECK(K >= 1 && K <= 8, "K must be in [1, 8]");
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

  // The pixel record (VisRecord) of one view at a time: a few MB, cache-resident while that
  // view's points read it; planes (structure of arrays) for the vector path, one record per
  // pixel otherwise (a scalar evaluation then reads 2 cache lines, not one per field). Kept
  // between calls (no fresh pages per call).
  const int64_t HW = H * W;
  // The vector path needs window rows of at least 8 pixels (window >= 4); narrower windows would
  // only run eval_scalar on planes, slower than on per-pixel records.
  const bool vec = mode == 0 && stride == 1 && 2 * window + 1 >= 8 && use_vector_path();
  std::vector<double> gsum((size_t)(N * 3), 0.0);  // world gradient, summed over views in view order
  const int64_t Krt = K, Crt = C;  // run-time values; the evaluation loop may fix them at compile time
  const int64_t kChunk = 64;
  const float inf = std::numeric_limits<float>::infinity();
#ifdef DSS_HAVE_AVX2
  // windows of 9 to 15 columns in 16 lanes, a row per vector, where the CPU has AVX-512; the
  // 8-lane walk's chunk plan otherwise
  const bool rows16 = vec && use_avx512() && window >= 4 && window <= 7;
  VisFlatPlan flat_plan;
  const VisFlatPlan* flat = vec && !rows16 && flat_plan.build(window, W) ? &flat_plan : nullptr;
#endif
  static thread_local std::vector<float> rec_f;
  static thread_local std::vector<int32_t> rec_i;
#ifdef DSS_HAVE_AVX2
  // Per point, a flag per window row (kFlagRows bytes; windows of 9 to 15 rows): non-zero where k is
  // cached at some evaluated pixel of that row; the vector walks' rows (chunks) without it skip
  // the cache scan (VisLanes16::eval_nok, VisLanes::eval_nok). Flags, not a bit mask: the record
  // build sets them from both threads, and plain byte stores of 1 need no atomic
  // read-modify-write (which cost a fifth of the build).
  const bool kf = vec && window >= 4 && 2 * window + 1 <= kFlagRows;
  static thread_local std::vector<uint8_t> krows;
  if (kf) krows.resize((size_t)(N * kFlagRows));
  uint8_t* const kr = krows.data();  // (the vector is this thread's: the tasks use the pointer)
#endif
  auto run = [&](auto layout) {
    constexpr bool kSoA = decltype(layout)::value;
    VisRecord<kSoA> rec;
    rec.C_ = C;
    rec.K_ = K;
    if (kSoA) {
      rec.S = VisRecord<kSoA>::plane_stride(HW);
      rec_f.resize((size_t)(rec.S * VisRecord<kSoA>::fields(C, K)));
      rec_i.resize((size_t)(rec.S * K));
      rec.ix = rec_i.data();
    } else {
      rec.S = VisRecord<kSoA>::fields(C, K);
      rec_f.resize((size_t)(rec.S * HW));
    }
    rec.f = rec_f.data();
    for (int64_t v = 0; v < V; ++v) {
      if (!kSoA) rec.ix = const_cast<int32_t*>(I + v * HW * K);  // read only
#ifdef DSS_HAVE_AVX2
      if (kf) std::memset(kr, 0, (size_t)(N * kFlagRows));
#endif
      dynamic_for(H, 4, [&](int64_t i) {
        // the row's pixels with a non-zero loss gradient (the only ones an evaluation reads
        // further), found in one pass over the gradient row
        static thread_local std::vector<int32_t> col_list;  // (this worker thread's)
        if ((int64_t)col_list.size() < W) col_list.resize((size_t)W);
        int32_t* const cols = col_list.data();
        int ncols = 0;
        for (int64_t j = 0; j < W; ++j) {
          const float* gp = GR + (v * HW + i * W + j) * C;
          bool nz = false;
          for (int64_t ch = 0; ch < C; ++ch) nz |= (gp[ch] != 0.f);
          rec.nz(i * W + j) = nz ? 1.f : 0.f;
          cols[ncols] = (int32_t)j;
          ncols += nz;
        }
        for (int c = 0; c < ncols; ++c) {
          const int64_t j = cols[c], p = i * W + j, g = v * HW + p;
          if (c + kPixelsAhead < ncols) {
            // the cached splats' attributes are scattered rows (a miss each): fetch those of the
            // pixel kPixelsAhead on while this one is built (as the blend backward does)
            const int32_t* qi = I + (v * HW + i * W + cols[c + kPixelsAhead]) * K;
            for (int e = 0; e < K && qi[e] >= 0; ++e) {
              __builtin_prefetch(A + (v * N + qi[e]) * C);
#ifdef DSS_HAVE_AVX2
              if (kf) __builtin_prefetch(P + (v * N + qi[e]) * kFields);
#endif
            }
          }
          const float* gp = GR + g * C;
          const int32_t* pi = I + g * K;
          const float* pd = D + g * K;
          const float* pr = Rh + g * K;
          const float* ip = IMG + g * C;
          float gi = 0.f, gb = 0.f;
          for (int64_t ch = 0; ch < C; ++ch) {
            rec.g(ch, p) = gp[ch];
            gi += gp[ch] * ip[ch];
            gb += gp[ch] * BG[ch];
          }
          rec.gi(p) = gi;
          rec.gb(p) = gb;
          const float d0 = pi[0] >= 0 ? pd[0] : inf;
#ifdef DSS_HAVE_AVX2
          if (kf) {
            // mark row i of the window of every point cached here, if this pixel is in it (the
            // window's centre pixel as the point loop computes it)
            for (int e = 0; e < K && pi[e] >= 0; ++e) {
              const float* sk = P + (v * N + pi[e]) * kFields;
              const int64_t r = i - ((int64_t)std::floor(sk[1]) - window), c = j - ((int64_t)std::floor(sk[0]) - window);
              if (r >= 0 && r <= 2 * window && c >= 0 && c <= 2 * window)
                __atomic_store_n(&kr[pi[e] * kFlagRows + r], (uint8_t)1, __ATOMIC_RELAXED);
            }
          }
#endif
          float gwe[8];
          for (int64_t e = 0; e < K; ++e) {
            if (kSoA) rec.idx(e, p) = pi[e];
            rec.dep(e, p) = pd[e];
            rec.rho(e, p) = pr[e];
            float ga = 0.f;
            if (pi[e] >= 0) {
              const float* a = A + (v * N + pi[e]) * C;
              for (int64_t ch = 0; ch < C; ++ch) ga += gp[ch] * a[ch];
            }
            rec.gw(e, p) = gwe[e] = ga;
          }
          float den = 0.f, gnum = 0.f;
          for (int64_t e = 0; e < K && pi[e] >= 0 && pd[e] <= d0 + merge; ++e) {
            den += pr[e];
            gnum += pr[e] * gwe[e];
          }
          rec.d0(p) = d0;
          rec.den(p) = den;
          rec.gn(p) = gnum;
        }
      });
      const VisConsts Q{F[v], PP[v * 2], PP[v * 2 + 1], 1.f / F[v], cutoff, merge, eps};
      const float* Rv = Rm + v * 9;
      const float* PLv = PL + v * N * 3;
      // A task is a run of consecutive (spatially sorted) points: their windows overlap in the
      // record. Each point is one task's, so it owns its gsum row (no race; views added in view
      // order). (Ordering the points by screen tile first measured no faster.)
      const int64_t nchunks = (N + kChunk - 1) / kChunk;
      // The evaluation, compiled for the common (K, C) = (5, 3) and (5, 1) with constant trip
      // counts (the cache scans and channel dots unroll) and for any (K, C) at run time.
      auto points_task = [&](auto KT, auto CT, int64_t task) {
        constexpr int64_t KC = decltype(KT)::value, CC = decltype(CT)::value;
        const auto R = rec.template fixed<KC, CC>();
        const int64_t k_begin = task * kChunk, k_end = std::min(N, k_begin + kChunk);
        for (int64_t k = k_begin; k < k_end; ++k) {
          const float* s = P + (v * N + k) * kFields;
          if (!(s[9] > 0.f)) continue;
          VisPoint pt;
          pt.s = s;
          pt.wk = A + (v * N + k) * Crt;
          pt.pl = PLv + k * 3;
          pt.k = (int32_t)k;
          pt.u = s[0];
          pt.v = s[1];
          pt.z = s[6];
          pt.nk = s[5];
          pt.z_f = pt.z * Q.inv_f;
          pt.X = (pt.u - Q.cx) * pt.z_f;
          pt.Y = (pt.v - Q.cy) * pt.z_f;
          pt.slope = kMaxSlope * pt.z_f;
          const int ic = (int)std::floor(pt.v), jc = (int)std::floor(pt.u);
          double acc[3] = {0, 0, 0};
          bool done = false;
#ifdef DSS_HAVE_AVX2
          if constexpr (kSoA) {
            if (rows16) {
              window_rows_avx512<KC, CC>(R, Krt, Crt, pt, Q, H, W, window, ic, jc, kr + k * kFlagRows, acc);
              done = true;
            } else if (vec) {
              window_dss_avx2<KC, CC>(R, Krt, Crt, pt, Q, H, W, window, ic, jc, flat, kf ? kr + k * kFlagRows : nullptr,
                                      acc);
              done = true;
            }
          }
#endif
          if (!done) {  // partial sums in the order of dss_splat::vis_partial, as the vector path
            double part[dss_splat::kVisPartials][3] = {};
            const int mw = dss_splat::vis_window_runs(window);
            for (int64_t dy = -window; dy <= window; dy += stride) {
              const int64_t i = ic + dy;
              if (i < 0 || i >= H) continue;
              const float py = (float)i + 0.5f;
              for (int64_t dx = -window; dx <= window; dx += stride) {
                const int64_t j = jc + dx;
                if (j < 0 || j >= W) continue;
                const int64_t p = i * W + j;
                if (R.nz(p) == 0.f) continue;
                eval_scalar<KC, CC>(R, Krt, Crt, pt, Q, mode, p, (float)j + 0.5f, py,
                                    part[dss_splat::vis_partial(dx + window, mw)]);
              }
            }
            add_partials(part, dss_splat::vis_partial_count(window), acc);
          }
          double* gk = gsum.data() + k * 3;  // world gradient = R^T acc
          for (int a = 0; a < 3; ++a)
            gk[a] += Rv[0 * 3 + a] * acc[0] + Rv[1 * 3 + a] * acc[1] + Rv[2 * 3 + a] * acc[2];
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
  };
  if (vec)
    run(std::true_type{});
  else
    run(std::false_type{});
  for (int64_t e = 0; e < N * 3; ++e) G[e] = (float)gsum[e];
  return out;
}
