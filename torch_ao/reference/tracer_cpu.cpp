// AO rays of the reference renderer on analytic scenes (planes, spheres, boxes, capped cylinders), one
// pixel's samples at a time: the stratified sample numbers, the hemisphere directions and the any-hit
// occlusion test, without the (rays x primitives) intermediates of the tensor path. Pixels are spread
// over torch's intra-op threads.
//
// It repeats torch_ao/reference/sampling.py and the tensor tracer (torch_ao/reference/tracer.py)
// operation by operation in float32 (built with -ffp-contract=off; cos/sin are the functions torch's own
// CPU kernels call), so the sample directions are the tensor path's bit for bit; a hit test can still
// differ where torch computes a dot product by a matrix multiply (BLAS may fuse), which flips a ray only
// when it grazes an edge or ends within rounding of R (docs/performance.md has the measured agreement).
// Primitives whose bounding sphere is farther than R (with a margin) from a pixel's origin are skipped:
// they cannot be hit, so skipping them changes nothing.
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/cpu/vec/functional.h>
#include <ATen/cpu/vec/vec.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "../kernels/mkl_vml.h"

namespace {

using Vec = at::vec::Vectorized<float>;
constexpr float kInf = std::numeric_limits<float>::infinity();
constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();

// sampling.py's lowbias32 hash and uniform(): s and s2 are the per-(seed, stream) constants
inline uint32_t mix(uint32_t x) {
  x ^= x >> 16;
  x *= 0x7FEB352Du;
  x ^= x >> 15;
  x *= 0x846CA68Bu;
  return x ^ (x >> 16);
}
inline uint32_t hash(int64_t key, uint32_t s, uint32_t s2) {
  const uint64_t k = uint64_t(key);
  return mix(mix(uint32_t(k) ^ s) ^ uint32_t(k >> 32) ^ s2);
}
inline float unit(uint32_t h) { return float(h >> 8) * (1.0f / float(1 << 24)); }

// torch.minimum / torch.maximum: NaN if either is NaN
inline float nmin(float a, float b) { return (a < b || std::isnan(a)) ? a : b; }
inline float nmax(float a, float b) { return (a > b || std::isnan(a)) ? a : b; }
inline float dot3(const float* a, const float* b) { return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]; }

struct Prims {
  // planes: n (P,3), off (P,)
  int64_t np = 0;
  const float *pn = nullptr, *poff = nullptr;
  // spheres: c (S,3), r2 (S,)
  int64_t ns = 0;
  const float *sc = nullptr, *sr2 = nullptr;
  // boxes: Rcat (3, 3X) axis-major columns, cl (3X,), h (3, X)
  int64_t nb = 0;
  const float *bR = nullptr, *bcl = nullptr, *bh = nullptr;
  // cylinders: c (C,3), a (C,3), r2 (C,), half height h (C,)
  int64_t nc = 0;
  const float *cc = nullptr, *ca = nullptr, *cr2 = nullptr, *ch = nullptr;
  // bounding spheres (S + X + C, 4) float64 in that order: centre, radius
  const double* bounds = nullptr;
};

inline bool hit_plane(const Prims& P, int64_t i, const float* o, const float* d, float tmax) {
  const float* n = P.pn + 3 * i;
  const float t = (P.poff[i] - dot3(o, n)) / dot3(d, n);
  return t > 0 && t < tmax;
}

inline bool hit_sphere(const Prims& P, int64_t i, const float* o, const float* d, float tmax) {
  const float* c = P.sc + 3 * i;
  const float oc[3] = {o[0] - c[0], o[1] - c[1], o[2] - c[2]};
  const float b = dot3(oc, d);
  const float perp[3] = {oc[0] - b * d[0], oc[1] - b * d[1], oc[2] - b * d[2]};
  const float disc = P.sr2[i] - dot3(perp, perp);
  const float sq = std::sqrt(std::max(disc, 0.0f));
  const float t0 = -b - sq, t1 = sq - b;
  const float t = t0 > 0 ? t0 : t1;
  return disc >= 0 && t > 0 && t < tmax;
}

inline bool hit_box(const Prims& P, int64_t i, const float* o, const float* d, float tmax) {
  const int64_t X = P.nb;
  float lo[3], hi[3];
  for (int k = 0; k < 3; ++k) {
    const int64_t col = k * X + i;
    const float R0 = P.bR[col], R1 = P.bR[3 * X + col], R2 = P.bR[6 * X + col];
    const float ol = ((o[0] * R0 + o[1] * R1) + o[2] * R2) - P.bcl[col];
    const float inv = 1.0f / ((d[0] * R0 + d[1] * R1) + d[2] * R2);
    const float h = P.bh[k * X + i];
    const float t1 = (-h - ol) * inv, t2 = (h - ol) * inv;
    lo[k] = nmin(t1, t2);
    hi[k] = nmax(t1, t2);
  }
  const float tn = nmax(nmax(lo[0], lo[1]), lo[2]), tf = nmin(nmin(hi[0], hi[1]), hi[2]);
  const float t = tn > 0 ? tn : tf;
  return tn <= tf && t > 0 && t < tmax;
}

inline bool hit_cylinder(const Prims& P, int64_t i, const float* o, const float* d, float tmax) {
  const float *c = P.cc + 3 * i, *a = P.ca + 3 * i;
  const float oc[3] = {o[0] - c[0], o[1] - c[1], o[2] - c[2]};
  const float da = dot3(d, a), oa = dot3(oc, a);
  const float op[3] = {oc[0] - oa * a[0], oc[1] - oa * a[1], oc[2] - oa * a[2]};
  const float dp[3] = {d[0] - da * a[0], d[1] - da * a[1], d[2] - da * a[2]};
  const float A = dot3(dp, dp), B = dot3(op, dp), C = dot3(op, op) - P.cr2[i];
  const float disc = B * B - A * C;
  const float sq = std::sqrt(std::max(disc, 0.0f));
  const bool parallel = A < 1e-12f;
  const float Asafe = parallel ? 1.0f : A;
  const float c_near = parallel ? (C < 0 ? -kInf : kInf) : (-B - sq) / Asafe;
  const float c_far = parallel ? (C < 0 ? kInf : -kInf) : (-B + sq) / Asafe;
  const bool miss = disc < 0 && !parallel;
  const float inv = 1.0f / da, h = P.ch[i];
  const float s1 = (-h - oa) * inv, s2 = (h - oa) * inv;
  const float tn = nmax(c_near, std::fmin(s1, s2)), tf = nmin(c_far, std::fmax(s1, s2));
  const float t = tn > 0 ? tn : tf;
  return !miss && tn <= tf && t > 0 && t < tmax;
}

struct Settings {
  int64_t spp, groups, nx, ny;  // ny x nx: the jitter grid of a group (sampling.group_grid)
  bool cosine;
  float tmax;
  uint32_t s[3], s2[3];  // hash constants of the streams: u1, u2, group offset
};

// One pixel: spp directions into dirs (3 x spp, component-major), then the occlusion of each.
void pixel(const Settings& cfg, const Prims& P, const float* o, const float* t, const float* b, const float* n,
           int64_t key, std::vector<float>& u1, std::vector<float>& phi, std::vector<float>& cs,
           std::vector<float>& sn, std::vector<int64_t>& active, bool* out) {
  const int64_t spp = cfg.spp, nper = spp / cfg.groups, gx = cfg.nx, gy = cfg.ny, cells = gx * gy;
  const float clamp = float(1 - 1e-7);
  int64_t offset = 0;
  for (int64_t j = 0; j < spp; ++j) {
    if (j % nper == 0) {
      const double u = double(unit(hash(key * cfg.groups + j / nper, cfg.s[2], cfg.s2[2])));
      offset = std::min<int64_t>(int64_t(u * double(cells)), cells - 1);
    }
    const int64_t cell = (j % nper + offset) % cells;
    const int64_t k = key * spp + j;
    const float a = (float(cell % gx) + unit(hash(k, cfg.s[0], cfg.s2[0]))) / float(gx);
    const float c = (float(cell / gx) + unit(hash(k, cfg.s[1], cfg.s2[1]))) / float(gy);
    u1[j] = std::min(a, clamp);
    phi[j] = float(2 * M_PI) * std::min(c, clamp);
  }
#ifdef TORCH_AO_MKL_VML
  vmsCos(int(spp), phi.data(), cs.data(), kVmlMode);
  vmsSin(int(spp), phi.data(), sn.data(), kVmlMode);
#else
  for (int64_t j = 0; j < spp; j += Vec::size()) {
    const int m = int(std::min<int64_t>(Vec::size(), spp - j));
    Vec x = Vec::loadu(phi.data() + j, m);
    x.cos().store(cs.data() + j, m);
    x.sin().store(sn.data() + j, m);
  }
#endif
  // primitives that can be reached within tmax from this origin
  active.clear();
  const double reach = double(cfg.tmax);
  const double margin = 1e-3 * (1.0 + std::abs(double(o[0])) + std::abs(double(o[1])) + std::abs(double(o[2])));
  for (int64_t i = 0; i < P.np; ++i) {
    const float* pn = P.pn + 3 * i;
    const double dist = std::abs(double(o[0]) * pn[0] + double(o[1]) * pn[1] + double(o[2]) * pn[2] - P.poff[i]);
    if (!(dist > reach + margin)) active.push_back(i);
  }
  for (int64_t q = 0; q < P.ns + P.nb + P.nc; ++q) {
    const double* s = P.bounds + 4 * q;
    const double dx = o[0] - s[0], dy = o[1] - s[1], dz = o[2] - s[2];
    const double dist = std::sqrt(dx * dx + dy * dy + dz * dz) - s[3];
    if (!(dist > reach + margin + 1e-3 * s[3])) active.push_back(P.np + q);
  }
  for (int64_t j = 0; j < spp; ++j) {
    float l0, l1, l2;
    if (cfg.cosine) {
      const float r = std::sqrt(u1[j]);
      l0 = r * cs[j];
      l1 = r * sn[j];
      l2 = std::sqrt(std::max(1.0f - u1[j], 0.0f));
    } else {
      const float z = u1[j];
      const float r = std::sqrt(std::max(1.0f - z * z, 0.0f));
      l0 = r * cs[j];
      l1 = r * sn[j];
      l2 = z;
    }
    const float d[3] = {(l0 * t[0] + l1 * b[0]) + l2 * n[0], (l0 * t[1] + l1 * b[1]) + l2 * n[1],
                        (l0 * t[2] + l1 * b[2]) + l2 * n[2]};
    bool hit = false;
    for (int64_t q : active) {
      if (q < P.np) {
        hit = hit_plane(P, q, o, d, cfg.tmax);
      } else if ((q -= P.np) < P.ns) {
        hit = hit_sphere(P, q, o, d, cfg.tmax);
      } else if ((q -= P.ns) < P.nb) {
        hit = hit_box(P, q, o, d, cfg.tmax);
      } else {
        hit = hit_cylinder(P, q - P.nb, o, d, cfg.tmax);
      }
      if (hit) break;
    }
    out[j] = hit;
  }
}

const float* f32(const at::Tensor& x, const char* name) {
  TORCH_CHECK(x.scalar_type() == at::kFloat && x.is_contiguous() && x.device().is_cpu(), name,
              ": expected a contiguous float32 CPU tensor");
  return x.data_ptr<float>();
}

at::Tensor ao_occlusion(const at::Tensor& origins, const at::Tensor& tangents, const at::Tensor& bitangents,
                        const at::Tensor& normals, const at::Tensor& keys, int64_t spp, int64_t groups, int64_t nx,
                        int64_t ny, bool cosine,
                        double tmax, const std::vector<int64_t>& hash_constants, const at::Tensor& plane_n,
                        const at::Tensor& plane_off, const at::Tensor& sphere_c, const at::Tensor& sphere_r2,
                        const at::Tensor& box_R, const at::Tensor& box_cl, const at::Tensor& box_h,
                        const at::Tensor& cyl_c, const at::Tensor& cyl_a, const at::Tensor& cyl_r2,
                        const at::Tensor& cyl_h, const at::Tensor& bounds) {
  TORCH_CHECK(hash_constants.size() == 6, "hash_constants: expected 6 values");
  TORCH_CHECK(keys.scalar_type() == at::kLong && keys.is_contiguous(), "keys: expected contiguous int64");
  TORCH_CHECK(bounds.scalar_type() == at::kDouble && bounds.is_contiguous(), "bounds: expected contiguous float64");
  TORCH_CHECK(spp > 0 && groups > 0 && spp % groups == 0, "spp: expected a positive multiple of groups");
  const int64_t m = origins.size(0);
  TORCH_CHECK(nx > 0 && ny > 0 && nx * ny >= spp / groups, "nx, ny: expected a grid of at least spp / groups cells");
  Settings cfg{spp, groups, nx, ny, cosine, float(tmax), {}, {}};
  for (int i = 0; i < 3; ++i) {
    cfg.s[i] = uint32_t(hash_constants[2 * i]);
    cfg.s2[i] = uint32_t(hash_constants[2 * i + 1]);
  }
  Prims P;
  P.np = plane_off.numel(), P.pn = f32(plane_n, "plane_n"), P.poff = f32(plane_off, "plane_off");
  P.ns = sphere_r2.numel(), P.sc = f32(sphere_c, "sphere_c"), P.sr2 = f32(sphere_r2, "sphere_r2");
  P.nb = box_h.numel() / 3, P.bR = f32(box_R, "box_R"), P.bcl = f32(box_cl, "box_cl"), P.bh = f32(box_h, "box_h");
  P.nc = cyl_r2.numel(), P.cc = f32(cyl_c, "cyl_c"), P.ca = f32(cyl_a, "cyl_a"), P.cr2 = f32(cyl_r2, "cyl_r2");
  P.ch = f32(cyl_h, "cyl_h");
  TORCH_CHECK(bounds.numel() == 4 * (P.ns + P.nb + P.nc), "bounds: expected one row per sphere, box, cylinder");
  P.bounds = bounds.data_ptr<double>();
  const float *o = f32(origins, "origins"), *t = f32(tangents, "tangents"), *b = f32(bitangents, "bitangents"),
              *n = f32(normals, "normals");
  const int64_t* k = keys.data_ptr<int64_t>();
  at::Tensor out = at::empty({m, spp}, origins.options().dtype(at::kBool));
  bool* occ = out.data_ptr<bool>();
  // pixels handed out a few at a time to whichever thread is free (an even split stalls on a busy core)
  const int64_t chunk = 16;
  std::atomic<int64_t> next{0};
  at::parallel_for(0, at::get_num_threads(), 1, [&](int64_t, int64_t) {
#ifdef TORCH_AO_MKL_VML
    const int mkl_threads = MKL_Set_Num_Threads_Local(1);
#endif
    const int64_t padded = (spp + Vec::size() - 1) / Vec::size() * Vec::size();
    std::vector<float> u1(padded), phi(padded), cs(padded), sn(padded);
    std::vector<int64_t> active;
    for (int64_t p0 = next.fetch_add(chunk); p0 < m; p0 = next.fetch_add(chunk))
      for (int64_t p = p0; p < std::min(m, p0 + chunk); ++p)
        pixel(cfg, P, o + 3 * p, t + 3 * p, b + 3 * p, n + 3 * p, k[p], u1, phi, cs, sn, active, occ + p * spp);
#ifdef TORCH_AO_MKL_VML
    MKL_Set_Num_Threads_Local(mkl_threads);
#endif
  });
  return out;
}

}  // namespace

TORCH_LIBRARY(torch_ao_tracer, m) {
  m.def("ao_occlusion(Tensor origins, Tensor tangents, Tensor bitangents, Tensor normals, Tensor keys, int spp, "
        "int groups, int nx, int ny, bool cosine, float tmax, int[] hash_constants, Tensor plane_n, Tensor plane_off, "
        "Tensor sphere_c, Tensor sphere_r2, Tensor box_R, Tensor box_cl, Tensor box_h, Tensor cyl_c, Tensor cyl_a, "
        "Tensor cyl_r2, Tensor cyl_h, Tensor bounds) -> Tensor");
  m.impl("ao_occlusion", c10::DispatchKey::CPU, TORCH_FN(ao_occlusion));
}
