// Tile rasterizer of 2D Gaussians, forward and backward, one tight loop per pixel (see rasterize_compiled.py).
//
// Same tiles, order, thresholds and gradients as tracegs/splat/rasterize.py: square tiles of `tile_size`
// pixels, every splat binned to the tiles its 1/255-alpha box touches, depth order kept within a tile (the
// splats arrive sorted front to back and a counting sort is stable), alpha = min(0.99, o exp(power)) skipped
// below 1/255, and a pixel stops at the first splat whose transmittance before it is below `occlusion_eps`.
// No torch headers: plain C ABI over float32 buffers keeps the one-time compile near a second.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr float kAlphaMin = 1.0f / 255.0f;
constexpr float kAlphaMax = 0.99f;

struct Splat {  // what the inner loop reads, packed together
  float mx, my, a, b, c, o;
  // Below this power alpha < 1/255 for sure (a margin under log(1 / (255 o)) so rounding never decides): most
  // (pixel, splat) pairs of a tile are skipped without evaluating exp.
  float min_power;
  float pad;
};

// The splats of every tile, front to back: `splats[offsets[t] .. offsets[t + 1])`.
struct Bins {
  std::vector<int64_t> offsets;
  std::vector<int32_t> splats;
};

int64_t clamp_tile(float coordinate, int tile_size, int64_t tiles) {
  const auto index = static_cast<int64_t>(std::floor(coordinate / static_cast<float>(tile_size)));
  return std::min(std::max<int64_t>(index, 0), tiles - 1);
}

Bins bin_tiles(int64_t m, const float* means2d, const float* extents, int64_t tiles_x, int64_t tiles_y,
               int tile_size) {
  std::vector<int64_t> box(4 * m);  // x0, x1, y0, y1 (inclusive) per splat
  Bins bins;
  bins.offsets.assign(tiles_x * tiles_y + 1, 0);
  for (int64_t s = 0; s < m; ++s) {
    int64_t* b = &box[4 * s];
    b[0] = clamp_tile(means2d[2 * s] - extents[2 * s], tile_size, tiles_x);
    b[1] = clamp_tile(means2d[2 * s] + extents[2 * s], tile_size, tiles_x);
    b[2] = clamp_tile(means2d[2 * s + 1] - extents[2 * s + 1], tile_size, tiles_y);
    b[3] = clamp_tile(means2d[2 * s + 1] + extents[2 * s + 1], tile_size, tiles_y);
    for (int64_t ty = b[2]; ty <= b[3]; ++ty)
      for (int64_t tx = b[0]; tx <= b[1]; ++tx) ++bins.offsets[ty * tiles_x + tx + 1];
  }
  for (size_t t = 1; t < bins.offsets.size(); ++t) bins.offsets[t] += bins.offsets[t - 1];
  std::vector<int64_t> cursor(bins.offsets.begin(), bins.offsets.end() - 1);
  bins.splats.resize(bins.offsets.back());
  for (int64_t s = 0; s < m; ++s) {
    const int64_t* b = &box[4 * s];
    for (int64_t ty = b[2]; ty <= b[3]; ++ty)
      for (int64_t tx = b[0]; tx <= b[1]; ++tx) bins.splats[cursor[ty * tiles_x + tx]++] = static_cast<int32_t>(s);
  }
  return bins;
}

std::vector<Splat> pack(int64_t m, const float* means2d, const float* conics, const float* opacities) {
  std::vector<Splat> packed(m);
  for (int64_t s = 0; s < m; ++s)
    packed[s] = {means2d[2 * s], means2d[2 * s + 1], conics[3 * s], conics[3 * s + 1], conics[3 * s + 2],
                 opacities[s], std::log(kAlphaMin / opacities[s]) - 1e-3f, 0.0f};
  return packed;
}

// Gaussian exponent -1/2 d^T C^-1 d at pixel centre (px, py), d = pixel - mean.
inline float power_at(const Splat& g, float px, float py, float& dx, float& dy) {
  dx = px - g.mx;
  dy = py - g.my;
  return -0.5f * (g.a * dx * dx + g.c * dy * dy) - g.b * dx * dy;
}

}  // namespace

extern "C" {

// out [H,W,C] = sum_k w_k f_k, final [H,W] = transmittance after the last composited splat, stop [H,W] = index
// (within the pixel's tile list) one past the last splat the pixel visited (the backward pass starts there).
void rasterize_forward(int64_t m, int64_t channels, int64_t width, int64_t height, int tile_size,
                       float occlusion_eps, const float* means2d, const float* conics, const float* opacities,
                       const float* features, const float* extents, float* out, float* final_transmittance,
                       int64_t* stop) {
  const int64_t tiles_x = (width + tile_size - 1) / tile_size, tiles_y = (height + tile_size - 1) / tile_size;
  const Bins bins = bin_tiles(m, means2d, extents, tiles_x, tiles_y, tile_size);
  const std::vector<Splat> splats = pack(m, means2d, conics, opacities);
  std::vector<float> colour(channels);
  for (int64_t ty = 0; ty < tiles_y; ++ty)
    for (int64_t tx = 0; tx < tiles_x; ++tx) {
      const int64_t tile = ty * tiles_x + tx, first = bins.offsets[tile], last = bins.offsets[tile + 1];
      for (int64_t y = ty * tile_size; y < std::min(height, (ty + 1) * tile_size); ++y)
        for (int64_t x = tx * tile_size; x < std::min(width, (tx + 1) * tile_size); ++x) {
          const float px = static_cast<float>(x) + 0.5f, py = static_cast<float>(y) + 0.5f;
          std::fill(colour.begin(), colour.end(), 0.0f);
          float transmittance = 1.0f;
          int64_t i = first;
          for (; i < last && transmittance >= occlusion_eps; ++i) {
            const int32_t s = bins.splats[i];
            float dx, dy;
            const float power = power_at(splats[s], px, py, dx, dy);
            if (!(power >= splats[s].min_power)) continue;
            float alpha = splats[s].o * std::exp(power);
            if (!(alpha >= kAlphaMin)) continue;  // also skips NaN
            alpha = std::min(alpha, kAlphaMax);
            const float weight = alpha * transmittance;
            const float* f = features + s * channels;
            for (int64_t k = 0; k < channels; ++k) colour[k] += weight * f[k];
            transmittance *= 1.0f - alpha;
          }
          const int64_t pixel = y * width + x;
          std::copy(colour.begin(), colour.end(), out + pixel * channels);
          final_transmittance[pixel] = transmittance;
          stop[pixel] = i;
        }
    }
}

// Walks every pixel's splats back to front, recovering T_k = T_{k+1} / (1 - alpha_k), with
// dL/dalpha_k = T_k h_k - (sum_{j>k} w_j h_j + T_final dL/dT_final) / (1 - alpha_k), h_k = f_k . dL/dout, and
// alpha_k = o_k exp(power_k) where it is neither skipped nor clamped. Gradients are added into the grad buffers
// (zeroed by the caller).
void rasterize_backward(int64_t m, int64_t channels, int64_t width, int64_t height, int tile_size,
                        const float* means2d, const float* conics, const float* opacities, const float* features,
                        const float* extents, const float* final_transmittance, const int64_t* stop,
                        const float* grad_out, const float* grad_final, float* grad_means2d, float* grad_conics,
                        float* grad_opacities, float* grad_features) {
  const int64_t tiles_x = (width + tile_size - 1) / tile_size, tiles_y = (height + tile_size - 1) / tile_size;
  const Bins bins = bin_tiles(m, means2d, extents, tiles_x, tiles_y, tile_size);
  const std::vector<Splat> splats = pack(m, means2d, conics, opacities);
  for (int64_t ty = 0; ty < tiles_y; ++ty)
    for (int64_t tx = 0; tx < tiles_x; ++tx) {
      const int64_t first = bins.offsets[ty * tiles_x + tx];
      for (int64_t y = ty * tile_size; y < std::min(height, (ty + 1) * tile_size); ++y)
        for (int64_t x = tx * tile_size; x < std::min(width, (tx + 1) * tile_size); ++x) {
          const int64_t pixel = y * width + x;
          const float px = static_cast<float>(x) + 0.5f, py = static_cast<float>(y) + 0.5f;
          const float* g = grad_out + pixel * channels;
          // double: the running sums span the whole pixel and T is recovered by repeated division
          double transmittance = final_transmittance[pixel];
          const double behind_final = transmittance * grad_final[pixel];
          double behind = 0.0;  // sum_{j>k} w_j h_j
          for (int64_t i = stop[pixel] - 1; i >= first; --i) {
            const int32_t s = bins.splats[i];
            const Splat& splat = splats[s];
            float dx, dy;
            const float power = power_at(splat, px, py, dx, dy);
            if (!(power >= splat.min_power)) continue;
            const float gaussian = std::exp(power);
            const float raw = splat.o * gaussian;
            if (!(raw >= kAlphaMin)) continue;
            const float alpha = std::min(raw, kAlphaMax);
            transmittance /= 1.0 - alpha;
            const float weight = static_cast<float>(alpha * transmittance);
            const float* f = features + s * channels;
            float* gf = grad_features + s * channels;
            double h = 0.0;
            for (int64_t k = 0; k < channels; ++k) {
              h += static_cast<double>(f[k]) * g[k];
              gf[k] += weight * g[k];
            }
            const double grad_alpha = transmittance * h - (behind + behind_final) / (1.0 - alpha);
            behind += weight * h;
            if (raw >= kAlphaMax) continue;  // clamped: alpha does not depend on o or the power here
            grad_opacities[s] += static_cast<float>(grad_alpha * gaussian);
            const float grad_power = static_cast<float>(grad_alpha * alpha);
            // power = -1/2 (a dx^2 + c dy^2) - b dx dy with d = pixel - mean
            grad_means2d[2 * s] += grad_power * (splat.a * dx + splat.b * dy);
            grad_means2d[2 * s + 1] += grad_power * (splat.b * dx + splat.c * dy);
            grad_conics[3 * s] += -0.5f * grad_power * dx * dx;
            grad_conics[3 * s + 1] += -grad_power * dx * dy;
            grad_conics[3 * s + 2] += -0.5f * grad_power * dy * dy;
          }
        }
    }
}

}  // extern "C"
