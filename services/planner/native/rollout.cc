// The planner's K rollouts on a CPU, as an XLA FFI custom call.
//
// The same computation as services/planner/mppi.py (`rollout`, vmapped over the samples):
// the plant's bicycle model (services/plant/dynamics.py, `derivatives` and `rk4_step`), the
// controls clamped by `clamp_control`, RK4 with `substeps` steps per dt, and the vectorisable
// arctan, arctan2, sin, cos and tan of services/planner/fastmath.py (the same Cephes
// reductions and polynomials). Written once over a vector of W samples (GCC vector
// extensions: every line below is one instruction on W lanes), W = 16 where the CPU has
// AVX-512, else 8.
//
// Why native: XLA:CPU runs the vmapped scan as some hundreds of small loops per step, about
// 260 ns per model evaluation and sample on this project's CPU (docs/benchmarks.md); here an
// evaluation is a few hundred vector instructions for W samples at once.
//
// Inputs: model (kModelSize,) f32 the vehicle's parameters in the order of `Model` below
// (services/planner/native/__init__.py, MODEL, builds it), x0 (6,) f32, u_prev (2,)
// f32, controls (K, N, 2) f32. Outputs: states (K, N + 1, 6) (row 0 = x0), applied controls
// (K, N, 2), dx/dt at each step's start (K, N, 6). Attributes: dt, substeps, threads.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>

#include "parallel.h"
#include "vecmath.h"
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

#if defined(__AVX512F__)
constexpr int W = 16;
#else
constexpr int W = 8;
#endif
typedef float vf __attribute__((vector_size(W * 4)));
typedef int32_t vi __attribute__((vector_size(W * 4)));

// __init__.py's MODEL names each entry (tests check the two name for name; the handler
// checks the size)
enum Model {
  kMass, kLf, kLr, kTrack, kB, kC, kD, kE, kCd, kAf, kRho, kCr, kG, kCgHeight, kIz,
  kKinBelow, kDynAbove, kTau, kSlipFloor, kBrakeEps,
  kSteerLo, kForceLo, kSteerHi, kForceHi, kSteerRate, kForceRate,
  kModelSize
};

inline vf splat(float s) { return vf{} + s; }
inline vf vmax(vf a, vf b) { return a > b ? a : b; }   // jnp.maximum (no NaNs here)
inline vf vmin(vf a, vf b) { return a < b ? a : b; }
inline vf vabs(vf a) { return (vf)((vi)a & 0x7fffffff); }
inline vi sign_bits(vf a) { return (vi)a & static_cast<int32_t>(0x80000000u); }
inline vf copysign(vf mag, vf sgn) { return (vf)(((vi)vabs(mag)) | sign_bits(sgn)); }
// round half to even, as jnp.round, for |x| < 2^22
inline vf round_even(vf x) { return (x + 12582912.0f) - 12582912.0f; }

// fastmath._atan_nonneg: atan(t) for t >= 0, Cephes atanf
inline vf atan_nonneg(vf t) {
  const vi big = t > 2.414213562373095f;
  const vi mid = (t > 0.4142135623730950f) & ~big;
  const vf safe = big ? t : splat(1.0f);
  const vf z = big ? -1.0f / safe : (mid ? (t - 1.0f) / (t + 1.0f) : t);
  const vf base = big ? splat(1.57079632679489662f)
                      : (mid ? splat(0.785398163397448310f) : splat(0.0f));
  const vf z2 = z * z;
  const vf p = ((((8.05374449538e-2f * z2 - 1.38776856032e-1f) * z2 + 1.99777106478e-1f) * z2
                 - 3.33329491539e-1f) * z2 * z + z);
  return base + p;
}

inline vf atan(vf x) { return copysign(atan_nonneg(vabs(x)), x); }

inline vf atan2(vf y, vf x) {
  const vf ax = vabs(x), ay = vabs(y);
  const vi swap = ay > ax;
  const vf num = swap ? ax : ay;
  const vf den = swap ? ay : ax;
  vf a = atan_nonneg(num / (den > 0.0f ? den : splat(1.0f)));
  a = swap ? 1.57079632679489662f - a : a;
  a = sign_bits(x) != 0 ? 3.14159265358979324f - a : a;
  return copysign(a, y);
}

// fastmath._reduce and _sin_cos_reduced: x = k pi/2 + r, |r| <= pi/4
struct Reduced {
  vf s, c;
  vi q;
};

inline Reduced reduce(vf x) {
  const vf k = round_even(x * 0.636619772367581343f);
  const vf r = ((x - k * 1.5703125f) - k * 4.837512969970703125e-4f) - k * 7.54978995489188216e-8f;
  const vf z = r * r;
  Reduced out;
  out.s = r + r * z * ((-1.9515295891e-4f * z + 8.3321608736e-3f) * z - 1.6666654611e-1f);
  out.c = 1.0f - 0.5f * z + z * z * ((2.443315711809948e-5f * z - 1.388731625493765e-3f) * z
                                     + 4.166664568298827e-2f);
  out.q = __builtin_convertvector(k, vi) & 3;
  return out;
}

inline void sincos(vf x, vf& s, vf& c) {
  const Reduced a = reduce(x);
  const vi odd = (a.q & 1) == 1;
  const vf vs = odd ? a.c : a.s, vc = odd ? a.s : a.c;
  s = a.q >= 2 ? -vs : vs;
  c = (a.q == 1) | (a.q == 2) ? -vc : vc;
}

inline vf cos(vf x) {
  vf s, c;
  sincos(x, s, c);
  return c;
}

inline vf tan(vf x) {
  const Reduced a = reduce(x);
  const vi odd = (a.q & 1) == 1;
  return (odd ? -a.c : a.s) / (odd ? a.s : a.c);
}

// exp(x) for x <= 0: vecmath.h's, on this file's vectors
struct VecOps {
  static vf splat(float s) { return vf{} + s; }
  static vf max(vf a, vf b) { return vmax(a, b); }
  static vf round_even(vf x) { return ::round_even(x); }
  static vf exp2(vf n) { return (vf)((__builtin_convertvector(n, vi) + 127) << 23); }
  static vf zero_below(vf x, float lo, vf v) { return x < lo ? splat(0.0f) : v; }
};

inline vf exp_nonpositive(vf x) { return vamppi::exp_nonpositive_of<vf, VecOps>(x); }

// tanh (Cephes tanhf): an odd polynomial below 0.625, 1 - 2 / (e^{2|x|} + 1) above
inline vf tanh(vf x) {
  const vf ax = vabs(x);
  const vf z = x * x;
  const vf small = ((((-5.70498872745e-3f * z + 2.06390887954e-2f) * z - 5.37397155531e-2f) * z
                     + 1.33314422036e-1f) * z - 3.33332819422e-1f) * z * x + x;
  const vf e = exp_nonpositive(-2.0f * ax);
  const vf large = copysign((1.0f - e) / (1.0f + e), x);
  return ax < 0.625f ? small : large;
}

// The model's constants, float32 as JAX uses them (products of Python floats are taken in
// double and rounded once, as JAX's weak typing does).
struct Params {
  float m, lf, lr, L, h, tr, B, C, D, E, Iz, tau, floor, eps, kin_below, blend_span;
  float drag_k, rolling_k, fz_front0, fz_rear0, lr_over_L, lf_over_L, half_tr;
  float lo[2], hi[2], rate_dt[2];
  float dt, half_h, h_sub, sixth_h;
  int substeps;
};

Params make_params(const float* mp, float dt, int substeps) {
  const double m = mp[kMass], g = mp[kG], lf = mp[kLf], lr = mp[kLr], L = lf + lr;
  Params p{};
  p.m = m;
  p.lf = lf;
  p.lr = lr;
  p.L = static_cast<float>(L);
  p.h = mp[kCgHeight];
  p.tr = mp[kTrack];
  p.B = mp[kB];
  p.C = mp[kC];
  p.D = mp[kD];
  p.E = mp[kE];
  p.Iz = mp[kIz];
  p.tau = mp[kTau];
  p.floor = mp[kSlipFloor];
  p.eps = mp[kBrakeEps];
  p.kin_below = mp[kKinBelow];
  p.blend_span = static_cast<float>(static_cast<double>(mp[kDynAbove]) - mp[kKinBelow]);
  p.drag_k = static_cast<float>(0.5 * mp[kRho] * mp[kCd] * mp[kAf]);
  p.rolling_k = static_cast<float>(m * g * mp[kCr]);
  p.fz_front0 = static_cast<float>(m * g * lr / L);
  p.fz_rear0 = static_cast<float>(m * g * lf / L);
  p.lr_over_L = static_cast<float>(lr / L);
  p.lf_over_L = static_cast<float>(lf / L);
  p.half_tr = static_cast<float>(0.5 * mp[kTrack]);
  p.lo[0] = mp[kSteerLo];
  p.lo[1] = mp[kForceLo];
  p.hi[0] = mp[kSteerHi];
  p.hi[1] = mp[kForceHi];
  p.rate_dt[0] = mp[kSteerRate] * dt;   // float32 products, as clamp_control's
  p.rate_dt[1] = mp[kForceRate] * dt;
  p.dt = dt;
  const double h_sub = static_cast<double>(dt) / substeps;
  p.h_sub = static_cast<float>(h_sub);
  p.half_h = static_cast<float>(0.5 * h_sub);
  p.sixth_h = static_cast<float>(h_sub / 6.0);
  p.substeps = substeps;
  return p;
}

struct State {
  vf x[6];
};

inline vf tire(const Params& p, vf alpha, vf fz) {
  const vf ba = p.B * alpha;
  const vf shape = ba - p.E * (ba - atan(ba));
  vf s, c;
  sincos(p.C * atan(shape), s, c);
  return p.D * fz * s;
}

// services/plant/dynamics.py, derivatives(), line by line
inline State derivatives(const Params& p, const State& st, vf delta, vf f) {
  const vf V = st.x[0], v = st.x[1], r = st.x[2], psi = st.x[5];
  const vf zero = splat(0.0f);
  const vf fade = tanh(V / p.eps);
  const vf f_long = vmax(f, zero) + vmin(f, zero) * fade;
  const vf drag = p.drag_k * V * vabs(V);
  const vf rolling = p.rolling_k * fade;
  const vf ax = (f_long - drag - rolling) / p.m;

  const vf ay = V * r;
  const vf fz_front = p.fz_front0 - p.m * ax * p.h / p.L;
  const vf fz_rear = p.fz_rear0 + p.m * ax * p.h / p.L;
  const vf dfz_front = p.m * ay * p.h / p.tr * p.lr_over_L;
  const vf dfz_rear = p.m * ay * p.h / p.tr * p.lf_over_L;
  const vf fz_fl = vmax(fz_front / 2.0f - dfz_front, zero);
  const vf fz_fr = vmax(fz_front / 2.0f + dfz_front, zero);
  const vf fz_rl = vmax(fz_rear / 2.0f - dfz_rear, zero);
  const vf fz_rr = vmax(fz_rear / 2.0f + dfz_rear, zero);

  const vf tan_d = tan(delta);
  const vf d_left = atan2(p.L * tan_d, p.L - p.half_tr * tan_d);
  const vf d_right = atan2(p.L * tan_d, p.L + p.half_tr * tan_d);

  const vf u_left = vmax(V - p.half_tr * r, splat(p.floor));
  const vf u_right = vmax(V + p.half_tr * r, splat(p.floor));
  const vf front_lat = v + p.lf * r, rear_lat = v - p.lr * r;
  const vf a_fl = d_left - atan2(front_lat, u_left);
  const vf a_fr = d_right - atan2(front_lat, u_right);
  const vf a_rl = -atan2(rear_lat, u_left);
  const vf a_rr = -atan2(rear_lat, u_right);
  const vf f_fl = tire(p, a_fl, fz_fl) * cos(d_left);
  const vf f_fr = tire(p, a_fr, fz_fr) * cos(d_right);
  const vf f_rl = tire(p, a_rl, fz_rl);
  const vf f_rr = tire(p, a_rr, fz_rr);

  const vf v_dot_dyn = (f_fl + f_fr + f_rl + f_rr) / p.m - V * r;
  const vf r_dot_dyn = (p.lf * (f_fl + f_fr) - p.lr * (f_rl + f_rr)) / p.Iz;

  const vf r_kin = V * tan_d / p.L;
  const vf v_kin = r_kin * p.lr;
  const vf v_dot_kin = (v_kin - v) / p.tau;
  const vf r_dot_kin = (r_kin - r) / p.tau;
  const vf w = vmin(vmax((V - p.kin_below) / p.blend_span, zero), splat(1.0f));

  vf sp, cp;
  sincos(psi, sp, cp);
  State d;
  d.x[0] = ax + v * r;
  d.x[1] = w * v_dot_dyn + (1.0f - w) * v_dot_kin;
  d.x[2] = w * r_dot_dyn + (1.0f - w) * r_dot_kin;
  d.x[3] = V * cp - v * sp;
  d.x[4] = V * sp + v * cp;
  d.x[5] = r;
  return d;
}

inline State axpy(const State& x, float a, const State& k) {
  State out;
  for (int j = 0; j < 6; ++j) out.x[j] = x.x[j] + a * k.x[j];
  return out;
}

// services/plant/dynamics.py, rk4_step(); k1 (dx/dt at x) is given
inline State rk4(const Params& p, const State& x, const State& k1, vf delta, vf f) {
  const State k2 = derivatives(p, axpy(x, p.half_h, k1), delta, f);
  const State k3 = derivatives(p, axpy(x, p.half_h, k2), delta, f);
  const State k4 = derivatives(p, axpy(x, p.h_sub, k3), delta, f);
  State out;
  for (int j = 0; j < 6; ++j) {
    out.x[j] = x.x[j] + p.sixth_h * (k1.x[j] + 2.0f * k2.x[j] + 2.0f * k3.x[j] + k4.x[j]);
  }
  return out;
}

struct Problem {
  Params prm;
  const float* x0;
  const float* u_prev;
  const float* controls;
  int64_t k, n;
  float* states;
  float* applied;
  float* xdots;
};

// samples [k0, k1) in blocks of W lanes; a short last block repeats its last sample
void blocks(const Problem& pb, int64_t b0, int64_t b1) {
  const Params& p = pb.prm;
  const int64_t n = pb.n;
  for (int64_t b = b0; b < b1; ++b) {
    int64_t idx[W];
    int lanes = 0;
    for (int l = 0; l < W; ++l) {
      idx[l] = std::min<int64_t>(b * W + l, pb.k - 1);
      if (b * W + l < pb.k) lanes = l + 1;
    }
    State x;
    for (int j = 0; j < 6; ++j) x.x[j] = splat(pb.x0[j]);
    vf u_last[2] = {splat(pb.u_prev[0]), splat(pb.u_prev[1])};
    for (int l = 0; l < lanes; ++l) {
      std::memcpy(pb.states + idx[l] * (n + 1) * 6, pb.x0, 6 * sizeof(float));
    }
    for (int64_t i = 0; i < n; ++i) {
      vf u[2];
      for (int c = 0; c < 2; ++c) {   // clamp_control: the rate limit, then the bounds
        vf raw;
        for (int l = 0; l < W; ++l) raw[l] = pb.controls[(idx[l] * n + i) * 2 + c];
        const vf lo = u_last[c] - p.rate_dt[c], hi = u_last[c] + p.rate_dt[c];
        u[c] = vmin(vmax(vmin(vmax(raw, lo), hi), splat(p.lo[c])), splat(p.hi[c]));
      }
      const State xdot = derivatives(p, x, u[0], u[1]);
      State xn = rk4(p, x, xdot, u[0], u[1]);
      for (int s = 1; s < p.substeps; ++s) {
        xn = rk4(p, xn, derivatives(p, xn, u[0], u[1]), u[0], u[1]);
      }
      for (int l = 0; l < lanes; ++l) {
        float* so = pb.states + (idx[l] * (n + 1) + i + 1) * 6;
        float* xo = pb.xdots + (idx[l] * n + i) * 6;
        for (int j = 0; j < 6; ++j) {
          so[j] = xn.x[j][l];
          xo[j] = xdot.x[j][l];
        }
        float* ao = pb.applied + (idx[l] * n + i) * 2;
        ao[0] = u[0][l];
        ao[1] = u[1][l];
      }
      x = xn;
      u_last[0] = u[0];
      u_last[1] = u[1];
    }
  }
}

ffi::Error RolloutImpl(ffi::Buffer<ffi::F32> model, ffi::Buffer<ffi::F32> x0,
                       ffi::Buffer<ffi::F32> u_prev, ffi::Buffer<ffi::F32> controls,
                       ffi::ResultBuffer<ffi::F32> states, ffi::ResultBuffer<ffi::F32> applied,
                       ffi::ResultBuffer<ffi::F32> xdots, float dt, int64_t substeps,
                       int64_t threads) {
  auto cd = controls.dimensions();
  if (model.element_count() != kModelSize || x0.element_count() != 6 ||
      u_prev.element_count() != 2 || cd.size() != 3 || cd[2] != 2 || cd[0] < 1 ||
      substeps < 1) {
    return ffi::Error::InvalidArgument("rollout: inconsistent shapes or settings");
  }
  Problem pb{make_params(model.typed_data(), dt, static_cast<int>(substeps)),
             x0.typed_data(), u_prev.typed_data(), controls.typed_data(), cd[0], cd[1],
             states->typed_data(), applied->typed_data(), xdots->typed_data()};
  vamppi::parallel_ranges((pb.k + W - 1) / W, threads, 2, [&pb](vamppi::Ranges& ranges) {
    for (int64_t b0, b1; ranges.next(b0, b1);) blocks(pb, b0, b1);
  });
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(Rollout, RolloutImpl,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::F32>>()   // model
                                  .Arg<ffi::Buffer<ffi::F32>>()   // x0
                                  .Arg<ffi::Buffer<ffi::F32>>()   // u_prev
                                  .Arg<ffi::Buffer<ffi::F32>>()   // controls
                                  .Ret<ffi::Buffer<ffi::F32>>()   // states
                                  .Ret<ffi::Buffer<ffi::F32>>()   // applied
                                  .Ret<ffi::Buffer<ffi::F32>>()   // xdots
                                  .Attr<float>("dt")
                                  .Attr<int64_t>("substeps")
                                  .Attr<int64_t>("threads"));
