// Vector-friendly float math shared by the planner's native kernels (va_counts.cc,
// surface.cc): branch-free, so GCC vectorises the loops that call it.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>

namespace vamppi {

// exp(x) for x <= 0 as vector code: x = n ln2 + r (Cody-Waite, two-part ln2),
// |r| <= ln2 / 2, e^r by its degree-6 Taylor polynomial (remainder r^7 / 7! < 1.3e-7
// relative), times 2^n built in the exponent bits; 0 below -87 (the end of the normal
// range: a variance times e^-87 is nothing a cost can feel).
__attribute__((always_inline)) inline float exp_nonpositive(float x) {
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

}  // namespace vamppi
