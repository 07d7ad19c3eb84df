// The depth camera's ray caster on a CPU, a plain C function (ctypes).
//
// The same computation as render_depth in services/sensor/core.py, ray by ray in float32:
// march t = min((i + 1) step, range) over the bilinear heightmap (common/geometry.py,
// clamped at the border) until the first step that ends below the surface inside the map,
// bisect that step `refine` times, then the secant across what is left; z-depth out, 0 = no
// return. Why native: the JAX form marches every ray the whole range (a scan of 250 steps
// over all rays, about 100 ms a frame on this project's CPU); a ray here stops at its
// crossing, when it has left the map, or when it rises above the highest cell.
//
// Inputs: heightmap (h, w) f32 row-major, origin (2,) f32 (world x, y of its corner),
// cam_position (3,) f32, cam_rotation (3, 3) f32 camera -> world, dirs_cam (R, 3) f32 unit
// rays in the camera frame. Output: depth (R,) f32.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>

namespace {

struct Map {
  const float* z;
  int64_t h, w;
  float x0, y0, x1, y1, res;

  // common/geometry.py bilinear, float32, the same order of operations
  float ground(float x, float y) const {
    float gc = (x - x0) / res - 0.5f, gr = (y - y0) / res - 0.5f;
    gc = std::min(std::max(gc, 0.0f), static_cast<float>(w) - 1.0f);
    gr = std::min(std::max(gr, 0.0f), static_cast<float>(h) - 1.0f);
    const int64_t c0 = std::clamp<int64_t>(static_cast<int32_t>(std::floor(gc)), 0, w - 2);
    const int64_t r0 = std::clamp<int64_t>(static_cast<int32_t>(std::floor(gr)), 0, h - 2);
    const float fc = gc - static_cast<float>(c0), fr = gr - static_cast<float>(r0);
    const float* row0 = z + r0 * w + c0;
    const float* row1 = row0 + w;
    return (row0[0] * (1.0f - fc) + row0[1] * fc) * (1.0f - fr) +
           (row1[0] * (1.0f - fc) + row1[1] * fc) * fr;
  }
  bool inside(float x, float y) const { return x >= x0 && x < x1 && y >= y0 && y < y1; }
};

}  // namespace

extern "C" int vamppi_render_depth(const float* heightmap, int64_t h, int64_t w,
                                   const float* origin, float resolution, const float* position,
                                   const float* rotation, const float* dirs_cam, int64_t rays,
                                   float range, float step, int64_t refine, float* depth) {
  if (h < 2 || w < 2 || rays < 0 || !(step > 0.0f) || !(range > 0.0f) || refine < 0) return 1;
  Map m{heightmap, h, w, origin[0], origin[1],
        origin[0] + static_cast<float>(w) * resolution,
        origin[1] + static_cast<float>(h) * resolution, resolution};
  float top = -std::numeric_limits<float>::infinity();
  for (int64_t i = 0; i < h * w; ++i) top = std::max(top, heightmap[i]);
  top += 1e-3f;                          // above every bilinear value, rounding included
  const int64_t n_steps = static_cast<int64_t>(std::ceil(static_cast<double>(range) / step));
  const float ox = position[0], oy = position[1], oz = position[2];
  const float* r = rotation;

  for (int64_t k = 0; k < rays; ++k) {
    const float* dc = dirs_cam + 3 * k;
    // dirs_cam @ rotation.T
    const float dx = (dc[0] * r[0] + dc[1] * r[1]) + dc[2] * r[2];
    const float dy = (dc[0] * r[3] + dc[1] * r[4]) + dc[2] * r[5];
    const float dz = (dc[0] * r[6] + dc[1] * r[7]) + dc[2] * r[8];
    auto gap = [&](float t) { return (oz + t * dz) - m.ground(ox + t * dx, oy + t * dy); };

    bool was_inside = m.inside(ox, oy);
    float gap_prev = was_inside ? gap(0.0f) : std::numeric_limits<float>::infinity();
    float t_prev = 0.0f, t_lo = 0.0f, t_hi = -1.0f;
    for (int64_t i = 0; i < n_steps; ++i) {
      const float t = std::min(static_cast<float>(i + 1) * step, range);
      const float x = ox + t * dx, y = oy + t * dy;
      const bool in = m.inside(x, y);
      if (!in && was_inside) break;      // a straight ray that left the map stays out
      was_inside = was_inside || in;
      if (dz >= 0.0f && oz + t * dz > top) break;   // rising above every cell
      const float g = in ? gap(t) : std::numeric_limits<float>::infinity();
      if (in && g <= 0.0f && gap_prev > 0.0f) {
        t_lo = t_prev;
        t_hi = t;
        break;
      }
      gap_prev = g;
      t_prev = t;
    }
    if (t_hi < 0.0f) {
      depth[k] = 0.0f;
      continue;
    }
    for (int64_t j = 0; j < refine; ++j) {
      const float mid = 0.5f * (t_lo + t_hi);
      if (gap(mid) > 0.0f) t_lo = mid; else t_hi = mid;
    }
    const float g_lo = gap(t_lo), g_hi = gap(t_hi);
    const float frac = std::min(std::max(g_lo / std::max(g_lo - g_hi, 1e-12f), 0.0f), 1.0f);
    depth[k] = (t_lo + frac * (t_hi - t_lo)) * dc[2];
  }
  return 0;
}
