// Weighted-PCA frames of the surface regularisers on the CPU (dss/regularizers.py local_frames,
// paper section "Surface regularization"), and the neighbour differences p_i - p_k with their
// backward.
//
// The torch expressions in local_frames are the twin (tests/test_regularizers.py compares). What
// decides which neighbours count (p_i - p_k, its squared length and the bandwidth test) is
// computed in the points' dtype in torch's operation order, so the two agree on the valid set;
// the weights, centroid and covariance are accumulated in double (torch: the points' dtype, then
// the covariance converted to double for its eigh), so values agree to the points' precision,
// not bit for bit. The 3x3 eigen-decomposition is cyclic Jacobi in double: eigenvalues ascending
// as torch.linalg.eigh returns them, eigenvectors orthonormal to double precision; their signs
// (and the basis of a repeated eigenvalue's plane) may differ from LAPACK's, which none of the
// regularisers' terms sees (they use n n^T and the tangent plane's projector).
//
// Why a kernel: torch runs the per-step weighted PCA as ~40 passes over (N, K) and (N, K, 3)
// tensors plus a batched eigh that LAPACK decomposes one matrix after another; at 20K points,
// K = 16 that was ~27 ms of the Quickstart job's ~60 ms steps, and the backward of the
// neighbour gather (an index_put with accumulation) another ~11 ms.
#include <torch/types.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <vector>

namespace {

// Cyclic Jacobi on n <= kEighBatch symmetric 3x3 matrices a (overwritten): eigenvalues ascending,
// eigenvectors as columns. Each matrix is first scaled by a power of two (exact) so that its
// largest entry is in [1, 2): no square below underflows or overflows for any scene scale. The
// matrices get the same rotations as each would alone (each stops at its own convergence), but
// interleaved, so the divisions and square roots of different matrices overlap: one matrix is a
// chain of them (measured ~400 ns per matrix alone, ~250 ns four at a time).
constexpr int kEighBatch = 4;
void sym3_eigh_batch(int n, double a[][3][3], double evals[][3], double evecs[][3][3]) {
  double v[kEighBatch][3][3];
  bool live[kEighBatch];
  int ex[kEighBatch];
  for (int m = 0; m < n; ++m) {
    double mx = 0;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) {
        v[m][r][c] = r == c ? 1.0 : 0.0;
        mx = std::max(mx, std::fabs(a[m][r][c]));
      }
    ex[m] = mx > 0 ? std::ilogb(mx) : 0;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) a[m][r][c] = std::ldexp(a[m][r][c], -ex[m]);
    live[m] = true;
  }
  for (int sweep = 0; sweep < 50; ++sweep) {
    bool any = false;
    for (int m = 0; m < n; ++m) {
      if (!live[m]) continue;
      const double off = std::fabs(a[m][0][1]) + std::fabs(a[m][0][2]) + std::fabs(a[m][1][2]);
      const double diag = std::fabs(a[m][0][0]) + std::fabs(a[m][1][1]) + std::fabs(a[m][2][2]);
      // off-diagonal below the diagonal's last bits (or an exact zero): converged (~3.4 sweeps
      // on planar neighbourhoods)
      live[m] = !(off == 0.0 || off <= 1e-18 * diag);
      any |= live[m];
    }
    if (!any) break;
    for (int p = 0; p < 2; ++p) {
      for (int q = p + 1; q < 3; ++q) {
        const int r = 3 - p - q;  // the third index
        for (int m = 0; m < n; ++m) {
          double(&A)[3][3] = a[m];
          const double g = 2.0 * A[p][q];
          if (!live[m] || g == 0.0) continue;
          // the rotation that zeroes A[p][q]: t = tan of its angle, the smaller root of
          // t^2 + 2 t theta - 1 = 0 with theta = h / g, written without theta's division
          const double h = A[q][q] - A[p][p];
          const double rr = std::sqrt(h * h + g * g);
          if (!(rr > 0)) {  // both below the scaled matrix's last bits
            A[p][q] = A[q][p] = 0.0;
            continue;
          }
          const double t = g / (h >= 0 ? h + rr : h - rr);
          const double c = 1.0 / std::sqrt(t * t + 1.0), s = t * c;
          const double apq = A[p][q];
          A[p][p] -= t * apq;
          A[q][q] += t * apq;
          A[p][q] = A[q][p] = 0.0;
          const double arp = A[r][p], arq = A[r][q];
          A[r][p] = A[p][r] = c * arp - s * arq;
          A[r][q] = A[q][r] = s * arp + c * arq;
          for (int i = 0; i < 3; ++i) {
            const double vip = v[m][i][p], viq = v[m][i][q];
            v[m][i][p] = c * vip - s * viq;
            v[m][i][q] = s * vip + c * viq;
          }
        }
      }
    }
  }
  for (int m = 0; m < n; ++m) {
    // ascending, ties in index order (three compare-exchanges)
    int order[3] = {0, 1, 2};
    const double d[3] = {a[m][0][0], a[m][1][1], a[m][2][2]};
    auto order_pair = [&](int x, int y) {
      if (d[order[y]] < d[order[x]]) std::swap(order[x], order[y]);
    };
    order_pair(0, 1);
    order_pair(1, 2);
    order_pair(0, 1);
    for (int c = 0; c < 3; ++c) {
      evals[m][c] = std::ldexp(d[order[c]], ex[m]);
      for (int i = 0; i < 3; ++i) evecs[m][i][c] = v[m][i][order[c]];
    }
  }
}

template <typename T>
void frames_impl(const T* P, const int64_t* I, const T* Nrm, const T* Occ, int64_t N, int64_t K, T lim2, double inv_d2,
                 int64_t min_nb, double inv_sharp, bool squared, bool* valid, T* psi, T* w, T* centroid, T* evals,
                 T* evecs) {
  // unit normals (F.normalize: x / max(|x|, 1e-12)), each read by ~K neighbourhoods
  std::vector<double> un(Nrm ? (size_t)N * 3 : 0);
  if (Nrm)
    at::parallel_for(0, N, 4096, [&](int64_t begin, int64_t end) {
      for (int64_t i = begin; i < end; ++i) {
        const T* n = Nrm + i * 3;
        const double len = std::max(std::sqrt((double)n[0] * n[0] + (double)n[1] * n[1] + (double)n[2] * n[2]), 1e-12);
        for (int c = 0; c < 3; ++c) un[(size_t)(i * 3 + c)] = n[c] / len;
      }
    });
  at::parallel_for(0, N, 256, [&](int64_t begin, int64_t end) {
    std::vector<double> ww((size_t)K);
    double covs[kEighBatch][3][3];  // the covariances of points i0..i, decomposed as a group
    int64_t i0 = begin;
    for (int64_t i = begin; i < end; ++i) {
      const T* pi = P + i * 3;
      const int64_t* ii = I + i * K;
      bool* vi = valid + i * K;
      T* psii = psi + i * K;
      const double* ni = Nrm ? un.data() + i * 3 : nullptr;
      double wsum = 0.0;
      for (int64_t k = 0; k < K; ++k) {
        const int64_t j = ii[k];
        const T* pj = P + std::max<int64_t>(j, 0) * 3;  // -1 gathers row 0, masked below (as torch)
        // the points' dtype and torch's order: (p_i - p_k) per axis, then ((x^2 + y^2) + z^2)
        const T dx = pi[0] - pj[0], dy = pi[1] - pj[1], dz = pi[2] - pj[2];
        const T dist2 = dx * dx + dy * dy + dz * dz;
        const bool ok = j >= 0 && (dist2 <= lim2 || k < min_nb);
        vi[k] = ok;
        double wk = 0.0;
        if (ok) {
          // exponentials in the points' dtype (psi is stored in it; float's exp is ~3x cheaper)
          const double ps = std::exp((T)(-(double)dist2 * inv_d2));
          psii[k] = (T)ps;
          wk = ps;
          if (ni) {
            const double* nj = un.data() + j * 3;
            const double cs = nj[0] * ni[0] + nj[1] * ni[1] + nj[2] * ni[2];
            wk *= std::exp((T)(-(1.0 - cs) * (1.0 - cs) * inv_sharp));
          }
          if (Occ) wk *= 1.0 / ((double)Occ[j] + 1.0);
        } else {
          psii[k] = 0;
        }
        ww[(size_t)k] = wk;
        wsum += wk;
      }
      // rows whose weights all vanish keep w = 0 (and a zero covariance: identity frame)
      const double inv_sum = wsum > 0 ? 1.0 / wsum : 0.0;
      double c[3] = {0, 0, 0};
      for (int64_t k = 0; k < K; ++k) {
        ww[(size_t)k] *= inv_sum;
        w[i * K + k] = (T)ww[(size_t)k];
        const T* pj = P + std::max<int64_t>(ii[k], 0) * 3;
        for (int a = 0; a < 3; ++a) c[a] += ww[(size_t)k] * pj[a];
      }
      double(&cov)[3][3] = covs[i - i0];
      for (int a = 0; a < 3; ++a)
        for (int b = 0; b < 3; ++b) cov[a][b] = 0.0;
      for (int64_t k = 0; k < K; ++k) {
        if (!vi[k]) continue;
        const T* pj = P + ii[k] * 3;
        const double e[3] = {pj[0] - c[0], pj[1] - c[1], pj[2] - c[2]};
        const double cw = squared ? ww[(size_t)k] * ww[(size_t)k] : ww[(size_t)k];
        for (int a = 0; a < 3; ++a)
          for (int b = a; b < 3; ++b) cov[a][b] += cw * e[a] * e[b];
      }
      cov[1][0] = cov[0][1], cov[2][0] = cov[0][2], cov[2][1] = cov[1][2];
      for (int a = 0; a < 3; ++a) centroid[i * 3 + a] = (T)c[a];
      if (i - i0 + 1 < kEighBatch && i + 1 < end) continue;
      // decompose the group's covariances together
      const int n = (int)(i - i0 + 1);
      double ev[kEighBatch][3], V[kEighBatch][3][3];
      sym3_eigh_batch(n, covs, ev, V);
      for (int m = 0; m < n; ++m)
        for (int a = 0; a < 3; ++a) {
          evals[(i0 + m) * 3 + a] = (T)ev[m][a];
          for (int b = 0; b < 3; ++b) evecs[(i0 + m) * 9 + a * 3 + b] = (T)V[m][a][b];
        }
      i0 = i + 1;
    }
  });
}

void check_points(const torch::Tensor& points, const torch::Tensor& idx) {
  TORCH_CHECK(points.dim() == 2 && points.size(1) == 3, "points must be (N, 3)");
  TORCH_CHECK(points.scalar_type() == torch::kFloat32 || points.scalar_type() == torch::kFloat64,
              "points must be float32 or float64");
  TORCH_CHECK(idx.dim() == 2 && idx.size(0) == points.size(0) && idx.scalar_type() == torch::kInt64,
              "idx must be (N, K) int64");
  TORCH_CHECK(!points.is_cuda() && !idx.is_cuda(), "CPU tensors only");
}

// Neighbour indices must be -1 (none) or a point's row: the kernels read those rows unchecked.
void check_indices(const torch::Tensor& idx, int64_t n_points) {
  const int64_t* I = idx.data_ptr<int64_t>();
  const int64_t n = idx.numel();
  bool ok = true;
  for (int64_t e = 0; e < n; ++e) ok &= I[e] >= -1 && I[e] < n_points;
  TORCH_CHECK(ok, "neighbour indices must be -1 or in [0, ", n_points, "): the neighbour list is not for these points");
}

}  // namespace

// local_frames' detached part: returns (valid (N,K) bool, psi (N,K), w (N,K), centroid (N,3),
// eigenvalues (N,3) ascending, eigenvectors (N,3,3) as columns), all but valid in the points'
// dtype. normals / occlusion: (N,3) / (N,) or empty tensors for none. lim2 = (cutoff D)^2,
// inv_d2 = 1 / D^2, inv_sharp = 1 / max(1e-5, 1 - cos Theta); neighbour idx -1 = none.
std::vector<torch::Tensor> local_frames_forward(torch::Tensor points, torch::Tensor idx, torch::Tensor normals,
                                                torch::Tensor occlusion, double lim2, double inv_d2,
                                                int64_t min_neighbors, double inv_sharp, bool squared) {
  check_points(points, idx);
  points = points.contiguous();
  idx = idx.contiguous();
  const int64_t N = points.size(0), K = idx.size(1);
  check_indices(idx, N);
  const bool has_n = normals.numel() > 0, has_o = occlusion.numel() > 0;
  if (has_n) {
    TORCH_CHECK(normals.dim() == 2 && normals.size(0) == N && normals.size(1) == 3, "normals must be (N, 3)");
    normals = normals.contiguous().to(points.scalar_type());
  }
  if (has_o) {
    TORCH_CHECK(occlusion.dim() == 1 && occlusion.size(0) == N, "occlusion must be (N,)");
    occlusion = occlusion.contiguous().to(points.scalar_type());
  }
  auto opt = points.options();
  auto valid = torch::empty({N, K}, opt.dtype(torch::kBool));
  auto psi = torch::empty({N, K}, opt), w = torch::empty({N, K}, opt);
  auto centroid = torch::empty({N, 3}, opt), evals = torch::empty({N, 3}, opt), evecs = torch::empty({N, 3, 3}, opt);
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "local_frames_forward", [&] {
    frames_impl<scalar_t>(points.data_ptr<scalar_t>(), idx.data_ptr<int64_t>(),
                          has_n ? normals.data_ptr<scalar_t>() : nullptr,
                          has_o ? occlusion.data_ptr<scalar_t>() : nullptr, N, K, (scalar_t)lim2, inv_d2,
                          min_neighbors, inv_sharp, squared, valid.data_ptr<bool>(), psi.data_ptr<scalar_t>(),
                          w.data_ptr<scalar_t>(), centroid.data_ptr<scalar_t>(), evals.data_ptr<scalar_t>(),
                          evecs.data_ptr<scalar_t>());
  });
  return {valid, psi, w, centroid, evals, evecs};
}

// diff[i, k] = (p_i - p_idx[i,k]) if valid[i, k] else 0: (N, K, 3) in the points' dtype, the
// values of torch's (points[:, None] - points[idx.clamp(min=0)]) * valid.
torch::Tensor neighbor_diff_forward(torch::Tensor points, torch::Tensor idx, torch::Tensor valid) {
  check_points(points, idx);
  TORCH_CHECK(valid.sizes() == idx.sizes() && valid.scalar_type() == torch::kBool, "valid must be (N, K) bool like idx");
  points = points.contiguous();
  idx = idx.contiguous();
  valid = valid.contiguous();
  const int64_t N = points.size(0), K = idx.size(1);
  check_indices(idx, N);
  auto out = torch::empty({N, K, 3}, points.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "neighbor_diff_forward", [&] {
    const scalar_t* P = points.data_ptr<scalar_t>();
    const int64_t* I = idx.data_ptr<int64_t>();
    const bool* Vd = valid.data_ptr<bool>();
    scalar_t* O = out.data_ptr<scalar_t>();
    at::parallel_for(0, N, 1024, [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i)
        for (int64_t k = 0; k < K; ++k) {
          const int64_t j = I[i * K + k];
          scalar_t* o = O + (i * K + k) * 3;
          if (Vd[i * K + k] && j >= 0) {
            for (int a = 0; a < 3; ++a) o[a] = P[i * 3 + a] - P[j * 3 + a];
          } else {
            o[0] = o[1] = o[2] = 0;
          }
        }
    });
  });
  return out;
}

// Backward of neighbor_diff_forward: dL/dp_i = sum_k g[i,k] - sum_{(m,k): idx[m,k] = i} g[m,k]
// over valid entries. The first sum runs per point in parallel; the second is a scatter, run on
// one thread in (m, k) order so the result does not depend on the thread count.
torch::Tensor neighbor_diff_backward(torch::Tensor grad, torch::Tensor idx, torch::Tensor valid) {
  TORCH_CHECK(grad.dim() == 3 && grad.size(2) == 3 && grad.size(0) == idx.size(0) && grad.size(1) == idx.size(1),
              "grad must be (N, K, 3) like the neighbour list");
  grad = grad.contiguous();
  idx = idx.contiguous();
  valid = valid.contiguous();
  const int64_t N = idx.size(0), K = idx.size(1);  // one neighbour row per point
  auto out = torch::empty({N, 3}, grad.options());
  AT_DISPATCH_FLOATING_TYPES(grad.scalar_type(), "neighbor_diff_backward", [&] {
    const scalar_t* G = grad.data_ptr<scalar_t>();
    const int64_t* I = idx.data_ptr<int64_t>();
    const bool* Vd = valid.data_ptr<bool>();
    scalar_t* O = out.data_ptr<scalar_t>();
    at::parallel_for(0, N, 1024, [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i) {
        scalar_t s[3] = {0, 0, 0};
        for (int64_t k = 0; k < K; ++k)
          if (Vd[i * K + k])
            for (int a = 0; a < 3; ++a) s[a] += G[(i * K + k) * 3 + a];
        for (int a = 0; a < 3; ++a) O[i * 3 + a] = s[a];
      }
    });
    for (int64_t m = 0; m < N; ++m)
      for (int64_t k = 0; k < K; ++k) {
        const int64_t j = I[m * K + k];
        if (!Vd[m * K + k] || j < 0) continue;
        for (int a = 0; a < 3; ++a) O[j * 3 + a] -= G[(m * K + k) * 3 + a];
      }
  });
  return out;
}
