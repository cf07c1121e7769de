// GroupNorm (the codebook's Normalize: 32 groups, eps 1e-6, affine, docs/math.md §4), optionally fused
// with the swish that follows it in ResnetBlock (norm1, norm2) and before conv_out (norm_out);
// and swish alone. Forward and backward, float32 and float64.
//
// Shapes (conv.h, GNDims): x, y, dx (B, C, P) with P = Hi*Wi pixels, C order; gamma, beta,
// dgamma, dbeta (C,); stats (B, G, 3): per group (mean, r, rstd) as below. Group g of image b is the M = (C/G)*P contiguous numbers of
// channels g*C/G .. (g+1)*C/G - 1 (torch's grouping).
//
//   forward   mean = sum(x) / M in double, rounded to T; xc = x - mean, then xc -= r = (sum(xc) / M
//             in double, rounded): the rounded mean can miss by an ulp, which rstd up to
//             1/sqrt(eps) = 1000 would amplify on a constant group; var = sum(xc^2) / M in
//             double, rounded; rstd = 1 / sqrt(var + eps) in T (where var + eps overflows T,
//             1 / sqrt(sum(xc^2) / M + eps) in double, rounded: rstd_wide). xhat = xc * rstd,
//             y = xhat * gamma[c] + beta[c], and with swish z = y * sigmoid(y). xhat is never
//             stored: the backward recomputes it from x and (mean, r, rstd) by the same operations,
//             bitwise (an array fewer to allocate and keep: in a training step the fresh pages of
//             a stored xhat cost more than the forward's arithmetic).
//             A constant group gives xhat = 0 and y = beta exactly; a group of mean 1e4 and
//             spread 0.1 keeps its digits (x - mean is exact there). As pyvf/conv.py's NumPy
//             groupnorm_forward, with the sums in double instead of NumPy's pairwise T sums.
//   backward  (swish: g = dz * swish'(y), y recomputed from x as in the forward; else g = dy)
//             dgamma[c] = sum over b, pixels of g * xhat, dbeta[c] = sum of g (per image and
//             channel in double, then over images in order); dxhat = g * gamma[c];
//             dx = rstd * (dxhat - mean_g(dxhat) - xhat * mean_g(dxhat * xhat)), the means in
//             double. Outputs overwritten, never accumulated.
//   swish     sigmoid from z = exp(-|x|) in (0, 1]: sigmoid(|x|) = 1 / (1 + z), sigmoid(-|x|) =
//             z / (1 + z), each assigned by the sign of x (no overflow, and sigmoid(-x) never as
//             1 - sigmoid(x), which cancels). exp is simd.h's exp_vec (about 1 ulp) where -|x| is
//             above the smallest normal result, else std::exp (into the subnormals, as NumPy's).
//             swish(x) = x * sigmoid(x); swish'(x) = sigmoid(x) * (1 + x * sigmoid(-x)).
// Overflow: y (forward) and dx (backward) are checked finite by the task that wrote them, while
// they are in cache; the kernels return kConvNonFinite, which the bindings raise naming the output.
// Tasks: one per (image, group), or per block of elements for swish; every output element and
// every partial sum is computed by one task in one order: bitwise the same for any thread count.
//
// Test: pytest tests/test_conv.py (torch float64, mpmath on the hard cases, the NumPy functions of
// pyvf/conv.py, 1 vs 2 threads). Benchmark: pyvf bench codebook --quick (time per layer type).
#include <algorithm>
#include <cmath>
#include <cstring>
#include <new>
#include <vector>

#include "conv.h"
#include "simd.h"
#include "threads.h"

namespace pyvf {

namespace {

template <typename T> using V = typename Simd<T>::V;
using VD = Simd<double>::V;
constexpr int WD = Simd<double>::W;

// sum over i < n of the double values of elements i in double: WD lanes, 4 accumulators, lanes and
// accumulators added in a fixed order. fv(i, v) writes the values of elements i .. i + 4*WD into
// the 4 double vectors v (widen_to_double: whole T vectors, no lane-by-lane inserts); f(i) is
// element i's, for the last n % (4*WD).
template <typename FV, typename F> inline double dsum(int64_t n, FV fv, F f) {
    VD a0 = {}, a1 = {}, a2 = {}, a3 = {};
    int64_t i = 0;
    for (; i + 4 * WD <= n; i += 4 * WD) {
        VD v[4];
        fv(i, v);
        a0 += v[0];
        a1 += v[1];
        a2 += v[2];
        a3 += v[3];
    }
    double tail = 0;
    for (; i < n; ++i) tail += f(i);
    return hsum<double>((a0 + a1) + (a2 + a3)) + tail;
}

// fv of dsum for the values g(j) of T vectors at j = i, i + W, ...: the 4*WD elements from
// 4*WD / W of them, each widened.
template <typename T, typename G> inline auto widened(G g) {
    return [g](int64_t i, VD* v) {
        constexpr int W = Simd<T>::W, per = W / WD;  // double vectors per T vector
        for (int q = 0; q < 4 / per; ++q) widen_to_double<T>(g(i + q * W), v + q * per);
    };
}

// fv of dsum for the products g(j) * h(j) in double of T vectors g, h: each widened, then multiplied.
template <typename T, typename G, typename H> inline auto widened_product(G g, H h) {
    return [g, h](int64_t i, VD* v) {
        constexpr int W = Simd<T>::W, per = W / WD;
        for (int q = 0; q < 4 / per; ++q) {
            VD u[per], w[per];
            widen_to_double<T>(g(i + q * W), u);
            widen_to_double<T>(h(i + q * W), w);
            for (int l = 0; l < per; ++l) v[q * per + l] = u[l] * w[l];
        }
    };
}

// z = exp(-|x|) in (0, 1] of a vector, as the header says.
template <typename T> inline V<T> exp_neg_abs(V<T> x) {
    const V<T> a = x < T(0) ? x : -x;  // -|x| <= 0 (x = -0.0 gives +0.0 or -0.0: e^0 = 1 either way)
    return exp_vec_subnormal<T>(a);
}

// (sigmoid(x), sigmoid(-x)) of a vector, as the header says.
template <typename T> inline void sigmoids(V<T> x, V<T>& s, V<T>& sn) {
    const V<T> z = exp_neg_abs<T>(x);
    const V<T> one_z = T(1) + z;
    const V<T> sp = T(1) / one_z, sm = z / one_z;  // sigmoid(|x|), sigmoid(-|x|)
    s = x >= T(0) ? sp : sm;
    sn = x >= T(0) ? sm : sp;
}

// x * sigmoid(x) with the one division sigmoids' s needs: (x >= 0 ? 1 : z) / (1 + z), the same
// quotient lane by lane as sigmoids' (which divides twice and picks).
template <typename T> inline V<T> swish_vec(V<T> x) {
    const V<T> z = exp_neg_abs<T>(x);
    const V<T> one = vset1<T>(T(1));
    return x * ((x >= T(0) ? one : z) / (T(1) + z));
}

// d swish / dx = s + x * s * (1 - s) = s * (1 + x * sigmoid(-x))
template <typename T> inline V<T> swish_grad_vec(V<T> x) {
    V<T> s, sn;
    sigmoids<T>(x, s, sn);
    return s * (T(1) + x * sn);
}

// a tail of n < W elements through one zero-padded vector
template <typename T, typename F> inline void tail_apply(T* out, const T* in, int64_t n, F f) {
    constexpr int W = Simd<T>::W;
    T buf[W] = {};
    for (int64_t l = 0; l < n; ++l) buf[l] = in[l];
    const V<T> r = f(vload<T>(buf));
    for (int64_t l = 0; l < n; ++l) out[l] = r[l];
}

// elementwise passes below 2^16 elements (about 20 us) run on one thread (see conv.cpp's kParallelFlops)
inline bool worth_threads(int64_t n) { return parallel_work(n, 1 << 16); }

}  // namespace

// =========================================================================================
// swish

template <typename T> void swish_forward(T* y, const T* x, int64_t n) {
    constexpr int64_t W = Simd<T>::W, kBlock = 1 << 14;
    RegionEnd end;
#pragma omp parallel num_threads(num_threads()) if (worth_threads(n))
    {
#pragma omp for schedule(static) nowait
        for (int64_t b0 = 0; b0 < n; b0 += kBlock) {
            const int64_t e = std::min(n, b0 + kBlock);
            int64_t i = b0;
            for (; i + W <= e; i += W) vstore<T>(y + i, swish_vec<T>(vload<T>(x + i)));
            if (i < e) tail_apply<T>(y + i, x + i, e - i, swish_vec<T>);
        }
        end.arrive();
    }
}

template <typename T> void swish_backward(T* dx, const T* dy, const T* x, int64_t n) {
    constexpr int64_t W = Simd<T>::W, kBlock = 1 << 14;
    RegionEnd end;
#pragma omp parallel num_threads(num_threads()) if (worth_threads(n))
    {
#pragma omp for schedule(static) nowait
        for (int64_t b0 = 0; b0 < n; b0 += kBlock) {
            const int64_t e = std::min(n, b0 + kBlock);
            int64_t i = b0;
            for (; i + W <= e; i += W) vstore<T>(dx + i, vload<T>(dy + i) * swish_grad_vec<T>(vload<T>(x + i)));
            for (; i < e; ++i) {
                T g;
                tail_apply<T>(&g, x + i, 1, swish_grad_vec<T>);
                dx[i] = dy[i] * g;
            }
        }
        end.arrive();
    }
}

// =========================================================================================
// GroupNorm (+ swish)

// xhat of element i of group t: ((x - mean) - r) * rstd, stats[t] = (mean, r, rstd), the
// forward's exact operations, so the backward recomputes the forward's xhat bitwise.
template <typename T> inline T xhat_of(T x, const T* st) { return ((x - st[0]) - st[1]) * st[2]; }
template <typename T> inline V<T> xhat_of(V<T> x, const T* st) { return ((x - st[0]) - st[1]) * st[2]; }

// rstd = 1 / sqrt(sum(xc^2) / M + eps) in double, for a group whose variance (or variance + eps)
// overflows T: float32 spreads |x - mean| beyond ~1.8e19, whose rstd is still a float32 (that
// group was refused, its var rounded to inf). Where sum(xc^2) = ss overflowed double too
// (float64 beyond ~1e154), xc is first scaled by 2^-k, max |xc| < 2^k (exact).
template <typename T> double rstd_wide(const T* xg, int64_t M, T mean, T r, double ss, double eps) {
    if (std::isfinite(ss)) return 1.0 / std::sqrt(ss / (double)M + eps);
    double amax = 0;
    for (int64_t i = 0; i < M; ++i) amax = std::max(amax, std::fabs((double)((xg[i] - mean) - r)));
    if (!std::isfinite(amax)) return 0.0;  // xc itself overflowed: y is not finite (the kernel says so)
    int k;
    std::frexp(amax, &k);
    double s2 = 0;
    for (int64_t i = 0; i < M; ++i) {
        const double c = std::ldexp((double)((xg[i] - mean) - r), -k);
        s2 += c * c;
    }
    return std::ldexp(1.0 / std::sqrt(s2 / (double)M + std::ldexp(eps, -2 * k)), -k);
}

template <typename T>
int groupnorm_forward(T* y, T* stats, const T* x, const T* gamma, const T* beta, const GNDims& d, double eps,
                      bool swish) {
    constexpr int64_t W = Simd<T>::W;
    const int64_t cpg = d.C / d.G, M = cpg * d.P;
    const T teps = (T)eps;
    int nonfinite = 0;
    RegionEnd end;
#pragma omp parallel num_threads(num_threads()) if (worth_threads(d.B * d.C * d.P))
    {
#pragma omp for schedule(static) nowait
        for (int64_t t = 0; t < d.B * d.G; ++t) {
            const int64_t off = t * M;  // group (b, g) is x[off : off + M]
            const T* xg = x + off;
            T* st = stats + 3 * t;
            if (M == 0) {  // an empty group (no pixels, or no channels): nothing to normalise
                st[0] = T(0), st[1] = T(0), st[2] = T(1) / std::sqrt(teps);
                continue;
            }
            const T mean = (T)(dsum(M, widened<T>([&](int64_t i) { return vload<T>(xg + i); }),
                                    [&](int64_t i) { return (double)xg[i]; }) / (double)M);
            // xc = x - mean, recomputed in each pass (never stored: the backward recomputes it too)
            const T r = (T)(dsum(M, widened<T>([&](int64_t i) { return vload<T>(xg + i) - mean; }),
                                 [&](int64_t i) { return (double)(T)(xg[i] - mean); }) / (double)M);
            const auto xc2 = [&](int64_t i) { return (vload<T>(xg + i) - mean) - r; };  // T vector
            const double ss = dsum(M, widened_product<T>(xc2, xc2), [&](int64_t i) {
                const double c = (double)((T)(xg[i] - mean) - r);
                return c * c;
            });
            const T var = (T)(ss / (double)M);
            T rstd = T(1) / std::sqrt(var + teps);  // the published order, in T
            if (!(rstd > 0)) rstd = (T)rstd_wide(xg, M, mean, r, ss, eps);  // var + eps beyond T
            st[0] = mean, st[1] = r, st[2] = rstd;
            const int64_t c0 = (t % d.G) * cpg;
            for (int64_t c = 0; c < cpg; ++c) {
                const T* xc = xg + c * d.P;
                T* yc = y + off + c * d.P;
                const T ga = gamma[c0 + c], be = beta[c0 + c];
                int64_t i = 0;
                for (; i + W <= d.P; i += W) {
                    const V<T> yv = xhat_of<T>(vload<T>(xc + i), st) * ga + be;
                    vstore<T>(yc + i, swish ? swish_vec<T>(yv) : yv);
                }
                for (; i < d.P; ++i) {
                    const T yv = xhat_of<T>(xc[i], st) * ga + be;
                    if (swish)
                        tail_apply<T>(yc + i, &yv, 1, swish_vec<T>);
                    else
                        yc[i] = yv;
                }
                if (!finite_run(yc, d.P)) {  // checked while in cache (the binding raises naming y)
    #pragma omp atomic write
                    nonfinite = 1;
                }
            }
        }
        end.arrive();
    }
    return nonfinite ? kConvNonFinite : kConvOk;
}

template <typename T>
int groupnorm_backward(T* dx, T* dgamma, T* dbeta, const T* x, const T* stats, const T* gamma, const T* beta,
                       const T* dy, const GNDims& d, bool swish) {
    constexpr int64_t W = Simd<T>::W;
    const int64_t cpg = d.C / d.G, M = cpg * d.P;
    std::vector<double> pg, pb;  // per (image, channel) partial sums of dgamma, dbeta
    try {
        pg.resize(d.B * d.C);
        pb.resize(d.B * d.C);
    } catch (const std::bad_alloc&) {
        return kConvOutOfMemory;
    }
    int nonfinite = 0;
    RegionEnd end;
#pragma omp parallel num_threads(num_threads()) if (worth_threads(d.B * d.C * d.P))
    {
#pragma omp for schedule(static) nowait
        for (int64_t t = 0; t < d.B * d.G; ++t) {
            const int64_t off = t * M, b = t / d.G, c0 = (t % d.G) * cpg;
            const T* xg = x + off;
            const T* st = stats + 3 * t;
            T* dg = dx + off;  // holds dxhat until the last pass
            // forward was y = xhat * gamma[c] + beta[c] (then z = swish(y)): g = dL/dy
            for (int64_t c = 0; c < cpg; ++c) {
                const T* xc = xg + c * d.P;
                const T* dyc = dy + off + c * d.P;
                T* o = dg + c * d.P;
                const T ga = gamma[c0 + c], be = beta ? beta[c0 + c] : T(0);
                if (swish) {
                    int64_t i = 0;
                    for (; i + W <= d.P; i += W)
                        vstore<T>(o + i, vload<T>(dyc + i) *
                                             swish_grad_vec<T>(xhat_of<T>(vload<T>(xc + i), st) * ga + be));
                    for (; i < d.P; ++i) {
                        const T yv = xhat_of<T>(xc[i], st) * ga + be;
                        T gr;
                        tail_apply<T>(&gr, &yv, 1, swish_grad_vec<T>);
                        o[i] = dyc[i] * gr;
                    }
                } else {
                    std::copy(dyc, dyc + d.P, o);
                }
                const auto ov = [&](int64_t i) { return vload<T>(o + i); };
                const auto xv = [&](int64_t i) { return xhat_of<T>(vload<T>(xc + i), st); };
                pg[b * d.C + c0 + c] = dsum(d.P, widened_product<T>(ov, xv),
                                            [&](int64_t i) { return (double)o[i] * (double)xhat_of<T>(xc[i], st); });
                pb[b * d.C + c0 + c] = dsum(d.P, widened<T>(ov), [&](int64_t i) { return (double)o[i]; });
                for (int64_t i = 0; i < d.P; ++i) o[i] *= ga;  // dxhat = g * gamma[c]
            }
            // forward was xhat = (x - mean) * rstd, rstd = (mean((x - mean)^2) + eps)^(-1/2), so
            // dx = rstd * (dxhat - mean_g(dxhat) - xhat * mean_g(dxhat * xhat))
            const auto gv = [&](int64_t i) { return vload<T>(dg + i); };
            const auto xv = [&](int64_t i) { return xhat_of<T>(vload<T>(xg + i), st); };
            const T m1 = (T)(dsum(M, widened<T>(gv), [&](int64_t i) { return (double)dg[i]; }) / (double)M);
            const T m2 = (T)(dsum(M, widened_product<T>(gv, xv),
                                  [&](int64_t i) { return (double)dg[i] * (double)xhat_of<T>(xg[i], st); }) /
                             (double)M);
            const T rs = st[2];
            for (int64_t i = 0; i < M; ++i) dg[i] = rs * (dg[i] - m1 - xhat_of<T>(xg[i], st) * m2);
            if (!finite_run(dg, M)) {  // checked while in cache (the binding raises naming dx)
#pragma omp atomic write
                nonfinite = 1;
            }
        }
        end.arrive();
    }
    // the partial sums over images, in image order, after the region: B*C additions (8 Ki for a
    // batch of 16 images of 512 channels, a few us) cost less than the barrier they would need in it
    for (int64_t c = 0; c < d.C; ++c) {
        double sg = 0, sb = 0;
        for (int64_t b = 0; b < d.B; ++b) {
            sg += pg[b * d.C + c];
            sb += pb[b * d.C + c];
        }
        dgamma[c] = (T)sg;
        dbeta[c] = (T)sb;
    }
    return nonfinite ? kConvNonFinite : kConvOk;
}

template void swish_forward<float>(float*, const float*, int64_t);
template void swish_forward<double>(double*, const double*, int64_t);
template void swish_backward<float>(float*, const float*, const float*, int64_t);
template void swish_backward<double>(double*, const double*, const double*, int64_t);
template int groupnorm_forward<float>(float*, float*, const float*, const float*, const float*, const GNDims&,
                                      double, bool);
template int groupnorm_forward<double>(double*, double*, const double*, const double*, const double*, const GNDims&,
                                       double, bool);
template int groupnorm_backward<float>(float*, float*, float*, const float*, const float*, const float*,
                                       const float*, const float*, const GNDims&, bool);
template int groupnorm_backward<double>(double*, double*, double*, const double*, const double*, const double*,
                                        const double*, const double*, const GNDims&, bool);

}  // namespace pyvf
