// VA-MPPI's expected surface cost of one trajectory (costs.surface_expectation, closed
// form), shared by surface.cc (its own custom call) and va_counts.cc (fused after the
// variance update, so the variances never leave the thread's cache).
//
// For every footprint point of every step: the five cells it reads (centre, +x, -x, +y,
// -y: costs.OFFSETS) gathered from the mean map, the five Gaussian quantities of Eq.
// occupied (x and y gradient, the step from the previous step's cell, the step from the
// previous point of its array, the height against the ground under the vehicle now) with
// their variances from the variance each cell was met with, and the sum of the five
// probabilities P(|X| > threshold); 5 where the point is off the map. The same arithmetic
// as the JAX form, with erfc from Abramowitz & Stegun 7.1.26 (absolute error below
// 1.5e-7) instead of XLA's erf: XLA:CPU took about 10 ms for the ten erf a footprint
// point needs at K = 800, one core.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "vecmath.h"

namespace vamppi::surface {

constexpr int64_t kQueries = 5;    // costs.OFFSETS

struct Params {
  const float* mean;
  int64_t h, w;
  int64_t t_len, n_pts, n_across;
  float two_res, two_res2;
  float grad, step, height;   // thresholds on |quantity|
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
  const float e = p * t * exp_nonpositive(-a * a);
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

// A thread's scratch, per point of a trajectory (step-major): the centre cell's mean and
// variance, the gradients and their variances; 1 where a point has a previous step / a
// previous point in its array, else 0.
struct Scratch {
  explicit Scratch(const Params& p)
      : n(p.t_len * p.n_pts), hc(n), vc(n), gx(n), vx(n), gy(n), vy(n),
        after_first_step(n), after_first_point(n) {
    for (int64_t j = 0; j < n; ++j) {
      after_first_step[j] = j >= p.n_pts ? 1.0f : 0.0f;
      after_first_point[j] = (j % p.n_pts) % p.n_across == 0 ? 0.0f : 1.0f;
    }
  }
  int64_t n;
  std::vector<float> hc, vc, gx, vx, gy, vy, after_first_step, after_first_point;
};

// One trajectory: rows, cols, outside (T, P) its footprint points' cells (clamped one cell
// inside the map here) and 1 where off the map, variance (T, 5 P) met at the five cells
// (query-major, as va_counts.cc writes it), h0 the ground under the vehicle now; out (T, P)
// the expected tripped indicators.
__attribute__((target("prefer-vector-width=512")))
inline void trajectory(const Params& p, Scratch& s, const int32_t* rows, const int32_t* cols,
                       const int32_t* outside, const float* variance, float h0, float* out) {
  const int64_t n_pts = p.n_pts, n = s.n;
  const int32_t h = static_cast<int32_t>(p.h), w = static_cast<int32_t>(p.w);
  float *hc = s.hc.data(), *vc = s.vc.data(), *gx = s.gx.data(), *vx = s.vx.data(),
        *gy = s.gy.data(), *vy = s.vy.data();
  const float *after_step = s.after_first_step.data(), *after_point = s.after_first_point.data();
  for (int64_t i = 0; i < p.t_len; ++i) {   // the five cells (costs.five_cells)
    const float* v = variance + i * n_pts * kQueries;   // query-major
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
#pragma omp simd
  for (int64_t j = 0; j < n; ++j) {
    const int64_t jt = j >= n_pts ? j - n_pts : j, ja = j > 0 ? j - 1 : j;
    const float st = (hc[j] - hc[jt]) * after_step[j];
    const float vst = (vc[j] + vc[jt]) * after_step[j];
    const float sa = (hc[j] - hc[ja]) * after_point[j];
    const float vsa = (vc[j] + vc[ja]) * after_point[j];
    const float e = exceed(gx[j], vx[j], p.grad) + exceed(gy[j], vy[j], p.grad) +
                    exceed(st, vst, p.step) + exceed(sa, vsa, p.step) +
                    exceed(hc[j] - h0, vc[j], p.height);
    out[j] = outside[j] ? 5.0f : e;
  }
}

}  // namespace vamppi::surface
