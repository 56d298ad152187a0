// Torch glue of the DSS CUDA kernels (dss_cuda.cu): checks, allocation, the binning scan and the
// launches on the current CUDA stream. Same function names and signatures as dss_cpu.cpp, taking
// CUDA tensors, so the two modules are interchangeable.
//
// Built by dss/_ext_cuda.py with torch.utils.cpp_extension.load on a machine with a GPU. With
// -DDSS_CUDA_EMULATION (tests/cuda_emu) it is built against CPU tensors and the kernels run on
// CPU threads, so the glue and the kernels are exercised where there is no GPU.
#include <torch/extension.h>

#include <climits>
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
  TORCH_CHECK(t.device() == dev, "dss_cuda: ", name, " is on ", t.device(), " but the splats are on ", dev);
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
  check_launch(dss_cuda::launch_bin_count(P, V, N, (int)H, (int)W, counts.data_ptr<int32_t>(), stream), "bin_count");
  auto bin_end = torch::cumsum(counts, 0, torch::kInt64);
  auto bin_start = bin_end - counts;
  const int64_t total = VT > 0 ? bin_end[VT - 1].item<int64_t>() : 0;  // synchronises: sizes the bins
  auto cursor = bin_start.clone();
  auto list = torch::empty({std::max<int64_t>(total, 1)}, opt_i32);
  check_launch(dss_cuda::launch_bin_fill(P, V, N, (int)H, (int)W, cursor.data_ptr<int64_t>(),
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

// Visibility gradient (paper Eqs. gradcase, filteredG); the rules of dss_cpu.cpp
// visibility_backward, one thread per (view, point). Returns dL/dp (N,3) f32, world space.
torch::Tensor visibility_backward(torch::Tensor packed, torch::Tensor attrs, torch::Tensor idx, torch::Tensor depth,
                                  torch::Tensor rho, torch::Tensor images, torch::Tensor grad, torch::Tensor R,
                                  torch::Tensor focal, torch::Tensor principal, torch::Tensor background,
                                  torch::Tensor planes, int64_t window, int64_t stride, double cutoff_d, double merge_d, double eps_d,
                                  int64_t mode) {
  TORCH_CHECK(packed.dim() == 3 && packed.size(2) == dss_cuda::kFields, "packed splats must be (V,N,10)");
  TORCH_CHECK(!kOnGpu || packed.is_cuda(), "dss_cuda: packed splats must be a CUDA tensor");
  TORCH_CHECK(packed.size(1) < INT_MAX, "too many points for int32 indices");
  TORCH_CHECK(idx.dim() == 4 && idx.scalar_type() == torch::kInt32, "idx must be (V,H,W,K) int32");
  TORCH_CHECK(stride >= 1, "window stride must be >= 1");
  TORCH_CHECK(window >= 0 && window < (1 << 20), "window must be in [0, 2^20)");
  TORCH_CHECK(mode == 0 || mode == 1, "mode must be 0 (dss) or 1 (rbf)");
  DSS_DEVICE_GUARD(packed);
  const auto dev = packed.device();
  packed = packed.to(torch::kFloat32).contiguous();
  const int64_t V = packed.size(0), N = packed.size(1), H = idx.size(1), W = idx.size(2), K = idx.size(3);
  TORCH_CHECK(idx.size(0) == V, "idx must have V = ", V, " views");
  TORCH_CHECK(K >= 1 && K <= dss_cuda::kMaxK, "K must be in [1, ", dss_cuda::kMaxK, "]");
  TORCH_CHECK(attrs.dim() == 3 && attrs.size(0) == V && attrs.size(1) == N, "attrs must be (V,N,C)");
  const int64_t C = attrs.size(2);
  TORCH_CHECK(C >= 1 && C <= dss_cuda::kMaxC, "1 to ", dss_cuda::kMaxC, " channels, got ", C);
  attrs = prep(attrs, dev, torch::kFloat32, "attrs");
  idx = prep(idx, dev, torch::kInt32, "idx");
  depth = prep(depth, dev, torch::kFloat32, "depth");
  rho = prep(rho, dev, torch::kFloat32, "rho");
  images = prep(images, dev, torch::kFloat32, "images");
  grad = prep(grad, dev, torch::kFloat32, "grad");
  R = prep(R, dev, torch::kFloat32, "R");
  focal = prep(focal, dev, torch::kFloat32, "focal");
  principal = prep(principal, dev, torch::kFloat32, "principal");
  background = prep(background, dev, torch::kFloat32, "background");
  planes = prep(planes, dev, torch::kFloat32, "planes");
  TORCH_CHECK(planes.numel() == V * N * 3, "planes must be (V,N,3)");
  TORCH_CHECK(depth.sizes() == idx.sizes() && rho.sizes() == idx.sizes(), "depth and rho must be shaped like idx");
  TORCH_CHECK(images.numel() == V * H * W * C && grad.numel() == V * H * W * C, "images and grad must be (V,H,W,C)");
  TORCH_CHECK(R.numel() == V * 9 && focal.numel() == V && principal.numel() == V * 2,
              "camera tensors must have V views");
  TORCH_CHECK(background.numel() == C, "background must have C entries");

  const cudaStream_t stream = current_stream();
  auto partial = torch::empty({V, N, 3}, torch::TensorOptions().dtype(torch::kFloat64).device(dev));
  auto records = torch::empty({V * H * W * dss_cuda::vis_record_floats((int)K, (int)C)},
                              torch::TensorOptions().dtype(torch::kFloat32).device(dev));
  auto out = torch::empty({N, 3}, torch::TensorOptions().dtype(torch::kFloat32).device(dev));
  check_launch(dss_cuda::launch_visibility(
                   packed.data_ptr<float>(), attrs.data_ptr<float>(), idx.data_ptr<int32_t>(),
                   depth.data_ptr<float>(), rho.data_ptr<float>(), images.data_ptr<float>(), grad.data_ptr<float>(),
                   R.data_ptr<float>(), focal.data_ptr<float>(), principal.data_ptr<float>(),
                   background.data_ptr<float>(), planes.data_ptr<float>(), V, N, (int)H, (int)W, (int)K, (int)C, (int)window, (int)stride,
                   (float)cutoff_d, (float)merge_d, (float)eps_d, (int)mode, records.data_ptr<float>(),
                   partial.data_ptr<double>(), stream),
               "visibility");
  check_launch(dss_cuda::launch_reduce_views(packed.data_ptr<float>(), partial.data_ptr<double>(), V, N,
                                             out.data_ptr<float>(), stream),
               "reduce_views");
  return out;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("rasterize_forward", &rasterize_forward, "DSS forward rasterisation (CUDA, tile binned)");
  m.def("visibility_backward", &visibility_backward, "DSS visibility gradient (CUDA)");
}
