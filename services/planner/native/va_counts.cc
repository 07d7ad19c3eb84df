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
// of every ray block it but do not count (`planner.visibility_in_time`).
// After each trajectory the box of cells its patches read (below), where all its counts lie,
// is set back to zero, so one map per thread serves every trajectory. The mean is read from
// a padded copy laid out like the count map, so one index serves both.
//
// What no read can feel is not counted (the variances returned are the same): a point seen
// from pose i - lag outside the box of the cells that the patches of steps i and later read
// (`read_boxes`); and a ray is walked only up to its last point that could count (none: not
// walked). A ray's cells come from its first point, its direction and each point's distance
// along it (the grid's rays are straight), so a point within float32 rounding of a cell
// boundary may fall in the neighbouring cell of the JAX form's (tests/test_visibility.py
// leaves those out).
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
//
// `vamppi_va_surface` (VaSurface) takes the same inputs and surface.cc's `outside` and `h0`
// and returns VA-MPPI's expected surface cost (K, T, P) instead: each trajectory's
// variances go to surface.h while they are in the thread's cache and are not returned
// (half the memory; at K = 4000 8 % faster than the two calls, at K = 800 the same).

#include <algorithm>
#include <climits>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <memory>
#include <vector>

#include "parallel.h"
#include "surface.h"
#include "vecmath.h"
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;
namespace surface = vamppi::surface;

namespace {

constexpr int kX = 3, kY = 4, kPsi = 5, kStateDim = 6;
constexpr int64_t kMaxPoints = 1024;   // config: visibility_points <= 1000
constexpr int64_t kMaxQueries = 16;
constexpr int64_t kLanes = 16;         // a patch row is read as segments of 16 counts
constexpr int64_t kGrain = 4;          // trajectories a thread takes at a time (parallel.h)

typedef float v16f __attribute__((vector_size(64)));
typedef uint16_t v16u __attribute__((vector_size(32)));

// The 16 sums of 16 vectors, in one vector (lane j = the sum of v[j]'s lanes): a transposing
// tree of 15 adds instead of 16 horizontal sums of 4 shuffles and 4 adds each.
inline v16f lo_hi(v16f a, v16f b, int level) {
  switch (level) {   // lanes of a and b paired at distance 8, 4, 2, 1, then added
    case 0:
      return __builtin_shufflevector(a, b, 0, 1, 2, 3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 22,
                                     23) +
             __builtin_shufflevector(a, b, 8, 9, 10, 11, 12, 13, 14, 15, 24, 25, 26, 27, 28, 29,
                                     30, 31);
    case 1:
      return __builtin_shufflevector(a, b, 0, 1, 2, 3, 8, 9, 10, 11, 16, 17, 18, 19, 24, 25, 26,
                                     27) +
             __builtin_shufflevector(a, b, 4, 5, 6, 7, 12, 13, 14, 15, 20, 21, 22, 23, 28, 29, 30,
                                     31);
    case 2:
      return __builtin_shufflevector(a, b, 0, 1, 4, 5, 8, 9, 12, 13, 16, 17, 20, 21, 24, 25, 28,
                                     29) +
             __builtin_shufflevector(a, b, 2, 3, 6, 7, 10, 11, 14, 15, 18, 19, 22, 23, 26, 27, 30,
                                     31);
    default:
      return __builtin_shufflevector(a, b, 0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28,
                                     30) +
             __builtin_shufflevector(a, b, 1, 3, 5, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25, 27, 29,
                                     31);
  }
}

inline v16f sums16(const v16f* v) {
  v16f c[8], d[4], e[2];
  for (int k = 0; k < 8; ++k) c[k] = lo_hi(v[2 * k], v[2 * k + 1], 0);
  for (int k = 0; k < 4; ++k) d[k] = lo_hi(c[2 * k], c[2 * k + 1], 1);
  for (int k = 0; k < 2; ++k) e[k] = lo_hi(d[2 * k], d[2 * k + 1], 2);
  return lo_hi(e[0], e[1], 3);
}

struct Problem {
  const float* mean;
  const float* mean_padded;   // (H + 2 pad, W + 2 pad): the mean at the count map's indices
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
  const float* ray_base;      // (rays, 2) body-frame offset of each ray's first point
  const float* ray_dir;       // (rays, 2) its unit direction
  const float* ray_along;     // (rays, stride) each point's distance from the first, padded to
                              // `stride` (a multiple of 16) with the last
  int64_t rays, points, stride;
  const float* weights;       // (queries, size, segments * 16): each patch row's weights,
  int64_t size, queries;      // zero past `size`
  int64_t lag, pad;
  float gamma;
  float* out;
  // the weights as outer products, when they are (the Gaussian splat is separable): query o's
  // patch weights are u[which[o]] (a weight per patch row) times v[o] (per column, 16 lanes)
  int64_t n_u;                // distinct u; 0: not separable
  const float* u;             // (n_u, size)
  const int32_t* which;       // (queries,)
  const float* v;             // (queries, 16), zero past `size`
};

// sum over e < n of rows[e] * w[e], the even and the odd terms apart, then the two
inline v16f products(const v16f* rows, const v16f* w, int64_t n) {
  v16f acc0 = v16f{}, acc1 = v16f{};
  int64_t e = 0;
  for (; e + 1 < n; e += 2) {
    acc0 += rows[e] * w[e];
    acc1 += rows[e + 1] * w[e + 1];
  }
  if (e < n) acc0 += rows[e] * w[e];
  return acc0 + acc1;
}

// The paper's sizes at compile time (a 9 x 9 splat read at a cell and its four neighbours:
// patches of 11 x 11 raw counts), for weights that are outer products, as the Gaussian
// splat's are (Problem::u, v): one footprint point's 11 patch rows, each one 16-lane vector,
// stay in registers; they are combined by each distinct u (a multiply-add of a row by a
// scalar each), then times each query's column weights. For the paper's 5 queries (3
// distinct u): 3 * 11 + 5 vector operations instead of the general path's 5 * 11 products
// and sums. Fused multiply-adds here (the counts' sums are in another order than the JAX
// form's anyway; tests/test_visibility.py bounds the difference).
constexpr int kFixedSize = 11;

template <int S>
__attribute__((optimize("fp-contract=fast")))
inline void separable_products(const uint16_t* src, int64_t wp, const Problem& p, v16f* acc,
                               int64_t acc_stride) {
  static_assert(S <= kLanes && S >= 2, "a patch row is one 16-lane vector");
  v16f rows[S];
  for (int a = 0; a < S; ++a) {
    v16u raw;
    std::memcpy(&raw, src + a * wp, sizeof raw);
    rows[a] = __builtin_convertvector(raw, v16f);
  }
  v16f cols[kMaxQueries];
  for (int64_t j = 0; j < p.n_u; ++j) {
    const float* u = p.u + j * S;
    v16f sum = rows[0] * u[0];
    for (int a = 1; a < S; ++a) sum += rows[a] * u[a];
    cols[j] = sum;
  }
  for (int64_t o = 0; o < p.queries; ++o) {
    v16f v;
    std::memcpy(&v, p.v + o * kLanes, sizeof v);
    acc[o * acc_stride] = cols[p.which[o]] * v;
  }
}

// A box of cells: first and last row, column (inclusive; empty when r0 > r1).
struct Box {
  int32_t r0, r1, c0, c1;
};

// A thread's scratch for add_visible: every ray's points (rays x stride) and last point.
struct Walks {
  explicit Walks(int64_t rays, int64_t stride)
      : store(static_cast<size_t>(2 * rays * stride + rays)),
        at(store.data()), counts(at + rays * stride), last(counts + rays * stride) {}
  std::vector<int32_t> store;
  int32_t *at, *counts, *last;
};

// Adds pose `s`'s visible ray points that lie in `box` to the raw count map (padded). Every
// ray's cells are computed first (vector code, one ray after another), then each ray is
// walked to its first blocker or its last point that could count, whichever comes first.
// (A point used to count where its 8 x 8-cell block lay under a patch, looked up
// by a vector gather; the box test is a comparison, and the outputs are the same bit for
// bit: 13-17 % less time for the whole iteration at K = 800 on an AMD Zen 5, where that
// gather was a fifth of this function.)
__attribute__((target("prefer-vector-width=512")))
void add_visible(const Problem& p, const float* s, int32_t skip, const Box& box, Walks& ws,
                 uint16_t* map) {
  const float x = s[kX], y = s[kY];
  const float c = std::cos(s[kPsi]), sn = std::sin(s[kPsi]);
  const int32_t wp = static_cast<int32_t>(p.w + 2 * p.pad);
  const int32_t pad = static_cast<int32_t>(p.pad);
  int64_t vr = static_cast<int64_t>(std::floor((y - p.oy) / p.res));
  int64_t vc = static_cast<int64_t>(std::floor((x - p.ox) / p.res));
  vr = std::clamp<int64_t>(vr, 0, p.h - 1);
  vc = std::clamp<int64_t>(vc, 0, p.w - 1);
  const float threshold = p.mean[vr * p.w + vc] + p.height;
  const float fh = static_cast<float>(p.h), fw = static_cast<float>(p.w);
  const float inv = 1.0f / p.res;
  const int n = static_cast<int>(p.points);
  const int stride = static_cast<int>(p.stride);
  for (int64_t r = 0; r < p.rays; ++r) {
    // the ray's points are collinear (VisibilityParams.ray_grid): its first point, and the
    // direction and distance of the others from it, in the world and in cells
    const float* __restrict base = p.ray_base + 2 * r;
    const float* __restrict dir = p.ray_dir + 2 * r;
    const float* __restrict along = p.ray_along + r * p.stride;
    const float c0 = (x + c * base[0] - sn * base[1] - p.ox) * inv;
    const float r0 = (y + sn * base[0] + c * base[1] - p.oy) * inv;
    const float dc = (c * dir[0] - sn * dir[1]) * inv;
    const float dr = (sn * dir[0] + c * dir[1]) * inv;
    int32_t* __restrict at = ws.at + r * stride;
    int32_t* __restrict counts = ws.counts + r * stride;
    // the walk can stop at the last point that could count (in the box, not skipped): what
    // lies beyond it changes nothing read, and a ray with none is not walked;
    // nor beyond its first point off the map, which blocks it and is not seen
    int last = -1, first_out = stride;
    // (16 lanes asked for: GCC's own choice here is 8, about 12 % slower)
#pragma omp simd simdlen(16) reduction(max : last) reduction(min : first_out)
    for (int k = 0; k < stride; ++k) {   // visibility.ray_cells' cells, in float32
      const float fc = std::floor(c0 + along[k] * dc);
      const float fr = std::floor(r0 + along[k] * dr);
      const bool inside = fr >= 0.0f && fr < fh && fc >= 0.0f && fc < fw;
      first_out = std::min(first_out, inside ? stride : k);
      const int32_t row = static_cast<int32_t>(std::min(std::max(fr, 0.0f), fh - 1.0f));
      const int32_t col = static_cast<int32_t>(std::min(std::max(fc, 0.0f), fw - 1.0f));
      at[k] = (row + pad) * wp + col + pad;
      const int32_t counts_here = (row >= box.r0) & (row <= box.r1) & (col >= box.c0) &
                                  (col <= box.c1) & (k >= skip) & (k < n);
      counts[k] = counts_here;
      last = std::max(last, counts_here ? k : -1);
    }
    ws.last[r] = std::min(last, first_out - 1);
  }
  for (int64_t r = 0; r < p.rays; ++r) {
    const int32_t* at = ws.at + r * stride;
    const int32_t* counts = ws.counts + r * stride;
    for (int k = 0; k <= ws.last[r]; ++k) {
      map[at[k]] += counts[k];            // nearer points block but do not count
      if (p.mean_padded[at[k]] > threshold) break;   // the first blocker is seen
    }
  }
}

// `vamppi_va_surface`: the expected surface cost computed from each trajectory's variances
// as soon as they are (surface.h), which then never leave the thread's cache
struct Fused {
  surface::Params sp;
  const int32_t* outside;   // (K, T, P)
  const float* h0;          // (K,)
  float* out;               // (K, T, P) expected tripped indicators
};

// The boxes of cells that the patches of steps i .. T - 1 read, for every step i (`boxes`,
// T of them; `rows`, `cols` the trajectory's footprint cells, `n_pts` a step): a point seen
// from pose i - lag is read, if at all, by a patch of step i or later, so one counted outside
// boxes[i] changes nothing read.
void read_boxes(const Problem& p, const int32_t* rows, const int32_t* cols, Box* boxes) {
  const int32_t reach = static_cast<int32_t>(p.reach), pad = static_cast<int32_t>(p.pad);
  const int32_t h = static_cast<int32_t>(p.h), w = static_cast<int32_t>(p.w);
  const int64_t np = p.n_pts;
  Box box{INT32_MAX, -1, INT32_MAX, -1};
  for (int64_t i = p.t_len - 1; i >= 0; --i) {
    for (int64_t q = i * np; q < (i + 1) * np; ++q) {
      // the patch around the clipped cell (as `trajectories` reads it), 2 pad + 1 wide
      const int32_t r0 = std::clamp(rows[q], reach, h - 1 - reach);
      const int32_t c0 = std::clamp(cols[q], reach, w - 1 - reach);
      box = {std::min(box.r0, std::max(r0 - pad, 0)),
             std::max(box.r1, std::min(r0 + pad, h - 1)),
             std::min(box.c0, std::max(c0 - pad, 0)),
             std::max(box.c1, std::min(c0 + pad, w - 1))};
    }
    boxes[i] = box;
  }
}

void trajectories(const Problem& p, vamppi::Ranges& ranges, const Fused* fused) {
  const int64_t wp = p.w + 2 * p.pad;
  const int64_t width = p.queries * p.n_pts;
  const int64_t segments = (p.size + kLanes - 1) / kLanes, row_len = segments * kLanes;
  // raw counts as uint16 (at most rays * points * T per cell, checked on the Python side):
  // half the cache footprint of floats; a patch row's last segment may read past the map
  std::vector<uint16_t> map(static_cast<size_t>((p.h + 2 * p.pad) * wp + row_len), 0);
  Walks walks(p.rays, p.stride);
  std::vector<float> prior(static_cast<size_t>(width));
  const int64_t n_vec = p.size * segments;                  // 16-lane vectors in a patch
  std::vector<v16f> patch(static_cast<size_t>(n_vec));
  std::vector<v16f> weights(static_cast<size_t>(p.queries * n_vec));
  std::memcpy(weights.data(), p.weights, weights.size() * sizeof(v16f));
  std::vector<Box> boxes(static_cast<size_t>(p.t_len));
  // each query cell's 16 products, lanes not yet summed (padded to whole vectors of zeros)
  const int64_t width_padded = (width + kLanes - 1) / kLanes * kLanes;
  std::vector<v16f> acc(static_cast<size_t>(width_padded), v16f{});
  std::vector<float> counts(static_cast<size_t>(width_padded));
  const bool separable = p.size == kFixedSize && p.n_u > 0;
  std::vector<float> met(fused ? static_cast<size_t>(p.t_len * width) : 0);
  std::unique_ptr<surface::Scratch> scratch;
  if (fused) scratch = std::make_unique<surface::Scratch>(fused->sp);
  for (int64_t k0, k1; ranges.next(k0, k1);) {
    for (int64_t k = k0; k < k1; ++k) {
      const float* st = p.states + k * p.t_len * kStateDim;
      const int32_t* skip = p.skip + k * p.t_len;
      const int32_t* rows = p.rows + k * p.t_len * p.n_pts;
      const int32_t* cols = p.cols + k * p.t_len * p.n_pts;
      float* out = fused ? met.data() : p.out + k * p.t_len * width;
      read_boxes(p, rows, cols, boxes.data());
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
        add_visible(p, st + (i - p.lag) * kStateDim, skip[i - p.lag], boxes[i], walks,
                    map.data());
        for (int64_t q = 0; q < p.n_pts; ++q) {
          // the patch around the footprint cell starts at the cell itself in padded coordinates
          const int64_t r0 = std::clamp<int64_t>(ri[q], p.reach, p.h - 1 - p.reach);
          const int64_t c0 = std::clamp<int64_t>(ci[q], p.reach, p.w - 1 - p.reach);
          const uint16_t* src = map.data() + r0 * wp + c0;
          if (separable) {
            separable_products<kFixedSize>(src, wp, p, acc.data() + q, p.n_pts);
            continue;
          }
          for (int64_t a = 0; a < p.size; ++a) {   // the patch's rows as floats
            for (int64_t g = 0; g < segments; ++g) {
              v16u raw;
              std::memcpy(&raw, src + a * wp + g * kLanes, sizeof raw);
              patch[a * segments + g] = __builtin_convertvector(raw, v16f);
            }
          }
          for (int64_t o = 0; o < p.queries; ++o) {   // times each query's weights, summed
            acc[o * p.n_pts + q] =                    // across its lanes below
                products(patch.data(), weights.data() + o * n_vec, n_vec);
          }
        }
        for (int64_t j = 0; j < width; j += kLanes) {
          const v16f sums = sums16(acc.data() + j);
          std::memcpy(counts.data() + j, &sums, sizeof sums);
        }
        const float g = -p.gamma;
        const float* pr = prior.data();
        const float* cn = counts.data();
#pragma omp simd
        for (int64_t j = 0; j < width; ++j) oi[j] = pr[j] * vamppi::exp_nonpositive(g * cn[j]);
      }
      // every count lies in boxes[lag], which holds the later ones: clear it, row by row
      if (p.lag < p.t_len) {
        const Box& all = boxes[p.lag];
        for (int64_t r = all.r0; r <= all.r1; ++r) {
          std::memset(map.data() + (r + p.pad) * wp + all.c0 + p.pad, 0,
                      (all.c1 - all.c0 + 1) * sizeof(uint16_t));
        }
      }
      if (fused) {
        const int64_t n = p.t_len * p.n_pts;
        surface::trajectory(fused->sp, *scratch, rows, cols, fused->outside + k * n, out,
                            fused->h0[k], fused->out + k * n);
      }
    }
  }
}

// The problem both handlers solve, with the tables it points into.
struct Prepared {
  std::vector<float> base, dir, along, wt, us, vs, mean_padded;
  std::vector<int32_t> which;
  Problem p;
};

// Checks the inputs' shapes and builds `pr` (pr.p.out left null).
ffi::Error prepare(ffi::Buffer<ffi::F32>& mean, ffi::Buffer<ffi::F32>& variance,
                   ffi::Buffer<ffi::F32>& origin, ffi::Buffer<ffi::F32>& states,
                   ffi::Buffer<ffi::S32>& skip, ffi::Buffer<ffi::S32>& rows,
                   ffi::Buffer<ffi::S32>& cols, ffi::Buffer<ffi::S32>& offsets,
                   ffi::Buffer<ffi::F32>& grid, ffi::Buffer<ffi::F32>& weights, float resolution,
                   float height, float gamma, int64_t rays, int64_t points, int64_t lag,
                   int64_t pad, Prepared& pr) {
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
  if (points > kMaxPoints - kLanes) {
    return ffi::Error::InvalidArgument("va_counts: too many points");
  }
  if (wd[1] > kMaxQueries) return ffi::Error::InvalidArgument("va_counts: too many queries");
  const float* o = origin.typed_data();
  const int64_t stride = (points + kLanes - 1) / kLanes * kLanes, queries = wd[1];
  const int64_t row_len = (size + kLanes - 1) / kLanes * kLanes;
  std::vector<float>&base = pr.base, &dir = pr.dir, &along = pr.along, &wt = pr.wt;
  base.assign(2 * rays, 0.0f);
  dir.assign(2 * rays, 0.0f);
  along.assign(rays * stride, 0.0f);
  wt.assign(queries * size * row_len, 0.0f);
  const float* g = grid.typed_data();
  for (int64_t r = 0; r < rays; ++r) {   // each ray: its first point, direction, distances
    const float* first = g + 2 * r * points;
    const float* end = g + 2 * (r * points + points - 1);
    const double ex = double(end[0]) - first[0], ey = double(end[1]) - first[1];
    const double len = std::hypot(ex, ey);
    const double ux = len > 0 ? ex / len : 1.0, uy = len > 0 ? ey / len : 0.0;
    base[2 * r] = first[0];
    base[2 * r + 1] = first[1];
    dir[2 * r] = static_cast<float>(ux);
    dir[2 * r + 1] = static_cast<float>(uy);
    for (int64_t k = 0; k < stride; ++k) {
      const float* pt = g + 2 * (r * points + std::min(k, points - 1));
      const double ax = double(pt[0]) - first[0], ay = double(pt[1]) - first[1];
      if (std::abs(ax * uy - ay * ux) > 1e-4) {
        return ffi::Error::InvalidArgument("va_counts: a ray's points are not on a line");
      }
      along[r * stride + k] = static_cast<float>(ax * ux + ay * uy);
    }
  }
  for (int64_t a = 0; a < size; ++a) {   // weights (size * size, queries), row-major patches
    for (int64_t b = 0; b < size; ++b) {
      for (int64_t q = 0; q < queries; ++q) {
        wt[(q * size + a) * row_len + b] = weights.typed_data()[(a * size + b) * queries + q];
      }
    }
  }
  // each query's weights as an outer product u v (u from the column, v from the row of its
  // largest weight), kept if that reproduces every weight to 1e-6 of the largest; equal u
  // stored once. Only for patch rows of one vector (v has 16 lanes; wider patches, splats
  // over 13, take the general path)
  std::vector<float>&us = pr.us, &vs = pr.vs;
  std::vector<int32_t>& which = pr.which;
  us.clear();
  vs.assign(queries * kLanes, 0.0f);
  which.assign(queries, 0);
  bool separable = size <= kLanes;
  for (int64_t q = 0; q < queries && separable; ++q) {
    const float* wq = wt.data() + q * size * row_len;
    int64_t a0 = 0, b0 = 0;
    for (int64_t a = 0; a < size; ++a) {
      for (int64_t b = 0; b < size; ++b) {
        if (std::abs(wq[a * row_len + b]) > std::abs(wq[a0 * row_len + b0])) a0 = a, b0 = b;
      }
    }
    const double top = wq[a0 * row_len + b0];
    std::vector<float> u(size);
    for (int64_t a = 0; a < size; ++a) {
      u[a] = top != 0 ? static_cast<float>(wq[a * row_len + b0] / top) : 0.0f;
    }
    for (int64_t b = 0; b < size; ++b) vs[q * kLanes + b] = wq[a0 * row_len + b];
    for (int64_t a = 0; a < size; ++a) {
      for (int64_t b = 0; b < size; ++b) {
        const double err = double(u[a]) * vs[q * kLanes + b] - wq[a * row_len + b];
        if (std::abs(err) > 1e-6 * std::abs(top)) separable = false;
      }
    }
    int64_t j = 0;
    while (j * size < static_cast<int64_t>(us.size()) &&
           !std::equal(u.begin(), u.end(), us.begin() + j * size)) ++j;
    if (j * size == static_cast<int64_t>(us.size())) us.insert(us.end(), u.begin(), u.end());
    which[q] = static_cast<int32_t>(j);
  }
  const int64_t n_u = separable ? static_cast<int64_t>(us.size()) / size : 0;
  const int64_t wp = md[1] + 2 * pad;
  pr.mean_padded.assign((md[0] + 2 * pad) * wp, 0.0f);
  for (int64_t r = 0; r < md[0]; ++r) {
    std::memcpy(pr.mean_padded.data() + (r + pad) * wp + pad, mean.typed_data() + r * md[1],
                md[1] * sizeof(float));
  }
  pr.p = Problem{mean.typed_data(), pr.mean_padded.data(), variance.typed_data(), md[0], md[1], o[0], o[1],
                 resolution, height, states.typed_data(), skip.typed_data(), sd[1],
                 rows.typed_data(), cols.typed_data(), rd[2], offsets.typed_data(), reach,
                 base.data(), dir.data(), along.data(), rays, points, stride, wt.data(), size,
                 queries, lag, pad, gamma, nullptr, n_u, us.data(), which.data(), vs.data()};
  return ffi::Error::Success();
}

ffi::Error VaCountsImpl(ffi::Buffer<ffi::F32> mean, ffi::Buffer<ffi::F32> variance,
                        ffi::Buffer<ffi::F32> origin, ffi::Buffer<ffi::F32> states,
                        ffi::Buffer<ffi::S32> skip, ffi::Buffer<ffi::S32> rows,
                        ffi::Buffer<ffi::S32> cols,
                        ffi::Buffer<ffi::S32> offsets, ffi::Buffer<ffi::F32> grid,
                        ffi::Buffer<ffi::F32> weights, ffi::ResultBuffer<ffi::F32> out,
                        float resolution, float height, float gamma, int64_t rays,
                        int64_t points, int64_t lag, int64_t pad, int64_t threads) {
  Prepared pr;
  ffi::Error err = prepare(mean, variance, origin, states, skip, rows, cols, offsets, grid,
                           weights, resolution, height, gamma, rays, points, lag, pad, pr);
  if (err.failure()) return err;
  pr.p.out = out->typed_data();
  const Problem& p = pr.p;
  vamppi::parallel_ranges(states.dimensions()[0], threads, kGrain,
                          [&p](vamppi::Ranges& ranges) { trajectories(p, ranges, nullptr); });
  return ffi::Error::Success();
}

// The variance update and the expected surface cost (surface.h) in one pass: the
// expected tripped indicators (K, T, P) from VaCounts's inputs and surface.cc's `outside`
// and `h0`; the variances are not returned.
ffi::Error VaSurfaceImpl(ffi::Buffer<ffi::F32> mean, ffi::Buffer<ffi::F32> variance,
                         ffi::Buffer<ffi::F32> origin, ffi::Buffer<ffi::F32> states,
                         ffi::Buffer<ffi::S32> skip, ffi::Buffer<ffi::S32> rows,
                         ffi::Buffer<ffi::S32> cols, ffi::Buffer<ffi::S32> offsets,
                         ffi::Buffer<ffi::F32> grid, ffi::Buffer<ffi::F32> weights,
                         ffi::Buffer<ffi::S32> outside, ffi::Buffer<ffi::F32> h0,
                         ffi::ResultBuffer<ffi::F32> out, float resolution, float height,
                         float gamma, int64_t rays, int64_t points, int64_t lag, int64_t pad,
                         int64_t threads, float two_res, float two_res2, float grad,
                         float step, float height_threshold, int64_t n_across) {
  Prepared pr;
  ffi::Error err = prepare(mean, variance, origin, states, skip, rows, cols, offsets, grid,
                           weights, resolution, height, gamma, rays, points, lag, pad, pr);
  if (err.failure()) return err;
  auto rd = rows.dimensions(), od = outside.dimensions(), hd = h0.dimensions(),
       md = mean.dimensions();
  if (od.size() != 3 || od[0] != rd[0] || od[1] != rd[1] || od[2] != rd[2] || hd.size() != 1 ||
      hd[0] != rd[0] || weights.dimensions()[1] != surface::kQueries) {
    return ffi::Error::InvalidArgument("va_surface: inconsistent shapes");
  }
  if (md[0] < 3 || md[1] < 3 || n_across < 1) {
    return ffi::Error::InvalidArgument("va_surface: a map under 3 x 3 cells or no array");
  }
  const Fused fused{{mean.typed_data(), md[0], md[1], rd[1], rd[2], n_across, two_res, two_res2,
                     grad, step, height_threshold},
                    outside.typed_data(), h0.typed_data(), out->typed_data()};
  const Problem& p = pr.p;
  vamppi::parallel_ranges(rd[0], threads, kGrain, [&p, &fused](vamppi::Ranges& ranges) {
    trajectories(p, ranges, &fused);
  });
  return ffi::Error::Success();
}

// The inputs and attributes both handlers share (prepare's); each adds its own.
template <class Binding>
auto with_update_attrs(Binding&& b) {
  return std::move(b)
      .template Attr<float>("resolution")
      .template Attr<float>("height")
      .template Attr<float>("gamma")
      .template Attr<int64_t>("rays")
      .template Attr<int64_t>("points")
      .template Attr<int64_t>("lag")
      .template Attr<int64_t>("pad")
      .template Attr<int64_t>("threads");
}

auto update_args() {
  return ffi::Ffi::Bind()
      .Arg<ffi::Buffer<ffi::F32>>()   // mean
      .Arg<ffi::Buffer<ffi::F32>>()   // variance
      .Arg<ffi::Buffer<ffi::F32>>()   // origin
      .Arg<ffi::Buffer<ffi::F32>>()   // states
      .Arg<ffi::Buffer<ffi::S32>>()   // skip
      .Arg<ffi::Buffer<ffi::S32>>()   // rows
      .Arg<ffi::Buffer<ffi::S32>>()   // cols
      .Arg<ffi::Buffer<ffi::S32>>()   // offsets
      .Arg<ffi::Buffer<ffi::F32>>()   // grid
      .Arg<ffi::Buffer<ffi::F32>>();  // weights
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(VaCounts, VaCountsImpl,
                              with_update_attrs(update_args()
                                  .Ret<ffi::Buffer<ffi::F32>>()));   // variance met

XLA_FFI_DEFINE_HANDLER_SYMBOL(VaSurface, VaSurfaceImpl,
                              with_update_attrs(update_args()
                                  .Arg<ffi::Buffer<ffi::S32>>()   // outside
                                  .Arg<ffi::Buffer<ffi::F32>>()   // h0
                                  .Ret<ffi::Buffer<ffi::F32>>())  // expected indicators
                                  .Attr<float>("two_res")
                                  .Attr<float>("two_res2")
                                  .Attr<float>("grad")
                                  .Attr<float>("step")
                                  .Attr<float>("height_threshold")
                                  .Attr<int64_t>("n_across"));
