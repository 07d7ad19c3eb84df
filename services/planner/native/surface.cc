// VA-MPPI's expected surface cost (costs.surface_expectation, closed form) on a CPU, as
// an XLA FFI custom call: surface.h for every trajectory. VA-MPPI's iteration uses it fused
// into the variance update instead (va_counts.cc, `vamppi_va_surface`) unless the variances
// are needed on their own (`planner.crash_variance`).
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
#include "surface.h"
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;
namespace surface = vamppi::surface;

namespace {

constexpr int64_t kGrain = 8;      // trajectories a thread takes at a time

struct Problem {
  surface::Params sp;
  const int32_t *rows, *cols, *outside;
  const float* variance;
  const float* h0;
  float* out;
};

void trajectories(const Problem& p, vamppi::Ranges& ranges) {
  surface::Scratch scratch(p.sp);
  const int64_t n = scratch.n;
  for (int64_t k0, k1; ranges.next(k0, k1);) {
    for (int64_t k = k0; k < k1; ++k) {
      surface::trajectory(p.sp, scratch, p.rows + k * n, p.cols + k * n, p.outside + k * n,
                          p.variance + k * n * surface::kQueries, p.h0[k], p.out + k * n);
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
      vd[0] != rd[0] || vd[1] != rd[1] || vd[2] != surface::kQueries * rd[2] || hd[0] != rd[0]) {
    return ffi::Error::InvalidArgument("surface: inconsistent shapes");
  }
  if (md[0] < 3 || md[1] < 3 || n_across < 1) {
    return ffi::Error::InvalidArgument("surface: a map under 3 x 3 cells or no array");
  }
  Problem p{{mean.typed_data(), md[0], md[1], rd[1], rd[2], n_across, two_res, two_res2, grad,
             step, height},
            rows.typed_data(), cols.typed_data(), outside.typed_data(), variance.typed_data(),
            h0.typed_data(), out->typed_data()};
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
