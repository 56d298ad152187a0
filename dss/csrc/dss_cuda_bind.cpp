// Torch glue of the DSS CUDA kernels (the *_cuda.cu files, dss_cuda.h): checks, allocation, the binning scan and the
// launches on the current CUDA stream. Same function names and signatures as the CPU module (dss_cpu.h), taking
// CUDA tensors, so the two modules are interchangeable.
//
// Built by dss/_ext_cuda.py with torch.utils.cpp_extension.load on a machine with a GPU. With
// -DDSS_CUDA_EMULATION (tests/cuda_emu) it is built against CPU tensors and the kernels run on
// CPU threads, so the glue and the kernels are exercised where there is no GPU.
#include <torch/extension.h>

#include <climits>
#include <cstdlib>
#include <vector>

#include "dss_cuda.h"

#ifndef DSS_CUDA_EMULATION
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#endif

namespace {

#ifndef DSS_CUDA_EMULATION
constexpr bool kOnGpu = true;
inline cudaStream_t current_stream() { return c10::cuda::getCurrentCUDAStream().stream(); }
#define DSS_DEVICE_GUARD(t) const c10::cuda::CUDAGuard dss_device_guard_((t).device())
#else
constexpr bool kOnGpu = false;
inline cudaStream_t current_stream() { return nullptr; }
#define DSS_DEVICE_GUARD(t) (void)0
#endif

void check_launch(cudaError_t err, const char* what) {
  TORCH_CHECK(err == cudaSuccess, "dss_cuda: ", what, " failed: ", cudaGetErrorString(err));
}

// Same device as the splats, float32 (or the given type), contiguous.
torch::Tensor prep(const torch::Tensor& t, const torch::Device& dev, torch::ScalarType type, const char* name) {
  TORCH_CHECK(t.device() == dev, "dss_cuda: ", name, " is on ", t.device(), " but the other inputs are on ", dev);
  return t.to(type).contiguous();
}

}  // namespace

// Forward: top-K cache per pixel and (optionally) the blended image.
// packed (V,N,10) f32, attrs (V,N,C) f32 or empty, background (C) f32.
// Returns idx (V,H,W,K) i32, depth, rho (V,H,W,K) f32, images (V,H,W,C) f32 (empty without attrs),
// mask (V,H,W) bool.
std::vector<torch::Tensor> rasterize_forward(torch::Tensor packed, torch::Tensor attrs, int64_t H, int64_t W,
                                             int64_t K, double cutoff_d, double merge_d, torch::Tensor background) {
  TORCH_CHECK(packed.dim() == 3 && packed.size(2) == dss_cuda::kFields, "packed splats must be (V,N,10)");
  TORCH_CHECK(!kOnGpu || packed.is_cuda(), "dss_cuda: packed splats must be a CUDA tensor");
  TORCH_CHECK(K >= 1 && K <= dss_cuda::kMaxK, "K must be in [1, ", dss_cuda::kMaxK, "], got ", K);
  TORCH_CHECK(H >= 1 && W >= 1, "image size must be positive, got ", H, "x", W);
  TORCH_CHECK(packed.size(1) < INT_MAX, "too many points for int32 indices");
  DSS_DEVICE_GUARD(packed);
  const auto dev = packed.device();
  packed = packed.to(torch::kFloat32).contiguous();
  const int64_t V = packed.size(0), N = packed.size(1);
  const bool do_blend = attrs.numel() > 0;
  const int64_t C = do_blend ? attrs.size(2) : 0;
  if (do_blend) {
    TORCH_CHECK(attrs.dim() == 3 && attrs.size(0) == V && attrs.size(1) == N, "attrs must be (V,N,C)");
    TORCH_CHECK(C <= dss_cuda::kMaxC, "at most ", dss_cuda::kMaxC, " channels, got ", C);
    attrs = prep(attrs, dev, torch::kFloat32, "attrs");
    background = prep(background, dev, torch::kFloat32, "background");
    TORCH_CHECK(background.numel() == C, "background must have C entries");
  }
  const int64_t TX = (W + dss_cuda::kTile - 1) / dss_cuda::kTile, TY = (H + dss_cuda::kTile - 1) / dss_cuda::kTile;
  const int64_t VT = V * TX * TY;
  TORCH_CHECK(VT < INT_MAX, "too many screen tiles");
  const auto opt_i32 = torch::TensorOptions().dtype(torch::kInt32).device(dev);
  const auto opt_f32 = torch::TensorOptions().dtype(torch::kFloat32).device(dev);
  const cudaStream_t stream = current_stream();
  const float* P = packed.data_ptr<float>();

  // Tile binning: count, exclusive scan, fill.
  auto counts = torch::zeros({VT}, opt_i32);
  check_launch(dss_cuda::launch_bin_count(P, V, N, (int)H, (int)W, (float)cutoff_d, counts.data_ptr<int32_t>(), stream),
               "bin_count");
  auto bin_end = torch::cumsum(counts, 0, torch::kInt64);
  auto bin_start = bin_end - counts;
  const int64_t total = VT > 0 ? bin_end[VT - 1].item<int64_t>() : 0;  // synchronises: sizes the bins
  auto cursor = bin_start.clone();
  auto list = torch::empty({std::max<int64_t>(total, 1)}, opt_i32);
  check_launch(dss_cuda::launch_bin_fill(P, V, N, (int)H, (int)W, (float)cutoff_d, cursor.data_ptr<int64_t>(),
                                         list.data_ptr<int32_t>(), stream),
               "bin_fill");

  auto idx = torch::empty({V, H, W, K}, opt_i32);
  auto depth = torch::empty({V, H, W, K}, opt_f32);
  auto rho = torch::empty({V, H, W, K}, opt_f32);
  auto images = do_blend ? torch::empty({V, H, W, C}, opt_f32) : torch::empty({0}, opt_f32);
  auto mask = torch::empty({V, H, W}, torch::TensorOptions().dtype(torch::kBool).device(dev));
  check_launch(dss_cuda::launch_rasterize_tiles(
                   P, V, N, (int)H, (int)W, (int)K, bin_start.data_ptr<int64_t>(), bin_end.data_ptr<int64_t>(),
                   list.data_ptr<int32_t>(), (float)cutoff_d, (float)merge_d,
                   do_blend ? attrs.data_ptr<float>() : nullptr, (int)C,
                   do_blend ? background.data_ptr<float>() : nullptr, idx.data_ptr<int32_t>(),
                   depth.data_ptr<float>(), rho.data_ptr<float>(), do_blend ? images.data_ptr<float>() : nullptr,
                   mask.data_ptr<bool>(), stream),
               "rasterize_tiles");
  return {idx, depth, rho, images, mask};
}

namespace {

// The inputs of the backward kernels that read the forward's cache, checked (the CPU kernel's
// rules) and on the splats' device, float32 / int32, contiguous; with their sizes.
struct CacheInputs {
  torch::Tensor packed, attrs, idx, depth, rho, images, grad;
  int64_t V, N, H, W, K, C;
};

CacheInputs cache_inputs(torch::Tensor packed, torch::Tensor attrs, torch::Tensor idx, torch::Tensor depth,
                         torch::Tensor rho, torch::Tensor images, torch::Tensor grad) {
  TORCH_CHECK(packed.dim() == 3 && packed.size(2) == dss_cuda::kFields, "packed splats must be (V,N,10)");
  TORCH_CHECK(!kOnGpu || packed.is_cuda(), "dss_cuda: packed splats must be a CUDA tensor");
  TORCH_CHECK(packed.size(1) < INT_MAX, "too many points for int32 indices");
  TORCH_CHECK(idx.dim() == 4 && idx.scalar_type() == torch::kInt32, "idx must be (V,H,W,K) int32");
  const auto dev = packed.device();
  packed = packed.to(torch::kFloat32).contiguous();
  const int64_t V = packed.size(0), N = packed.size(1), H = idx.size(1), W = idx.size(2), K = idx.size(3);
  TORCH_CHECK(idx.size(0) == V, "idx must have V = ", V, " views");
  TORCH_CHECK(K >= 1 && K <= dss_cuda::kMaxK, "K must be in [1, ", dss_cuda::kMaxK, "]");
  TORCH_CHECK(attrs.dim() == 3 && attrs.size(0) == V && attrs.size(1) == N, "attrs must be (V,N,C)");
  const int64_t C = attrs.size(2);
  TORCH_CHECK(C >= 1 && C <= dss_cuda::kMaxC, "1 to ", dss_cuda::kMaxC, " channels, got ", C);
  CacheInputs in{packed, prep(attrs, dev, torch::kFloat32, "attrs"), prep(idx, dev, torch::kInt32, "idx"),
                 prep(depth, dev, torch::kFloat32, "depth"), prep(rho, dev, torch::kFloat32, "rho"),
                 prep(images, dev, torch::kFloat32, "images"), prep(grad, dev, torch::kFloat32, "grad"),
                 V, N, H, W, K, C};
  TORCH_CHECK(in.depth.sizes() == in.idx.sizes() && in.rho.sizes() == in.idx.sizes(),
              "depth and rho must be shaped like idx");
  TORCH_CHECK(in.images.numel() == V * H * W * C && in.grad.numel() == V * H * W * C,
              "images and grad must be (V,H,W,C)");
  return in;
}

}  // namespace

// Backward of Eq. sumI for the smooth terms (blend_backward_cpu.cpp): dL/dpacked (V,N,10)
// (fields 0-5, the rest zero) and dL/dattrs (V,N,C) from dL/dimages and the forward's cache.
std::vector<torch::Tensor> blend_backward(torch::Tensor packed, torch::Tensor attrs, torch::Tensor idx,
                                          torch::Tensor depth, torch::Tensor rho, torch::Tensor images,
                                          torch::Tensor grad, double merge_d) {
  DSS_DEVICE_GUARD(packed);
  const CacheInputs in = cache_inputs(packed, attrs, idx, depth, rho, images, grad);
  const int64_t V = in.V, N = in.N, C = in.C;
  auto gpk = torch::empty({V, N, dss_cuda::kFields}, in.packed.options());
  auto gat = torch::empty({V, N, C}, in.packed.options());
  check_launch(dss_cuda::launch_blend_backward(in.packed.data_ptr<float>(), in.attrs.data_ptr<float>(),
                                               in.idx.data_ptr<int32_t>(), in.depth.data_ptr<float>(),
                                               in.rho.data_ptr<float>(), in.images.data_ptr<float>(),
                                               in.grad.data_ptr<float>(), V, N, (int)in.H, (int)in.W, (int)in.K,
                                               (int)C, (float)merge_d, gpk.data_ptr<float>(), gat.data_ptr<float>(),
                                               current_stream()),
               "blend_backward");
  return {gpk, gat};
}

// Visibility gradient (paper Eqs. gradcase, filteredG); the rules of visibility_backward_cpu.h
// visibility_backward, one thread per (view, point). Returns dL/dp (N,3) f32, world space.
torch::Tensor visibility_backward(torch::Tensor packed, torch::Tensor attrs, torch::Tensor idx, torch::Tensor depth,
                                  torch::Tensor rho, torch::Tensor images, torch::Tensor grad, torch::Tensor R,
                                  torch::Tensor focal, torch::Tensor principal, torch::Tensor background,
                                  torch::Tensor planes, int64_t window, int64_t stride, double cutoff_d, double merge_d, double eps_d,
                                  int64_t mode) {
  TORCH_CHECK(stride >= 1, "window stride must be >= 1");
  TORCH_CHECK(window >= 0 && window < (1 << 20), "window must be in [0, 2^20)");
  TORCH_CHECK(mode == 0 || mode == 1, "mode must be 0 (dss) or 1 (rbf)");
  TORCH_CHECK(dss_cuda::visibility_order() >= 0, "the environment variable DSS_CUDA_VIS_ORDER must be 'partials' "
              "(the default) or 'rows', got '", std::getenv("DSS_CUDA_VIS_ORDER"), "'");
  DSS_DEVICE_GUARD(packed);
  const CacheInputs in = cache_inputs(packed, attrs, idx, depth, rho, images, grad);
  const int64_t V = in.V, N = in.N, H = in.H, W = in.W, K = in.K, C = in.C;
  const auto dev = in.packed.device();
  R = prep(R, dev, torch::kFloat32, "R");
  focal = prep(focal, dev, torch::kFloat32, "focal");
  principal = prep(principal, dev, torch::kFloat32, "principal");
  background = prep(background, dev, torch::kFloat32, "background");
  planes = prep(planes, dev, torch::kFloat32, "planes");
  TORCH_CHECK(planes.numel() == V * N * 3, "planes must be (V,N,3)");
  TORCH_CHECK(R.numel() == V * 9 && focal.numel() == V && principal.numel() == V * 2,
              "camera tensors must have V views");
  TORCH_CHECK(background.numel() == C, "background must have C entries");

  const cudaStream_t stream = current_stream();
  auto partial = torch::empty({V, N, 3}, torch::TensorOptions().dtype(torch::kFloat64).device(dev));
  auto records = torch::empty({V * H * W * dss_cuda::vis_record_floats((int)K, (int)C)},
                              torch::TensorOptions().dtype(torch::kFloat32).device(dev));
  auto out = torch::empty({N, 3}, torch::TensorOptions().dtype(torch::kFloat32).device(dev));
  check_launch(dss_cuda::launch_visibility(
                   in.packed.data_ptr<float>(), in.attrs.data_ptr<float>(), in.idx.data_ptr<int32_t>(),
                   in.depth.data_ptr<float>(), in.rho.data_ptr<float>(), in.images.data_ptr<float>(),
                   in.grad.data_ptr<float>(),
                   R.data_ptr<float>(), focal.data_ptr<float>(), principal.data_ptr<float>(),
                   background.data_ptr<float>(), planes.data_ptr<float>(), V, N, (int)H, (int)W, (int)K, (int)C, (int)window, (int)stride,
                   (float)cutoff_d, (float)merge_d, (float)eps_d, (int)mode, records.data_ptr<float>(),
                   partial.data_ptr<double>(), stream),
               "visibility");
  check_launch(dss_cuda::launch_reduce_views(in.packed.data_ptr<float>(), partial.data_ptr<double>(), V, N,
                                             out.data_ptr<float>(), stream),
               "reduce_views");
  return out;
}

namespace {

// The projection's inputs on the points' device, float32, contiguous, with the CPU kernel's checks.
struct ProjectInputs {
  torch::Tensor points, normals, R, t, focal, principal, sigma;
  int64_t V, N;
};

ProjectInputs project_inputs(torch::Tensor points, torch::Tensor normals, torch::Tensor R, torch::Tensor t,
                             torch::Tensor focal, torch::Tensor principal, torch::Tensor sigma) {
  TORCH_CHECK(points.dim() == 2 && points.size(1) == 3, "points must be (N,3)");
  TORCH_CHECK(!kOnGpu || points.is_cuda(), "dss_cuda: points must be a CUDA tensor");
  TORCH_CHECK(normals.sizes() == points.sizes(), "normals must be shaped like points");
  const auto dev = points.device();
  const int64_t N = points.size(0), V = R.size(0);
  ProjectInputs in{prep(points, dev, torch::kFloat32, "points"), prep(normals, dev, torch::kFloat32, "normals"),
                   prep(R, dev, torch::kFloat32, "R"), prep(t, dev, torch::kFloat32, "t"),
                   prep(focal, dev, torch::kFloat32, "focal"), prep(principal, dev, torch::kFloat32, "principal"),
                   prep(sigma, dev, torch::kFloat32, "sigma"), V, N};
  TORCH_CHECK(in.R.numel() == V * 9 && in.t.numel() == V * 3 && in.focal.numel() == V &&
                  in.principal.numel() == V * 2,
              "camera tensors must have V views");
  TORCH_CHECK(in.sigma.numel() == 1 || in.sigma.numel() == N, "sigma must be a scalar or (N,)");
  in.sigma = in.sigma.expand({N}).contiguous();
  return in;
}

}  // namespace

// EWA splat projection (dss/splats.py project_splats), forward only: packed (V,N,10) f32.
torch::Tensor project_splats_forward(torch::Tensor points, torch::Tensor normals, torch::Tensor R, torch::Tensor t,
                                     torch::Tensor focal, torch::Tensor principal, torch::Tensor sigma, double cutoff,
                                     bool culling, double znear, double filter_variance) {
  DSS_DEVICE_GUARD(points);
  const ProjectInputs in = project_inputs(points, normals, R, t, focal, principal, sigma);
  auto out = torch::empty({in.V, in.N, dss_cuda::kFields}, in.points.options());
  check_launch(dss_cuda::launch_project_forward(
                   in.points.data_ptr<float>(), in.normals.data_ptr<float>(), in.R.data_ptr<float>(),
                   in.t.data_ptr<float>(), in.focal.data_ptr<float>(), in.principal.data_ptr<float>(),
                   in.sigma.data_ptr<float>(), in.V, in.N, (float)cutoff, culling, (float)znear,
                   (float)filter_variance, out.data_ptr<float>(), current_stream()),
               "project_forward");
  return out;
}

// Its backward: dL/dpoints, dL/dnormals (N,3) f32 from dL/dpacked (V,N,10), sigma and cameras fixed.
std::vector<torch::Tensor> project_splats_backward(torch::Tensor points, torch::Tensor normals, torch::Tensor R,
                                                   torch::Tensor t, torch::Tensor focal, torch::Tensor principal,
                                                   torch::Tensor sigma, torch::Tensor packed, torch::Tensor grad,
                                                   double cutoff, double filter_variance) {
  DSS_DEVICE_GUARD(points);
  const ProjectInputs in = project_inputs(points, normals, R, t, focal, principal, sigma);
  const auto dev = in.points.device();
  packed = prep(packed, dev, torch::kFloat32, "packed");
  grad = prep(grad, dev, torch::kFloat32, "grad");
  TORCH_CHECK(packed.dim() == 3 && packed.size(0) == in.V && packed.size(1) == in.N &&
                  packed.size(2) == dss_cuda::kFields,
              "packed must be (V,N,10)");
  TORCH_CHECK(grad.sizes() == packed.sizes(), "grad must be shaped like packed");
  auto gp = torch::empty({in.N, 3}, in.points.options());
  auto gn = torch::empty({in.N, 3}, in.points.options());
  check_launch(dss_cuda::launch_project_backward(
                   in.points.data_ptr<float>(), in.normals.data_ptr<float>(), in.R.data_ptr<float>(),
                   in.t.data_ptr<float>(), in.focal.data_ptr<float>(), in.sigma.data_ptr<float>(),
                   packed.data_ptr<float>(), grad.data_ptr<float>(), in.V, in.N, (float)cutoff,
                   (float)filter_variance, gp.data_ptr<float>(), gn.data_ptr<float>(), current_stream()),
               "project_backward");
  return {gp, gn};
}

namespace {

// The sun shader's inputs on the normals' device, float32, contiguous, with the CPU kernel's checks.
std::vector<torch::Tensor> sun_inputs(torch::Tensor normals, torch::Tensor albedo, torch::Tensor dirs) {
  TORCH_CHECK(normals.dim() == 2 && normals.size(1) == 3, "normals must be (N, 3)");
  TORCH_CHECK(!kOnGpu || normals.is_cuda(), "dss_cuda: normals must be a CUDA tensor");
  const auto dev = normals.device();
  normals = prep(normals, dev, torch::kFloat32, "normals");
  dirs = prep(dirs, dev, torch::kFloat32, "dirs");
  TORCH_CHECK(dirs.dim() == 3 && dirs.size(1) == 3 && dirs.size(2) == 3, "dirs must be (V, 3, 3)");
  if (albedo.numel() > 0) {
    albedo = prep(albedo, dev, torch::kFloat32, "albedo");
    TORCH_CHECK(albedo.dim() == 2 && albedo.size(0) == normals.size(0) && albedo.size(1) == 3, "albedo must be (N, 3)");
  }
  return {normals, albedo, dirs};
}

}  // namespace

// Sun shading, one light per channel: (V,N,3) f32.
torch::Tensor sun_shade_forward(torch::Tensor normals, torch::Tensor albedo, torch::Tensor dirs, double ambient) {
  DSS_DEVICE_GUARD(normals);
  const auto in = sun_inputs(normals, albedo, dirs);
  const int64_t V = in[2].size(0), N = in[0].size(0);
  const bool has_alb = in[1].numel() > 0;
  auto out = torch::empty({V, N, 3}, in[0].options());
  check_launch(dss_cuda::launch_sun_forward(in[0].data_ptr<float>(), has_alb ? in[1].data_ptr<float>() : nullptr,
                                            in[2].data_ptr<float>(), V, N, (float)ambient, out.data_ptr<float>(),
                                            current_stream()),
               "sun_forward");
  return out;
}

// Its backward: dL/dnormals (N,3) and, with albedo and need_albedo, dL/dalbedo (N,3) (else empty).
std::vector<torch::Tensor> sun_shade_backward(torch::Tensor normals, torch::Tensor albedo, torch::Tensor dirs,
                                              double ambient, torch::Tensor grad, bool need_albedo) {
  DSS_DEVICE_GUARD(normals);
  const auto in = sun_inputs(normals, albedo, dirs);
  const int64_t V = in[2].size(0), N = in[0].size(0);
  const bool has_alb = in[1].numel() > 0;
  need_albedo = need_albedo && has_alb;
  grad = prep(grad, in[0].device(), torch::kFloat32, "grad");
  TORCH_CHECK(grad.dim() == 3 && grad.size(0) == V && grad.size(1) == N && grad.size(2) == 3, "grad must be (V, N, 3)");
  auto gn = torch::empty({N, 3}, in[0].options());
  auto ga = need_albedo ? torch::empty({N, 3}, in[0].options()) : torch::empty({0}, in[0].options());
  check_launch(dss_cuda::launch_sun_backward(in[0].data_ptr<float>(), has_alb ? in[1].data_ptr<float>() : nullptr,
                                             in[2].data_ptr<float>(), grad.data_ptr<float>(), V, N, (float)ambient,
                                             gn.data_ptr<float>(), need_albedo ? ga.data_ptr<float>() : nullptr,
                                             current_stream()),
               "sun_backward");
  return {gn, ga};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("sun_shade_forward", &sun_shade_forward, "sun shading, one light per channel (CUDA)");
  m.def("sun_shade_backward", &sun_shade_backward, "backward of sun_shade_forward (CUDA)");
  m.def("project_splats_forward", &project_splats_forward, "EWA splat projection, forward only (CUDA)");
  m.def("project_splats_backward", &project_splats_backward, "EWA splat projection, backward (CUDA)");
  m.def("rasterize_forward", &rasterize_forward, "DSS forward rasterisation (CUDA, tile binned)");
  m.def("visibility_backward", &visibility_backward, "DSS visibility gradient (CUDA)");
  m.def("blend_backward", &blend_backward, "DSS smooth-term backward of the normalised sum (CUDA)");
}
