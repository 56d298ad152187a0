// Per-splat formulas shared by the CPU kernels (*_cpu.cpp, vectorised loops over points) and the
// CUDA kernels (*_cuda.cu, a thread per point or splat): the EWA projection of one (view, point)
// (dss/splats.py project_splats) forward and backward, the splat's quadratic form, one cache
// entry's share of the blend backward (Eq. sumI's smooth terms), and the order in which the
// visibility gradient adds a window's contributions. float32 in the torch expressions'
// order; both are built without contraction (g++ -ffp-contract=off, nvcc --fmad=false) and with
// IEEE division and square root, and exp as splat_exp below (not the libraries' expf, which differ
// in the last bit between the host and CUDA), so the CPU and the GPU give the same bits.
//
// Packed fields (dss/splats.py): u v conic_a conic_b2 conic_c norm depth rx ry valid.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstring>

#if defined(__CUDACC__) || defined(DSS_EMU_KERNELS)
#define DSS_SPLAT_FN __host__ __device__ __forceinline__
#else
#define DSS_SPLAT_FN inline __attribute__((always_inline))
#endif

namespace dss_splat {

// exp(x) in float32 operations only (rho = norm exp(-q/2), the smooth visibility exp(-q/2)):
// Cephes' expf: x = n ln 2 + r with ln 2 in two parts, a degree-5 polynomial in r, and 2^n as two
// factors so that results down to the denormals come out. Within 1 ulp of the correctly rounded
// value over [-104, 88] (equal to it for 90% of x in [-3, 0]; tests/test_render_forward.py checks
// it against float64). The CPU kernel's AVX2 twin (splat_exp_avx2) does the same operations.
namespace splat_exp_c {
constexpr float kLo = -104.f, kHi = 88.f;  // exp(-104) rounds to 0; exp(88) < FLT_MAX
constexpr float kLog2e = 1.44269504088896341f, kLn2Hi = 0.693359375f, kLn2Lo = -2.12194440e-4f;
constexpr float kP0 = 1.9875691500e-4f, kP1 = 1.3981999507e-3f, kP2 = 8.3334519073e-3f, kP3 = 4.1665795894e-2f,
                kP4 = 1.6666665459e-1f, kP5 = 5.0000001201e-1f;
}  // namespace splat_exp_c

// 2^n for -126 <= n <= 127
DSS_SPLAT_FN float pow2i(int n) {
  const int32_t bits = (n + 127) << 23;
#ifdef __CUDA_ARCH__
  return __int_as_float(bits);
#else
  float f;
  std::memcpy(&f, &bits, sizeof f);
  return f;
#endif
}

DSS_SPLAT_FN float splat_exp(float x) {
  using namespace splat_exp_c;
  x = x > kLo ? x : kLo;  // (as _mm256_max_ps / _mm256_min_ps: the bound on a NaN)
  x = x < kHi ? x : kHi;
  const float fx = floorf(x * kLog2e + 0.5f);
  const float r = (x - fx * kLn2Hi) - fx * kLn2Lo;
  float y = ((((kP0 * r + kP1) * r + kP2) * r + kP3) * r + kP4) * r + kP5;
  y = (y * (r * r) + r) + 1.f;
  const int n = (int)fx, n1 = n >> 1;  // n in [-150, 127]: both factors are normal numbers
  return (y * pow2i(n1)) * pow2i(n - n1);
}

// q = (a dx) dx + (b2 dx) dy + (c dy) dy, left to right, as torch evaluates it.
DSS_SPLAT_FN float quad(float a, float b2, float c, float dx, float dy) {
  const float t1 = a * dx * dx;
  const float t2 = b2 * dx * dy;
  const float t3 = c * dy * dy;
  return (t1 + t2) + t3;
}

// One visible cache entry's share of the blend backward (I = sum_f rho_f w_f / sum_f rho_f):
// s, the entry's packed splat; wk (C), its attributes; gp, ip (C), the pixel's dL/dI and image;
// rf, its rho; rden = 1 / sum_f rho_f; (dx, dy) = pixel centre - (u, v). Adds dL/d(u, v, a, b2,
// c, norm) to acc[0..5] and dL/dw_k to acc[6..6+C), in double.
DSS_SPLAT_FN void blend_entry_grad(const float* s, const float* wk, const float* gp, const float* ip, int64_t C,
                                   float rf, double rden, float dx, float dy, double* acc) {
  double drho = 0;
  for (int64_t c = 0; c < C; ++c) {
    drho += (double)gp[c] * (wk[c] - ip[c]) * rden;
    acc[6 + c] += (double)gp[c] * rf * rden;
  }
  // d rho / d norm = exp(-q/2) = rho / norm and d rho / dq = -rho / 2, from the forward's rho (no
  // second exp; rho / norm is within one float32 rounding of the forward's exp). A zero norm
  // (rho = 0) takes the exp.
  const double ex = s[5] > 0.f ? (double)rf / (double)s[5] : (double)splat_exp(-0.5f * quad(s[2], s[3], s[4], dx, dy));
  acc[5] += drho * ex;
  const double dq = -0.5 * drho * (double)rf;
  acc[2] += dq * dx * dx;
  acc[3] += dq * dx * dy;
  acc[4] += dq * dy * dy;
  acc[0] += -dq * (2.0 * s[2] * dx + s[3] * dy);
  acc[1] += -dq * (s[3] * dx + 2.0 * s[4] * dy);
}

// A world point p and normal n in the camera frame: pc = Rv p + tv, nc = Rv n (left to right).
DSS_SPLAT_FN void to_camera(const float* p, const float* n, const float* Rv, const float* tv, float* pc, float* nc) {
  for (int a = 0; a < 3; ++a) {
    pc[a] = Rv[a * 3] * p[0] + Rv[a * 3 + 1] * p[1] + Rv[a * 3 + 2] * p[2] + tv[a];
    nc[a] = Rv[a * 3] * n[0] + Rv[a * 3 + 1] * n[1] + Rv[a * 3 + 2] * n[2];
  }
}

struct SplatGeometry {
  float X, Y, Z, Zs, nc[3], inv, nh[3], m1[3], m2[3], m1n, m2n, A11, A12, A22, w, detJ, s2, S11, S12, S22, detS;
};

// Camera-frame position and normal, the local affine map's rows m1, m2 (paper Eq. J), the
// screen-space covariance S = s^2 A + fv I and its determinant. p, n: world (3); Rv (3x3), tv (3):
// the view's world-to-camera rotation and translation; f: focal (px); zn: near plane (a point
// behind it is projected with Z = 1 so that its values stay finite; it is not valid anyway).
DSS_SPLAT_FN SplatGeometry splat_geometry(const float* p, const float* n, const float* Rv, const float* tv, float f,
                                          float sigma, float fv, float zn) {
  SplatGeometry g;
  float pc[3];
  to_camera(p, n, Rv, tv, pc, g.nc);
  g.X = pc[0], g.Y = pc[1], g.Z = pc[2];
  const float Zs = g.Z > zn ? g.Z : 1.f;
  g.Zs = Zs;
  const float nl2 = g.nc[0] * g.nc[0] + g.nc[1] * g.nc[1] + g.nc[2] * g.nc[2];
  g.inv = 1.f / sqrtf(nl2 + 1e-20f);
  for (int a = 0; a < 3; ++a) g.nh[a] = g.nc[a] * g.inv;
  g.m1[0] = f / Zs, g.m1[1] = 0.f, g.m1[2] = -f * g.X / (Zs * Zs);
  g.m2[0] = 0.f, g.m2[1] = f / Zs, g.m2[2] = -f * g.Y / (Zs * Zs);
  g.m1n = g.m1[0] * g.nh[0] + g.m1[2] * g.nh[2];
  g.m2n = g.m2[1] * g.nh[1] + g.m2[2] * g.nh[2];
  g.A11 = g.m1[0] * g.m1[0] + g.m1[2] * g.m1[2] - g.m1n * g.m1n;
  g.A12 = g.m1[2] * g.m2[2] - g.m1n * g.m2n;
  g.A22 = g.m2[1] * g.m2[1] + g.m2[2] * g.m2[2] - g.m2n * g.m2n;
  g.w = g.nh[0] * g.X + g.nh[1] * g.Y + g.nh[2] * Zs;
  g.detJ = f * f * fabsf(g.w) / (Zs * Zs * Zs);
  g.s2 = sigma * sigma;
  g.S11 = g.s2 * g.A11 + fv, g.S12 = g.s2 * g.A12, g.S22 = g.s2 * g.A22 + fv;
  g.detS = g.s2 * g.s2 * (g.detJ * g.detJ) + g.s2 * fv * (g.A11 + g.A22) + fv * fv;
  return g;
}

// The 10 packed fields of one splat into o. Straight-line code (the branches are selects) so
// that the CPU kernel's loop over points vectorises. C2 = 2 * cutoff.
DSS_SPLAT_FN void project_forward_one(const float* p, const float* n, const float* Rv, const float* tv, float f,
                                      float cx, float cy, float sigma, float fv, float C2, float zn, bool culling,
                                      float* o) {
  const SplatGeometry g = splat_geometry(p, n, Rv, tv, f, sigma, fv, zn);
  const float X = g.X, Y = g.Y, Z = g.Z, Zs = g.Zs, S11 = g.S11, S12 = g.S12, S22 = g.S22, detS = g.detS;
  o[0] = f * X / Zs + cx;
  o[1] = f * Y / Zs + cy;
  o[2] = S22 / detS;
  o[3] = -2.f * S12 / detS;
  o[4] = S11 / detS;
  o[5] = g.detJ / (2.f * 3.14159265358979f * sqrtf(detS));
  o[6] = Z;
  o[7] = sqrtf(C2 * S11);
  o[8] = sqrtf(C2 * S22);
  // valid: in front of the near plane and (without culling, or) facing the camera
  const int front = Z > zn, facing = (g.nc[0] * X + g.nc[1] * Y + g.nc[2] * Z) < 0.f;
  o[9] = (front & (facing | !culling)) ? 1.f : 0.f;
}

struct SplatGrad {
  float gp[3], gn[3];  // dL/dp, dL/dn (world frame)
};

// dL/dp and dL/dn of one splat from dL/dpacked fields 0-8 (gu .. gry); the valid flag is a step
// function. rx, ry: the splat's packed fields 7 and 8; C = cutoff. A splat that is not valid gets
// zeros (the renderer never reads it); its values are still computed, so the CPU loop stays
// straight-line. Scalars in, a struct out (no pointers): the CPU loop over points vectorises.
DSS_SPLAT_FN SplatGrad project_backward_one(const float* p, const float* n, const float* Rv, const float* tv,
                                            float f, float sigma, float fv, float C, float gu, float gv, float ga,
                                            float gb2, float gc, float gnorm, float gz, float grx, float gry,
                                            float rx, float ry, bool valid) {
  // valid splats only (Z > znear): no near-plane substitute for Z
  const SplatGeometry g = splat_geometry(p, n, Rv, tv, f, sigma, fv, -INFINITY);
  const float X = g.X, Y = g.Y, Z = g.Z, iZ = 1.f / Z, inv = g.inv, w = g.w, detJ = g.detJ, s2 = g.s2;
  const float m1n = g.m1n, m2n = g.m2n, S11 = g.S11, S12 = g.S12, S22 = g.S22, detS = g.detS;
  // (copies, not pointers into g: g then stays in registers and the CPU loop vectorises)
  const float nc[3] = {g.nc[0], g.nc[1], g.nc[2]}, nh[3] = {g.nh[0], g.nh[1], g.nh[2]};
  const float m1[3] = {g.m1[0], g.m1[1], g.m1[2]}, m2[3] = {g.m2[0], g.m2[1], g.m2[2]};
  const float iS = 1.f / detS;
  const float sqS = sqrtf(detS);
  const float k2pi = 1.f / (2.f * 3.14159265358979f);
  float gS11 = gc * iS, gS22 = ga * iS, gS12 = -2.f * gb2 * iS;
  // rx = sqrt(2 C S11), ry = sqrt(2 C S22)
  gS11 = rx > 0.f ? gS11 + grx * C / rx : gS11;
  gS22 = ry > 0.f ? gS22 + gry * C / ry : gS22;
  const float gdetS = -(ga * S22 - 2.f * gb2 * S12 + gc * S11) * iS * iS - 0.5f * gnorm * detJ * k2pi * iS / sqS;
  const float gdetJ = gnorm * k2pi / sqS + gdetS * s2 * s2 * 2.f * detJ;
  const float gA11 = s2 * gS11 + gdetS * s2 * fv, gA22 = s2 * gS22 + gdetS * s2 * fv, gA12 = s2 * gS12;
  float gm1[3], gm2[3];
  for (int c = 0; c < 3; ++c) {
    gm1[c] = 2.f * gA11 * m1[c] + gA12 * m2[c];
    gm2[c] = 2.f * gA22 * m2[c] + gA12 * m1[c];
  }
  const float gm1n = -2.f * gA11 * m1n - gA12 * m2n;
  const float gm2n = -2.f * gA22 * m2n - gA12 * m1n;
  float gnh[3];
  for (int c = 0; c < 3; ++c) {
    gm1[c] += gm1n * nh[c];
    gm2[c] += gm2n * nh[c];
    gnh[c] = gm1n * m1[c] + gm2n * m2[c];
  }
  // detJ = f^2 |w| / Z^3
  const float gw = gdetJ * f * f * (w > 0.f ? 1.f : (w < 0.f ? -1.f : 0.f)) * iZ * iZ * iZ;
  gnh[0] += gw * X;
  gnh[1] += gw * Y;
  gnh[2] += gw * Z;
  float gX = gw * nh[0], gY = gw * nh[1];
  float gZ = gw * nh[2] - 3.f * gdetJ * detJ * iZ + gz;
  // m1 = f (1/Z, 0, -X/Z^2), m2 = f (0, 1/Z, -Y/Z^2)
  gZ += -(gm1[0] + gm2[1]) * f * iZ * iZ + 2.f * f * (gm1[2] * X + gm2[2] * Y) * iZ * iZ * iZ;
  gX += -gm1[2] * f * iZ * iZ;
  gY += -gm2[2] * f * iZ * iZ;
  // u = f X / Z + cx, v = f Y / Z + cy
  gX += gu * f * iZ;
  gY += gv * f * iZ;
  gZ += -(gu * X + gv * Y) * f * iZ * iZ;
  // nh = nc / sqrt(|nc|^2 + 1e-20)
  const float dn = gnh[0] * nc[0] + gnh[1] * nc[1] + gnh[2] * nc[2];
  float gnc[3];
  for (int c = 0; c < 3; ++c) gnc[c] = inv * gnh[c] - inv * inv * inv * dn * nc[c];
  const float gpc[3] = {gX, gY, gZ};
  SplatGrad out;
  for (int c = 0; c < 3; ++c) {  // world = R^T camera
    const float op = Rv[0 * 3 + c] * gpc[0] + Rv[1 * 3 + c] * gpc[1] + Rv[2 * 3 + c] * gpc[2];
    const float on = Rv[0 * 3 + c] * gnc[0] + Rv[1 * 3 + c] * gnc[1] + Rv[2 * 3 + c] * gnc[2];
    out.gp[c] = valid ? op : 0.f;
    out.gn[c] = valid ? on : 0.f;
  }
  return out;
}

// The inverse-depth tangent plane of one (view, point) (dss/splats.py tangent_planes, whose torch
// expressions it follows term by term): out = (A, B, C) with 1 / z = A px + B py + C on the
// point's tangent plane; (0, 0, 1 / z) for planes through the camera centre, and always for
// center (the centre depth at every pixel). p, n: world (3); Rv (3x3), tv (3): world to camera.
DSS_SPLAT_FN void tangent_plane_one(const float* p, const float* n, const float* Rv, const float* tv, float f,
                                    float cx, float cy, bool center, float* out) {
  float pc[3], nc[3];
  to_camera(p, n, Rv, tv, pc, nc);
  const float z = pc[2];
  const float inv_z = z > 0.f ? 1.f / (z < 1e-12f ? 1e-12f : z) : 0.f;
  const float c0 = (nc[0] * pc[0] + nc[1] * pc[1]) + nc[2] * pc[2];  // n . p in the camera frame
  const bool ok = !center && (c0 < 0.f ? -c0 : c0) > 1e-12f;
  if (!ok) {
    out[0] = 0.f, out[1] = 0.f, out[2] = inv_z;
    return;
  }
  out[0] = nc[0] / (f * c0);
  out[1] = nc[1] / (f * c0);
  out[2] = ((nc[2] - nc[0] * cx / f) - nc[1] * cy / f) / c0;
}

// The visibility gradient's sum over a point's window (2 w + 1 columns, column offset c = dx + w)
// is formed in partial sums, each over its columns in row-major order, then added in partial
// order: partial c % 8 for the first mw = (2 w + 1) / 8 * 8 columns, partial 8 + (c - mw) for the
// rest. The CPU kernel's vector path then keeps lane l's sums in a vector lane (no serial chain
// through every pixel: 1.18x on the 20K position step's visibility backward), and the scalar
// path, the CUDA kernel and the emulator add in the same order, so all give the same bits. Each
// partial starts at +0 and a skipped pixel adds nothing, which equals adding +0: a sum that
// started at +0 is never -0.
constexpr int kVisPartials = 15;  // 8 lanes + at most 7 columns beyond the last run of 8
DSS_SPLAT_FN int vis_window_runs(int64_t window) { return (int)((2 * window + 1) / 8 * 8); }
DSS_SPLAT_FN int vis_partial_count(int64_t window) { return 8 + (int)(2 * window + 1) - vis_window_runs(window); }
DSS_SPLAT_FN int vis_partial(int64_t c, int mw) { return c < mw ? (int)(c & 7) : 8 + (int)(c - mw); }

// A splat's pixel box before tightening, as reference.bbox() computes it: the extent (rx, ry)
// around the centre (u, v) (packed fields 0, 1, 7, 8) rounded outwards in float32 (floor, ceil),
// widened by a pixel each way, then clamped to the image: columns j0..j1, rows i0..i1. A box
// wholly off screen collapses onto the border; the callers test the splat's validity, j0 <= j1
// and i0 <= i1, and tighten_box then drops the rows and columns the cutoff ellipse misses. The
// comparisons are std::max's and std::min's, so that the CPU's loop over a block of splats
// vectorises them.
struct Box {
  int j0, j1, i0, i1;
};

DSS_SPLAT_FN float clamp_to(float x, float lo, float hi) {
  const float y = (x < lo) ? lo : x;  // std::max(x, lo)
  return (hi < y) ? hi : y;           // std::min(y, hi)
}

DSS_SPLAT_FN Box splat_box(float u, float v, float rx, float ry, int H, int W) {
  const float j0 = clamp_to(floorf(u - rx - 0.5f), -1.f, (float)W) - 1.f;
  const float j1 = clamp_to(ceilf(u + rx - 0.5f), -1.f, (float)W) + 1.f;
  const float i0 = clamp_to(floorf(v - ry - 0.5f), -1.f, (float)H) - 1.f;
  const float i1 = clamp_to(ceilf(v + ry - 0.5f), -1.f, (float)H) + 1.f;
  Box b;
  b.j0 = (int)clamp_to(j0, 0.f, (float)(W - 1));
  b.j1 = (int)clamp_to(j1, 0.f, (float)(W - 1));
  b.i0 = (int)clamp_to(i0, 0.f, (float)(H - 1));
  b.i1 = (int)clamp_to(i1, 0.f, (float)(H - 1));
  return b;
}

// Shrinks a splat's pixel box [j0, j1] x [i0, i1] (the reference's bbox(), one to two rows and
// columns of margin on each side) by the rows and columns at its edges that cannot hold a pixel
// passing the cutoff test (0.5 q <= cutoff, q = quad() in float32 at pixel centres): the bins
// reach fewer tiles and the tile loops test fewer rows, while only pixels that must fail leave
// the box, so the caches keep their bits.
// - Over a row (pixel-centre offset dy from the centre, in float as the tile loops compute it) the
//   form is at least dy^2 D / (4a), D = 4ac - b2^2; over a column, dx^2 D / (4c).
// - quad()'s float result is within 4 eps S of the exact form (eps = 2^-24; at most four roundings
//   per term), S = |t1| + |t2| + |t3| <= kappa q with kappa = (1 + r) / (1 - r) <= 16 ac / D,
//   r = |b2| / (2 sqrt(ac)). So a row with dy^2 (D - 128 eps ac) > 4a * 2 cutoff has no pixel with
//   0.5 q <= cutoff (halving is exact); tested in double, without a division.
// - Each edge steps over at most two rejected rows or columns, without a branch on the data (on
//   the CPU, loops that run to the first accepted row mispredict their exits).
// Forms that are not clearly positive definite or too ill-conditioned for the margin keep their
// box. Returns false when no row or column is left.
DSS_SPLAT_FN int line_out(int line, float centre, double g, double lim) {
  const double d = ((float)line + 0.5f) - centre;
  return d * d * g > lim ? 1 : 0;
}

DSS_SPLAT_FN bool tighten_box(float u, float v, float fa, float fb2, float fc, float cutoff, int& j0, int& j1, int& i0,
                              int& i1) {
  const double a = fa, b2 = fb2, c = fc, two_cut = 2.0 * (double)cutoff;
  const double det4 = 4.0 * a * c - b2 * b2, g = det4 - 128.0 * 5.9604644775390625e-8 * a * c;
  const bool ok = (a > 1e-30) & (c > 1e-30) & (a < 1e30) & (c < 1e30) & (fabs(b2) < 1e30) & (two_cut > 0.0) &
                  (g > 0.5 * det4);
  // Straight-line (& rather than &&, and selects rather than an early return for the forms that
  // keep their box: with g = 0 and a positive limit no line is out), so that the CPU's loop over
  // a block of splats vectorises.
  const double ge = ok ? g : 0.0;
  const double lim_row = ok ? 4.0 * a * two_cut : 1.0, lim_col = ok ? 4.0 * c * two_cut : 1.0;
  for (int step = 0; step < 2; ++step) {
    i0 += line_out(i0, v, ge, lim_row);
    i1 -= line_out(i1, v, ge, lim_row);
    j0 += line_out(j0, u, ge, lim_col);
    j1 -= line_out(j1, u, ge, lim_col);
  }
  return (i0 <= i1) & (j0 <= j1);
}

// The same for a packed splat row s.
DSS_SPLAT_FN bool tighten_box(const float* s, float cutoff, int& j0, int& j1, int& i0, int& i1) {
  return tighten_box(s[0], s[1], s[2], s[3], s[4], cutoff, j0, j1, i0, i1);
}

}  // namespace dss_splat
