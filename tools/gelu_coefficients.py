"""Fit the float32 GELU kernel's polynomials (csrc/gelu.cpp) and print them as C++.

    python tools/gelu_coefficients.py

Least squares on Chebyshev nodes (near minimax) against mpmath at 30 digits, in float64, each
coefficient then rounded to float32; the printed maximum relative errors are of the float64
polynomial with the float32 coefficients, on a grid 30x denser than the fit's nodes:
    Phi(x) - 1/2 = x S(x^2),           |x| <= X0 (Phi(-X0) = 1/4: Phi >= 1/4 there)
    Phi(-a) = exp(-a^2 / 2) G_k(a - m_k),  a in piece k of [X0, 6], m_k a float32 near its midpoint
(exact_center).
Needs mpmath (installed with torch, the tests' oracle).
"""

import mpmath
import numpy as np

mpmath.mp.dps = 30
X0 = 0.6744897501960817  # Phi(-X0) = 1/4
S_DEGREE = 5
# (from, to, degree): the first covers |x| up to the double path's threshold (x = -3); the second
# only positive x, where 1 - Phi(x) < 1.4e-3 needs fewer digits
PIECES = [(X0, 3.0, 11), (3.0, 6.0, 8)]


def nodes(lo, hi, n):
    k = np.arange(n)
    return (lo + hi) / 2 + (hi - lo) / 2 * np.cos((2 * k + 1) * np.pi / (2 * n))


def s_true(t):  # (Phi(sqrt t) - 1/2) / sqrt t
    if t == 0:
        return 1 / mpmath.sqrt(2 * mpmath.pi)
    r = mpmath.sqrt(mpmath.mpf(t))
    return (mpmath.ncdf(r) - mpmath.mpf(1) / 2) / r


def g_true(a):  # Phi(-a) exp(a^2 / 2)
    a = mpmath.mpf(a)
    return mpmath.ncdf(-a) * mpmath.exp(a * a / 2)


def fit(f, lo, hi, degree, center=0.0):
    """float32 coefficients, highest power first, of the fit of f on [lo, hi] in t - center;
    and the max relative error of that polynomial on a dense grid."""
    x = nodes(lo, hi, 40 * (degree + 1))
    y = np.array([float(f(v)) for v in x])
    # rounded from the constant term up, each rounding's error absorbed by refitting the higher
    # powers (rounding all at once costs up to 2 ulp of the constant term alone)
    low = []
    for k in range(degree + 1):
        fixed = sum(ck * (x - center) ** i for i, ck in enumerate(low))
        c = np.polyfit(x - center, y - fixed, degree)[::-1]  # lowest power first
        low.append(float(np.float32(c[k])))
    c = np.array(low[::-1], np.float32)
    grid = np.linspace(lo, hi, 30 * x.size)
    truth = np.array([float(f(v)) for v in grid])
    return c, float(np.max(np.abs(np.polyval(c.astype(np.float64), grid - center) / truth - 1)))


def exact_center(f, lo, hi):
    """A float32 m near (lo + hi) / 2 where f(m) is within 1% of an ulp of a float32: the constant
    term of the fit in a - m is f(m), so its rounding, which no other coefficient can absorb
    (they all vanish at a = m), is then negligible."""
    best = None
    for k in range(4001):  # 0, +1, -1, +2, ... steps of 1e-5 of the piece
        step = (k + 1) // 2 * (1 if k % 2 else -1)
        m = float(np.float32((lo + hi) / 2 + step * 1e-5 * (hi - lo)))
        v = f(m)
        err = float(abs(mpmath.mpf(float(np.float32(float(v)))) - v) / np.spacing(np.float32(float(v))))
        if best is None or err < best[0]:
            best = (err, m)
        if err < 0.01:
            break
    return best[1]


def cpp(name, values, per_line=4):
    items = [f"{float(v):.9e}f" for v in values]
    lines = [", ".join(items[i:i + per_line]) for i in range(0, len(items), per_line)]
    return f"constexpr float {name}[{len(values)}] = {{\n    " + ",\n    ".join(lines) + "};"


def main():
    cS, eS = fit(s_true, 0.0, X0 * X0, S_DEGREE)
    print(f"// S, degree {S_DEGREE} in x^2 on |x| <= {X0}: max relative error {eS:.1e}")
    print(cpp("kGeluS", cS))
    rows, mids = [], []
    for k, (lo, hi, degree) in enumerate(PIECES):
        m = exact_center(g_true, lo, hi)
        c, e = fit(g_true, lo, hi, degree, center=m)
        rows.append(c)
        mids.append(m)
        print(f"// G_{k}, degree {degree} in a - {m} on [{lo:.4f}, {hi}]: max relative error {e:.1e}")
        print(cpp(f"kGeluG{k}", c))
    print(cpp("kGeluMid", mids))


if __name__ == "__main__":
    main()
