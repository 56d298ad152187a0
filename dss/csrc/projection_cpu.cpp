// The EWA splat projection on the CPU (dss/splats.py project_splats; the per-splat formulas are
// in splat_math.h, shared with the CUDA kernel), forward and backward, and the tangent planes of
// the visibility gradient's occlusion test. Each loop is compiled for the baseline and for AVX2
// (project_*_avx2, the same body): the same bits.
#include "cpu_common.h"
#include "dss_cpu.h"

using namespace dss_cpu;

// The projection of one splat, forward and backward: splat_math.h (shared with the CUDA kernel).
using dss_splat::project_backward_one;
using dss_splat::project_forward_one;

// One view's points [k0, k1) of project_splats_forward: straight-line code (the branches are
// selects) so that the compiler vectorises the loop; every lane does the scalar loop's float32
// operations in the same order (no contraction: -ffp-contract=off), so both give the same bits.
struct ProjectView {
  const float *Pp, *Nn, *Rv, *tv, *Sg;
  float f, cx, cy, fv, C2, zn;
  bool culling;
};

DSS_INLINE void project_forward_range(const ProjectView& a, int64_t k0, int64_t k1, float* O) {
  // (the view's values in locals: stores through o could alias a's fields otherwise)
  const float *Pp = a.Pp, *Nn = a.Nn, *Rv = a.Rv, *tv = a.tv, *Sg = a.Sg;
  const float f = a.f, cx = a.cx, cy = a.cy, fv = a.fv, C2 = a.C2, zn = a.zn;
  const bool culling = a.culling;
#pragma omp simd
  for (int64_t k = k0; k < k1; ++k)
    project_forward_one(Pp + k * 3, Nn + k * 3, Rv, tv, f, cx, cy, Sg[k], fv, C2, zn, culling, O + k * kFields);
}

#ifdef DSS_HAVE_AVX2
DSS_AVX2 void project_forward_avx2(const ProjectView& a, int64_t k0, int64_t k1, float* O) {
  project_forward_range(a, k0, k1, O);
}
#endif

// The point and camera inputs of the projection and tangent-plane kernels as contiguous float32
// (in place; no copy where they already are).
inline void points_cameras_f32(torch::Tensor& points, torch::Tensor& normals, torch::Tensor& R, torch::Tensor& t,
                               torch::Tensor& focal, torch::Tensor& principal) {
  for (torch::Tensor* x : {&points, &normals, &R, &t, &focal, &principal}) *x = x->contiguous().to(torch::kFloat32);
}

// Forward-only fused version of dss/splats.py project_splats (same formulas; used when no
// gradient is needed, where the torch version's many (V, N) temporaries dominate at 100K points).
torch::Tensor project_splats_forward(torch::Tensor points, torch::Tensor normals, torch::Tensor R, torch::Tensor t,
                                     torch::Tensor focal, torch::Tensor principal, torch::Tensor sigma,
                                     double cutoff, bool culling, double znear, double filter_variance) {
  points_cameras_f32(points, normals, R, t, focal, principal);
  const int64_t N = points.size(0), V = R.size(0);
  sigma = sigma.to(torch::kFloat32).expand({N}).contiguous();
  auto out = pooled_empty({V, N, kFields}, torch::kFloat32);
  const float* Rr = R.data_ptr<float>();
  const float* Tt = t.data_ptr<float>();
  const float* Ff = focal.data_ptr<float>();
  const float* Cc = principal.data_ptr<float>();
  float* O = out.data_ptr<float>();
  const bool vec = use_vector_path();
  const int64_t nb = (N + 1023) / 1024;
  dynamic_for(V * nb, 1, [&](int64_t item) {
    const int64_t v = item / nb, k0 = (item % nb) * 1024, k1 = std::min(N, k0 + 1024);
    const ProjectView a{points.data_ptr<float>(), normals.data_ptr<float>(), Rr + v * 9, Tt + v * 3,
                        sigma.data_ptr<float>(), Ff[v], Cc[v * 2], Cc[v * 2 + 1], (float)filter_variance,
                        2.f * (float)cutoff, (float)znear, culling};
#ifdef DSS_HAVE_AVX2
    if (vec) {
      project_forward_avx2(a, k0, k1, O + v * N * kFields);
      return;
    }
#endif
    project_forward_range(a, k0, k1, O + v * N * kFields);  // the baseline build
  });
  return out;
}

// One view's gradients of the points [b0, b0 + n), n <= 64, of project_splats_backward added to
// acc: dL/dp and dL/dn (world frame) as six planes (acc[c][j]: dL/dp_c of point b0 + j for c < 3,
// dL/dn_(c-3) after). Straight-line like project_forward_range (culled splats compute values that
// a select replaces with zeros), so the loop vectorises with the scalar bits; it runs only on
// groups of 8 splats of which one at least is valid with a gradient row that is not all zeros
// (49% of the groups in a 20K-point step, where 35% of the (view, point) pairs are such: half the
// splats face away, and many valid ones reach no pixel's visible set). The other groups add
// nothing: their splats' terms are +-0, which leave a sum that started at +0 unchanged.
// (Packing the active splats side by side first measured slower: 1.92 -> 2.49 ms at 20K points,
// the packing's scalar moves.)
struct ProjectGradView {
  const float *Pp, *Nn, *Rv, *tv, *Sg, *PK, *GK;
  float f, fv, C;
};
constexpr int kProjectBlock = 64;

template <bool kVec>
DSS_INLINE void project_backward_block(const ProjectGradView& a, int64_t b0, int n, float (*acc)[kProjectBlock]) {
  // (the view's values in locals: stores through acc could alias a's fields otherwise)
  const float *Pp = a.Pp, *Nn = a.Nn, *Rv = a.Rv, *tv = a.tv, *Sg = a.Sg, *PK = a.PK, *GK = a.GK;
  const float f = a.f, fv = a.fv, C = a.C;
  static_assert(kProjectBlock == 64, "rows_to_planes writes planes of 64");
  // The gradient's fields 0-8 and the packed rows' 7-9 transposed to planes first: the vectoriser
  // takes no strided loads from rows of 10 with gaps.
  // (fields 2-9 of the packed rows: rows_to_planes moves at least 8; 7-9 are pk[5..7])
  alignas(32) float gk[9][kProjectBlock], pk[8][kProjectBlock];
  rows_to_planes<kVec>(GK + b0 * kFields, n, 0, 9, gk);
  rows_to_planes<kVec>(PK + b0 * kFields, n, 2, 8, pk);
  alignas(32) int act[kProjectBlock];
  for (int j = 0; j < n; ++j) {
    bool nz = false;
    for (int c = 0; c < 9; ++c) nz |= gk[c][j] != 0.f;
    act[j] = (pk[7][j] > 0.f) & nz;
  }
  for (int g0 = 0; g0 < n; g0 += 8) {
    const int g1 = std::min(n, g0 + 8);
    int any = 0;
    for (int j = g0; j < g1; ++j) any |= act[j];
    if (!any) continue;
#pragma omp simd
    for (int j = g0; j < g1; ++j) {
      const int64_t k = b0 + j;
      // culled splats get no gradient (the renderer never reads them)
      const dss_splat::SplatGrad sg =
          project_backward_one(Pp + k * 3, Nn + k * 3, Rv, tv, f, Sg[k], fv, C, gk[0][j], gk[1][j], gk[2][j],
                               gk[3][j], gk[4][j], gk[5][j], gk[6][j], gk[7][j], gk[8][j], pk[5][j], pk[6][j],
                               pk[7][j] > 0.f);
      for (int c = 0; c < 3; ++c) {
        acc[c][j] += sg.gp[c];
        acc[3 + c][j] += sg.gn[c];
      }
    }
  }
}

#ifdef DSS_HAVE_AVX2
DSS_AVX2 void project_backward_avx2(const ProjectGradView& a, int64_t b0, int n, float (*acc)[kProjectBlock]) {
  project_backward_block<true>(a, b0, n, acc);
}
#endif

// Inverse-depth tangent planes (V, N, 3) for the visibility gradient's occlusion test
// (dss/splats.py tangent_planes, its torch twin; splat_math.h tangent_plane_one): one pass over
// (view, point) instead of ~20 torch operators on (V, N) tensors (20K points, 12 views, 2
// threads: 3.2-4.0 ms in torch, 1.0-1.2 ms here). center: (0, 0, 1 / z) for every point.
torch::Tensor tangent_planes_forward(torch::Tensor points, torch::Tensor normals, torch::Tensor R, torch::Tensor t,
                                     torch::Tensor focal, torch::Tensor principal, bool center) {
  TORCH_CHECK(points.dim() == 2 && points.size(1) == 3 && normals.sizes() == points.sizes(),
              "points and normals must be (N, 3)");
  TORCH_CHECK(R.dim() == 3 && R.size(1) == 3 && R.size(2) == 3, "R must be (V, 3, 3)");
  points_cameras_f32(points, normals, R, t, focal, principal);
  const int64_t N = points.size(0), V = R.size(0);
  TORCH_CHECK(t.numel() == V * 3 && focal.numel() == V && principal.numel() == V * 2, "one camera per view");
  auto out = pooled_empty({V, N, 3}, torch::kFloat32);  // every entry is written below
  const float *Pp = points.data_ptr<float>(), *Nn = normals.data_ptr<float>(), *Rr = R.data_ptr<float>();
  const float *Tt = t.data_ptr<float>(), *Ff = focal.data_ptr<float>(), *Cc = principal.data_ptr<float>();
  float* O = out.data_ptr<float>();
  const int64_t nb = (N + 4095) / 4096;
  dynamic_for(V * nb, 1, [&](int64_t item) {
    const int64_t v = item / nb, k0 = (item % nb) * 4096, k1 = std::min(N, k0 + 4096);
    for (int64_t k = k0; k < k1; ++k)
      dss_splat::tangent_plane_one(Pp + k * 3, Nn + k * 3, Rr + v * 9, Tt + v * 3, Ff[v], Cc[v * 2], Cc[v * 2 + 1],
                                   center, O + (v * N + k) * 3);
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
  points_cameras_f32(points, normals, R, t, focal, principal);
  packed = packed.contiguous().to(torch::kFloat32);
  grad = grad.contiguous().to(torch::kFloat32);
  const int64_t N = points.size(0), V = R.size(0);
  TORCH_CHECK(packed.size(0) == V && packed.size(1) == N && packed.size(2) == kFields, "packed must be (V,N,10)");
  TORCH_CHECK(grad.sizes() == packed.sizes(), "grad must be shaped like packed");
  sigma = sigma.to(torch::kFloat32).expand({N}).contiguous();
  const float* Rr = R.data_ptr<float>();
  const float* Tt = t.data_ptr<float>();
  const float* Ff = focal.data_ptr<float>();
  const float* PK = packed.data_ptr<float>();
  const float* GK = grad.data_ptr<float>();
  auto gp = torch::empty({N, 3}, torch::TensorOptions().dtype(torch::kFloat32));
  auto gn = torch::empty({N, 3}, torch::TensorOptions().dtype(torch::kFloat32));
  float* GP = gp.data_ptr<float>();
  float* GN = gn.data_ptr<float>();
  const bool vec = use_vector_path();
  // A work item is a run of points; each block of them goes through the views in view order,
  // adding to its own sums (the same order at any thread count, and no per-view planes to write
  // and read back).
  constexpr int kItemBlocks = 16;  // a view's rows of an item in one sequential run (40 KB each)
  constexpr int64_t kItem = kItemBlocks * kProjectBlock;
  dynamic_for((N + kItem - 1) / kItem, 1, [&](int64_t item) {
    const int64_t k0 = item * kItem, k1 = std::min(N, k0 + kItem);
    alignas(32) float acc[kItemBlocks][6][kProjectBlock] = {};
    for (int64_t v = 0; v < V; ++v) {
      const ProjectGradView a{points.data_ptr<float>(), normals.data_ptr<float>(), Rr + v * 9, Tt + v * 3,
                              sigma.data_ptr<float>(), PK + v * N * kFields, GK + v * N * kFields, Ff[v],
                              (float)filter_variance, (float)cutoff};
      for (int64_t b0 = k0; b0 < k1; b0 += kProjectBlock) {
        const int n = (int)std::min<int64_t>(kProjectBlock, k1 - b0);
        auto* ab = acc[(b0 - k0) / kProjectBlock];
#ifdef DSS_HAVE_AVX2
        if (vec) {
          project_backward_avx2(a, b0, n, ab);
          continue;
        }
#endif
        project_backward_block<false>(a, b0, n, ab);  // the baseline build
      }
    }
    for (int64_t k = k0; k < k1; ++k)
      for (int c = 0; c < 3; ++c) {
        const auto* ab = acc[(k - k0) / kProjectBlock];
        GP[k * 3 + c] = ab[c][(k - k0) % kProjectBlock];
        GN[k * 3 + c] = ab[3 + c][(k - k0) % kProjectBlock];
      }
  });
  return {gp, gn};
}
