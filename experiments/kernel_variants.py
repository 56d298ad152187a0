"""Named source variants of the CPU visibility backward, timed against the shipped kernel.

    python -m experiments.kernel_variants --list
    python -m experiments.kernel_variants --variants window_twice flagged_rows_as_nok --threads 2 --reps 31
    python -m experiments.kernel_variants --branch-log --out results/bench/visibility_branches.json

Sessions 37 and 38 timed variants of ``dss/csrc/dss_cpu.cpp`` with ``experiments.ab_kernels``
against HEAD and did not keep their sources, so their numbers could not be measured again. Here a
variant is a list of text substitutions on the working tree's ``dss_cpu.cpp`` (each must match
exactly once: a variant that no longer applies to a changed kernel says so instead of timing
something else). ``run`` captures the inputs of one optimisation step as ``ab_kernels`` does (the
20K-point kangaroo cloud, 12 views at 256x256), builds the unmodified source and every chosen
variant in this process, and calls them in turn ``--reps`` times each, caches evicted before each
call. It prints and writes each variant's median, its speed-up against the shipped source, and
whether its output equals the shipped output bit for bit (the bytes compared, so -0 against +0
counts as a change). A variant marked ``exact`` must keep the
output (a change is reported as an error); the others are timing-only probes (work removed,
results wrong) that bound what a real change could gain.

``--branch-log`` answers a different question: how predictable are the kernel's data-dependent
branches? It builds the shipped source with the AVX-512 window walk's data-dependent branches
logged (``BRANCH_SITES``: the point loop's invalid-point test, the row's flag and the branches of
``eval`` and ``eval_nok``; not the loops' exits nor the border rows' masked loads), a byte per
outcome, one thread; runs one call; and replays the outcome stream through a gshare predictor
(2-bit counters, 2^22 entries, indexed by a hash of the branch site and the last h logged
outcomes) for several history lengths h. The per-site mispredictions of the best h are an
estimate standing in for the counters this VM does not expose, not a bound: a core's predictor
is better than gshare, but its tables are smaller and its history holds the other branches too.
"""

from __future__ import annotations

import argparse
import hashlib
import statistics
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import torch

from experiments.ab_kernels import (
    SOURCE,
    accepted_args,
    add_step_args,
    build,
    capture_inputs,
    time_interleaved,
)
from experiments.bench_common import REPO, git_short, main_for, run_cpp_program, write_result
from experiments.figures import command_line


class VariantError(ValueError):
    """A variant's substitution does not match the source exactly once."""


@dataclass(frozen=True)
class Variant:
    """Text substitutions (old, new) on dss_cpu.cpp; exact: the output must not change."""

    name: str
    summary: str
    exact: bool
    subs: tuple[tuple[str, str], ...]


def apply_variant(text: str, variant: Variant, source_name: str = SOURCE) -> str:
    """``text`` with the variant's substitutions made in order; each must match exactly once."""
    for old, new in variant.subs:
        n = text.count(old)
        if n != 1:
            head = old.strip().splitlines()[0][:70]
            raise VariantError(f"variant {variant.name!r} does not apply to {source_name}: "
                               f"{'not found' if n == 0 else f'found {n} times'}: {head!r}")
        text = text.replace(old, new)
    return text


# -- the substitutions (anchors in dss_cpu.cpp as of session 39) ----------------------------------

_NOK_ALIVE = ("    if (alive) {  // k becomes the front: entries beyond zp + T drop out\n",
              "    {  // k becomes the front: entries beyond zp + T drop out\n")
_NO_NEW_FRONT = (_NOK_ALIVE[0], "    if (false) {  // k becomes the front: entries beyond zp + T drop out\n")
_CLAMP = ("    if (cl) {\n      const __m512 dmax", "    {\n      const __m512 dmax")
_FLAGGED_AS_NOK = ("    if (krows[i - (ic - (int)window)])\n      L.eval(", "    if (false)\n      L.eval(")
_AVX512_CALL = "              window_rows_avx512<KC, CC>(R, Krt, Crt, pt, Q, H, W, window, ic, jc, kr + k * kFlagRows, acc);\n"
_WINDOW_TWICE = (_AVX512_CALL, _AVX512_CALL + """\
              {  // the same window again into a discarded sum: the cost of a second, warm pass
                double again[3] = {0, 0, 0};
                window_rows_avx512<KC, CC>(R, Krt, Crt, pt, Q, H, W, window, ic, jc, kr + k * kFlagRows, again);
                asm volatile("" ::"m"(again[0]), "m"(again[1]), "m"(again[2]));
              }
""")
_ROW_LOOP = "  for (int i = std::max(ic - (int)window, 0); i <= std::min(ic + (int)window, (int)H - 1); ++i) {\n    a.p0"
_WINDOW_DEF = "template <int64_t KC, int64_t CC>\nDSS_AVX512 void window_rows_avx512("
_TOUCH_DEF = (_WINDOW_DEF, """\
// (kernel_variants) every float plane of the window's rows read once, 8 independent maxima
template <int64_t KC, int64_t CC>
DSS_AVX512 __attribute__((noinline)) void touch_window(const VisRecord<true, KC, CC>& rec, int64_t nplanes, int64_t H,
                                                      int64_t W, int64_t window, int ic, int jc) {
  const int j0 = std::max(jc - (int)window, 0);
  __m512 x[8];
  for (int q = 0; q < 8; ++q) x[q] = _mm512_setzero_ps();
  for (int i = std::max(ic - (int)window, 0); i <= std::min(ic + (int)window, (int)H - 1); ++i)
    for (int64_t f = 0; f < nplanes; ++f)
      x[f & 7] = _mm512_max_ps(x[f & 7], _mm512_loadu_ps(rec.plane(f) + (int64_t)i * W + j0));
  for (int q = 0; q < 8; ++q) asm volatile("" ::"v"(x[q]));
}

""" + _WINDOW_DEF)
_TOUCH_CALL = (_AVX512_CALL, "              touch_window<KC, CC>(R, 6 + Crt + 3 * Krt, H, W, window, ic, jc);\n"
               + _AVX512_CALL)
_POINT_LOOP = """\
          const float* s = P + (v * N + k) * kFields;
          if (!(s[9] > 0.f)) continue;
"""
_PREFETCH = (_POINT_LOOP, """\
          const float* s = P + (v * N + k) * kFields;
          if (k + 2 < k_end) {  // (kernel_variants) the window of the point two on, float planes 0-8 + idx 0
            const float* s2 = P + (v * N + k + 2) * kFields;
            if (s2[9] > 0.f) {
              const int i2 = (int)std::floor(s2[1]), j2 = std::max((int)std::floor(s2[0]) - (int)window, 0);
              for (int i = std::max(i2 - (int)window, 0); i <= std::min(i2 + (int)window, (int)H - 1); ++i) {
                const int64_t q = (int64_t)i * W + j2;
                for (int64_t f = 0; f < 9; ++f) {
                  __builtin_prefetch(R.plane(f) + q);
                  __builtin_prefetch(R.plane(f) + q + 15);
                }
                __builtin_prefetch(R.idx_plane(0) + q);
                __builtin_prefetch(R.idx_plane(0) + q + 15);
              }
            }
          }
          if (!(s[9] > 0.f)) continue;
""")
_CHUNKS = "      const int64_t nchunks = (N + kChunk - 1) / kChunk;\n"
_BAND_ORDER = (_CHUNKS, """\
      // (kernel_variants) the view's points in bands of 8 image rows, each band along x
      // (serpentine), by a counting sort on (band, column); invalid points last
      static thread_local std::vector<int32_t> order_v, count_v;
      order_v.resize((size_t)N);
      const int64_t nband = (H + 7) / 8, nkey = nband * W + 1;
      count_v.assign((size_t)(nkey + 1), 0);
      auto key_of = [&](int64_t k) -> int64_t {
        const float* s = P + (v * N + k) * kFields;
        if (!(s[9] > 0.f)) return nkey - 1;
        const int64_t i = std::min(std::max((int64_t)std::floor(s[1]), (int64_t)0), H - 1);
        const int64_t j = std::min(std::max((int64_t)std::floor(s[0]), (int64_t)0), W - 1);
        return (i / 8) * W + ((i / 8) & 1 ? W - 1 - j : j);
      };
      for (int64_t k = 0; k < N; ++k) count_v[key_of(k) + 1]++;
      for (int64_t q = 0; q < nkey; ++q) count_v[q + 1] += count_v[q];
      for (int64_t k = 0; k < N; ++k) order_v[count_v[key_of(k)]++] = (int32_t)k;
      const int32_t* const order = order_v.data();
""" + _CHUNKS)
_BAND_LOOP = ("        for (int64_t k = k_begin; k < k_end; ++k) {\n          const float* s = P + (v * N + k) * kFields;\n",
              "        for (int64_t kk = k_begin; kk < k_end; ++kk) {\n          const int64_t k = order[kk];\n"
              "          const float* s = P + (v * N + k) * kFields;\n")

_KROWS = """\
  static thread_local std::vector<uint8_t> krows;
  if (kf) krows.resize((size_t)(N * kFlagRows));
  uint8_t* const kr = krows.data();  // (the vector is this thread's: the tasks use the pointer)
"""
_KR_MEMSET = "      if (kf) std::memset(kr, 0, (size_t)(N * kFlagRows));\n"
_MARK_LOOP = """\
            for (int e = 0; e < K && pi[e] >= 0; ++e) {
              const float* sk = P + (v * N + pi[e]) * kFields;
              const int64_t r = i - ((int64_t)std::floor(sk[1]) - window), c = j - ((int64_t)std::floor(sk[0]) - window);
"""
_MARK_PREFETCH = """\
#ifdef DSS_HAVE_AVX2
              if (kf) __builtin_prefetch(P + (v * N + qi[e]) * kFields);
#endif
"""
_DENSE_ORIGINS = (
    (_KROWS, _KROWS + """\
  static thread_local std::vector<int32_t> korigin;  // (kernel_variants) per point: window row, column
  if (kf) korigin.resize((size_t)(N * 2));
  int32_t* const ko = korigin.data();
"""),
    (_KR_MEMSET, """\
      if (kf) {
        std::memset(kr, 0, (size_t)(N * kFlagRows));
        dynamic_for((N + 4095) / 4096, 1, [&](int64_t t) {
          for (int64_t k = t * 4096; k < std::min(N, (t + 1) * 4096); ++k) {
            const float* s = P + (v * N + k) * kFields;
            const bool ok = s[9] > 0.f;  // an invalid splat is in no cache: its rows stay unmarked
            ko[2 * k] = ok ? (int32_t)std::floor(s[1]) - (int32_t)window : std::numeric_limits<int32_t>::min() / 2;
            ko[2 * k + 1] = ok ? (int32_t)std::floor(s[0]) - (int32_t)window : std::numeric_limits<int32_t>::min() / 2;
          }
        });
      }
"""),
    (_MARK_LOOP, """\
            for (int e = 0; e < K && pi[e] >= 0; ++e) {
              const int32_t* o = ko + 2 * (int64_t)pi[e];
              const int64_t r = i - (int64_t)o[0], c = j - (int64_t)o[1];
"""),
    (_MARK_PREFETCH, ""),
)
_PER_THREAD_FLAGS = (
    (_KROWS, """\
  static thread_local std::vector<uint8_t> krows;
  const int64_t nflag = std::max<int>(1, at::get_num_threads());  // (kernel_variants) an array per thread
  if (kf) krows.resize((size_t)(nflag * N * kFlagRows));
  uint8_t* const kr = krows.data();
"""),
    (_KR_MEMSET, "      if (kf) std::memset(kr, 0, (size_t)(nflag * N * kFlagRows));\n"),
    (_MARK_LOOP, """\
            uint8_t* const krt = kr + std::min<int64_t>(at::get_thread_num(), nflag - 1) * N * kFlagRows;
""" + _MARK_LOOP),
    ("                __atomic_store_n(&kr[pi[e] * kFlagRows + r], (uint8_t)1, __ATOMIC_RELAXED);\n",
     "                __atomic_store_n(&krt[pi[e] * kFlagRows + r], (uint8_t)1, __ATOMIC_RELAXED);\n"),
    ("          const int ic = (int)std::floor(pt.v), jc = (int)std::floor(pt.u);\n", """\
          const int ic = (int)std::floor(pt.v), jc = (int)std::floor(pt.u);
          alignas(16) uint8_t kflags[kFlagRows];  // the threads' flags of this point, ORed
          if (kf) {
            std::memcpy(kflags, kr + k * kFlagRows, kFlagRows);
            for (int64_t t = 1; t < nflag; ++t)
              for (int r = 0; r < kFlagRows; ++r) kflags[r] |= kr[(t * N + k) * kFlagRows + r];
          }
"""),
    (_AVX512_CALL, _AVX512_CALL.replace("kr + k * kFlagRows", "kflags")),
    ("flat, kf ? kr + k * kFlagRows : nullptr,", "flat, kf ? kflags : nullptr,"),
)

VARIANTS: dict[str, Variant] = {v.name: v for v in (
    Variant("nok_alive_branchless", "eval_nok's new-front section run in every row (its mask unchanged), "
            "no branch on whether some lane needs it", True, (_NOK_ALIVE,)),
    Variant("clamp_branchless", "plane_depth's kMaxSlope clamp computed in every row, no branch", True, (_CLAMP,)),
    Variant("both_branchless", "nok_alive_branchless and clamp_branchless together", True, (_NOK_ALIVE, _CLAMP)),
    Variant("prefetch_next_window", "before each point, software prefetches of the window rows of the point two on "
            "(float planes 0-8, with 3 channels the 9 that eval_nok reads, and index plane 0)", True, (_PREFETCH,)),
    Variant("screen_band_order", "each view's points walked in bands of 8 image rows along x (serpentine) "
            "instead of the spatial sort's order", True, (_BAND_ORDER, _BAND_LOOP)),
    Variant("window_twice", "every window evaluated a second time right after the first, into a discarded sum: "
            "the extra time is what a warm pass (data cached, the same branch outcomes just seen) costs", True,
            (_WINDOW_TWICE,)),
    Variant("touch_then_eval", "every float plane of the window's rows read once just before the window is "
            "evaluated: the extra time is the cold read, what the evaluation then saves is its memory stall",
            True, (_TOUCH_DEF, _TOUCH_CALL)),
    Variant("dense_origins", "the row marking reads each cached point's window origin from a dense per-view "
            "array (8 bytes, computed once per view) instead of its 40-byte splat row and two floors", True,
            _DENSE_ORIGINS),
    Variant("per_thread_flags", "the row marking writes one flag array per thread (ORed per point by the point "
            "loop), so that no flag line is written from both cores", True, _PER_THREAD_FLAGS),
    Variant("no_windows", "timing only: no window evaluated (the record build, the flags and the point loop "
            "alone): the shipped time less this is the window walk's", False,
            ((_AVX512_CALL, "              (void)acc;  // (kernel_variants: no window)\n"),)),
    Variant("half_the_rows", "timing only: every other window row evaluated (9 rows -> 5 vectors): more than what "
            "packing a 9 x 9 window's 81 pixels into fewer 16-lane vectors (at best 6) could gain, the packing free",
            False,
            ((_ROW_LOOP, _ROW_LOOP.replace("; ++i) {", "; i += 2) {")),)),
    Variant("flagged_rows_as_nok", "timing only: the rows where the point is cached also take eval_nok (case (c) "
            "dropped): the most any cheaper case (c) could gain", False, (_FLAGGED_AS_NOK,)),
    Variant("no_flags", "timing only: the record build marks no rows (every row takes eval_nok, as in "
            "flagged_rows_as_nok): against that variant, what the marking costs", False,
            (("          if (kf) {\n            // mark row i", "          if (false) {\n            // mark row i"),)),
    Variant("no_c_no_new_front", "timing only: flagged_rows_as_nok and no_new_front together (every row takes "
            "eval_nok, without its new-front section)", False, (_FLAGGED_AS_NOK, _NO_NEW_FRONT)),
    Variant("no_new_front", "timing only: eval_nok without its new-front section (entries beyond zp + T not "
            "dropped): the most any cheaper new-front sum could gain", False, (_NO_NEW_FRONT,)),
)}

# -- branch log --------------------------------------------------------------------------------

BRANCH_SITES = ("invalid point", "row flagged (eval, not eval_nok)", "plane_depth clamp", "eval_nok new front",
                "eval: k visible somewhere", "eval: k was the front", "eval: k not visible somewhere",
                "eval: new front", "eval: case (c) contributes", "eval: case (a)/(b) contributes",
                "row contributes nothing", "row has case (c)", "no loss gradient in the row")

_LOG_HEADER = """\
// (kernel_variants --branch-log) one byte per outcome of the window walk's data-dependent branches:
// site << 1 | taken. Single-threaded use only (a plain vector, no lock).
static std::vector<uint8_t>& branch_log_buffer() {
  static std::vector<uint8_t>* v = new std::vector<uint8_t>();
  return *v;
}
static inline bool BL(int site, bool c) {
  branch_log_buffer().push_back((uint8_t)(site << 1 | (c ? 1 : 0)));
  return c;
}
"""
_M0 = ("    if (m == 0) return;\n    const __m512 d0 = a.ld(R->plane(Rec::kD0)), r1 = a.ld(R->plane(Rec::kDen)), "
       "r2 = a.ld(R->plane(Rec::kGn));\n    const __m512 d0m = _mm512_add_ps(d0, vmerge);\n")
_LOG_SUBS: tuple[tuple[str, str], ...] = (
    ("struct Frag {\n", _LOG_HEADER + "struct Frag {\n"),
    (_POINT_LOOP, _POINT_LOOP.replace("if (!(s[9] > 0.f))", "if (BL(0, !(s[9] > 0.f)))")),
    ("    if (krows[i - (ic - (int)window)])\n      L.eval(", "    if (BL(1, krows[i - (ic - (int)window)]))\n      L.eval("),
    (_CLAMP[0], "    if (BL(2, cl)) {\n      const __m512 dmax"),
    (_NOK_ALIVE[0], _NOK_ALIVE[0].replace("if (alive)", "if (BL(3, alive))")),
    ("    if (m & kvis) {\n", "    if (BL(4, m & kvis)) {\n"),
    ("      if (K > 1 && (ek0 & kvis & m))", "      if (BL(5, K > 1 && (ek0 & kvis & m)))"),
    ("    if (m & ~kvis) {\n", "    if (BL(6, m & ~kvis)) {\n"),
    ("      if (alive) add_entries_within(ie, de, re, ge, 0, alive,",
     "      if (BL(7, alive)) add_entries_within(ie, de, re, ge, 0, alive,"),
    ("    if (act_v) {\n", "    if (BL(8, act_v)) {\n"),
    ("    if (act_n) ab_step(", "    if (BL(9, act_n)) ab_step("),
    ("    if (!o.any) continue;\n    // eval_scalar's order per pixel",
     "    if (BL(10, !o.any)) continue;\n    // eval_scalar's order per pixel"),
    ("    if (o.any_c) {\n      add(sx, o.x2);", "    if (BL(11, o.any_c)) {\n      add(sx, o.x2);"),
    # the early return of eval (its next line declares ie) and of eval_nok (empty)
    *((_M0 + tail, _M0.replace("if (m == 0)", "if (BL(12, m == 0))") + tail)
      for tail in ("    __m512i ie[8];", "    const __mmask16 empty")),
    ('  m.def("visibility_backward", &visibility_backward, "DSS visibility gradient (CPU)");\n',
     '  m.def("visibility_backward", &visibility_backward, "DSS visibility gradient (CPU)");\n'
     '  m.def("branch_log", [] {\n'
     '    auto& b = branch_log_buffer();\n'
     '    auto t = torch::empty({(int64_t)b.size()}, torch::kUInt8);\n'
     '    std::copy(b.begin(), b.end(), t.data_ptr<uint8_t>());\n'
     '    b.clear();\n'
     '    return t;\n'
     '  });\n'),
)
BRANCH_LOG = Variant("branch_log", "every data-dependent branch of the AVX-512 window walk logged", True, _LOG_SUBS)

_GSHARE_CPP = r"""
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <vector>
// gshare over a log of (site << 1 | taken) bytes: 2^22 2-bit counters indexed by a hash of the
// site and the last h outcomes; prints, per history length, the mispredictions of every site.
int main(int argc, char** argv) {
  FILE* f = std::fopen(argv[1], "rb");
  if (!f) {
    std::perror(argv[1]);
    return 2;
  }
  std::vector<uint8_t> b;
  uint8_t buf[1 << 16];
  size_t n;
  while ((n = std::fread(buf, 1, sizeof buf, f)) > 0) b.insert(b.end(), buf, buf + n);
  std::fclose(f);
  const int kBits = 22;
  for (int a = 2; a < argc; ++a) {
    const int h = std::atoi(argv[a]);
    std::vector<uint8_t> t(1u << kBits, 1);
    uint64_t hist = 0;
    long miss[128] = {0};
    for (uint8_t e : b) {
      const int site = e >> 1, o = e & 1;
      const uint64_t hh = h >= 64 ? hist : (hist & ((1ull << h) - 1));
      const uint64_t x = hh * 0x9E3779B97F4A7C15ull ^ (uint64_t)(site + 1) * 0xC2B2AE3D27D4EB4Full;
      uint8_t& c = t[x >> (64 - kBits)];
      miss[site] += (c >= 2) != o;
      if (o && c < 3) ++c;
      if (!o && c > 0) --c;
      hist = hist << 1 | (uint64_t)o;
    }
    std::printf("%d", h);
    for (int s = 0; s < 128; ++s) std::printf(" %ld", miss[s]);
    std::printf("\n");
  }
  return 0;
}
"""


def gshare_misses(log: bytes, histories: list[int], workdir: Path) -> dict[int, list[int]]:
    """Mispredictions per branch site (index = site) of a gshare predictor replaying ``log``."""
    data = workdir / "log.bin"
    data.write_bytes(log)
    out = run_cpp_program(_GSHARE_CPP, [str(data), *map(str, histories)], "the gshare replay")
    rows = [list(map(int, line.split())) for line in out.splitlines() if line.strip()]
    return {r[0]: r[1:] for r in rows}


def branch_report(log: torch.Tensor, histories: list[int], workdir: Path) -> dict:
    """Per site: outcomes, taken, and the gshare mispredictions for every history length."""
    b = log.numpy().tobytes()
    codes = log.to(torch.int64)
    sites, taken = codes >> 1, codes & 1
    n_sites = len(BRANCH_SITES)
    if sites.numel() and int(sites.max()) >= n_sites:
        raise ValueError(f"branch log holds site {int(sites.max())}: only {n_sites} are named")
    count = torch.bincount(sites, minlength=n_sites).tolist()
    tk = torch.bincount(sites, weights=taken.to(torch.float64), minlength=n_sites).tolist()
    miss = gshare_misses(b, histories, workdir)
    best = min(histories, key=lambda h: sum(miss[h]))
    per_site = [{"site": BRANCH_SITES[s], "outcomes": count[s], "taken": int(tk[s]),
                 "gshare_misses": {str(h): miss[h][s] for h in histories}} for s in range(n_sites)]
    return {"outcomes": len(b), "histories": histories, "best_history": best,
            "total_misses": {str(h): sum(miss[h]) for h in histories}, "sites": per_site}


def run(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--list", action="store_true", help="print the variants and exit")
    ap.add_argument("--variants", nargs="+", default=None, help="variants to time (default: all)")
    ap.add_argument("--branch-log", action="store_true",
                    help="log the window walk's branch outcomes in one single-threaded call and replay them "
                         "through a gshare predictor instead of timing variants")
    ap.add_argument("--histories", type=int, nargs="+", default=[0, 8, 16, 24, 32],
                    help="--branch-log: gshare history lengths (outcomes)")
    add_step_args(ap, threads=2, reps=21)
    ap.add_argument("--evict-mb", type=int, default=64, help="MB written before every call (cold caches, as in a step)")
    ap.add_argument("--out", default=None, help="JSON file for the result")
    args = ap.parse_args(argv)
    if args.list:
        for v in VARIANTS.values():
            print(f"{v.name:22s} {'exact ' if v.exact else 'timing'}  {v.summary}")
        return {"variants": {v.name: {"exact": v.exact, "summary": v.summary} for v in VARIANTS.values()}}
    names = args.variants or list(VARIANTS)
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        raise SystemExit(f"unknown variant(s) {unknown}; --list names them")
    text = (REPO / SOURCE).read_text()
    # the commit, and whether the working tree's kernel source differs from it (the runs time the
    # working tree's); the source's hash names it either way
    dirty = subprocess.run(["git", "diff", "--quiet", "HEAD", "--", str(Path(SOURCE).parent)], cwd=REPO).returncode != 0
    common = {"kernel": "visibility_backward", "kind": args.kind, "points": args.points, "views": args.views,
              "image_size": args.image_size, "source_commit": git_short("HEAD"), "source_modified": dirty,
              "source_sha256": hashlib.sha256(text.encode()).hexdigest()[:16],
              "command": command_line("python -m experiments.kernel_variants", argv)}
    if args.branch_log:
        patched = apply_variant(text, BRANCH_LOG)  # before the capture: a stale anchor fails fast
        torch.set_num_threads(1)
        call_args = list(capture_inputs(args.kind, args.points, args.views, args.image_size)["visibility_backward"])
        with tempfile.TemporaryDirectory() as tmp:
            mod = build("dss_branch_log", patched, Path(tmp))
            if not (hasattr(mod, "vector_level") and mod.vector_level() == 2):
                raise SystemExit("--branch-log logs the AVX-512 window walk: this CPU or build has no AVX-512 path")
            mod.visibility_backward(*accepted_args(mod.visibility_backward, call_args))
            report = branch_report(mod.branch_log(), args.histories, Path(tmp))
        best = str(report["best_history"])
        print(f"{report['outcomes']} branch outcomes; gshare mispredictions (history {best}): "
              f"{report['total_misses'][best]}")
        for s in report["sites"]:
            print(f"  {s['site']:34s} {s['outcomes']:9d} outcomes, {s['taken']:9d} taken, "
                  f"{s['gshare_misses'][best]:8d} mispredicted")
        return write_result({**common, "mode": "branch_log", "threads": 1, **report}, args.out)
    if args.reps <= args.skip:
        raise SystemExit("--reps must exceed --skip")
    sources = {"shipped": text, **{n: apply_variant(text, VARIANTS[n]) for n in names}}
    torch.set_num_threads(args.threads)
    call_args = list(capture_inputs(args.kind, args.points, args.views, args.image_size)["visibility_backward"])
    same: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        mods = {k: build(f"dss_var_{k}", src, Path(tmp)) for k, src in sources.items()}
        fns = {k: m.visibility_backward for k, m in mods.items()}
        fargs = {k: accepted_args(fn, call_args) for k, fn in fns.items()}
        ref = fns["shipped"](*fargs["shipped"])
        for k in names:
            out = fns[k](*fargs[k])
            same[k] = _same_bytes(ref, out)
        times = time_interleaved(fns, fargs, args.reps, args.evict_mb)
    med = {k: statistics.median(v[args.skip:]) for k, v in times.items()}
    rows = {}
    print(f"visibility_backward, {args.points} points, {args.threads} thread(s): shipped {med['shipped']:.2f} ms")
    for k in names:
        v = VARIANTS[k]
        rows[k] = {"summary": v.summary, "exact": v.exact, "same_bits": same[k], "median_ms": med[k],
                   "speedup": med["shipped"] / med[k],
                   "error": "an exact variant changed the output" if v.exact and not same[k] else None}
        flag = "same bits" if same[k] else ("OUTPUT CHANGED" if v.exact else "output differs (timing only)")
        print(f"  {k:22s} {med[k]:7.2f} ms  {rows[k]['speedup']:.2f}x  {flag}")
    result = {**common, "mode": "timing", "threads": args.threads, "reps": args.reps, "skip": args.skip,
              "evict_mb": args.evict_mb, "vector_level": int(mods["shipped"].vector_level())
              if hasattr(mods["shipped"], "vector_level") else None,
              "shipped_median_ms": med["shipped"], "variants": rows, "runs_ms": times}
    write_result(result, args.out)
    bad = [k for k, r in rows.items() if r["error"]]
    if bad:
        raise SystemExit(f"exact variant(s) {bad} changed the output")
    return result


def _tensors(out) -> list:
    return [out] if isinstance(out, torch.Tensor) else [t for t in out if isinstance(t, torch.Tensor)]


def _same_bytes(a, b) -> bool:
    """The two kernel outputs hold the same tensors byte for byte (-0 and +0 differ, NaN equals itself)."""
    ta, tb = _tensors(a), _tensors(b)
    return len(ta) == len(tb) and all(
        x.shape == y.shape and x.dtype == y.dtype
        and x.contiguous().view(torch.uint8).numpy().tobytes() == y.contiguous().view(torch.uint8).numpy().tobytes()
        for x, y in zip(ta, tb))


main = main_for(run)


if __name__ == "__main__":
    raise SystemExit(main())
