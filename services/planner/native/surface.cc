// VA-MPPI's expected surface cost (costs.surface_expectation, closed form) on a CPU, as
// an XLA FFI custom call.
//
// For every footprint point of every step of every trajectory: the five cells it reads
// (centre, +x, -x, +y, -y: costs.OFFSETS) gathered from the mean map, the five Gaussian
// quantities of Eq. occupied (x and y gradient, the step from the previous step's cell,
// the step from the previous point of its array, the height against the ground under the
// vehicle now) with their variances from the variance each cell was met with, and the
// sum of the five probabilities P(|X| > threshold); 5 where the point is off the map.
// The same arithmetic as the JAX form, with erfc from Abramowitz & Stegun 7.1.26
// (absolute error below 1.5e-7) instead of XLA's erf: XLA:CPU took about 10 ms for the
// ten erf a footprint point needs at K = 800, one core (docs/benchmarks.md, session 17).
//
// Inputs (the handler checks their shapes agree and returns an error if not):
//   mean (H, W) f32, rows, cols (K, T, P) i32 the footprint points' cells (clipped one
//   cell inside the map, as costs.footprint_cells has them; clamped here again, so that
//   nothing is read outside the map), outside (K, T, P) i32 1 for points off the map,
//   variance (K, T, 5 P) f32 the variance met at the five cells (query-major, as
//   va_counts.cc writes it), h0 (K,) f32 the ground under the vehicle now.
// Output: expected tripped indicators (K, T, P) f32.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "parallel.h"
#include "vecmath.h"
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

constexpr int64_t kGrain = 8;      // trajectories a thread takes at a time
constexpr int64_t kQueries = 5;    // costs.OFFSETS

struct Problem {
  const float* mean;
  int64_t h, w;
  const int32_t *rows, *cols, *outside;
  const float* variance;
  const float* h0;
  int64_t t_len, n_pts, n_across;
  float two_res, two_res2;
  float grad, step, height;   // thresholds on |quantity|
  float* out;
};

// erfc(z), Abramowitz & Stegun 7.1.26 for |z| and erfc(-z) = 2 - erfc(z)
__attribute__((always_inline)) inline float erfc_as(float z) {
  const float a = std::abs(z);
  const float t = 1.0f / (1.0f + 0.3275911f * a);
  float p = 1.061405429f;
  p = p * t - 1.453152027f;
  p = p * t + 1.421413741f;
  p = p * t - 0.284496736f;
  p = p * t + 0.254829592f;
  const float e = p * t * vamppi::exp_nonpositive(-a * a);
  return z < 0.0f ? 2.0f - e : e;
}

// P(|X| > threshold) for X ~ N(mean, var); the indicator where var is 0 (costs.exceed_prob)
__attribute__((always_inline)) inline float exceed(float mean, float var, float threshold) {
  const float s = std::sqrt(std::max(var, 0.0f));
  const float inv = 1.0f / std::max(s * 1.41421356f, 1e-30f);
  const float p = 0.5f * (erfc_as((threshold + mean) * inv) + erfc_as((threshold - mean) * inv));
  const float indicator = std::abs(mean) > threshold ? 1.0f : 0.0f;
  return s > 0.0f ? std::min(std::max(p, 0.0f), 1.0f) : indicator;
}

__attribute__((target("prefer-vector-width=512")))
void trajectories(const Problem& p, vamppi::Ranges& ranges) {
  const int64_t n_pts = p.n_pts, n = p.t_len * n_pts;
  const int32_t h = static_cast<int32_t>(p.h), w = static_cast<int32_t>(p.w);
  // per point of a trajectory (step-major): the centre cell's mean and variance, the
  // gradients and their variances
  std::vector<float> hc(n), vc(n), gx(n), vx(n), gy(n), vy(n);
  // 1 where a point has a previous step / a previous point in its array, else 0
  std::vector<float> after_first_step(n), after_first_point(n);
  for (int64_t j = 0; j < n; ++j) {
    after_first_step[j] = j >= n_pts ? 1.0f : 0.0f;
    after_first_point[j] = (j % n_pts) % p.n_across == 0 ? 0.0f : 1.0f;
  }
  for (int64_t k0, k1; ranges.next(k0, k1);) {
    for (int64_t k = k0; k < k1; ++k) {
      const int32_t* rows = p.rows + k * n;
      const int32_t* cols = p.cols + k * n;
      const int32_t* outside = p.outside + k * n;
      for (int64_t i = 0; i < p.t_len; ++i) {   // the five cells (costs.query_cells)
        const float* v = p.variance + (k * n + i * n_pts) * kQueries;   // query-major
#pragma omp simd
        for (int64_t q = 0; q < n_pts; ++q) {
          const int64_t j = i * n_pts + q;
          const int32_t row = rows[j], col = cols[j];
          const int32_t r = row < 1 ? 1 : row > h - 2 ? h - 2 : row;
          const int32_t c = col < 1 ? 1 : col > w - 2 ? w - 2 : col;
          const int32_t at = r * w + c;
          hc[j] = p.mean[at];
          vc[j] = v[q];
          gx[j] = (p.mean[at + 1] - p.mean[at - 1]) / p.two_res;
          vx[j] = (v[n_pts + q] + v[2 * n_pts + q]) / p.two_res2;
          gy[j] = (p.mean[at + w] - p.mean[at - w]) / p.two_res;
          vy[j] = (v[3 * n_pts + q] + v[4 * n_pts + q]) / p.two_res2;
        }
      }
      // the five indicators' probabilities (costs.indicator_quantities, exceed_prob)
      const float h0 = p.h0[k];
      float* out = p.out + k * n;
#pragma omp simd
      for (int64_t j = 0; j < n; ++j) {
        const int64_t jt = j >= n_pts ? j - n_pts : j, ja = j > 0 ? j - 1 : j;
        const float st = (hc[j] - hc[jt]) * after_first_step[j];
        const float vst = (vc[j] + vc[jt]) * after_first_step[j];
        const float sa = (hc[j] - hc[ja]) * after_first_point[j];
        const float vsa = (vc[j] + vc[ja]) * after_first_point[j];
        const float e = exceed(gx[j], vx[j], p.grad) + exceed(gy[j], vy[j], p.grad) +
                        exceed(st, vst, p.step) + exceed(sa, vsa, p.step) +
                        exceed(hc[j] - h0, vc[j], p.height);
        out[j] = outside[j] ? 5.0f : e;
      }
    }
  }
}

ffi::Error SurfaceImpl(ffi::Buffer<ffi::F32> mean, ffi::Buffer<ffi::S32> rows,
                       ffi::Buffer<ffi::S32> cols, ffi::Buffer<ffi::S32> outside,
                       ffi::Buffer<ffi::F32> variance,
                       ffi::Buffer<ffi::F32> h0, ffi::ResultBuffer<ffi::F32> out,
                       float two_res, float two_res2, float grad, float step, float height,
                       int64_t n_across, int64_t threads) {
  auto md = mean.dimensions(), rd = rows.dimensions(), cd = cols.dimensions(),
       od = outside.dimensions(), vd = variance.dimensions(), hd = h0.dimensions();
  if (md.size() != 2 || rd.size() != 3 || cd.size() != 3 || vd.size() != 3 ||
      hd.size() != 1 || cd[0] != rd[0] || cd[1] != rd[1] || cd[2] != rd[2] || od.size() != 3 ||
      od[0] != rd[0] || od[1] != rd[1] || od[2] != rd[2] ||
      vd[0] != rd[0] || vd[1] != rd[1] || vd[2] != kQueries * rd[2] || hd[0] != rd[0]) {
    return ffi::Error::InvalidArgument("surface: inconsistent shapes");
  }
  if (md[0] < 3 || md[1] < 3 || n_across < 1) {
    return ffi::Error::InvalidArgument("surface: a map under 3 x 3 cells or no array");
  }
  Problem p{mean.typed_data(), md[0], md[1], rows.typed_data(), cols.typed_data(),
            outside.typed_data(),
            variance.typed_data(), h0.typed_data(), rd[1], rd[2], n_across, two_res,
            two_res2, grad, step, height, out->typed_data()};
  vamppi::parallel_ranges(rd[0], threads, kGrain,
                          [&p](vamppi::Ranges& ranges) { trajectories(p, ranges); });
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(Surface, SurfaceImpl,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::F32>>()   // mean
                                  .Arg<ffi::Buffer<ffi::S32>>()   // rows
                                  .Arg<ffi::Buffer<ffi::S32>>()   // cols
                                  .Arg<ffi::Buffer<ffi::S32>>()   // outside
                                  .Arg<ffi::Buffer<ffi::F32>>()   // variance met
                                  .Arg<ffi::Buffer<ffi::F32>>()   // h0
                                  .Ret<ffi::Buffer<ffi::F32>>()   // expected indicators
                                  .Attr<float>("two_res")    // 2 g
                                  .Attr<float>("two_res2")   // (2 g)^2
                                  .Attr<float>("grad")
                                  .Attr<float>("step")
                                  .Attr<float>("height")
                                  .Attr<int64_t>("n_across")
                                  .Attr<int64_t>("threads"));
