// Tile rasterizer of 2D Gaussians, forward and backward (see rasterize_compiled.py).
//
// Same tiles, order, thresholds and gradients as tracegs/splat/rasterize.py: square tiles of `tile_size`
// pixels, every splat binned to the tiles its 1/255-alpha box touches, depth order kept within a tile (the
// splats arrive sorted front to back and a counting sort is stable), alpha = min(0.99, o exp(power)) skipped
// below 1/255, and a pixel stops at the first splat whose transmittance before it is below `occlusion_eps`.
// No torch headers: plain C ABI over float32 buffers keeps the one-time compile near a second.
//
// Each tile walks its splats once and updates all its pixels together in loops the compiler vectorises
// (`omp simd`, compiled with -fopenmp-simd: no OpenMP runtime, no threads); a pixel whose transmittance has
// fallen below the cut-off is masked out, and the tile stops when all its pixels are.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

namespace {

constexpr float kAlphaMin = 1.0f / 255.0f;
constexpr float kAlphaMax = 0.99f;

struct Splat {  // what the inner loop reads, packed together
  float mx, my, a, b, c, o;
  // Below this power alpha < 1/255 for sure (a margin under log(1 / (255 o)) so rounding never decides): most
  // (pixel, splat) pairs of a tile are skipped without evaluating exp.
  float min_power;
  int32_t row;  // the splat's row in the input buffers
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

Bins bin_tiles(int64_t m, const int64_t* order, const float* means2d, const float* extents, int64_t tiles_x,
               int64_t tiles_y, int tile_size) {
  std::vector<int64_t> box(4 * m);  // x0, x1, y0, y1 (inclusive) per splat
  Bins bins;
  bins.offsets.assign(tiles_x * tiles_y + 1, 0);
  for (int64_t s = 0; s < m; ++s) {
    int64_t* b = &box[4 * s];
    const int64_t r = order[s];
    b[0] = clamp_tile(means2d[2 * r] - extents[2 * r], tile_size, tiles_x);
    b[1] = clamp_tile(means2d[2 * r] + extents[2 * r], tile_size, tiles_x);
    b[2] = clamp_tile(means2d[2 * r + 1] - extents[2 * r + 1], tile_size, tiles_y);
    b[3] = clamp_tile(means2d[2 * r + 1] + extents[2 * r + 1], tile_size, tiles_y);
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

std::vector<Splat> pack(int64_t m, const int64_t* order, const float* means2d, const float* conics,
                        const float* opacities) {
  std::vector<Splat> packed(m);
  for (int64_t s = 0; s < m; ++s) {
    const int64_t r = order[s];
    packed[s] = {means2d[2 * r], means2d[2 * r + 1], conics[3 * r], conics[3 * r + 1], conics[3 * r + 2],
                 opacities[r], std::log(kAlphaMin / opacities[r]) - 1e-3f, static_cast<int32_t>(r)};
  }
  return packed;
}

// What forward and backward both walk: the tile grid, every tile's splats, the packed splats.
struct Scene {
  int64_t tiles_x, tiles_y;
  Bins bins;
  std::vector<Splat> splats;

  Scene(int64_t m, const int64_t* order, int64_t width, int64_t height, int tile_size, const float* means2d,
        const float* conics, const float* opacities, const float* extents)
      : tiles_x((width + tile_size - 1) / tile_size),
        tiles_y((height + tile_size - 1) / tile_size),
        bins(bin_tiles(m, order, means2d, extents, tiles_x, tiles_y, tile_size)),
        splats(pack(m, order, means2d, conics, opacities)) {}
};

// exp(x) for x <= 88 without a libm call, so the pixel loops vectorise: Cody-Waite reduction x = n ln2 + r,
// |r| <= ln2 / 2, and Cephes' degree-6 expf polynomial (relative error about 1e-7, that of std::exp in float).
// Forward and backward both use it, so the backward pass recomputes exactly the forward alphas.
#pragma omp declare simd
inline float fast_exp(float x) {
  x = x > -87.0f ? x : -87.0f;  // also maps NaN to -87; the callers mask those pairs out
  x = x < 88.0f ? x : 88.0f;
  const float t = x * 1.44269504088896341f;
  const int n = static_cast<int>(t + (t >= 0.0f ? 0.5f : -0.5f));
  const float nf = static_cast<float>(n);
  const float r = (x - nf * 0.693359375f) + nf * 2.12194440e-4f;
  float p = 1.9875691500e-4f;
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * r * r + r + 1.0f;
  const uint32_t bits = static_cast<uint32_t>(n + 127) << 23;
  float scale;
  std::memcpy(&scale, &bits, sizeof(scale));
  return p * scale;
}

// One tile's pixel centres, and which of them lie inside the image (edge tiles may overhang it).
template <int tile_size>
struct TilePixels {
  float x[tile_size * tile_size], y[tile_size * tile_size];
  int64_t index[tile_size * tile_size];  // y * width + x, or -1 outside the image

  void place(int64_t tx, int64_t ty, int64_t width, int64_t height) {
    for (int p = 0; p < tile_size * tile_size; ++p) {
      const int64_t px = tx * tile_size + p % tile_size, py = ty * tile_size + p / tile_size;
      x[p] = static_cast<float>(px) + 0.5f;
      y[p] = static_cast<float>(py) + 0.5f;
      index[p] = px < width && py < height ? py * width + px : -1;
    }
  }
};

// out [H,W,C] = sum_k w_k f_k, final [H,W] = transmittance after the last composited splat, stop [H,W] = index
// (within the pixel's tile list) one past the last splat composited into the pixel (the backward pass starts
// there).
template <int tile_size>
[[gnu::always_inline]] inline void forward(int64_t m, const int64_t* order, int64_t channels, int64_t width,
                                           int64_t height, float occlusion_eps, const float* means2d,
                                           const float* conics, const float* opacities, const float* features,
                                           const float* extents, float* out, float* final_transmittance,
                                           int64_t* stop) {
  constexpr int pixels = tile_size * tile_size;
  const Scene scene(m, order, width, height, tile_size, means2d, conics, opacities, extents);
  TilePixels<tile_size> tile_pixels;
  std::vector<float> transmittance(pixels), alpha(pixels), colour(channels * pixels);  // colour [C, pixels]
  std::vector<int32_t> last(pixels);  // relative to the tile's first pair: int32 keeps the loops float-wide
  const float* px = tile_pixels.x;
  const float* py = tile_pixels.y;
  float* t = transmittance.data();
  float* al = alpha.data();
  for (int64_t ty = 0; ty < scene.tiles_y; ++ty)
    for (int64_t tx = 0; tx < scene.tiles_x; ++tx) {
      const int64_t tile = ty * scene.tiles_x + tx;
      const int64_t first = scene.bins.offsets[tile], end = scene.bins.offsets[tile + 1];
      tile_pixels.place(tx, ty, width, height);
      for (int p = 0; p < pixels; ++p) t[p] = tile_pixels.index[p] >= 0 ? 1.0f : 0.0f;  // 0: never composited
      std::fill(colour.begin(), colour.end(), 0.0f);
      std::fill(last.begin(), last.end(), 0);
      for (int64_t i = first; i < end; ++i) {
        float open = 0.0f;
#pragma omp simd reduction(max : open)
        for (int p = 0; p < pixels; ++p) open = std::max(open, t[p]);
        if (open < occlusion_eps) break;  // every pixel of the tile is opaque
        const int32_t s = scene.bins.splats[i];
        const Splat g = scene.splats[s];
        const auto local = static_cast<int32_t>(i - first);
        int any = 0;  // bitwise logic below: short-circuit operators are branches and stop vectorisation
#pragma omp simd reduction(| : any)
        for (int p = 0; p < pixels; ++p) {
          const float dx = px[p] - g.mx, dy = py[p] - g.my;
          const float power = -0.5f * (g.a * dx * dx + g.c * dy * dy) - g.b * dx * dy;
          const float raw = g.o * fast_exp(power);
          const int on = (power >= g.min_power) & (raw >= kAlphaMin) & (t[p] >= occlusion_eps);
          al[p] = on ? std::min(raw, kAlphaMax) : 0.0f;
          any |= on;
        }
        if (!any) continue;
        const float* f = features + static_cast<int64_t>(g.row) * channels;
        for (int64_t k = 0; k < channels; ++k) {
          float* c = colour.data() + k * pixels;
          const float fk = f[k];
#pragma omp simd
          for (int p = 0; p < pixels; ++p) c[p] += al[p] * t[p] * fk;
        }
#pragma omp simd
        for (int p = 0; p < pixels; ++p) {
          t[p] *= 1.0f - al[p];
          last[p] = al[p] > 0.0f ? local + 1 : last[p];
        }
      }
      for (int p = 0; p < pixels; ++p) {
        const int64_t pixel = tile_pixels.index[p];
        if (pixel < 0) continue;
        for (int64_t k = 0; k < channels; ++k) out[pixel * channels + k] = colour[k * pixels + p];
        final_transmittance[pixel] = t[p];
        stop[pixel] = first + last[p];
      }
    }
}

// Walks every tile's splats back to front, recovering each pixel's T_k = T_{k+1} / (1 - alpha_k), with
// dL/dalpha_k = T_k h_k - (sum_{j>k} w_j h_j + T_final dL/dT_final) / (1 - alpha_k), h_k = f_k . dL/dout, and
// alpha_k = o_k exp(power_k) where it is neither skipped nor clamped. Gradients are added into the grad buffers
// (zeroed by the caller).
template <int tile_size>
[[gnu::always_inline]] inline void backward(int64_t m, const int64_t* order, int64_t channels, int64_t width,
                                            int64_t height, const float* means2d, const float* conics,
                                            const float* opacities, const float* features, const float* extents,
                                            const float* final_transmittance, const int64_t* stop,
                                            const float* grad_out, const float* grad_final, float* grad_means2d,
                                            float* grad_conics, float* grad_opacities, float* grad_features) {
  constexpr int pixels = tile_size * tile_size;
  const Scene scene(m, order, width, height, tile_size, means2d, conics, opacities, extents);
  TilePixels<tile_size> tile_pixels;
  std::vector<float> transmittance(pixels), behind(pixels), behind_final(pixels), weight(pixels), h_values(pixels);
  std::vector<float> grad(channels * pixels);  // dL/dout [C, pixels]
  std::vector<int32_t> last(pixels);  // stop relative to the tile's first pair, as in the forward pass
  const float* px = tile_pixels.x;
  const float* py = tile_pixels.y;
  float* t = transmittance.data();
  float* bh = behind.data();
  float* bf = behind_final.data();
  float* w = weight.data();
  float* hs = h_values.data();  // h_k = f_k . dL/dout per pixel
  const float* gr = grad.data();
  const int32_t* lt = last.data();
  for (int64_t ty = 0; ty < scene.tiles_y; ++ty)
    for (int64_t tx = 0; tx < scene.tiles_x; ++tx) {
      const int64_t first = scene.bins.offsets[ty * scene.tiles_x + tx];
      tile_pixels.place(tx, ty, width, height);
      int64_t end = first;
      for (int p = 0; p < pixels; ++p) {
        const int64_t pixel = tile_pixels.index[p];
        t[p] = pixel >= 0 ? final_transmittance[pixel] : 0.0f;
        bf[p] = pixel >= 0 ? t[p] * grad_final[pixel] : 0.0f;
        bh[p] = 0.0f;
        const int64_t pixel_stop = pixel >= 0 ? stop[pixel] : first;
        last[p] = static_cast<int32_t>(pixel_stop - first);
        end = std::max(end, pixel_stop);
        for (int64_t k = 0; k < channels; ++k)
          grad[k * pixels + p] = pixel >= 0 ? grad_out[pixel * channels + k] : 0.0f;
      }
      for (int64_t i = end - 1; i >= first; --i) {
        const int32_t s = scene.bins.splats[i];
        const Splat g = scene.splats[s];
        const auto local = static_cast<int32_t>(i - first);
        const float* f = features + static_cast<int64_t>(g.row) * channels;
        std::fill(hs, hs + pixels, 0.0f);
        for (int64_t k = 0; k < channels; ++k) {
          const float fk = f[k];
          const float* gk = gr + k * pixels;
#pragma omp simd
          for (int p = 0; p < pixels; ++p) hs[p] += fk * gk[p];
        }
        float g_mx = 0.0f, g_my = 0.0f, g_a = 0.0f, g_b = 0.0f, g_c = 0.0f, g_o = 0.0f;
        int any = 0;
#pragma omp simd reduction(+ : g_mx, g_my, g_a, g_b, g_c, g_o) reduction(| : any)
        for (int p = 0; p < pixels; ++p) {
          const float dx = px[p] - g.mx, dy = py[p] - g.my;
          const float power = -0.5f * (g.a * dx * dx + g.c * dy * dy) - g.b * dx * dy;
          const float gaussian = fast_exp(power);
          const float raw = g.o * gaussian;
          const int on = (local < lt[p]) & (power >= g.min_power) & (raw >= kAlphaMin);
          const int free = on & (raw < kAlphaMax);  // clamped alphas do not depend on o or the power
          const float alpha = on ? std::min(raw, kAlphaMax) : 0.0f;
          const float inverse = 1.0f / (1.0f - alpha);
          const float before = t[p] * inverse;  // T_k; unchanged where the pair is skipped
          const float h = hs[p];
          const float grad_alpha = before * h - (bh[p] + bf[p]) * inverse;
          w[p] = alpha * before;
          bh[p] += w[p] * h;
          t[p] = before;
          const float grad_power = free ? grad_alpha * alpha : 0.0f;
          g_o += free ? grad_alpha * gaussian : 0.0f;
          // power = -1/2 (a dx^2 + c dy^2) - b dx dy with d = pixel - mean
          g_mx += grad_power * (g.a * dx + g.b * dy);
          g_my += grad_power * (g.b * dx + g.c * dy);
          g_a += -0.5f * grad_power * dx * dx;
          g_b += -grad_power * dx * dy;
          g_c += -0.5f * grad_power * dy * dy;
          any |= on;
        }
        if (!any) continue;
        const int64_t r = g.row;
        grad_means2d[2 * r] += g_mx;
        grad_means2d[2 * r + 1] += g_my;
        grad_conics[3 * r] += g_a;
        grad_conics[3 * r + 1] += g_b;
        grad_conics[3 * r + 2] += g_c;
        grad_opacities[r] += g_o;
        for (int64_t k = 0; k < channels; ++k) {
          float sum = 0.0f;
          const float* gk = gr + k * pixels;
#pragma omp simd reduction(+ : sum)
          for (int p = 0; p < pixels; ++p) sum += w[p] * gk[p];
          grad_features[r * channels + k] += sum;
        }
      }
    }
}

}  // namespace

// The tile size is a template parameter so the pixel loops have a fixed trip count the compiler unrolls. Each
// entry point is compiled twice, for x86-64-v3 (AVX2, FMA) and for the baseline, and the loader picks the
// variant this CPU runs (GCC function multi-versioning), so one cached library serves every x86-64 machine.
#define TILE_SIZES(call) \
  switch (tile_size) {   \
    case 4: call(4); return 0; \
    case 8: call(8); return 0; \
    case 16: call(16); return 0; \
    default: return 1; \
  }
#if defined(__x86_64__)
#define MULTIVERSION [[gnu::target_clones("arch=x86-64-v3", "default")]]
#else
#define MULTIVERSION
#endif

extern "C" {

// m splats, the rows `order[0 .. m)` of the input buffers front to back (their gradients go to the same rows).
// Returns 0, or 1 for an unsupported tile size (4, 8 and 16 are compiled).
MULTIVERSION int rasterize_forward(int64_t m, const int64_t* order, int64_t channels, int64_t width, int64_t height,
                                   int tile_size, float occlusion_eps, const float* means2d, const float* conics,
                                   const float* opacities, const float* features, const float* extents, float* out,
                                   float* final_transmittance, int64_t* stop) {
#define FORWARD(size) forward<size>(m, order, channels, width, height, occlusion_eps, means2d, conics, \
                                    opacities, features, extents, out, final_transmittance, stop)
  TILE_SIZES(FORWARD)
}

MULTIVERSION int rasterize_backward(int64_t m, const int64_t* order, int64_t channels, int64_t width, int64_t height,
                                    int tile_size, const float* means2d, const float* conics, const float* opacities,
                                    const float* features, const float* extents, const float* final_transmittance,
                                    const int64_t* stop, const float* grad_out, const float* grad_final,
                                    float* grad_means2d, float* grad_conics, float* grad_opacities,
                                    float* grad_features) {
#define BACKWARD(size) backward<size>(m, order, channels, width, height, means2d, conics, opacities, features, \
                                      extents, final_transmittance, stop, grad_out, grad_final, grad_means2d, \
                                      grad_conics, grad_opacities, grad_features)
  TILE_SIZES(BACKWARD)
}

}  // extern "C"
