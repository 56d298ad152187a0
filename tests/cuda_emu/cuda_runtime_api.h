// CPU stand-in for the CUDA runtime, for tests only (tests/test_cuda_build.py).
//
// With this directory first on the include path, the CUDA kernels (dss/csrc/*_cuda.cu) compile as plain C++:
// every kernel launch (DSS_LAUNCH) runs its blocks one after the other, each block's threads as
// real std::threads with a real barrier for __syncthreads(), __shared__ arrays are function
// statics (one block at a time), atomics are GCC atomics. Slow, but it runs the kernels' own
// code, indexing and synchronisation included, where there is no GPU.
#pragma once

#include <condition_variable>
#include <cstdint>
#include <mutex>
#include <thread>
#include <vector>

typedef int cudaError_t;
constexpr cudaError_t cudaSuccess = 0;
constexpr cudaError_t cudaErrorInvalidValue = 1;
typedef struct CUstream_st* cudaStream_t;

inline const char* cudaGetErrorString(cudaError_t e) { return e == cudaSuccess ? "no error" : "invalid argument"; }
inline cudaError_t cudaGetLastError() { return cudaSuccess; }

struct dim3 {
  unsigned int x, y, z;
  dim3(unsigned int x_ = 1, unsigned int y_ = 1, unsigned int z_ = 1) : x(x_), y(y_), z(z_) {}
};

namespace dss_emu {

class Barrier {
 public:
  explicit Barrier(int n) : n_(n) {}
  void wait() {
    std::unique_lock<std::mutex> lk(m_);
    const long gen = gen_;
    if (++waiting_ == n_) {
      waiting_ = 0;
      ++gen_;
      cv_.notify_all();
    } else {
      cv_.wait(lk, [&] { return gen_ != gen; });
    }
  }

 private:
  std::mutex m_;
  std::condition_variable cv_;
  int n_, waiting_ = 0;
  long gen_ = 0;
};

inline thread_local dim3 tl_threadIdx, tl_blockIdx, tl_blockDim, tl_gridDim;
inline thread_local Barrier* tl_barrier = nullptr;

template <class... P>
struct Launch {
  dim3 grid, block;
  void (*kernel)(P...);
  template <class... A>
  void operator()(A... args) const {
    const unsigned int nt = block.x * block.y * block.z;
    for (unsigned int bz = 0; bz < grid.z; ++bz)
      for (unsigned int by = 0; by < grid.y; ++by)
        for (unsigned int bx = 0; bx < grid.x; ++bx) {
          Barrier bar((int)nt);
          std::vector<std::thread> threads;
          threads.reserve(nt);
          for (unsigned int t = 0; t < nt; ++t)
            threads.emplace_back([&, t] {
              tl_threadIdx = dim3(t % block.x, (t / block.x) % block.y, t / (block.x * block.y));
              tl_blockIdx = dim3(bx, by, bz);
              tl_blockDim = block;
              tl_gridDim = grid;
              tl_barrier = &bar;
              kernel(args...);
            });
          for (auto& th : threads) th.join();
        }
  }
};

template <class... P>
Launch<P...> launch(dim3 grid, dim3 block, void (*kernel)(P...)) {
  return Launch<P...>{grid, block, kernel};
}

}  // namespace dss_emu

#define DSS_LAUNCH(kernel, grid, block, stream) ((void)(stream), ::dss_emu::launch(dim3(grid), dim3(block), kernel))

#ifdef DSS_EMU_KERNELS  // device-side vocabulary, only in the translation unit of the kernels
#define __global__
#define __device__
#define __host__
#define __forceinline__ inline
#define __launch_bounds__(...)
#define __shared__ static
#define threadIdx (::dss_emu::tl_threadIdx)
#define blockIdx (::dss_emu::tl_blockIdx)
#define blockDim (::dss_emu::tl_blockDim)
#define gridDim (::dss_emu::tl_gridDim)
inline void __syncthreads() { ::dss_emu::tl_barrier->wait(); }
template <class T>
inline T atomicAdd(T* p, T v) {
  return __atomic_fetch_add(p, v, __ATOMIC_SEQ_CST);
}
template <class T>
inline T min(T a, T b) {
  return b < a ? b : a;
}
template <class T>
inline T max(T a, T b) {
  return a < b ? b : a;
}
#endif
