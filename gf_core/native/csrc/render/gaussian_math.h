// Per-Gaussian and per-pixel math of the splatting renderer, with hand-written derivatives.
// Shared by the CPU backend (render_cpu.cpp) and a CUDA backend: every function is GF_HD
// (__host__ __device__ under nvcc) and uses no STL. The math mirrors gf_core/render/reference.py
// line by line; the constants must equal gf_core/render/constants.py (a test checks).
//
// Paper: GaussFluids Sec. 3.1, Eq. (3) (front-to-back compositing of Gaussian particles);
// EWA splatting (Zwicker et al. 2001) and 3D Gaussian Splatting (Kerbl et al. 2023).
#pragma once
#include <cmath>

#ifdef __CUDACC__
#define GF_HD __host__ __device__ inline
#else
#define GF_HD inline
#endif

namespace gf {

constexpr double kLowPass = 0.3;
constexpr double kAlphaMax = 0.99;
constexpr double kTransmittanceMin = 1e-4;
constexpr double kFrustumSlack = 1.3;

constexpr double kShC0 = 0.28209479177387814;
constexpr double kShC1 = 0.4886025119029199;
// (scalars, not arrays: namespace-scope constexpr arrays are not visible in CUDA device code)
constexpr double kShC2_0 = 1.0925484305920792, kShC2_1 = -1.0925484305920792, kShC2_2 = 0.31539156525252005,
                 kShC2_3 = -1.0925484305920792, kShC2_4 = 0.5462742152960396;
constexpr double kShC3_0 = -0.5900435899266435, kShC3_1 = 2.890611442640554, kShC3_2 = -0.4570457994644658,
                 kShC3_3 = 0.3731763325901154, kShC3_4 = -0.4570457994644658, kShC3_5 = 1.445305721320277,
                 kShC3_6 = -0.5900435899266435;

// Camera: world-to-camera rotation (row-major) and translation, intrinsics, image size.
struct Cam {
  double R[9];
  double t[3];
  double fx, fy, cx, cy;
  double campos[3];  // -R^T t
  int width, height;
  double near;
};

// ---- quaternion (w, x, y, z) -> rotation ------------------------------------------------------
GF_HD double quat_normalise(const double q_in[4], double q[4]) {
  double n2 = q_in[0] * q_in[0] + q_in[1] * q_in[1] + q_in[2] * q_in[2] + q_in[3] * q_in[3];
  double inv = 1.0 / sqrt(n2 > 1e-24 ? n2 : 1e-24);
  for (int i = 0; i < 4; ++i) q[i] = q_in[i] * inv;
  return n2 > 1e-24 ? inv : -inv;  // sign flags the clamped branch for the backward pass
}

GF_HD void quat_to_rotmat(const double q[4], double R[9]) {
  double w = q[0], x = q[1], y = q[2], z = q[3];
  R[0] = 1 - 2 * (y * y + z * z); R[1] = 2 * (x * y - w * z);     R[2] = 2 * (x * z + w * y);
  R[3] = 2 * (x * y + w * z);     R[4] = 1 - 2 * (x * x + z * z); R[5] = 2 * (y * z - w * x);
  R[6] = 2 * (x * z - w * y);     R[7] = 2 * (y * z + w * x);     R[8] = 1 - 2 * (x * x + y * y);
}

// dL/dq (unnormalised input) from dL/dR, given the normalised q and the value returned by
// quat_normalise.
GF_HD void quat_to_rotmat_vjp(const double q[4], double inv_signed, const double gR[9], double gq[4]) {
  double w = q[0], x = q[1], y = q[2], z = q[3];
  double gw = 2 * (-z * gR[1] + y * gR[2] + z * gR[3] - x * gR[5] - y * gR[6] + x * gR[7]);
  double gx = 2 * (y * gR[1] + z * gR[2] + y * gR[3] - 2 * x * gR[4] - w * gR[5] + z * gR[6] +
                   w * gR[7] - 2 * x * gR[8]);
  double gy = 2 * (-2 * y * gR[0] + x * gR[1] + w * gR[2] + x * gR[3] + z * gR[5] - w * gR[6] +
                   z * gR[7] - 2 * y * gR[8]);
  double gz = 2 * (-2 * z * gR[0] - w * gR[1] + x * gR[2] + w * gR[3] - 2 * z * gR[4] + y * gR[5] +
                   x * gR[6] + y * gR[7]);
  double g[4] = {gw, gx, gy, gz};
  if (inv_signed > 0) {  // q = q_in / |q_in|: project out the radial part
    double dot = g[0] * q[0] + g[1] * q[1] + g[2] * q[2] + g[3] * q[3];
    for (int i = 0; i < 4; ++i) gq[i] = (g[i] - q[i] * dot) * inv_signed;
  } else {  // |q_in| clamped: q = q_in * const
    for (int i = 0; i < 4; ++i) gq[i] = g[i] * (-inv_signed);
  }
}

// ---- spherical harmonics ------------------------------------------------------------------------
GF_HD int sh_count(int degree) { return (degree + 1) * (degree + 1); }

GF_HD void sh_basis(int degree, const double d[3], double Y[16]) {
  double x = d[0], y = d[1], z = d[2];
  Y[0] = kShC0;
  if (degree > 0) { Y[1] = -kShC1 * y; Y[2] = kShC1 * z; Y[3] = -kShC1 * x; }
  if (degree > 1) {
    double xx = x * x, yy = y * y, zz = z * z;
    Y[4] = kShC2_0 * x * y; Y[5] = kShC2_1 * y * z; Y[6] = kShC2_2 * (2 * zz - xx - yy);
    Y[7] = kShC2_3 * x * z; Y[8] = kShC2_4 * (xx - yy);
    if (degree > 2) {
      Y[9] = kShC3_0 * y * (3 * xx - yy);  Y[10] = kShC3_1 * x * y * z;
      Y[11] = kShC3_2 * y * (4 * zz - xx - yy); Y[12] = kShC3_3 * z * (2 * zz - 3 * xx - 3 * yy);
      Y[13] = kShC3_4 * x * (4 * zz - xx - yy); Y[14] = kShC3_5 * z * (xx - yy);
      Y[15] = kShC3_6 * x * (xx - 3 * yy);
    }
  }
}

// gd = sum_k gY[k] * grad(Y_k)(d)
GF_HD void sh_basis_vjp(int degree, const double d[3], const double gY[16], double gd[3]) {
  double x = d[0], y = d[1], z = d[2];
  gd[0] = gd[1] = gd[2] = 0;
  if (degree > 0) { gd[1] += -kShC1 * gY[1]; gd[2] += kShC1 * gY[2]; gd[0] += -kShC1 * gY[3]; }
  if (degree > 1) {
    double xx = x * x, yy = y * y, zz = z * z;
    gd[0] += kShC2_0 * y * gY[4]; gd[1] += kShC2_0 * x * gY[4];
    gd[1] += kShC2_1 * z * gY[5]; gd[2] += kShC2_1 * y * gY[5];
    gd[0] += -2 * kShC2_2 * x * gY[6]; gd[1] += -2 * kShC2_2 * y * gY[6]; gd[2] += 4 * kShC2_2 * z * gY[6];
    gd[0] += kShC2_3 * z * gY[7]; gd[2] += kShC2_3 * x * gY[7];
    gd[0] += 2 * kShC2_4 * x * gY[8]; gd[1] += -2 * kShC2_4 * y * gY[8];
    if (degree > 2) {
      gd[0] += 6 * kShC3_0 * x * y * gY[9]; gd[1] += kShC3_0 * (3 * xx - 3 * yy) * gY[9];
      gd[0] += kShC3_1 * y * z * gY[10]; gd[1] += kShC3_1 * x * z * gY[10]; gd[2] += kShC3_1 * x * y * gY[10];
      gd[0] += -2 * kShC3_2 * x * y * gY[11]; gd[1] += kShC3_2 * (4 * zz - xx - 3 * yy) * gY[11];
      gd[2] += 8 * kShC3_2 * y * z * gY[11];
      gd[0] += -6 * kShC3_3 * x * z * gY[12]; gd[1] += -6 * kShC3_3 * y * z * gY[12];
      gd[2] += kShC3_3 * (6 * zz - 3 * xx - 3 * yy) * gY[12];
      gd[0] += kShC3_4 * (4 * zz - 3 * xx - yy) * gY[13]; gd[1] += -2 * kShC3_4 * x * y * gY[13];
      gd[2] += 8 * kShC3_4 * x * z * gY[13];
      gd[0] += 2 * kShC3_5 * x * z * gY[14]; gd[1] += -2 * kShC3_5 * y * z * gY[14];
      gd[2] += kShC3_5 * (xx - yy) * gY[14];
      gd[0] += kShC3_6 * (3 * xx - 3 * yy) * gY[15]; gd[1] += -6 * kShC3_6 * x * y * gY[15];
    }
  }
}

// ---- projection of one Gaussian ------------------------------------------------------------------
// Everything the forward computes that the backward needs again.
struct Proj {
  double t[3];          // camera-space mean
  double q[4];          // normalised quaternion
  double qinv;          // quat_normalise's return value
  double R[9];          // rotation of the Gaussian
  double Sigma[9];      // 3D covariance
  double rx, ry;        // clamped x/z, y/z
  bool rx_free, ry_free;
  double T[6];          // J * R_w2c (2x3)
  double a, b, c, det;  // 2D covariance (with low-pass) and its determinant
  double u, v;          // pixel position of the mean
  double dir[3], dir_norm;
  double Y[16];
};

// Returns false when the Gaussian is culled (behind the near plane or degenerate).
GF_HD bool project_core(const Cam& cam, const double p[3], const double s[3], const double q_in[4],
                        Proj& P) {
  for (int i = 0; i < 3; ++i)
    P.t[i] = cam.R[3 * i] * p[0] + cam.R[3 * i + 1] * p[1] + cam.R[3 * i + 2] * p[2] + cam.t[i];
  double z = P.t[2];
  if (!(z >= cam.near) || !isfinite(z)) return false;
  P.qinv = quat_normalise(q_in, P.q);
  quat_to_rotmat(P.q, P.R);
  double M[9];
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k) M[3 * r + k] = P.R[3 * r + k] * s[k];
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k)
      P.Sigma[3 * r + k] = M[3 * r] * M[3 * k] + M[3 * r + 1] * M[3 * k + 1] + M[3 * r + 2] * M[3 * k + 2];
  double lox = -kFrustumSlack * cam.cx / cam.fx, hix = kFrustumSlack * (cam.width - cam.cx) / cam.fx;
  double loy = -kFrustumSlack * cam.cy / cam.fy, hiy = kFrustumSlack * (cam.height - cam.cy) / cam.fy;
  double rx = P.t[0] / z, ry = P.t[1] / z;
  P.rx_free = rx >= lox && rx <= hix;
  P.ry_free = ry >= loy && ry <= hiy;
  P.rx = rx < lox ? lox : (rx > hix ? hix : rx);
  P.ry = ry < loy ? loy : (ry > hiy ? hiy : ry);
  double J[6] = {cam.fx / z, 0, -cam.fx * P.rx / z, 0, cam.fy / z, -cam.fy * P.ry / z};
  for (int r = 0; r < 2; ++r)
    for (int k = 0; k < 3; ++k)
      P.T[3 * r + k] = J[3 * r] * cam.R[k] + J[3 * r + 1] * cam.R[3 + k] + J[3 * r + 2] * cam.R[6 + k];
  double TS[6];
  for (int r = 0; r < 2; ++r)
    for (int k = 0; k < 3; ++k)
      TS[3 * r + k] = P.T[3 * r] * P.Sigma[k] + P.T[3 * r + 1] * P.Sigma[3 + k] + P.T[3 * r + 2] * P.Sigma[6 + k];
  P.a = TS[0] * P.T[0] + TS[1] * P.T[1] + TS[2] * P.T[2] + kLowPass;
  P.b = TS[0] * P.T[3] + TS[1] * P.T[4] + TS[2] * P.T[5];
  P.c = TS[3] * P.T[3] + TS[4] * P.T[4] + TS[5] * P.T[5] + kLowPass;
  P.det = P.a * P.c - P.b * P.b;
  if (!(P.det > 0) || !isfinite(P.det)) return false;
  P.u = cam.fx * P.t[0] / z + cam.cx;
  P.v = cam.fy * P.t[1] / z + cam.cy;
  double d[3] = {p[0] - cam.campos[0], p[1] - cam.campos[1], p[2] - cam.campos[2]};
  double n = sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
  P.dir_norm = n > 1e-12 ? n : 1e-12;
  for (int i = 0; i < 3; ++i) P.dir[i] = d[i] / P.dir_norm;
  return true;
}

// Splat radius in pixels (0: not drawn). Beyond it the splat's alpha is below min_alpha.
GF_HD int splat_radius(const Proj& P, double opacity, double min_alpha, int width, int height) {
  if (!(opacity > min_alpha)) return 0;
  double kappa = sqrt(2.0 * log(opacity / min_alpha));
  double h = 0.5 * (P.a - P.c);
  double lam = 0.5 * (P.a + P.c) + sqrt(h * h + P.b * P.b);
  double r = ceil(kappa * sqrt(lam));
  if (!(r > 0) || !isfinite(r)) return 0;
  if (P.u + r - 0.5 < 0 || P.u - r - 0.5 > width - 1 || P.v + r - 0.5 < 0 || P.v - r - 0.5 > height - 1)
    return 0;
  return r > 1073741824.0 ? 1073741824 : (int)r;
}

// Inclusive tile rectangle of a splat; returns false if it covers no tile.
GF_HD bool tile_rect(double u, double v, int radius, int tile, int tiles_x, int tiles_y, int rect[4]) {
  if (radius <= 0) return false;
  double r = radius;
  double x0 = floor((u - r - 0.5) / tile), x1 = floor((u + r - 0.5) / tile);
  double y0 = floor((v - r - 0.5) / tile), y1 = floor((v + r - 0.5) / tile);
  x0 = x0 < 0 ? 0 : (x0 > tiles_x - 1 ? tiles_x - 1 : x0);
  x1 = x1 < 0 ? 0 : (x1 > tiles_x - 1 ? tiles_x - 1 : x1);
  y0 = y0 < 0 ? 0 : (y0 > tiles_y - 1 ? tiles_y - 1 : y0);
  y1 = y1 < 0 ? 0 : (y1 > tiles_y - 1 ? tiles_y - 1 : y1);
  rect[0] = (int)x0; rect[1] = (int)y0; rect[2] = (int)x1; rect[3] = (int)y1;
  return rect[0] <= rect[2] && rect[1] <= rect[3];
}

// Backward of project_core (+ SH colour): from dL/d(u, v), dL/dconic, dL/ddepth and dL/dY
// (gY: SH basis gradient, already contracted with the coefficients) to dL/dp, dL/ds, dL/dq.
GF_HD void project_core_vjp(const Cam& cam, const double s[3], const Proj& P, const double g_uv[2],
                            const double g_conic[3], double g_depth, const double gY[16], int degree,
                            double gp[3], double gs[3], double gq[4]) {
  double z = P.t[2];
  // conic = inverse(cov):  dL/dcov = -Q G Q  with G the symmetric form of dL/dconic
  double A = P.c / P.det, B = -P.b / P.det, C = P.a / P.det;
  double G00 = g_conic[0], G01 = 0.5 * g_conic[1], G11 = g_conic[2];
  // QG = Q * G
  double QG00 = A * G00 + B * G01, QG01 = A * G01 + B * G11;
  double QG10 = B * G00 + C * G01, QG11 = B * G01 + C * G11;
  double M00 = -(QG00 * A + QG01 * B), M01 = -(QG00 * B + QG01 * C), M11 = -(QG10 * B + QG11 * C);
  double Msym[4] = {M00, M01, M01, M11};  // dL/dcov2d (symmetric form)
  // cov2d = T Sigma T^T:  dL/dSigma = T^T M T ; dL/dT = 2 M T Sigma
  double gSigma[9];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      double acc = 0;
      for (int r = 0; r < 2; ++r)
        for (int k = 0; k < 2; ++k) acc += P.T[3 * r + i] * Msym[2 * r + k] * P.T[3 * k + j];
      gSigma[3 * i + j] = acc;
    }
  double TS[6];
  for (int r = 0; r < 2; ++r)
    for (int k = 0; k < 3; ++k)
      TS[3 * r + k] = P.T[3 * r] * P.Sigma[k] + P.T[3 * r + 1] * P.Sigma[3 + k] + P.T[3 * r + 2] * P.Sigma[6 + k];
  double gT[6];
  for (int r = 0; r < 2; ++r)
    for (int k = 0; k < 3; ++k) gT[3 * r + k] = 2 * (Msym[2 * r] * TS[k] + Msym[2 * r + 1] * TS[3 + k]);
  // T = J R_w2c:  dL/dJ = dL/dT R_w2c^T (only J00, J02, J11, J12 are non-zero functions)
  double gJ[6];
  for (int r = 0; r < 2; ++r)
    for (int k = 0; k < 3; ++k)
      gJ[3 * r + k] = gT[3 * r] * cam.R[3 * k] + gT[3 * r + 1] * cam.R[3 * k + 1] + gT[3 * r + 2] * cam.R[3 * k + 2];
  double gt[3] = {0, 0, 0};
  double z2 = z * z;
  gt[2] += gJ[0] * (-cam.fx / z2) + gJ[2] * (cam.fx * P.rx / z2) + gJ[4] * (-cam.fy / z2) +
           gJ[5] * (cam.fy * P.ry / z2);
  if (P.rx_free) {  // rx = tx / z
    double g_rx = gJ[2] * (-cam.fx / z);
    gt[0] += g_rx / z;
    gt[2] += -g_rx * P.t[0] / z2;
  }
  if (P.ry_free) {
    double g_ry = gJ[5] * (-cam.fy / z);
    gt[1] += g_ry / z;
    gt[2] += -g_ry * P.t[1] / z2;
  }
  // mean in pixels and depth
  gt[0] += g_uv[0] * cam.fx / z;
  gt[1] += g_uv[1] * cam.fy / z;
  gt[2] += -g_uv[0] * cam.fx * P.t[0] / z2 - g_uv[1] * cam.fy * P.t[1] / z2 + g_depth;
  for (int i = 0; i < 3; ++i) gp[i] = cam.R[i] * gt[0] + cam.R[3 + i] * gt[1] + cam.R[6 + i] * gt[2];
  // Sigma = M M^T, M = R diag(s):  dL/dM = 2 gSigma M
  double Mm[9];
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k) Mm[3 * r + k] = P.R[3 * r + k] * s[k];
  double gM[9];
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k)
      gM[3 * r + k] = 2 * (gSigma[3 * r] * Mm[k] + gSigma[3 * r + 1] * Mm[3 + k] + gSigma[3 * r + 2] * Mm[6 + k]);
  double gR[9];
  for (int k = 0; k < 3; ++k) {
    gs[k] = gM[k] * P.R[k] + gM[3 + k] * P.R[3 + k] + gM[6 + k] * P.R[6 + k];
    for (int r = 0; r < 3; ++r) gR[3 * r + k] = gM[3 * r + k] * s[k];
  }
  quat_to_rotmat_vjp(P.q, P.qinv, gR, gq);
  // SH direction d = (p - campos) / |p - campos|
  if (degree > 0) {
    double gd[3];
    sh_basis_vjp(degree, P.dir, gY, gd);
    double dot = gd[0] * P.dir[0] + gd[1] * P.dir[1] + gd[2] * P.dir[2];
    for (int i = 0; i < 3; ++i) gp[i] += (gd[i] - P.dir[i] * dot) / P.dir_norm;
  }
}

// Inputs a projection can use: finite, scales >= 0, opacity in [0, 1]. A Gaussian that fails
// gets radius -1 (not drawn), which the binning counts so that the caller can say what was wrong.
GF_HD bool inputs_valid(const double p[3], const double s[3], const double q[4], double opacity) {
  for (int i = 0; i < 3; ++i)
    if (!isfinite(p[i]) || !isfinite(s[i]) || !(s[i] >= 0)) return false;
  for (int i = 0; i < 4; ++i)
    if (!isfinite(q[i])) return false;
  return isfinite(opacity) && opacity >= 0 && opacity <= 1;
}

// ---- per-pixel ----------------------------------------------------------------------------------
// power = -0.5 (A dx^2 + C dy^2) - B dx dy with (dx, dy) = mean - pixel centre
template <typename S>
GF_HD S splat_power(S A, S B, S C, S dx, S dy) {
  return S(-0.5) * (A * dx * dx + C * dy * dy) - B * dx * dy;
}

}  // namespace gf
