"""Throughput and latency of the vector division, square root, reciprocal estimate and multiply
on this CPU, in cycles, for the questions the visibility backward raises (what bounds a window
row of ``VisLanes16::eval_nok``: its three divisions?).

    python -m experiments.vector_op_rates [--iters 20000000] [--out results/bench/vector_op_rates.json]

A small C++ program (compiled here with ``$CXX``, default ``g++``, at ``-O2``) times each
operation on 8 independent register chains (throughput: cycles per operation when the chains
overlap) and on one chain (latency: cycles from an operation's inputs to its result), for 8-lane
(AVX2, 256-bit) and, where the CPU has AVX-512F, 16-lane (512-bit) float vectors. Cycles are ns
times the clock estimated by a loop of one dependent integer addition per iteration (one cycle
each), so they hold only while the clock is steady; the ns are what was measured. No hardware
counters are needed (the development machine has none: a KVM guest). Single thread; run it
with the cores idle.
"""

from __future__ import annotations

import argparse
import json
import platform

from experiments.bench_common import main_for, run_cpp_program, write_result
from experiments.figures import command_line

# One function per (operation, width, chains): the operation applied to each chain in turn,
# the chains kept in registers by an empty asm that "reads and writes" them every iteration, so
# the compiler can neither hoist nor fuse the operations.
SOURCE = r"""
#include <immintrin.h>
#include <chrono>
#include <cstdio>
#include <cstdlib>

static double now_ns() {
  return std::chrono::duration<double, std::nano>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

static double clock_ghz(long n) {
  long x = 0;
  const double t0 = now_ns();
  for (long k = 0; k < n; ++k) { x += k; __asm__ volatile("" : "+r"(x)); }
  return n / (now_ns() - t0);
}

#define CHAINS8(F) a0 = F(a0); a1 = F(a1); a2 = F(a2); a3 = F(a3); a4 = F(a4); a5 = F(a5); a6 = F(a6); a7 = F(a7); \
  __asm__ volatile("" : "+v"(a0), "+v"(a1), "+v"(a2), "+v"(a3), "+v"(a4), "+v"(a5), "+v"(a6), "+v"(a7));
#define CHAIN1(F) a0 = F(a0); __asm__ volatile("" : "+v"(a0));

#define BENCH(NAME, WIDTH, T, SET1, F, ATTR)                                                         \
  ATTR static void bench_##NAME##_##WIDTH(long n, double ghz) {                                      \
    double ns[2];                                                                                    \
    for (int lat = 0; lat < 2; ++lat) {                                                              \
      T a0 = SET1(1.1f), a1 = a0, a2 = a0, a3 = a0, a4 = a0, a5 = a0, a6 = a0, a7 = a0;              \
      const double t0 = now_ns();                                                                    \
      if (lat) { for (long k = 0; k < n; ++k) { CHAIN1(F) } }                                        \
      else { for (long k = 0; k < n; ++k) { CHAINS8(F) } }                                           \
      const double t1 = now_ns();                                                                    \
      ns[lat] = (t1 - t0) / (lat ? n : 8.0 * n);                                                     \
    }                                                                                                \
    std::printf("{\"op\": \"%s\", \"lanes\": %d, \"throughput_ns\": %.4f, \"latency_ns\": %.4f, "    \
                "\"throughput_cycles\": %.2f, \"latency_cycles\": %.2f}\n",                         \
                #NAME, WIDTH / 32, ns[0], ns[1], ns[0] * ghz, ns[1] * ghz);                         \
  }

#define A2 __attribute__((target("avx2")))
#define A512 __attribute__((target("avx512f")))
#define B256 _mm256_set1_ps(1.0000001f)
#define B512 _mm512_set1_ps(1.0000001f)
#define DIV256(x) _mm256_div_ps(x, B256)
#define SQRT256(x) _mm256_sqrt_ps(x)
#define RCP256(x) _mm256_rcp_ps(x)
#define MUL256(x) _mm256_mul_ps(x, B256)
#define DIV512(x) _mm512_div_ps(x, B512)
#define SQRT512(x) _mm512_sqrt_ps(x)
#define RCP512(x) _mm512_rcp14_ps(x)
#define MUL512(x) _mm512_mul_ps(x, B512)
BENCH(div, 256, __m256, _mm256_set1_ps, DIV256, A2)
BENCH(sqrt, 256, __m256, _mm256_set1_ps, SQRT256, A2)
BENCH(rcp, 256, __m256, _mm256_set1_ps, RCP256, A2)
BENCH(mul, 256, __m256, _mm256_set1_ps, MUL256, A2)
BENCH(div, 512, __m512, _mm512_set1_ps, DIV512, A512)
BENCH(sqrt, 512, __m512, _mm512_set1_ps, SQRT512, A512)
BENCH(rcp, 512, __m512, _mm512_set1_ps, RCP512, A512)
BENCH(mul, 512, __m512, _mm512_set1_ps, MUL512, A512)

int main(int argc, char** argv) {
  const long n = argc > 1 ? std::atol(argv[1]) : 20000000;
  const double ghz = clock_ghz(10 * n);
  std::printf("{\"clock_ghz\": %.3f, \"avx2\": %d, \"avx512f\": %d}\n", ghz, __builtin_cpu_supports("avx2") ? 1 : 0,
              __builtin_cpu_supports("avx512f") ? 1 : 0);
  if (!__builtin_cpu_supports("avx2")) return 0;
  bench_div_256(n, ghz); bench_sqrt_256(n, ghz); bench_rcp_256(n, ghz); bench_mul_256(n, ghz);
  if (!__builtin_cpu_supports("avx512f")) return 0;
  bench_div_512(n, ghz); bench_sqrt_512(n, ghz); bench_rcp_512(n, ghz); bench_mul_512(n, ghz);
  return 0;
}
"""


def measure(iters: int) -> dict:
    """Compile and run the program; {"clock_ghz", "avx2", "avx512f", "ops": [...]}."""
    out = run_cpp_program(SOURCE, [str(iters)], "the op-rate program")
    lines = [json.loads(line) for line in out.splitlines() if line.strip()]
    head, ops = lines[0], lines[1:]
    return {**head, "avx2": bool(head["avx2"]), "avx512f": bool(head["avx512f"]), "ops": ops}


def run(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--iters", type=int, default=20_000_000, help="loop iterations per measurement")
    ap.add_argument("--out", default=None, help="JSON file for the result")
    args = ap.parse_args(argv)
    res = measure(args.iters)
    print(f"clock estimate {res['clock_ghz']:.2f} GHz (one dependent add per cycle)")
    for op in res["ops"]:
        print(f"{op['op']:>5} x{op['lanes']:<2}  throughput {op['throughput_cycles']:5.2f} cycles "
              f"({op['throughput_ns']:.3f} ns)   latency {op['latency_cycles']:5.2f} cycles ({op['latency_ns']:.3f} ns)")
    res.update(command=command_line("python -m experiments.vector_op_rates", argv), machine=platform.processor() or platform.machine(),
               iters=args.iters)
    return write_result(res, args.out)


main = main_for(run)

if __name__ == "__main__":
    raise SystemExit(main())
