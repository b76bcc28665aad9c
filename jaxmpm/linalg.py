"""Small-matrix linear algebra with derivatives that stay finite.

Autodiff through ``jnp.linalg.svd``/``eigh`` divides by differences of eigenvalues and returns
NaN when two coincide, which is every particle at F_e = I. Here symmetric matrix functions
f(A) = Q f(Λ) Qᵀ carry a custom JVP (the Daleckii–Krein formula)

    d f(A)[dA] = Q (Γ ∘ (Qᵀ dA Q)) Qᵀ,   Γ_ij = (f(λ_i) - f(λ_j)) / (λ_i - λ_j),  Γ_ii = f'(λ_i),

with the divided differences written in a form that is accurate for equal and for close
eigenvalues, so the derivative is exact and finite everywhere. The eigen-decomposition itself
is never differentiated: a closed form in 2D, a fixed number of cyclic Jacobi sweeps in 3D
(both vectorise well, unlike a batched LAPACK call on the CPU).

Planes. Inside the time step a small matrix is held as a nested list of (N,) arrays, one per
component ("planes": ``a[i][j]`` is the (i, j) entry of every particle), and a vector as a list
of d arrays. Every operation is then a sum of elementwise products of contiguous arrays, which
XLA's CPU backend vectorises; building (N, d, d) arrays with ``stack`` and slicing them again
inside the step made it fuse interleaving copies into its kernels and recompute their inputs
in each (docs/performance.md). ``planes`` and ``unplanes`` convert at the boundary; the
array functions below (``mm``, ``sym_log``, ``sym_exp``) are these plane functions between
them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["eigh_sym", "sym_log", "sym_exp", "sym", "trace", "det", "mm", "mt", "safe_sqrt", "safe_div",
           "planes", "unplanes", "mm_planes", "det_planes", "sym_log_planes", "sym_exp_planes"]

#: Cyclic Jacobi sweeps of the 3×3 eigen-solve: four leave an off-diagonal of 6e-16 relative on
#: 80,000 float64 matrices with random, repeated, clustered (1e-8) and triple eigenvalues (three
#: leave 7e-6); six cost a 3D elastic step 7 % more for nothing.
JACOBI_SWEEPS = 4


def planes(a):
    """The planes [[a[..., i, j]]] of a batch of matrices (..., m, n).

    Split by ``unstack``, whose transpose is a ``stack``: indexing (``a[..., i, j]``) transposes
    into m·n padded (..., m, n) arrays summed element by element, every pad's operand computed for
    every element, which made the reverse pass of a step several times its forward."""
    return [list(jnp.unstack(row, axis=-1)) for row in jnp.unstack(a, axis=-2)]


def unplanes(p):
    """The array (..., m, n) of matrix planes [[...]]."""
    return jnp.stack([jnp.stack(row, -1) for row in p], -2)


def mm_planes(a, b):
    """a @ b for matrices held as planes."""
    return [[sum(a[i][k] * b[k][j] for k in range(len(b))) for j in range(len(b[0]))] for i in range(len(a))]


def det_planes(a):
    """Determinant of a 2×2 or 3×3 matrix held as planes (cofactors)."""
    if len(a) == 2:
        return a[0][0] * a[1][1] - a[0][1] * a[1][0]
    return (a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1])
            - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
            + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0]))


def mm(a, b):
    """a @ b for batches of small matrices, unrolled (XLA's batched dot is slow for 2×2/3×3)."""
    return unplanes(mm_planes(planes(a), planes(b)))


def mt(a):
    """Transpose of the last two axes."""
    return jnp.swapaxes(a, -1, -2)


def sym(a):
    """Symmetric part of a batch of square matrices."""
    return 0.5 * (a + jnp.swapaxes(a, -1, -2))


def trace(a):
    return jnp.trace(a, axis1=-2, axis2=-1)


def det(a):
    """Determinant of 2×2 or 3×3 matrices by cofactors (cheaper than LU for tiny batches)."""
    return det_planes(planes(a))


def safe_sqrt(x, eps=None):
    """sqrt(x) for x > eps, else 0, with a zero (not NaN/inf) derivative where x <= eps.

    ``eps`` defaults to the smallest normal number of x's type: a subnormal x may be flushed to
    zero inside a fused kernel (XLA's CPU backend does so in float32), and sqrt(0) would then
    make the derivative 1/(2 sqrt x) infinite (inf · 0 = NaN in forward mode)."""
    x = jnp.asarray(x)
    if eps is None:
        eps = jnp.finfo(jnp.result_type(x, float)).tiny
    ok = x > eps
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1.0)), 0.0)


def safe_div(num, den, fill=0.0):
    """num / den, or ``fill`` where |den| is below sqrt(smallest normal) (there den² would
    underflow and the derivative -num/den² become inf·0 = NaN); finite derivatives everywhere."""
    den = jnp.asarray(den)
    ok = jnp.abs(den) > jnp.sqrt(jnp.finfo(jnp.result_type(den, float)).tiny)
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), fill)


# ---------------------------------------------------------------------------------------------
# Eigen-decomposition of symmetric matrices (values only; never differentiated)


def _eigh2(a):
    a00, a01, a11 = a[..., 0, 0], 0.5 * (a[..., 0, 1] + a[..., 1, 0]), a[..., 1, 1]
    mean = 0.5 * (a00 + a11)
    half = 0.5 * (a00 - a11)
    radius = jnp.sqrt(half * half + a01 * a01)
    theta = 0.5 * jnp.arctan2(a01, half)
    c, s = jnp.cos(theta), jnp.sin(theta)
    lam = jnp.stack([mean + radius, mean - radius], axis=-1)
    q = jnp.stack([jnp.stack([c, -s], -1), jnp.stack([s, c], -1)], axis=-2)
    return lam, q


def _jacobi_rotation(a, v, p, r):
    """One Jacobi rotation zeroing a[p][r]; ``a`` (symmetric) and ``v`` are 3×3 nested lists
    of batched scalars (element-wise formulas keep the compiled graph small)."""
    apr = a[p][r]
    nonzero = apr != 0
    theta = (a[r][r] - a[p][p]) / (2.0 * jnp.where(nonzero, apr, 1.0))
    t = jnp.where(theta >= 0, 1.0, -1.0) / (jnp.abs(theta) + jnp.sqrt(theta * theta + 1.0))
    t = jnp.where(nonzero, t, 0.0)
    c = jax.lax.rsqrt(t * t + 1.0)
    s = t * c
    a = [row[:] for row in a]
    k = 3 - p - r  # the third index
    akp, akr = a[k][p], a[k][r]
    a[k][p] = a[p][k] = c * akp - s * akr
    a[k][r] = a[r][k] = s * akp + c * akr
    a[p][p] = a[p][p] - t * apr
    a[r][r] = a[r][r] + t * apr
    a[p][r] = a[r][p] = jnp.zeros_like(apr)
    v = [row[:] for row in v]
    for i in range(3):
        vip, vir = v[i][p], v[i][r]
        v[i][p] = c * vip - s * vir
        v[i][r] = s * vip + c * vir
    return a, v


def _eigh3_planes(a):
    """Eigenvalues (3 planes) and eigenvectors (columns of 3×3 planes) of a symmetric 3×3 matrix
    held as planes, by ``JACOBI_SWEEPS`` cyclic Jacobi sweeps unrolled on the planes."""
    rows = [[a[i][i] if i == j else 0.5 * (a[i][j] + a[j][i]) for j in range(3)] for i in range(3)]
    one, zero = jnp.ones_like(a[0][0]), jnp.zeros_like(a[0][0])
    v = [[one if i == j else zero for j in range(3)] for i in range(3)]
    for _ in range(JACOBI_SWEEPS):
        for p, r in ((0, 1), (0, 2), (1, 2)):
            rows, v = _jacobi_rotation(rows, v, p, r)
    return [rows[0][0], rows[1][1], rows[2][2]], v


def _eigh3(a):
    lam, q = _eigh3_planes(planes(a))
    return jnp.stack(lam, axis=-1), unplanes(q)


def eigh_sym(a):
    """Eigenvalues (..., d) and eigenvectors (columns of (..., d, d)) of symmetric 2×2/3×3 ``a``."""
    a = jax.lax.stop_gradient(a)
    if a.shape[-1] == 2:
        return _eigh2(a)
    if a.shape[-1] == 3:
        return _eigh3(a)
    raise ValueError(f"eigh_sym supports 2x2 and 3x3 matrices, got shape {a.shape}")


# ---------------------------------------------------------------------------------------------
# Symmetric matrix functions with a finite, exact derivative


def _apply_planes(q, values):
    """Q diag(values) Qᵀ, all planes."""
    n = len(q)
    return [[sum(q[i][k] * values[k] * q[j][k] for k in range(n)) for j in range(n)] for i in range(n)]


def _small_series(x, c1, c2):
    """1 + c1 x + c2 x^2, used where a divided difference would cancel catastrophically."""
    return 1.0 + x * (c1 + c2 * x)


def _log_divided_difference(li, lj):
    # (log li - log lj) / (li - lj) = log1p(x) / (x lj) with x = (li - lj) / lj.
    x = (li - lj) / lj
    small = jnp.abs(x) < 1e-3
    xs = jnp.where(small, 1.0, x)
    ratio = jnp.where(small, _small_series(x, -0.5, 1.0 / 3.0), jnp.log1p(xs) / xs)
    return ratio / lj


def _exp_divided_difference(li, lj):
    # (exp li - exp lj) / (li - lj) = exp(lj) expm1(x) / x with x = li - lj.
    x = li - lj
    small = jnp.abs(x) < 1e-3
    xs = jnp.where(small, 1.0, x)
    ratio = jnp.where(small, _small_series(x, 0.5, 1.0 / 6.0), jnp.expm1(xs) / xs)
    return ratio * jnp.exp(lj)


def _make_sym_fn(f, divided_difference, name, positive=False):
    """The 3×3 matrix function f on planes (``_eigh3_planes``), with its Daleckii–Krein JVP."""

    def decompose(a):
        lam, q = _eigh3_planes(jax.lax.stop_gradient(a))
        if positive:  # clamp eigenvalues away from 0 (docs/model.md §1); J <= 0 is flagged elsewhere
            lam = [jnp.maximum(x, jnp.finfo(x.dtype).tiny) for x in lam]
        return lam, q

    @jax.custom_jvp
    def fn(a):
        lam, q = decompose(a)
        return _apply_planes(q, [f(x) for x in lam])

    @fn.defjvp
    def fn_jvp(primals, tangents):
        (a,), (da,) = primals, tangents
        lam, q = decompose(a)
        out = _apply_planes(q, [f(x) for x in lam])
        qt = [list(col) for col in zip(*q)]
        sym_da = [[0.5 * (da[i][j] + da[j][i]) for j in range(3)] for i in range(3)]
        rotated = mm_planes(qt, mm_planes(sym_da, q))
        scaled = [[divided_difference(lam[i], lam[j]) * rotated[i][j] for j in range(3)] for i in range(3)]
        return out, mm_planes(q, mm_planes(scaled, qt))

    fn.__name__ = name
    return fn


_sym_log3 = _make_sym_fn(jnp.log, _log_divided_difference, "sym_log", positive=True)
_sym_exp3 = _make_sym_fn(jnp.exp, _exp_divided_difference, "sym_exp")


# In 2D, f(A) = α I + β (A - m I) with m = tr(A)/2, r² = ((a00 - a11)/2)² + a01², and α, β even
# functions of r: written in r² with a series near r = 0, plain autodiff is finite and exact,
# and no eigenvectors (no atan2/cos/sin) are needed. This is several times cheaper on the CPU.


def _sym_parts2(a):
    """Mean m, half-difference, off-diagonal and r² of a symmetric 2×2 matrix held as planes."""
    a00, a11 = a[0][0], a[1][1]
    a01 = 0.5 * (a[0][1] + a[1][0])
    m = 0.5 * (a00 + a11)
    half = 0.5 * (a00 - a11)
    return m, half, a01, half * half + a01 * a01


def _compose2(alpha, beta, half, a01):
    """The planes of α I + β (A − m I)."""
    off = beta * a01
    return [[alpha + beta * half, off], [off, alpha - beta * half]]


def _even_series(x2, f, c0, c1, c2, cut):
    """f(x) for an even function given as f(sqrt(x2)), with its Taylor series c0 + c1 x2 + c2 x2²
    below ``cut`` so that value and derivative are finite at x2 = 0."""
    small = x2 < cut
    x = jnp.sqrt(jnp.where(small, 1.0, x2))
    return jnp.where(small, c0 + x2 * (c1 + c2 * x2), f(x))


def _sym_log2(a):
    m, half, a01, r2 = _sym_parts2(a)
    dtype = m.dtype
    det_ = jnp.maximum(m * m - r2, jnp.finfo(dtype).tiny)  # product of the eigenvalues, clamped away from 0
    x2 = jnp.minimum(r2 / (m * m), 1.0 - jnp.finfo(dtype).eps)  # (r/m)² < 1 for SPD input
    # β = atanh(r/m)/r = (1/m) atanh(x)/x, x = r/m
    beta = _even_series(x2, lambda x: jnp.arctanh(x) / x, 1.0, 1.0 / 3.0, 1.0 / 5.0, 1e-4) / m
    return _compose2(0.5 * jnp.log(det_), beta, half, a01)


def _sym_exp2(a):
    m, half, a01, r2 = _sym_parts2(a)
    em = jnp.exp(m)
    alpha = em * _even_series(r2, jnp.cosh, 1.0, 0.5, 1.0 / 24.0, 1e-4)
    beta = em * _even_series(r2, lambda x: jnp.sinh(x) / x, 1.0, 1.0 / 6.0, 1.0 / 120.0, 1e-4)
    return _compose2(alpha, beta, half, a01)


def sym_log_planes(a):
    """``sym_log`` of a symmetric matrix held as planes (2D in closed form, 3D by ``sym_log``)."""
    return _sym_log2(a) if len(a) == 2 else _sym_log3(a)


def sym_exp_planes(a):
    """``sym_exp`` of a symmetric matrix held as planes (2D in closed form, 3D by ``sym_exp``)."""
    return _sym_exp2(a) if len(a) == 2 else _sym_exp3(a)


def sym_log(a):
    """Matrix logarithm of symmetric positive-definite 2×2/3×3 matrices (eigenvalues clamped
    away from 0), with finite derivatives everywhere."""
    return unplanes(sym_log_planes(planes(a)))


def sym_exp(a):
    """Matrix exponential of symmetric 2×2/3×3 matrices, with finite derivatives everywhere."""
    return unplanes(sym_exp_planes(planes(a)))
