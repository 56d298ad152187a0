// The CPU module's Python bindings (dss/_ext.py builds it from every *_cpu.cpp file); the entry
// points and the file of each are listed in dss_cpu.h.
#include <torch/extension.h>

#include "dss_cpu.h"

using dss_cpu::empty_cache;
using dss_cpu::max_vector_level;
using dss_cpu::vector_level;
using dss_cpu::vector_path_available;

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("rasterize_forward", &rasterize_forward, "DSS forward rasterisation (CPU)");
  m.def("visibility_backward", &visibility_backward, "DSS visibility gradient (CPU)");
  m.def("set_vector_path", &set_vector_path,
        "enable/disable the vector paths (AVX2: rasterize_forward's tile loop and write-out, visibility_backward's "
        "dss rule, the projection's forward and backward loops, smape_sum, the sun shader's backward; AVX-512: "
        "visibility_backward's windows of 9-15 columns, the binning's box scan); returns whether they were enabled");
  m.def("vector_path_available", &vector_path_available, "whether this build and CPU have the AVX2 paths");
  m.def("set_vector_level", &set_vector_level,
        "the highest vector level the kernels may take: 0 scalar, 1 AVX2, 2 AVX-512; returns the previous setting");
  m.def("vector_level", &vector_level, "the vector level the kernels take now (0 scalar, 1 AVX2, 2 AVX-512)");
  m.def("max_vector_level", &max_vector_level, "the highest vector level this build and CPU have");
  m.def("project_splats_forward", &project_splats_forward, "EWA splat projection, forward only (CPU)");
  m.def("project_splats_backward", &project_splats_backward, "EWA splat projection, backward (CPU)");
  m.def("tangent_planes_forward", &tangent_planes_forward, "inverse-depth tangent planes (V,N,3) (CPU)");
  m.def("splat_exp", &splat_exp, "the kernels' float32 exp, element-wise (tests)");
  m.def("morton_order", &morton_order, "stable Z-order permutation of (N, 3) float32 points (CPU)");
  m.def("smape_sum", &smape_sum, "SMAPE sum and its derivative in one pass (CPU)");
  m.def("empty_cache", &empty_cache, "free the parked output blocks; returns the bytes released");
  m.def("blend_backward", &blend_backward, "DSS smooth-term backward of the normalised sum (CPU)", py::arg("packed"),
        py::arg("attrs"), py::arg("idx"), py::arg("depth"), py::arg("rho"), py::arg("images"), py::arg("grad"),
        py::arg("merge"), py::arg("mask") = py::none());
  m.def("sun_shade_forward", &sun_shade_forward, "sun-light shading (V,N,3) of (N,3) normals (CPU)");
  m.def("sun_shade_backward", &sun_shade_backward, "backward of sun_shade_forward (CPU)");
  m.def("local_frames_forward", &local_frames_forward, "the regularisers' weighted PCA frames, detached (CPU)");
  m.def("neighbor_diff_forward", &neighbor_diff_forward, "(p_i - p_k) over valid neighbours, (N,K,3) (CPU)");
  m.def("neighbor_diff_backward", &neighbor_diff_backward, "backward of neighbor_diff_forward (CPU)");
  m.def("knn_grid", &knn_grid, "exact k nearest 3D neighbours on a uniform grid (CPU)");
}
