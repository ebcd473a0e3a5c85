"""χ² and normal probabilities and quantiles, and small non-negative least squares, without scipy.

The consistency checks (:mod:`.consistency`) need a handful of scalars per evaluation: the
χ²(ν) quantile of the false-alarm probability, the normal quantile z_{α/2}, the trimmed-mean
correction F_{ν+2}(F_ν⁻¹(0.9)) and a two-unknown non-negative line fit. Importing
``scipy.stats`` for them cost 0.8–1.1 s of every ``pmdsim evaluate`` (issue 25); the routines
here need only :mod:`math`, :mod:`statistics` and :mod:`fractions` (evaluation layer, pure
Python, no kernels).

* χ²(ν) with integer ν ≥ 1 is the gamma distribution of shape a = ν/2 (integer or half-integer)
  at t = x/2. The regularised incomplete gamma P(a, t) is summed as its power series for
  t < a + 1 (Abramowitz & Stegun 6.5.29; Numerical Recipes ``gser``) and Q(a, t) = 1 − P as its
  finite sum otherwise (A&S 6.5.13 for integer a, with erfc for half-integer a: A&S 26.4.4/26.4.5),
  so the smaller of the two is never formed by cancellation: relative error ≲ 1e-14.
* Quantiles by Newton's method on log P or log Q (whichever is the smaller tail), safeguarded by
  bisection on a bracket, to a relative step of 4 ulp.
* The normal quantile is Wichura's AS 241 (``statistics.NormalDist.inv_cdf``), called on the
  smaller tail probability so that it keeps full relative precision there.
* :func:`nnls` solves min ‖A x − b‖₂, x ≥ 0 for a few unknowns exactly: it enumerates the
  active sets (Lawson & Hanson 1974, ch. 23: the solution is the least-squares solution on the
  passive set P with x_P > 0 and dual w_Z = A_Zᵀ(b − A x) ≤ 0 on the rest), each in exact
  rational arithmetic, and rounds the solution once (correctly rounded).
"""

from __future__ import annotations

import math
from fractions import Fraction
from itertools import combinations

import numpy as np

_EPS = 2.220446049250313e-16
#: Unknowns :func:`nnls` enumerates the active sets of (2**n subsets, each solved exactly).
NNLS_MAX_UNKNOWNS = 6


def _check_dof(dof) -> float:
    """The gamma shape a = ν/2 of χ²(ν) for integer ν ≥ 1 (ValueError otherwise)."""
    if int(dof) != dof or dof < 1:
        raise ValueError(f"degrees of freedom must be an integer >= 1, got {dof!r}")
    return 0.5 * int(dof)


def _prefix(a: float, t: float) -> float:
    """t^a·e^(−t)/Γ(a + 1) for a = k or k + ½ (k ≥ 0), t ≥ 0, as a product of exact factors
    e^(−t)·∏ t/j (j = 1 … a, or 3/2 … a after 2·√(t/π)); in log space where e^(−t) underflows."""
    if t == 0.0:
        return 0.0
    if t > 700.0:
        return math.exp(a * math.log(t) - t - math.lgamma(a + 1.0))
    v = math.exp(-t)
    j = 1.0
    if a != math.floor(a):
        v *= 2.0 * math.sqrt(t / math.pi)  # t^½/Γ(3/2)
        j = 1.5
    while j <= a:
        v *= t / j
        j += 1.0
    return v


def _gamma_q(a: float, t: float) -> float:
    """Q(a, t) for a = k or k + ½ (k ≥ 0), t > 0 finite, by its finite sum of positive terms:
    e^(−t)·Σ_{j<a} t^j/j! (integer a, A&S 6.5.13); erfc(√t) + e^(−t)·Σ_{j<a−½} t^(j+½)/Γ(j+3/2)
    (half-integer a, A&S 26.4.5). No cancellation for any t: relative error ≲ (a + t)·ε."""
    half = a != math.floor(a)
    j0 = 0.5 if half else 0.0  # the sum's terms are t^j·e^(−t)/Γ(j + 1), j = j0 … a − 1
    q = math.erfc(math.sqrt(t)) if half else 0.0
    if t > 700.0:  # e^(−t) underflows: each term in log space
        j = a - 1.0
        while j >= j0:
            q += math.exp(j * math.log(t) - t - math.lgamma(j + 1.0))
            j -= 1.0
        return q
    term = 2.0 * math.exp(-t) * math.sqrt(t / math.pi) if half else math.exp(-t)
    j = j0
    while j < a:
        q += term
        j += 1.0
        term *= t / j
    return q


def _gamma_pq(a: float, t: float) -> tuple[float, float]:
    """(P(a, t), Q(a, t)), the regularised lower and upper incomplete gamma functions for
    a = k or k + ½ (k ≥ 0, a > 0) and t ≥ 0, each accurate to ~1e-14 relative: Q by its finite
    sum (:func:`_gamma_q`), P by its power series below t = a + 1 (A&S 6.5.29, Numerical Recipes
    ``gser``: P = t^a e^(−t)/Γ(a+1)·Σ_n t^n/((a+1)…(a+n))), else as 1 − Q (then P > ½)."""
    if t <= 0.0:
        return 0.0, 1.0
    if math.isinf(t):
        return 1.0, 0.0
    q = _gamma_q(a, t)
    if t >= a + 1.0:
        return 1.0 - q, q
    term, total, n = 1.0, 1.0, 0
    while term > 0.5 * _EPS * total:  # terms decrease (t < a + 1)
        n += 1
        term *= t / (a + n)
        total += term
    return _prefix(a, t) * total, q


def chi2_cdf(x: float, dof: int) -> float:
    """P(χ²_ν ≤ x) for integer ν ≥ 1 (``scipy.stats.chi2.cdf``; A&S 26.4.19: P(ν/2, x/2)).

    Parameters
    ----------
    x : float
        The value (≤ 0 gives 0).
    dof : int
        Degrees of freedom ν ≥ 1.

    Returns
    -------
    float
    """
    return _gamma_pq(_check_dof(dof), 0.5 * float(x))[0]


def chi2_sf(x: float, dof: int) -> float:
    """P(χ²_ν > x) for integer ν ≥ 1 (``scipy.stats.chi2.sf``), without cancellation in the
    upper tail. Parameters as :func:`chi2_cdf`."""
    return _gamma_pq(_check_dof(dof), 0.5 * float(x))[1]


def _gamma_quantile(a: float, prob: float, upper: bool) -> float:
    """t with P(a, t) = prob (``upper`` False) or Q(a, t) = prob (True), 0 < prob ≤ ½ for the
    side asked; Newton on log P / log Q from the Wilson–Hilferty start, bisection-safeguarded."""
    lo, hi = 0.0, math.inf
    # Wilson–Hilferty (A&S 26.4.17) on ν = 2a, from the normal quantile of the tail given.
    z = -_normal_lower(prob) if upper else _normal_lower(prob)
    c = 1.0 / (9.0 * a)
    t = a * max(1.0 - c + z * math.sqrt(c), 0.05) ** 3
    if not t > 0.0:
        t = a
    log_target = math.log(prob)
    for _ in range(200):
        p, q = _gamma_pq(a, t)
        side = q if upper else p
        if side <= 0.0:  # far out in the tail: move by bisection towards the bracket
            g = -math.inf
        else:
            g = math.log(side) - log_target
        # P increases with t, Q decreases: keep [lo, hi] bracketing the root.
        if (g > 0.0) != upper:
            hi = t
        else:
            lo = t
        if g == 0.0:
            return t
        dens = _prefix(a, t) * a / t  # t^(a−1)e^(−t)/Γ(a)
        step = None
        if side > 0.0 and dens > 0.0:
            slope = (-dens if upper else dens) / side  # d log(side)/dt
            step = -g / slope
        new = t + step if step is not None and math.isfinite(step) else math.nan
        if not (lo < new < hi):
            new = 0.5 * (lo + hi) if math.isfinite(hi) else 2.0 * t + 1.0
        if abs(new - t) <= 4.0 * _EPS * new:
            return new
        if math.isfinite(hi) and hi - lo <= 4.0 * _EPS * hi:
            return 0.5 * (lo + hi)
        t = new
    return t


def _check_prob(p, name: str) -> float:
    p = float(p)
    if not (0.0 <= p <= 1.0):
        raise ValueError(f"{name} must be in [0, 1], got {p!r}")
    return p


def chi2_ppf(p: float, dof: int) -> float:
    """The χ²(ν) quantile x with P(χ²_ν ≤ x) = p (``scipy.stats.chi2.ppf``), integer ν ≥ 1.

    Parameters
    ----------
    p : float
        Probability in [0, 1] (0 → 0, 1 → inf).
    dof : int
        Degrees of freedom ν ≥ 1.

    Returns
    -------
    float
        Accurate to ~1e-14 relative; for p > ½ the upper tail 1 − p (exact) is solved for.
    """
    a, p = _check_dof(dof), _check_prob(p, "p")
    if p == 0.0:
        return 0.0
    if p == 1.0:
        return math.inf
    return 2.0 * (_gamma_quantile(a, p, upper=False) if p <= 0.5 else _gamma_quantile(a, 1.0 - p, upper=True))


def chi2_isf(q: float, dof: int) -> float:
    """The χ²(ν) quantile x with P(χ²_ν > x) = q (``scipy.stats.chi2.isf``), integer ν ≥ 1: full
    relative precision for small q (a false-alarm probability). Parameters as :func:`chi2_ppf`."""
    a, q = _check_dof(dof), _check_prob(q, "q")
    if q == 0.0:
        return math.inf
    if q == 1.0:
        return 0.0
    return 2.0 * (_gamma_quantile(a, q, upper=True) if q <= 0.5 else _gamma_quantile(a, 1.0 - q, upper=False))


def _normal_lower(p: float) -> float:
    """Φ⁻¹(p) for 0 < p < 1 (AS 241 via :class:`statistics.NormalDist`), on the smaller tail."""
    from statistics import NormalDist

    nd = NormalDist()
    return nd.inv_cdf(p) if p <= 0.5 else -nd.inv_cdf(1.0 - p)


def norm_isf(q: float) -> float:
    """The standard normal quantile z with P(Z > z) = q (``scipy.stats.norm.isf``).

    Parameters
    ----------
    q : float
        Upper-tail probability in [0, 1] (0 → inf, 1 → −inf).

    Returns
    -------
    float
        Wichura's AS 241 (relative error ~1e-16) on the smaller tail, so that z keeps full
        precision for q down to the smallest doubles.
    """
    q = _check_prob(q, "q")
    if q == 0.0:
        return math.inf
    if q == 1.0:
        return -math.inf
    return -_normal_lower(q)


def _solve_exact(cols: list[list[Fraction]], b: list[Fraction]) -> list[Fraction] | None:
    """The least-squares solution on the columns ``cols`` (normal equations, Gauss–Jordan in
    exact rationals), None if they are linearly dependent."""
    k = len(cols)
    m = [[sum((x * y for x, y in zip(ci, cj)), Fraction(0)) for cj in cols]
         + [sum((x * y for x, y in zip(ci, b)), Fraction(0))] for ci in cols]
    for c in range(k):
        piv = next((r for r in range(c, k) if m[r][c] != 0), None)
        if piv is None:
            return None
        m[c], m[piv] = m[piv], m[c]
        for r in range(k):
            if r != c and m[r][c] != 0:
                f = m[r][c] / m[c][c]
                m[r] = [x - f * y for x, y in zip(m[r], m[c])]
    return [m[r][k] / m[r][r] for r in range(k)]


def nnls(design, values) -> tuple[np.ndarray, float]:
    """min ‖A x − b‖₂ subject to x ≥ 0 (``scipy.optimize.nnls``) for a few unknowns, exactly.

    Every split of the unknowns into a passive set P and an active set Z (x_Z = 0) is tried,
    largest P first; the least-squares solution on P (exact rationals) is the answer when
    x_P > 0 and the dual w_Z = A_Zᵀ(b − A x) ≤ 0 (the Karush–Kuhn–Tucker conditions; Lawson &
    Hanson, *Solving Least Squares Problems*, 1974, ch. 23). For a design of full column rank the
    solution is unique and this returns it correctly rounded.

    Parameters
    ----------
    design : (m, n) array_like
        The design matrix A, finite, n ≤ :data:`NNLS_MAX_UNKNOWNS`.
    values : (m,) array_like
        The right-hand side b, finite.

    Returns
    -------
    x : (n,) numpy.ndarray
        The solution (float64).
    rnorm : float
        ‖A x − b‖₂ at the rounded solution.

    Raises
    ------
    ValueError
        If the shapes do not fit, n exceeds :data:`NNLS_MAX_UNKNOWNS`, or an entry is not finite.
    """
    a = np.asarray(design, dtype=np.float64)
    b = np.asarray(values, dtype=np.float64).reshape(-1)
    if a.ndim != 2 or a.shape[0] != b.size:
        raise ValueError(f"design of shape {a.shape} does not fit values of shape {b.shape}")
    n = a.shape[1]
    if n > NNLS_MAX_UNKNOWNS:
        raise ValueError(f"nnls enumerates active sets for at most {NNLS_MAX_UNKNOWNS} unknowns, got {n}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise ValueError("nnls needs finite design and values")
    cols = [[Fraction(float(v)) for v in a[:, j]] for j in range(n)]
    bq = [Fraction(float(v)) for v in b]
    best = [Fraction(0)] * n
    for size in range(n, 0, -1):
        found = None
        for passive in combinations(range(n), size):
            sol = _solve_exact([cols[j] for j in passive], bq)
            if sol is None or any(s <= 0 for s in sol):
                continue
            x = [Fraction(0)] * n
            for j, s in zip(passive, sol):
                x[j] = s
            r = [bi - sum((cols[j][i] * x[j] for j in passive), Fraction(0)) for i, bi in enumerate(bq)]
            if all(sum((c * ri for c, ri in zip(cols[j], r)), Fraction(0)) <= 0 for j in range(n) if j not in passive):
                found = x
                break
        if found is not None:
            best = found
            break
    x = np.array([float(v) for v in best], dtype=np.float64)
    return x, float(np.linalg.norm(a @ x - b))
