// GELU, exact erf form (docs/math.md §3): gelu(x) = x * Phi(x), Phi the standard normal CDF,
// computed as 0.5 * erfc(-x / sqrt(2)), never 0.5 * (1 + erf(x / sqrt(2))), which loses every
// digit for x <= -6 (Phi(-9) = 1e-19 < eps). NumPy has no erfc; std::erfc is a few ulp.
//     forward:  y  = x * Phi(x)
//     backward: dx = dy * (Phi(x) + x * phi(x)),   phi(x) = exp(-x^2 / 2) / sqrt(2 pi)
// Arrays are flat, any size, one dtype. Three evaluations:
//   float64:          scalar, std::erfc with its argument compensated (below);
//   float32, x < -3:  double lanes, Cody's erfc, rounded once (<= 0.5 ulp down to the underflow);
//   float32, x >= -3: float lanes, fitted polynomials, no division (<= 4 ulp; the bulk of any
//                     activation tensor, 1/5 the time of the double lanes).
// Test: tests/test_layers.py (torch, mpmath). Time against torch: pyvf bench accuracy --ops gelu.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>

#include "kernels.h"

#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#elif defined(__ARM_NEON)
#include <arm_neon.h>
#endif
#include "simd.h"
#include "threads.h"

namespace pyvf {

namespace {

// 1/sqrt(2) = kS_hi + kS_lo to ~2^-106; 2/sqrt(pi); 1/sqrt(2 pi)
constexpr double kS_hi = 0.70710678118654757;
constexpr double kS_lo = -4.8336466567264567e-17;
constexpr double k2_SqrtPi = 1.1283791670955126;
constexpr double kInvSqrt2Pi = 0.3989422804014327;

// Phi(x) and phi(x) in double, with the two roundings that the tail amplifies compensated:
// z = -x/sqrt(2) is carried as z + dz (fma), and erfc(z + dz) = erfc(z) - 2/sqrt(pi) e^(-z^2) dz;
// x^2 = h + l exactly (fma), and e^(-(h + l)/2) = e^(-h/2) (1 - l/2). Without these, for x ~ -37
// the relative error of Phi is x^2 * eps = 1400 ulp (the conditioning of erfc at its argument).
inline void normal_cdf_pdf(double x, double& cdf, double& pdf) {
    const double z = -x * kS_hi;
    const double dz = std::fma(-x, kS_hi, -z) - x * kS_lo;
    cdf = 0.5 * (std::erfc(z) - k2_SqrtPi * std::exp(-z * z) * dz);
    const double h = x * x;
    const double l = std::fma(x, x, -h);
    // e^(-h/2) underflows to 0 for h > 1490; past that (and where h overflows) pdf is 0
    pdf = h > 1500.0 ? 0.0 : kInvSqrt2Pi * std::exp(-0.5 * h) * (1.0 - 0.5 * l);
}

}  // namespace

// ---------------------------------------------------------------------------------------
// float32 below x = -3 (the float-lane path further down covers the rest): evaluated in double,
// W_double lanes at a time, and rounded once. erfc by W. J. Cody's rational Chebyshev
// approximations (Math. Comp. 23, 1969; the coefficients of his CALERF), one per range of
// z = |x| / sqrt(2):
//     z <= 0.46875:     erfc(z) = 1 - z P_a(z^2) / Q_b(z^2)
//     0.46875 < z <= 4: erfc(z) = exp(-z^2) P_c(z) / Q_d(z)
//     z > 4:            erfc(z) = exp(-z^2) (1/sqrt(pi) - w P_p(w) / Q_q(w)) / z,  w = 1 / z^2
// each about 1e-16 relative, and exp(-z^2) by the vectorised exp (the rounding of z^2 is 1e-14 at
// the float32 underflow): far below float32's ulp, so float32's correctly rounded value but for rare
// double-rounding ties. Where every lane of a vector lies in one range only that range is evaluated.

namespace {

constexpr double kA[5] = {3.16112374387056560e00, 1.13864154151050156e02, 3.77485237685302021e02,
                          3.20937758913846947e03, 1.85777706184603153e-1};
constexpr double kB[4] = {2.36012909523441209e01, 2.44024637934444173e02, 1.28261652607737228e03,
                          2.84423683343917062e03};
constexpr double kC[9] = {5.64188496988670089e-1, 8.88314979438837594e00, 6.61191906371416295e01,
                          2.98635138197400131e02, 8.81952221241769090e02, 1.71204761263407058e03,
                          2.05107837782607147e03, 1.23033935479799725e03, 2.15311535474403846e-8};
constexpr double kD[8] = {1.57449261107098347e01, 1.17693950891312499e02, 5.37181101862009858e02,
                          1.62138957456669019e03, 3.29079923573345963e03, 4.36261909014324716e03,
                          3.43936767414372164e03, 1.23033935480374942e03};
constexpr double kP[6] = {3.05326634961232344e-1, 3.60344899949804439e-1, 1.25781726111229246e-1,
                          1.60837851487422766e-2, 6.58749161529837803e-4, 1.63153871373020978e-2};
constexpr double kQ[5] = {2.56852019228982242e00, 1.87295284992346047e00, 5.27905102951428412e-1,
                          6.05183413124413191e-2, 2.33520497626869185e-3};
constexpr double kInvSqrtPi = 0.56418958354775628695;

using VD = Simd<double>::V;
constexpr int WD = Simd<double>::W;

// Phi(x) and phi(x) = exp(-x^2/2) / sqrt(2 pi) for W_double lanes (x finite).
inline void normal_cdf_pdf_vec(VD x, VD& cdf, VD& pdf) {
    const VD z = (x < 0.0 ? -x : x) * 0.70710678118654752440;  // |x| / sqrt 2
    const VD zz = z * z;
    const VD e = exp_vec(-zz);  // exp(-z^2) = exp(-x^2 / 2)
    pdf = e * kInvSqrt2Pi;
    bool lo = false, mid = false, hi = false;
    for (int l = 0; l < WD; ++l) {
        lo |= z[l] <= 0.46875;
        mid |= z[l] > 0.46875 && z[l] <= 4.0;
        hi |= z[l] > 4.0;
    }
    VD erfc = {};
    if (lo) {
        VD num = kA[4] * zz, den = zz;
        for (int i = 0; i < 3; ++i) {
            num = (num + kA[i]) * zz;
            den = (den + kB[i]) * zz;
        }
        const VD r = 1.0 - z * (num + kA[3]) / (den + kB[3]);
        erfc = z <= 0.46875 ? r : erfc;
    }
    if (mid) {
        VD num = kC[8] * z, den = z;
        for (int i = 0; i < 7; ++i) {
            num = (num + kC[i]) * z;
            den = (den + kD[i]) * z;
        }
        const VD r = e * ((num + kC[7]) / (den + kD[7]));
        erfc = (z > 0.46875) & (z <= 4.0) ? r : erfc;
    }
    if (hi) {
        const VD zs = z > 4.0 ? z : vset1<double>(5.0);  // keep the other lanes finite
        const VD w = 1.0 / (zs * zs);
        VD num = kP[5] * w, den = w;
        for (int i = 0; i < 4; ++i) {
            num = (num + kP[i]) * w;
            den = (den + kQ[i]) * w;
        }
        const VD r = e * ((kInvSqrtPi - w * (num + kP[4]) / (den + kQ[4])) / zs);
        erfc = z > 4.0 ? r : erfc;
    }
    cdf = x < 0.0 ? 0.5 * erfc : 1.0 - 0.5 * erfc;  // Phi(x) = erfc(-x / sqrt 2) / 2
}

}  // namespace

// ---------------------------------------------------------------------------------------
// float32, x >= -3: float lanes, no division, no table lookup. Coefficients by
// tools/gelu_coefficients.py (least squares on Chebyshev nodes against mpmath, each piece's
// centre m_k a float32 where G_k's constant term is exact):
//     |x| <= X0 = 0.6745 (Phi(-X0) = 1/4):  Phi(x) = 1/2 + x S(x^2)
//     a = |x| > X0:  Phi(-a) = exp(-a^2 / 2) G_k(a - m_k),  G_0 on [X0, 3], G_1 on [3, 6];
//                    Phi(x) = Phi(-a) for x < 0, 1 - Phi(-a) for x > 0; Phi = 1 past x = 6
//                    (1 - Phi(6) = 1e-9 < ulp(1) / 2)
// exp(-x^2 / 2) with x^2 = h + l exactly (Dekker: x split into its high and low 12 mantissa bits,
// every partial product exact, so no FMA is needed and contraction changes nothing), as
// exp(-h / 2) (1 - l / 2): without l the rounding of x^2 costs x^2 / 2 ulp (2.3 at x = -3).
// Rounding: the fits are within 3e-8 relative (0.5 ulp), exp_vec about 1 ulp, then a few
// products: gelu within 4 ulp over [-3, inf) (tests/test_layers.py, against mpmath on a dense
// grid); gelu' = Phi + x phi within 4 u (Phi + |x| phi) -- relative to the terms, since the sum
// cancels at its root x = -0.7518, where torch's float32 (and any float32 sum) loses as much.
// Below x = -3 (and for NaN) the vector takes the double path above, whose compensated tail
// keeps gelu within 0.5 ulp down to the underflow: a vector of N(0, 1) activations goes there
// with probability W * 0.13%.

namespace {

// S, degree 5 in x^2 on |x| <= 0.6744897501960817: max relative error 2.8e-08
constexpr float kGeluS[6] = {
    -8.582447663e-06f, 1.150012249e-04f, -1.187226851e-03f, 9.973546490e-03f,
    -6.649038196e-02f, 3.989422917e-01f};
// G_0, degree 11 in a - 1.837989091873169 on [0.6745, 3.0]: max relative error 7.9e-09
constexpr float kGeluG0[12] = {
    -1.960013805e-07f, 8.674021501e-07f, -2.991822612e-06f, 1.246338979e-05f,
    -5.093088839e-05f, 1.953908068e-04f, -7.149140001e-04f, 2.485263627e-03f,
    -8.142675273e-03f, 2.490743063e-02f, -7.020758837e-02f, 1.788556278e-01f};
// G_1, degree 8 in a - 4.500269889831543 on [3.0000, 6.0]: max relative error 4.8e-08
constexpr float kGeluG1[9] = {
    1.270711749e-07f, -7.520363283e-07f, 3.776668336e-06f, -2.155742004e-05f,
    1.206953821e-04f, -6.517854636e-04f, 3.415374085e-03f, -1.732515357e-02f,
    8.479871601e-02f};
constexpr float kGeluMid[2] = {
    1.837989092e+00f, 4.500269890e+00f};
constexpr float kGeluX0 = 0.6744897501960817f;
constexpr float kInvSqrt2PiF = 0.398942280f;

using VF = Simd<float>::V;
using IF = Simd<float>::I;
constexpr int WF = Simd<float>::W;

// Whether any lane of a float comparison's result (-1 where true, 0 where false) is true: one
// instruction where the target has one (a generic lane loop goes through memory).
inline bool any_lane(Simd<float>::I m) {
#if defined(__AVX512F__)
    __m512i v;
    std::memcpy(&v, &m, sizeof v);
    return _mm512_test_epi32_mask(v, v) != 0;
#elif defined(__AVX__)
    __m256 v;
    std::memcpy(&v, &m, sizeof v);
    return _mm256_movemask_ps(v) != 0;
#elif defined(__SSE2__)
    __m128 v;
    std::memcpy(&v, &m, sizeof v);
    return _mm_movemask_ps(v) != 0;
#elif defined(__ARM_NEON) && defined(__aarch64__)
    uint32x4_t v;
    std::memcpy(&v, &m, sizeof v);
    return vmaxvq_u32(v) != 0;
#else
    bool any = false;
    for (int i = 0; i < Simd<float>::W; ++i) any |= m[i] != 0;
    return any;
#endif
}

// Phi(x) and x phi(x) for float lanes, each x in [-3, inf]; false (outputs unset) if any lane
// is below -3 or NaN.
inline bool normal_cdf_xpdf_f(VF x, VF& cdf, VF& xpdf) {
    const VF a = x < 0.0f ? -x : x;
    if (any_lane(!(x >= -3.0f))) return false;
    const VF h = x * x;
    VF s = vset1<float>(kGeluS[0]);
    for (int i = 1; i < 6; ++i) s = s * h + kGeluS[i];
    const VF small = x * s + 0.5f;
    // x^2 - h, exactly: x = xh + xl, xh the sign, exponent and top 11 stored mantissa bits
    IF bits;
    std::memcpy(&bits, &x, sizeof bits);
    bits &= (int32_t)0xFFFFF000;
    VF xh;
    std::memcpy(&xh, &bits, sizeof xh);
    const VF xl = x - xh;
    const VF l = ((xh * xh - h) + 2.0f * xh * xl) + xl * xl;
    const VF e = exp_vec(-0.5f * h) * (1.0f - 0.5f * l);  // exp(-x^2 / 2); NaN where h = inf
    // G_k(a - m_k): G_0 for every lane, G_1 only where a vector has a lane past a = 3
    VF t = a - kGeluMid[0];
    VF g = vset1<float>(kGeluG0[0]);
    for (int i = 1; i < 12; ++i) g = g * t + kGeluG0[i];
    if (any_lane(a > 3.0f)) {
        t = (a < 6.0f ? a : vset1<float>(6.0f)) - kGeluMid[1];
        VF g1 = vset1<float>(kGeluG1[0]);
        for (int i = 1; i < 9; ++i) g1 = g1 * t + kGeluG1[i];
        g = a > 3.0f ? g1 : g;
    }
    const VF tail = e * g;  // Phi(-a)
    const auto far = a > 6.0f;
    cdf = a <= kGeluX0 ? small : x < 0.0f ? tail : far ? vset1<float>(1.0f) : 1.0f - tail;
    xpdf = far ? vset1<float>(0.0f) : x * (e * kInvSqrt2PiF);
    return true;
}

// Phi(x) and x phi(x) for float lanes by the double path (any x; NaN gives NaN).
inline void normal_cdf_xpdf_d(VF x, VF& cdf, VF& xpdf) {
    for (int half = 0; half < WF; half += WD) {
        VD xd;
        for (int l = 0; l < WD; ++l) xd[l] = x[half + l];
        VD c, p;
        normal_cdf_pdf_vec(xd, c, p);
        p *= xd;
        for (int l = 0; l < WD; ++l) {
            cdf[half + l] = (float)c[l];
            xpdf[half + l] = (float)p[l];
        }
    }
}

// f(i, m) on [i, i + m) for every block of WF floats of [0, n); the last one has m < WF.
template <typename F> inline void map_float(int64_t n, F f) {
#pragma omp parallel num_threads(num_threads()) if (parallel_work(n, 65537))
    {
#pragma omp for schedule(static) nowait
        for (int64_t i = 0; i < n; i += WF) f(i, std::min<int64_t>(WF, n - i));
    }
}

// the m <= WF floats at p as a vector, zero padded; and stored back
inline VF load_f(const float* p, int64_t m) {
    if (m == WF) return vload<float>(p);
    VF v = {};
    std::memcpy(&v, p, m * sizeof(float));
    return v;
}

inline void store_f(float* p, VF v, int64_t m) {
    if (m == WF) return vstore<float>(p, v);
    std::memcpy(p, &v, m * sizeof(float));
}

// out = gelu(x) (BWD false), or dy * gelu'(x) (BWD true)
template <bool BWD> void gelu_float(float* out, const float* dy, const float* x, int64_t n) {
    map_float(n, [&](int64_t i, int64_t m) {
        const VF xv = load_f(x + i, m);
        VF cdf, xpdf;
        if (!normal_cdf_xpdf_f(xv, cdf, xpdf)) normal_cdf_xpdf_d(xv, cdf, xpdf);
        store_f(out + i, BWD ? load_f(dy + i, m) * (cdf + xpdf) : xv * cdf, m);
    });
}

// float64: the scalar path, compensated as above.
template <bool BWD> void gelu_double(double* out, const double* dy, const double* x, int64_t n) {
#pragma omp parallel num_threads(num_threads()) if (parallel_work(n, 65537))
    {
#pragma omp for schedule(static) nowait
        for (int64_t i = 0; i < n; ++i) {
            double cdf, pdf;
            normal_cdf_pdf(x[i], cdf, pdf);
            out[i] = BWD ? dy[i] * (cdf + x[i] * pdf) : x[i] * cdf;
        }
    }
}

}  // namespace

template <> void gelu_forward<float>(float* y, const float* x, int64_t n) { gelu_float<false>(y, nullptr, x, n); }
template <> void gelu_backward<float>(float* dx, const float* dy, const float* x, int64_t n) {
    gelu_float<true>(dx, dy, x, n);
}
template <> void gelu_forward<double>(double* y, const double* x, int64_t n) { gelu_double<false>(y, nullptr, x, n); }
template <> void gelu_backward<double>(double* dx, const double* dy, const double* x, int64_t n) {
    gelu_double<true>(dx, dy, x, n);
}

}  // namespace pyvf
