// The CUDA kernels (dss/csrc/*_cuda.cu) compiled as C++ against the CPU stand-in of the CUDA runtime (tests only),
// plus C entry points for ctypes: g++ -shared -fPIC -pthread -I tests/cuda_emu -I dss/csrc.
#define DSS_EMU_KERNELS
#include "cuda_runtime_api.h"
#include "blend_backward_cuda.cu"
#include "projection_cuda.cu"
#include "rasterize_cuda.cu"
#include "shading_cuda.cu"
#include "visibility_backward_cuda.cu"

extern "C" {

int emu_bin_count(const float* packed, int64_t V, int64_t N, int H, int W, float cutoff, int32_t* counts) {
  return dss_cuda::launch_bin_count(packed, V, N, H, W, cutoff, counts, nullptr);
}

int emu_bin_fill(const float* packed, int64_t V, int64_t N, int H, int W, float cutoff, int64_t* cursor,
                 int32_t* list) {
  return dss_cuda::launch_bin_fill(packed, V, N, H, W, cutoff, cursor, list, nullptr);
}

int emu_rasterize_tiles(const float* packed, int64_t V, int64_t N, int H, int W, int K, const int64_t* bin_start,
                        const int64_t* bin_end, const int32_t* list, float cutoff, float merge, const float* attrs,
                        int C, const float* background, int32_t* idx, float* depth, float* rho, float* images,
                        bool* mask) {
  return dss_cuda::launch_rasterize_tiles(packed, V, N, H, W, K, bin_start, bin_end, list, cutoff, merge, attrs, C,
                                          background, idx, depth, rho, images, mask, nullptr);
}

int emu_visibility(const float* packed, const float* attrs, const int32_t* idx, const float* depth, const float* rho,
                   const float* images, const float* grad, const float* R, const float* focal, const float* principal,
                   const float* background, const float* planes, int64_t V, int64_t N, int H, int W, int K, int C, int window, int stride,
                   float cutoff, float merge, float eps, int mode, double* partial) {
  std::vector<float> records((size_t)(V * H * W * dss_cuda::vis_record_floats(K, C)));
  return dss_cuda::launch_visibility(packed, attrs, idx, depth, rho, images, grad, R, focal, principal, background,
                                     planes, V, N, H, W, K, C, window, stride, cutoff, merge, eps, mode,
                                     records.data(), partial, nullptr);
}

int emu_reduce_views(const float* packed, const double* partial, int64_t V, int64_t N, float* out) {
  return dss_cuda::launch_reduce_views(packed, partial, V, N, out, nullptr);
}

int emu_project_forward(const float* points, const float* normals, const float* R, const float* t, const float* focal,
                        const float* principal, const float* sigma, int64_t V, int64_t N, float cutoff, int culling,
                        float znear, float filter_variance, float* packed) {
  return dss_cuda::launch_project_forward(points, normals, R, t, focal, principal, sigma, V, N, cutoff, culling != 0,
                                          znear, filter_variance, packed, nullptr);
}

int emu_project_backward(const float* points, const float* normals, const float* R, const float* t, const float* focal,
                         const float* sigma, const float* packed, const float* grad, int64_t V, int64_t N, float cutoff,
                         float filter_variance, float* grad_points, float* grad_normals) {
  return dss_cuda::launch_project_backward(points, normals, R, t, focal, sigma, packed, grad, V, N, cutoff,
                                           filter_variance, grad_points, grad_normals, nullptr);
}

int emu_sun_forward(const float* normals, const float* albedo, const float* dirs, int64_t V, int64_t N, float ambient,
                    float* out) {
  return dss_cuda::launch_sun_forward(normals, albedo, dirs, V, N, ambient, out, nullptr);
}

int emu_sun_backward(const float* normals, const float* albedo, const float* dirs, const float* grad, int64_t V,
                     int64_t N, float ambient, float* grad_normals, float* grad_albedo) {
  return dss_cuda::launch_sun_backward(normals, albedo, dirs, grad, V, N, ambient, grad_normals, grad_albedo, nullptr);
}

int emu_blend_backward(const float* packed, const float* attrs, const int32_t* idx, const float* depth,
                       const float* rho, const float* images, const float* grad, int64_t V, int64_t N, int H, int W,
                       int K, int C, float merge, float* grad_packed, float* grad_attrs) {
  return dss_cuda::launch_blend_backward(packed, attrs, idx, depth, rho, images, grad, V, N, H, W, K, C, merge,
                                         grad_packed, grad_attrs, nullptr);
}

}  // extern "C"
