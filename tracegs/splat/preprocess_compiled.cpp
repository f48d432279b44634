// Per-Gaussian preprocessing of the compiled backend, forward and backward (see preprocess_compiled.py).
//
// The same maths as tracegs/splat/projection.py (EWA projection J W R S (J W R S)^T + 0.3 I, the 1.3 x half
// field-of-view clamp of the Jacobian, conics, 1/255-alpha extents, visibility, radii) and tracegs/splat/sh.py
// (3DGS real spherical harmonics of degree 0-3, colour = SH(dir) + 0.5 clamped at 0), one Gaussian at a time,
// with the chain rule written out by hand. The backward pass recomputes the forward intermediates of a
// Gaussian (a few hundred flops) instead of storing them. Plain C ABI over float32 buffers, no torch headers.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr float kLowPass = 0.3f;  // projection.LOW_PASS_VARIANCE
constexpr float kNearPlane = 0.01f;  // projection.NEAR_PLANE
constexpr float kAlphaMin = 1.0f / 255.0f;  // projection.ALPHA_MIN
constexpr float kFovClamp = 1.3f;  // projection.FOV_CLAMP
constexpr float kNormEps = 1e-12f;  // torch.nn.functional.normalize's eps

constexpr float kShC0 = 0.28209479177387814f;
constexpr float kShC1 = 0.4886025119029199f;
constexpr float kShC2[5] = {1.0925484305920792f, -1.0925484305920792f, 0.31539156525252005f,
                            -1.0925484305920792f, 0.5462742152960396f};
constexpr float kShC3[7] = {-0.5900435899266435f, 2.890611442640554f, -0.4570457994644658f,
                            0.3731763325901154f, -0.4570457994644658f, 1.445305721320277f,
                            -0.5900435899266435f};
constexpr int kShRest = 15;  // coefficients per Gaussian in sh_rest (degree 3)

struct View {
  float R[3][3], t[3], center[3], fx, fy, cx, cy, lim_x, lim_y;
  int64_t width, height;

  View(const float* world_to_camera, const float* K, int64_t w, int64_t h) : width(w), height(h) {
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) R[i][j] = world_to_camera[4 * i + j];
      t[i] = world_to_camera[4 * i + 3];
    }
    for (int j = 0; j < 3; ++j) center[j] = -(R[0][j] * t[0] + R[1][j] * t[1] + R[2][j] * t[2]);
    fx = K[0];
    fy = K[4];
    cx = K[2];
    cy = K[5];
    lim_x = kFovClamp * 0.5f * static_cast<float>(w) / fx;
    lim_y = kFovClamp * 0.5f * static_cast<float>(h) / fy;
  }
};

// Everything the forward pass computes for one Gaussian; the backward pass recomputes it.
struct Projection {
  float p[3];  // camera-space mean
  bool in_front;
  float tz, u, v, uc, vc;  // tz: the depth the projection divides by (1 behind the near plane)
  float M[2][3];  // J W
  float q[4], q_norm;  // normalised quaternion (w, x, y, z) and the norm it was divided by
  float Rq[3][3], s[3], RS[3][3];
  float T[2][3];  // J W R S
  float cxx, cxy, cyy, det;
};

Projection project(const View& view, const float* mean, const float* quat, const float* log_scale) {
  Projection P;
  for (int i = 0; i < 3; ++i)
    P.p[i] = view.R[i][0] * mean[0] + view.R[i][1] * mean[1] + view.R[i][2] * mean[2] + view.t[i];
  P.in_front = P.p[2] > kNearPlane;
  P.tz = P.in_front ? P.p[2] : 1.0f;  // behind the camera: a harmless depth, as in projection.py
  P.u = P.p[0] / P.tz;
  P.v = P.p[1] / P.tz;
  P.uc = std::min(std::max(P.u, -view.lim_x), view.lim_x);
  P.vc = std::min(std::max(P.v, -view.lim_y), view.lim_y);
  const float j00 = view.fx / P.tz, j02 = -view.fx * P.uc / P.tz;
  const float j11 = view.fy / P.tz, j12 = -view.fy * P.vc / P.tz;
  for (int j = 0; j < 3; ++j) {
    P.M[0][j] = j00 * view.R[0][j] + j02 * view.R[2][j];
    P.M[1][j] = j11 * view.R[1][j] + j12 * view.R[2][j];
  }
  P.q_norm = std::max(std::sqrt(quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3]),
                      kNormEps);
  for (int i = 0; i < 4; ++i) P.q[i] = quat[i] / P.q_norm;
  const float w = P.q[0], x = P.q[1], y = P.q[2], z = P.q[3];
  const float rq[3][3] = {{1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)},
                          {2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)},
                          {2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)}};
  for (int j = 0; j < 3; ++j) P.s[j] = std::exp(log_scale[j]);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      P.Rq[i][j] = rq[i][j];
      P.RS[i][j] = rq[i][j] * P.s[j];
    }
  for (int a = 0; a < 2; ++a)
    for (int j = 0; j < 3; ++j) P.T[a][j] = P.M[a][0] * P.RS[0][j] + P.M[a][1] * P.RS[1][j] + P.M[a][2] * P.RS[2][j];
  P.cxx = P.T[0][0] * P.T[0][0] + P.T[0][1] * P.T[0][1] + P.T[0][2] * P.T[0][2] + kLowPass;
  P.cxy = P.T[0][0] * P.T[1][0] + P.T[0][1] * P.T[1][1] + P.T[0][2] * P.T[1][2];
  P.cyy = P.T[1][0] * P.T[1][0] + P.T[1][1] * P.T[1][1] + P.T[1][2] * P.T[1][2] + kLowPass;
  P.det = P.cxx * P.cyy - P.cxy * P.cxy;
  return P;
}

// The unit viewing direction from the camera centre to a mean, and the length it was divided by.
struct Direction {
  float d[3], norm;
};

Direction direction(const View& view, const float* mean) {
  Direction D;
  float squared = 0.0f;
  for (int j = 0; j < 3; ++j) {
    D.d[j] = mean[j] - view.center[j];
    squared += D.d[j] * D.d[j];
  }
  D.norm = std::max(std::sqrt(squared), kNormEps);
  for (int j = 0; j < 3; ++j) D.d[j] /= D.norm;
  return D;
}

// The (degree + 1)^2 basis values at a unit direction (sh.py's order), and optionally their gradients.
int sh_basis(int degree, const float* d, float* basis, float (*gradient)[3]) {
  const float x = d[0], y = d[1], z = d[2];
  const float xx = x * x, yy = y * y, zz = z * z;
  basis[0] = kShC0;
  if (gradient) gradient[0][0] = gradient[0][1] = gradient[0][2] = 0.0f;
  if (degree < 1) return 1;
  basis[1] = -kShC1 * y;
  basis[2] = kShC1 * z;
  basis[3] = -kShC1 * x;
  if (gradient) {
    const float g[3][3] = {{0.0f, -kShC1, 0.0f}, {0.0f, 0.0f, kShC1}, {-kShC1, 0.0f, 0.0f}};
    std::copy(&g[0][0], &g[0][0] + 9, &gradient[1][0]);
  }
  if (degree < 2) return 4;
  basis[4] = kShC2[0] * x * y;
  basis[5] = kShC2[1] * y * z;
  basis[6] = kShC2[2] * (2.0f * zz - xx - yy);
  basis[7] = kShC2[3] * x * z;
  basis[8] = kShC2[4] * (xx - yy);
  if (gradient) {
    const float g[5][3] = {{kShC2[0] * y, kShC2[0] * x, 0.0f},
                           {0.0f, kShC2[1] * z, kShC2[1] * y},
                           {-2.0f * kShC2[2] * x, -2.0f * kShC2[2] * y, 4.0f * kShC2[2] * z},
                           {kShC2[3] * z, 0.0f, kShC2[3] * x},
                           {2.0f * kShC2[4] * x, -2.0f * kShC2[4] * y, 0.0f}};
    std::copy(&g[0][0], &g[0][0] + 15, &gradient[4][0]);
  }
  if (degree < 3) return 9;
  basis[9] = kShC3[0] * y * (3.0f * xx - yy);
  basis[10] = kShC3[1] * x * y * z;
  basis[11] = kShC3[2] * y * (4.0f * zz - xx - yy);
  basis[12] = kShC3[3] * z * (2.0f * zz - 3.0f * xx - 3.0f * yy);
  basis[13] = kShC3[4] * x * (4.0f * zz - xx - yy);
  basis[14] = kShC3[5] * z * (xx - yy);
  basis[15] = kShC3[6] * x * (xx - 3.0f * yy);
  if (gradient) {
    const float g[7][3] = {{kShC3[0] * 6.0f * x * y, kShC3[0] * 3.0f * (xx - yy), 0.0f},
                           {kShC3[1] * y * z, kShC3[1] * x * z, kShC3[1] * x * y},
                           {-2.0f * kShC3[2] * x * y, kShC3[2] * (4.0f * zz - xx - 3.0f * yy), 8.0f * kShC3[2] * y * z},
                           {-6.0f * kShC3[3] * x * z, -6.0f * kShC3[3] * y * z,
                            kShC3[3] * (6.0f * zz - 3.0f * xx - 3.0f * yy)},
                           {kShC3[4] * (4.0f * zz - 3.0f * xx - yy), -2.0f * kShC3[4] * x * y, 8.0f * kShC3[4] * x * z},
                           {2.0f * kShC3[5] * x * z, -2.0f * kShC3[5] * y * z, kShC3[5] * (xx - yy)},
                           {kShC3[6] * 3.0f * (xx - yy), -6.0f * kShC3[6] * x * y, 0.0f}};
    std::copy(&g[0][0], &g[0][0] + 21, &gradient[9][0]);
  }
  return 16;
}

// The first `terms` SH coefficients [terms][3] of Gaussian g (dc first), copied together.
void load_coefficients(int terms, const float* sh_dc, const float* sh_rest, int64_t g, float (*coefficients)[3]) {
  std::copy(sh_dc + 3 * g, sh_dc + 3 * g + 3, coefficients[0]);
  std::copy(sh_rest + g * kShRest * 3, sh_rest + (g * kShRest + terms - 1) * 3, coefficients[1]);
}

// The colour before the clamp at 0: sum_k basis_k coefficient_k + 0.5 per channel.
void sh_colour(int terms, const float* basis, const float (*coefficients)[3], float* rgb) {
  rgb[0] = rgb[1] = rgb[2] = 0.5f;
  for (int k = 0; k < terms; ++k)
    for (int c = 0; c < 3; ++c) rgb[c] += basis[k] * coefficients[k][c];
}

inline bool finite(float x) { return std::isfinite(x); }

}  // namespace

extern "C" {

// Outputs for n Gaussians: means2d [n,2], conics [n,3], features [n,4] (colour where visible, else 0; depth),
// extents [n,2], radii [n,2] (int32, 0 where not visible), visible [n] (bool), and order [<= n]: the visible
// Gaussians front to back (stable in index). Returns how many are visible.
int64_t preprocess_forward(int64_t n, int degree, int64_t width, int64_t height, const float* world_to_camera,
                           const float* K, const float* means, const float* quats, const float* log_scales,
                           const float* opacities, const float* sh_dc, const float* sh_rest, float* means2d,
                           float* conics, float* features, float* extents, int32_t* radii, bool* visible,
                           int64_t* order) {
  const View view(world_to_camera, K, width, height);
  int64_t count = 0;
  float basis[16], coefficients[16][3];
  for (int64_t g = 0; g < n; ++g) {
    const Projection P = project(view, means + 3 * g, quats + 4 * g, log_scales + 3 * g);
    const float mx = view.fx * P.u + view.cx, my = view.fy * P.v + view.cy;
    means2d[2 * g] = mx;
    means2d[2 * g + 1] = my;
    conics[3 * g] = P.cyy / P.det;
    conics[3 * g + 1] = -P.cxy / P.det;
    conics[3 * g + 2] = P.cxx / P.det;
    // alpha = o exp(-d^T C^-1 d / 2) >= 1/255  <=>  d^T C^-1 d <= 2 ln(255 o): that ellipse's bounding box.
    const float reach = std::sqrt(std::max(2.0f * std::log(opacities[g] / kAlphaMin), 0.0f));
    const float ex = std::sqrt(std::max(P.cxx, 0.0f)) * reach, ey = std::sqrt(std::max(P.cyy, 0.0f)) * reach;
    extents[2 * g] = ex;
    extents[2 * g + 1] = ey;
    const bool seen = P.in_front && opacities[g] >= kAlphaMin && mx + ex > 0.0f && mx - ex < width &&
                      my + ey > 0.0f && my - ey < height && finite(mx) && finite(my);
    visible[g] = seen;
    radii[2 * g] = seen ? static_cast<int32_t>(std::max(std::ceil(ex), 1.0f)) : 0;
    radii[2 * g + 1] = seen ? static_cast<int32_t>(std::max(std::ceil(ey), 1.0f)) : 0;
    float* f = features + 4 * g;
    f[0] = f[1] = f[2] = 0.0f;
    f[3] = P.p[2];
    if (!seen) continue;
    order[count++] = g;
    const Direction D = direction(view, means + 3 * g);
    const int terms = sh_basis(degree, D.d, basis, nullptr);
    load_coefficients(terms, sh_dc, sh_rest, g, coefficients);
    sh_colour(terms, basis, coefficients, f);
    for (int c = 0; c < 3; ++c) f[c] = std::max(f[c], 0.0f);
  }
  std::stable_sort(order, order + count, [features](int64_t i, int64_t j) { return features[4 * i + 3] <
                                                                                   features[4 * j + 3]; });
  return count;
}

// Gradients of the loss with respect to means [n,3], quats [n,4], log_scales [n,3], sh_dc [n,1,3] and
// sh_rest [n,15,3] (written, not accumulated) from those of means2d, conics and features.
void preprocess_backward(int64_t n, int degree, int64_t width, int64_t height, const float* world_to_camera,
                         const float* K, const float* means, const float* quats, const float* log_scales,
                         const float* sh_dc, const float* sh_rest, const float* grad_means2d, const float* grad_conics,
                         const float* grad_features, float* grad_means, float* grad_quats, float* grad_log_scales,
                         float* grad_sh_dc, float* grad_sh_rest) {
  const View view(world_to_camera, K, width, height);
  std::fill(grad_means, grad_means + 3 * n, 0.0f);
  std::fill(grad_quats, grad_quats + 4 * n, 0.0f);
  std::fill(grad_log_scales, grad_log_scales + 3 * n, 0.0f);
  std::fill(grad_sh_dc, grad_sh_dc + 3 * n, 0.0f);
  std::fill(grad_sh_rest, grad_sh_rest + kShRest * 3 * n, 0.0f);
  float basis[16], basis_gradient[16][3], coefficients[16][3];
  for (int64_t g = 0; g < n; ++g) {
    const float* gm2 = grad_means2d + 2 * g;
    const float* gcon = grad_conics + 3 * g;
    const float* gf = grad_features + 4 * g;
    const bool projection_used = gm2[0] != 0.0f || gm2[1] != 0.0f || gcon[0] != 0.0f || gcon[1] != 0.0f ||
                                 gcon[2] != 0.0f || gf[3] != 0.0f;
    const bool colour_used = gf[0] != 0.0f || gf[1] != 0.0f || gf[2] != 0.0f;
    if (!projection_used && !colour_used) continue;  // culled Gaussians: every gradient is 0
    float* gmean = grad_means + 3 * g;

    if (colour_used) {
      const Direction D = direction(view, means + 3 * g);
      const int terms = sh_basis(degree, D.d, basis, basis_gradient);
      float rgb[3], g_rgb[3];
      load_coefficients(terms, sh_dc, sh_rest, g, coefficients);
      sh_colour(terms, basis, coefficients, rgb);
      for (int c = 0; c < 3; ++c) g_rgb[c] = rgb[c] >= 0.0f ? gf[c] : 0.0f;  // clamp_min(0) passes at 0
      float g_dir[3] = {0.0f, 0.0f, 0.0f};
      for (int k = 0; k < terms; ++k) {
        float* target = k == 0 ? grad_sh_dc + 3 * g : grad_sh_rest + (g * kShRest + k - 1) * 3;
        float weight = 0.0f;  // sum_c coefficient_kc dL/drgb_c
        for (int c = 0; c < 3; ++c) {
          target[c] = basis[k] * g_rgb[c];
          weight += coefficients[k][c] * g_rgb[c];
        }
        for (int j = 0; j < 3; ++j) g_dir[j] += weight * basis_gradient[k][j];
      }
      // d = x / |x|: dL/dx = (dL/dd - d (d . dL/dd)) / |x|
      const float along = g_dir[0] * D.d[0] + g_dir[1] * D.d[1] + g_dir[2] * D.d[2];
      for (int j = 0; j < 3; ++j) gmean[j] += (g_dir[j] - D.d[j] * along) / D.norm;
    }
    if (!projection_used) continue;

    const Projection P = project(view, means + 3 * g, quats + 4 * g, log_scales + 3 * g);
    // conics = Sigma2d^-1 = Q: dL/dSigma2d = -Q G Q with G the symmetric gradient [[ga, gb/2], [gb/2, gc]].
    const float qa = P.cyy / P.det, qb = -P.cxy / P.det, qc = P.cxx / P.det;
    const float ga = gcon[0], gb = 0.5f * gcon[1], gc = gcon[2];
    const float qg00 = qa * ga + qb * gb, qg01 = qa * gb + qb * gc, qg10 = qb * ga + qc * gb, qg11 = qb * gb + qc * gc;
    const float g_cxx = -(qg00 * qa + qg01 * qb);
    const float g_cxy = -2.0f * (qg00 * qb + qg01 * qc);  // cxy fills both off-diagonal entries
    const float g_cyy = -(qg10 * qb + qg11 * qc);
    // Sigma2d = T T^T + 0.3 I
    float gT[2][3];
    for (int j = 0; j < 3; ++j) {
      gT[0][j] = 2.0f * g_cxx * P.T[0][j] + g_cxy * P.T[1][j];
      gT[1][j] = 2.0f * g_cyy * P.T[1][j] + g_cxy * P.T[0][j];
    }
    // T = M (R S)
    float gM[2][3], gRS[3][3];
    for (int a = 0; a < 2; ++a)
      for (int i = 0; i < 3; ++i) gM[a][i] = gT[a][0] * P.RS[i][0] + gT[a][1] * P.RS[i][1] + gT[a][2] * P.RS[i][2];
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) gRS[i][j] = P.M[0][i] * gT[0][j] + P.M[1][i] * gT[1][j];
    // R S = Rq diag(exp(log_scale))
    float gR[3][3];
    for (int j = 0; j < 3; ++j) {
      float g_s = 0.0f;
      for (int i = 0; i < 3; ++i) {
        gR[i][j] = gRS[i][j] * P.s[j];
        g_s += gRS[i][j] * P.Rq[i][j];
      }
      grad_log_scales[3 * g + j] = g_s * P.s[j];
    }
    // Rq of the normalised quaternion, then the normalisation q / |q|
    const float w = P.q[0], x = P.q[1], y = P.q[2], z = P.q[3];
    const float gq[4] = {
        2.0f * (-z * gR[0][1] + y * gR[0][2] + z * gR[1][0] - x * gR[1][2] - y * gR[2][0] + x * gR[2][1]),
        2.0f * (y * gR[0][1] + z * gR[0][2] + y * gR[1][0] - 2.0f * x * gR[1][1] - w * gR[1][2] + z * gR[2][0] +
                w * gR[2][1] - 2.0f * x * gR[2][2]),
        2.0f * (-2.0f * y * gR[0][0] + x * gR[0][1] + w * gR[0][2] + x * gR[1][0] + z * gR[1][2] - w * gR[2][0] +
                z * gR[2][1] - 2.0f * y * gR[2][2]),
        2.0f * (-2.0f * z * gR[0][0] - w * gR[0][1] + x * gR[0][2] + w * gR[1][0] - 2.0f * z * gR[1][1] +
                y * gR[1][2] + x * gR[2][0] + y * gR[2][1])};
    const float along = gq[0] * w + gq[1] * x + gq[2] * y + gq[3] * z;
    for (int i = 0; i < 4; ++i) grad_quats[4 * g + i] = (gq[i] - P.q[i] * along) / P.q_norm;
    // M = J W with J = [[fx/tz, 0, -fx uc/tz], [0, fy/tz, -fy vc/tz]]
    float g_j00 = 0.0f, g_j02 = 0.0f, g_j11 = 0.0f, g_j12 = 0.0f;
    for (int j = 0; j < 3; ++j) {
      g_j00 += gM[0][j] * view.R[0][j];
      g_j02 += gM[0][j] * view.R[2][j];
      g_j11 += gM[1][j] * view.R[1][j];
      g_j12 += gM[1][j] * view.R[2][j];
    }
    const float tz = P.tz, tz2 = P.tz * P.tz;
    float g_tz = -g_j00 * view.fx / tz2 + g_j02 * view.fx * P.uc / tz2 - g_j11 * view.fy / tz2 +
                 g_j12 * view.fy * P.vc / tz2;
    float g_u = view.fx * gm2[0], g_v = view.fy * gm2[1];  // means2d = (fx u + cx, fy v + cy)
    if (P.u >= -view.lim_x && P.u <= view.lim_x) g_u += -g_j02 * view.fx / tz;  // the clamp passes inside
    if (P.v >= -view.lim_y && P.v <= view.lim_y) g_v += -g_j12 * view.fy / tz;
    // u = p_x / tz, v = p_y / tz; tz = p_z in front of the near plane (else a constant); depth = p_z
    float gp[3] = {g_u / tz, g_v / tz, gf[3]};
    g_tz += -g_u * P.p[0] / tz2 - g_v * P.p[1] / tz2;
    if (P.in_front) gp[2] += g_tz;
    for (int j = 0; j < 3; ++j) gmean[j] += view.R[0][j] * gp[0] + view.R[1][j] * gp[1] + view.R[2][j] * gp[2];
  }
}

}  // extern "C"
