// Vector-friendly float math shared by the planner's native kernels (va_counts.cc,
// surface.cc, rollout.cc): branch-free, so GCC vectorises the loops that call it.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>

namespace vamppi {

// exp(x) for x <= 0 as vector code: x = n ln2 + r (Cody-Waite, two-part ln2),
// |r| <= ln2 / 2, e^r by its degree-6 Taylor polynomial (remainder r^7 / 7! < 1.3e-7
// relative), times 2^n built in the exponent bits; 0 below -87 (the end of the normal
// range: a variance times e^-87 is nothing a cost can feel). One body for a float and for
// a GCC vector of floats (rollout.cc's): `Ops` gives the few operations that differ.
template <class F, class Ops>
__attribute__((always_inline)) inline F exp_nonpositive_of(F x) {
  const F xc = Ops::max(x, Ops::splat(-87.0f));
  const F n = Ops::round_even(xc * 1.44269504f);
  const F r = (xc - n * 0.693145752f) - n * 1.42860677e-6f;
  F p = Ops::splat(1.0f / 720.0f);
  p = p * r + 1.0f / 120.0f;
  p = p * r + 1.0f / 24.0f;
  p = p * r + 1.0f / 6.0f;
  p = p * r + 0.5f;
  p = p * r + 1.0f;
  p = p * r + 1.0f;
  return Ops::zero_below(x, -87.0f, p * Ops::exp2(n));
}

struct FloatOps {
  static float splat(float s) { return s; }
  static float max(float a, float b) { return std::max(a, b); }
  static float round_even(float x) { return std::nearbyint(x); }
  static float exp2(float n) {            // 2^n for an integral n in the normal range
    const int32_t bits = (static_cast<int32_t>(n) + 127) << 23;
    float scale;
    std::memcpy(&scale, &bits, sizeof scale);
    return scale;
  }
  static float zero_below(float x, float lo, float v) { return x < lo ? 0.0f : v; }
};

__attribute__((always_inline)) inline float exp_nonpositive(float x) {
  return exp_nonpositive_of<float, FloatOps>(x);
}

}  // namespace vamppi
