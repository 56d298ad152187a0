// The entry points of the CPU module (dss_cpu_bind.cpp binds them; dss/_ext.py builds it), one
// source file per stage, all float32 unless named:
//
//   rasterize_cpu.cpp            rasterize_forward: packed (V,N,10), attrs (V,N,C) -> top-K cache
//                                (idx, depth, rho: (V,H,W,K)), images (V,H,W,C), mask (V,H,W)
//   visibility_backward_cpu.cpp  visibility_backward: the visibility term of dL/dpoints (N,3)
//   blend_backward_cpu.cpp       blend_backward: dL/dpacked (V,N,10), dL/dattrs (V,N,C)
//   projection_cpu.cpp           project_splats_forward / _backward, tangent_planes_forward
//   shading_cpu.cpp              sun_shade_forward / _backward: (V,N,3) sun-light weights
//   loss_cpu.cpp                 smape_sum: SMAPE sum and its derivative
//   ordering_cpu.cpp             morton_order: (N,) int64 Z-order permutation
//   frames_cpu.cpp               local_frames_forward, neighbor_diff_forward / _backward
//   knn_cpu.cpp                  knn_grid: exact k nearest neighbours on a uniform grid
//   cpu_runtime.cpp              the block cache, the vector-level switch, splat_exp
//
// Shared headers: cpu_common.h (every stage), splat_math.h (formulas shared with the CUDA
// kernels); a stage's own records and scalar code in <stage>_cpu.h, its AVX2 / AVX-512 code in
// <stage>_cpu_avx2.h / <stage>_cpu_avx512.h beside it.
#pragma once

#include <torch/types.h>

#include <optional>
#include <vector>

std::vector<torch::Tensor> rasterize_forward(torch::Tensor packed, torch::Tensor attrs, int64_t H, int64_t W,
                                             int64_t K, double cutoff_d, double merge_d, torch::Tensor background);
torch::Tensor visibility_backward(torch::Tensor packed, torch::Tensor attrs, torch::Tensor idx, torch::Tensor depth,
                                  torch::Tensor rho, torch::Tensor images, torch::Tensor grad, torch::Tensor R,
                                  torch::Tensor focal, torch::Tensor principal, torch::Tensor background,
                                  torch::Tensor planes, int64_t window, int64_t stride, double cutoff_d,
                                  double merge_d, double eps_d, int64_t mode);
std::vector<torch::Tensor> blend_backward(torch::Tensor packed, torch::Tensor attrs, torch::Tensor idx,
                                          torch::Tensor depth, torch::Tensor rho, torch::Tensor images,
                                          torch::Tensor grad, double merge_d, std::optional<torch::Tensor> mask_opt);
torch::Tensor project_splats_forward(torch::Tensor points, torch::Tensor normals, torch::Tensor R, torch::Tensor t,
                                     torch::Tensor focal, torch::Tensor principal, torch::Tensor sigma,
                                     double cutoff, bool culling, double znear, double filter_variance);
std::vector<torch::Tensor> project_splats_backward(torch::Tensor points, torch::Tensor normals, torch::Tensor R,
                                                   torch::Tensor t, torch::Tensor focal, torch::Tensor principal,
                                                   torch::Tensor sigma, torch::Tensor packed, torch::Tensor grad,
                                                   double cutoff, double filter_variance);
torch::Tensor tangent_planes_forward(torch::Tensor points, torch::Tensor normals, torch::Tensor R, torch::Tensor t,
                                     torch::Tensor focal, torch::Tensor principal, bool center);
torch::Tensor sun_shade_forward(torch::Tensor normals, torch::Tensor albedo, torch::Tensor dirs, double ambient);
std::vector<torch::Tensor> sun_shade_backward(torch::Tensor normals, torch::Tensor albedo, torch::Tensor dirs,
                                              double ambient, torch::Tensor grad, bool need_albedo);
std::vector<torch::Tensor> smape_sum(torch::Tensor pred, torch::Tensor target, double eps_d, double grad_scale,
                                     bool need_grad);
torch::Tensor morton_order(torch::Tensor points);
torch::Tensor splat_exp(torch::Tensor x);
bool set_vector_path(bool on);
int64_t set_vector_level(int64_t level);
std::vector<torch::Tensor> local_frames_forward(torch::Tensor points, torch::Tensor idx, torch::Tensor normals,
                                                torch::Tensor occlusion, double lim2, double inv_d2,
                                                int64_t min_neighbors, double inv_sharp, bool squared);
torch::Tensor neighbor_diff_forward(torch::Tensor points, torch::Tensor idx, torch::Tensor valid);
torch::Tensor neighbor_diff_backward(torch::Tensor grad, torch::Tensor idx, torch::Tensor valid);
std::vector<torch::Tensor> knn_grid(torch::Tensor ref, torch::Tensor query, int64_t k, double radius);

namespace dss_cpu {
int64_t empty_cache();            // frees the parked output blocks; returns the bytes released
bool vector_path_available();     // this build and CPU have the AVX2 paths
int64_t max_vector_level();       // the highest vector level this build and CPU have
int64_t vector_level();           // the level the kernels take now
}  // namespace dss_cpu
