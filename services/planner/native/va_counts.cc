// The visibility-aware variance update on a CPU, as an XLA FFI custom call.
//
// The same algorithm as services/planner/visibility.py (batched_decayed_variance),
// one trajectory at a time instead of vectorised: for every trajectory, a scan
// over the horizon adds the visible ray points of pose i - lag to a raw count
// map (visible points per cell) and reads the S x S patch of raw counts around
// each of step i's footprint cells; the patch times a fixed (S*S, Q) matrix (the
// Gaussian splat centred on the Q query cells, c folded in) gives the Q
// splatted counts C, and the variance met there is the map's variance at the
// query cell times exp(-gamma C). Each ray is marched from its nearest point and
// stops at its first blocker, which is itself seen; a pose's `skip` nearest points
// of every ray block it but do not count (`planner.visibility_stop_decel_mps2`).
// The visited cells are set back to zero after each trajectory, so one map per
// thread serves every trajectory.
//
// Why native: on XLA:CPU the vectorised form pays 3-4 ns per scatter and
// gather element for 19 M ray points at K = 800 (docs/benchmarks.md); here each
// ray stops at its first blocker and the raw counts are uint16 (the caller keeps
// T * rays * points below 2^16, so no cell can overflow). The prior's gather and
// the exponential are done here too (XLA:CPU spent some 30 ms on them at K = 800).
//
// Inputs (the handler checks their shapes agree and returns an error if not):
//   mean, variance (H, W) f32, origin (2,) f32, states (K, T, 6) f32 (T = N + 1; X,
//   Y, PSI at 3, 4, 5), skip (K, T) i32 the uncounted nearest points of each ray,
//   rows, cols (K, T, P) i32 the footprint points' cells (unclipped: the query cells
//   are clipped to the map, the patches `reach` inside it, as the JAX form does),
//   offsets (Q, 2) i32 the query cells around each footprint cell, grid (M, 2) f32
//   body offsets of the ray points, ray-major, weights (S*S, Q) f32.
// Output: variance (K, T, Q * P) f32, query-major (block q = offsets[q]); steps
// before `lag` meet the prior.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <thread>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

constexpr int kX = 3, kY = 4, kPsi = 5, kStateDim = 6;
constexpr int64_t kMaxPoints = 1024;   // config: visibility_points <= 1000

struct Problem {
  const float* mean;
  const float* variance;
  int64_t h, w;
  float ox, oy, res, height;
  const float* states;
  const int32_t* skip;
  int64_t t_len;
  const int32_t* rows;
  const int32_t* cols;
  int64_t n_pts;
  const int32_t* offsets;     // (queries, 2) row, col
  int64_t reach;              // max |offset|
  const float* grid_x;        // (rays, points) body-frame offsets, split by component
  const float* grid_y;
  int64_t rays, points;
  const float* weights_t;     // (queries, size * size): the weights transposed
  int64_t size, queries;
  int64_t lag, pad;
  float gamma;
  float* out;
};

// exp(x) for x <= 0 as vector code: x = n ln2 + r (Cody-Waite, two-part ln2),
// |r| <= ln2 / 2, e^r by its degree-6 Taylor polynomial (remainder r^7 / 7! < 1.3e-7
// relative), times 2^n built in the exponent bits; 0 below -87 (the end of the normal
// range: a variance times e^-87 is nothing a cost can feel).
inline float exp_nonpositive(float x) {
  const float xc = std::max(x, -87.0f);
  const float n = std::nearbyint(xc * 1.44269504f);
  const float r = (xc - n * 0.693145752f) - n * 1.42860677e-6f;
  float p = 1.0f / 720.0f;
  p = p * r + 1.0f / 120.0f;
  p = p * r + 1.0f / 24.0f;
  p = p * r + 1.0f / 6.0f;
  p = p * r + 0.5f;
  p = p * r + 1.0f;
  p = p * r + 1.0f;
  const int32_t bits = (static_cast<int32_t>(n) + 127) << 23;
  float scale;
  std::memcpy(&scale, &bits, sizeof scale);
  return x < -87.0f ? 0.0f : p * scale;
}

// Adds pose `s`'s visible ray points to the raw count map (padded) and appends their cells
// to `cells` (for the clean-up). A ray's cells are computed together (vector code), then
// walked to its first blocker; the count is added as the cell's height is read (the two
// maps' cache misses overlap).
void add_visible(const Problem& p, const float* s, int32_t skip, uint16_t* map,
                 std::vector<int32_t>& cells) {
  const float x = s[kX], y = s[kY];
  const float c = std::cos(s[kPsi]), sn = std::sin(s[kPsi]);
  const int64_t wp = p.w + 2 * p.pad;
  int64_t vr = static_cast<int64_t>(std::floor((y - p.oy) / p.res));
  int64_t vc = static_cast<int64_t>(std::floor((x - p.ox) / p.res));
  vr = std::clamp<int64_t>(vr, 0, p.h - 1);
  vc = std::clamp<int64_t>(vc, 0, p.w - 1);
  const float threshold = p.mean[vr * p.w + vc] + p.height;
  const float fh = static_cast<float>(p.h), fw = static_cast<float>(p.w);
  const float ox = p.ox, oy = p.oy, res = p.res;
  const int n = static_cast<int>(p.points);
  float fr[kMaxPoints], fc[kMaxPoints];
  for (int64_t r = 0; r < p.rays; ++r) {
    const float* __restrict gx = p.grid_x + r * p.points;
    const float* __restrict gy = p.grid_y + r * p.points;
    for (int k = 0; k < n; ++k) {   // as visibility.ray_cells, in float32
      fc[k] = std::floor((x + c * gx[k] - sn * gy[k] - ox) / res);
      fr[k] = std::floor((y + sn * gx[k] + c * gy[k] - oy) / res);
    }
    for (int64_t k = 0; k < p.points; ++k) {
      // off the map: blocks the ray and is not seen
      if (!(fr[k] >= 0.0f && fr[k] < fh && fc[k] >= 0.0f && fc[k] < fw)) break;
      const int64_t row = static_cast<int64_t>(fr[k]), col = static_cast<int64_t>(fc[k]);
      if (k >= skip) {   // nearer points block but do not count
        const int32_t cell = static_cast<int32_t>((row + p.pad) * wp + col + p.pad);
        ++map[cell];
        cells.push_back(cell);
      }
      if (p.mean[row * p.w + col] > threshold) break;  // the first blocker is seen
    }
  }
}

void trajectories(const Problem& p, int64_t k0, int64_t k1) {
  const int64_t wp = p.w + 2 * p.pad;
  const int64_t area = p.size * p.size, width = p.queries * p.n_pts;
  // raw counts as uint16 (at most rays * points * T per cell, checked on the Python side):
  // half the cache footprint of floats
  std::vector<uint16_t> map(static_cast<size_t>((p.h + 2 * p.pad) * wp), 0);
  std::vector<int32_t> cells;
  cells.reserve(static_cast<size_t>(p.t_len * p.rays * p.points));
  std::vector<float> patch(static_cast<size_t>(area)), prior(static_cast<size_t>(width));
  for (int64_t k = k0; k < k1; ++k) {
    const float* st = p.states + k * p.t_len * kStateDim;
    const int32_t* skip = p.skip + k * p.t_len;
    const int32_t* rows = p.rows + k * p.t_len * p.n_pts;
    const int32_t* cols = p.cols + k * p.t_len * p.n_pts;
    float* out = p.out + k * p.t_len * width;
    cells.clear();
    for (int64_t i = 0; i < p.t_len; ++i) {
      const int32_t* ri = rows + i * p.n_pts;
      const int32_t* ci = cols + i * p.n_pts;
      float* oi = out + i * width;
      for (int64_t o = 0; o < p.queries; ++o) {   // the prior at the query cells
        const int64_t dr = p.offsets[2 * o], dc = p.offsets[2 * o + 1];
        for (int64_t q = 0; q < p.n_pts; ++q) {
          const int64_t r = std::clamp<int64_t>(ri[q] + dr, 0, p.h - 1);
          const int64_t c = std::clamp<int64_t>(ci[q] + dc, 0, p.w - 1);
          prior[o * p.n_pts + q] = p.variance[r * p.w + c];
        }
      }
      if (i < p.lag) {                             // nothing seen yet
        std::copy(prior.begin(), prior.end(), oi);
        continue;
      }
      // poses 0 .. i - lag
      add_visible(p, st + (i - p.lag) * kStateDim, skip[i - p.lag], map.data(), cells);
      for (int64_t q = 0; q < p.n_pts; ++q) {
        // the patch around the footprint cell starts at the cell itself in padded coordinates
        const int64_t r0 = std::clamp<int64_t>(ri[q], p.reach, p.h - 1 - p.reach);
        const int64_t c0 = std::clamp<int64_t>(ci[q], p.reach, p.w - 1 - p.reach);
        for (int64_t a = 0; a < p.size; ++a) {
          const uint16_t* src = map.data() + (r0 + a) * wp + c0;
          float* dst = patch.data() + a * p.size;
          for (int64_t b = 0; b < p.size; ++b) dst[b] = static_cast<float>(src[b]);
        }
        for (int64_t o = 0; o < p.queries; ++o) {
          const float* wt = p.weights_t + o * area;
          float acc = 0.0f;
#pragma omp simd reduction(+ : acc)
          for (int64_t e = 0; e < area; ++e) acc += patch[e] * wt[e];
          oi[o * p.n_pts + q] = acc;
        }
      }
      const float g = -p.gamma;
      const float* pr = prior.data();
#pragma omp simd
      for (int64_t j = 0; j < width; ++j) oi[j] = pr[j] * exp_nonpositive(g * oi[j]);
    }
    for (int32_t cell : cells) map[cell] = 0;
  }
}

ffi::Error VaCountsImpl(ffi::Buffer<ffi::F32> mean, ffi::Buffer<ffi::F32> variance,
                        ffi::Buffer<ffi::F32> origin, ffi::Buffer<ffi::F32> states,
                        ffi::Buffer<ffi::S32> skip, ffi::Buffer<ffi::S32> rows,
                        ffi::Buffer<ffi::S32> cols,
                        ffi::Buffer<ffi::S32> offsets, ffi::Buffer<ffi::F32> grid,
                        ffi::Buffer<ffi::F32> weights, ffi::ResultBuffer<ffi::F32> out,
                        float resolution, float height, float gamma, int64_t rays,
                        int64_t points, int64_t lag, int64_t pad, int64_t threads) {
  auto md = mean.dimensions(), vd = variance.dimensions(), sd = states.dimensions(),
       kd = skip.dimensions(), rd = rows.dimensions(), cd = cols.dimensions(),
       od = offsets.dimensions(), wd = weights.dimensions();
  if (md.size() != 2 || vd.size() != 2 || vd[0] != md[0] || vd[1] != md[1] ||
      sd.size() != 3 || sd[2] != kStateDim || kd.size() != 2 || kd[0] != sd[0] ||
      kd[1] != sd[1] || rd.size() != 3 || rd[0] != sd[0] ||
      rd[1] != sd[1] || cd.size() != 3 || cd[0] != rd[0] || cd[1] != rd[1] ||
      cd[2] != rd[2] || wd.size() != 2 || od.size() != 2 || od[1] != 2 || od[0] != wd[1] ||
      grid.element_count() != 2 * rays * points || origin.element_count() != 2) {
    return ffi::Error::InvalidArgument("va_counts: inconsistent shapes");
  }
  const int64_t size = static_cast<int64_t>(std::lround(std::sqrt(static_cast<double>(wd[0]))));
  int64_t reach = 0;
  for (int64_t j = 0; j < 2 * od[0]; ++j) {
    reach = std::max<int64_t>(reach, std::abs(offsets.typed_data()[j]));
  }
  if (size * size != wd[0] || size != 2 * pad + 1 || reach > pad) {
    return ffi::Error::InvalidArgument(
        "va_counts: weights are not a square patch of side 2 pad + 1");
  }
  if (md[0] <= 2 * reach || md[1] <= 2 * reach) {
    return ffi::Error::InvalidArgument("va_counts: the map is smaller than a patch");
  }
  if (points > kMaxPoints) return ffi::Error::InvalidArgument("va_counts: too many points");
  const float* o = origin.typed_data();
  const int64_t m = rays * points, area = wd[0], queries = wd[1];
  std::vector<float> gx(m), gy(m), wt(area * queries);
  for (int64_t j = 0; j < m; ++j) {
    gx[j] = grid.typed_data()[2 * j];
    gy[j] = grid.typed_data()[2 * j + 1];
  }
  for (int64_t e = 0; e < area; ++e) {
    for (int64_t q = 0; q < queries; ++q) wt[q * area + e] = weights.typed_data()[e * queries + q];
  }
  Problem p{mean.typed_data(), variance.typed_data(), md[0], md[1], o[0], o[1], resolution,
            height, states.typed_data(), skip.typed_data(), sd[1], rows.typed_data(),
            cols.typed_data(), rd[2], offsets.typed_data(), reach, gx.data(), gy.data(), rays,
            points, wt.data(), size, queries, lag, pad, gamma, out->typed_data()};
  const int64_t k_traj = sd[0];
  const int64_t n = std::max<int64_t>(1, std::min<int64_t>(threads, k_traj));
  std::vector<std::thread> pool;
  for (int64_t t = 1; t < n; ++t) {
    pool.emplace_back(trajectories, std::cref(p), t * k_traj / n, (t + 1) * k_traj / n);
  }
  trajectories(p, 0, k_traj / n);
  for (auto& th : pool) th.join();
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(VaCounts, VaCountsImpl,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::F32>>()   // mean
                                  .Arg<ffi::Buffer<ffi::F32>>()   // variance
                                  .Arg<ffi::Buffer<ffi::F32>>()   // origin
                                  .Arg<ffi::Buffer<ffi::F32>>()   // states
                                  .Arg<ffi::Buffer<ffi::S32>>()   // skip
                                  .Arg<ffi::Buffer<ffi::S32>>()   // rows
                                  .Arg<ffi::Buffer<ffi::S32>>()   // cols
                                  .Arg<ffi::Buffer<ffi::S32>>()   // offsets
                                  .Arg<ffi::Buffer<ffi::F32>>()   // grid
                                  .Arg<ffi::Buffer<ffi::F32>>()   // weights
                                  .Ret<ffi::Buffer<ffi::F32>>()   // variance met
                                  .Attr<float>("resolution")
                                  .Attr<float>("height")
                                  .Attr<float>("gamma")
                                  .Attr<int64_t>("rays")
                                  .Attr<int64_t>("points")
                                  .Attr<int64_t>("lag")
                                  .Attr<int64_t>("pad")
                                  .Attr<int64_t>("threads"));
