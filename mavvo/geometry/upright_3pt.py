"""The 3-point solver (section 3.3), single and batched: null space, elimination template, quartic.

One compiled kernel solves one sample (:func:`solve_sample`); the batch runs it per sample, also in
compiled code. Conventions: see :mod:`mavvo.geometry.essential`.
"""

from __future__ import annotations

import math

import numpy as np

from mavvo.geometry.essential import as_bearing_pair, as_sample_batch, essential_from_vector, unit_rows
from mavvo.geometry.polyroots import quartic_roots
from mavvo.geometry.small_linalg import symmetric_eigen
from mavvo.jit import kernel

# A solution violating the det/trace constraints by more than this (unit Frobenius norm) is not an
# essential matrix of the upright form: it comes from an ill-conditioned elimination, not the data.
_MAX_CONSTRAINT_RESIDUAL = 1e-7
# The 3x6 system counts as rank-deficient (repeated or degenerate points) below this relative size.
_MIN_ROW_RANK_RATIO = 1e-9
# The elimination template of a pure rotation or of a degenerate line vanishes identically.
_MIN_TEMPLATE_NORM = 1e-9
# Below this angle (rad) between the epipolar planes of the three points they count as one plane.
_MIN_EPIPOLAR_PLANE_ANGLE = 1e-3
# sigma_max below the isolation ratio hold on a continuum.
_NEAR_VERTICAL = 1e-3
_SHEET_STEPS = 5
_SHEET_RADIUS = 1e-2
_MIN_ISOLATION = 1e-6
# Template roots closer than the copy distance to either are ill-conditioned copies of them.
_SHEET_SAME_DISTANCE = 1e-8
_SHEET_COPY_DISTANCE = 1e-2

# --------------------------------------------------------------------------- 3-point

# Cubic monomials a^i b^j as (i, j), in the paper's elimination order: those with a first, (20)-(22).
_CUBIC = ((3, 0), (2, 1), (2, 0), (1, 2), (1, 1), (1, 0), (0, 3), (0, 2), (0, 1), (0, 0))


def _padua_points() -> np.ndarray:
    """The ten Padua points of degree 3 in [-1, 1]^2, (10, 2): cubics in (a, b) are interpolated
    there with a monomial Vandermonde matrix of condition number 11."""
    return np.array(
        [(np.cos(j * np.pi / 3), np.cos(k * np.pi / 4)) for j in range(4) for k in range(5) if (j + k) % 2 == 0]
    )


def _shift_map() -> np.ndarray:
    """(3, 10, 10): the coefficients of a quadratic q (over _CUBIC, cubic terms zero) to those of
    q*a, q*b and q*1."""
    index = {m: i for i, m in enumerate(_CUBIC)}
    out = np.zeros((3, len(_CUBIC), len(_CUBIC)))
    for i, (da, db) in enumerate(_CUBIC):
        if da + db <= 2:
            for k, (va, vb) in enumerate(((1, 0), (0, 1), (0, 0))):
                out[k, index[(da + va, db + vb)], i] = 1.0
    return out


def _template_map() -> np.ndarray:
    """(60, 40): the values of Q, D, Re T, Im T at the Padua points -> the template, row-mixed.

    The template's six cubics Q a, Q b, Q, D, Re T, Im T over the ten monomials come from the
    interpolated coefficients. Its rows are then mixed by a fixed orthogonal matrix, a row
    operation that leaves the elimination's result unchanged and removes the structural zeros
    (Q b and Q have no a^3) that would otherwise force row exchanges.
    """
    from_values = np.linalg.inv(np.array([[a**i * b**j for i, j in _CUBIC] for a, b in _padua_points()]))
    template = np.zeros((6, 10, 4, 10))  # (equation, monomial) per (kind of value, point)
    template[:3, :, 0] = _shift_map() @ from_values
    for kind in (1, 2, 3):
        template[2 + kind, :, kind] = from_values
    mix = np.linalg.qr(np.random.default_rng(1999).standard_normal((6, 6)))[0]
    return np.einsum("rs,smkp->rmkp", mix, template).reshape(60, 40)


# The template is filled by evaluating Q, D and T on the null space at the Padua points, e(a, b) =
# a N0 + b N1 + N2, and mapping those values to the row-mixed template in one product.
_PADUA = _padua_points()  # (10 points, 2): (a, b)
_TEMPLATE_FROM_VALUES = _template_map()  # (60, 40)


def solve_upright_3pt_batch(F1: np.ndarray, F2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 3-point minimal solver for B samples in one call.

    Args:
        F1, F2: (B, 3, 3) level-frame bearings; sample b is the three pairs ``F1[b, i] <-> F2[b, i]``.

    Returns:
        E (B, 4, 3, 3) essential matrices with unit Frobenius norm (NaN in unused slots) and
        valid (B, 4) bool. Each sample has 0 to 4 valid solutions.
    """
    X1 = as_sample_batch("F1", F1)
    X2 = as_sample_batch("F2", F2)
    if X1.shape != X2.shape:
        raise ValueError(f"F1 and F2: expected the same shape, got {np.shape(F1)} and {np.shape(F2)}")
    e, valid = solve_samples(X1, X2)
    E = essential_from_vector(e)  # (B, 4, 3, 3)
    E[~valid] = np.nan
    return E, valid


@kernel
def solve_samples(F1: np.ndarray, F2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`solve_sample` over unit bearings F1, F2 (B, 3, 3): e (B, 4, 6), valid (B, 4)."""
    B = F1.shape[0]
    e = np.full((B, 4, 6), np.nan)
    valid = np.zeros((B, 4), dtype=np.bool_)
    for b in range(B):
        solve_sample(F1[b], F2[b], e[b], valid[b])
    return e, valid


@kernel
def solve_sample(X1: np.ndarray, X2: np.ndarray, e: np.ndarray, valid: np.ndarray) -> None:
    """The 3-point on one sample of unit bearings X1, X2 (3 points, 3): writes e (4 slots, 6) scaled to
    unit Frobenius norm and valid (4,); invalid slots hold anything."""
    valid[:] = False
    A = np.empty((3, 6))
    for j in range(3):
        x, y, z = X1[j, 0], X1[j, 1], X1[j, 2]
        xp, yp, zp = X2[j, 0], X2[j, 1], X2[j, 2]
        A[j, 0], A[j, 1], A[j, 2] = xp * z, yp * x - xp * y, xp * x + yp * y  # the paper's row (11)
        A[j, 3], A[j, 4], A[j, 5] = yp * z, zp * x, zp * y
    basis = np.empty((3, 6))
    if not _null_space(A, basis):
        return  # repeated or degenerate points
    C = _TEMPLATE_FROM_VALUES @ _constraint_values_at_padua(basis)  # (60,)
    C = C.reshape(6, 10)
    biggest = 0.0
    for v in C.ravel():
        biggest = max(biggest, abs(v))
    if not biggest > _MIN_TEMPLATE_NORM:
        return  # a pure rotation or a degenerate line: the template vanishes
    hi = np.empty((2, 4))
    if not _eliminate(C, hi):
        return
    h, i = hi[0], hi[1]
    # <k> = <h> - b <i>  (23): a quartic in b; a from <i>  (22).
    quartic = np.array([i[0], i[1] - h[0], i[2] - h[1], i[3] - h[2], -h[3]])
    roots = np.empty(4)
    quartic_roots(quartic, 1e-10, roots, valid)
    for k in range(4):
        b = roots[k]
        a = -(((i[0] * b + i[1]) * b + i[2]) * b + i[3])
        for m in range(6):
            e[k, m] = a * basis[0, m] + b * basis[1, m] + basis[2, m]
    if _maybe_near_vertical(basis):
        _use_sheet_solutions(e, valid, basis)
    for k in range(4):
        if valid[k]:
            _unit_frobenius(e[k])
            valid[k] = (
                _is_finite(e[k])
                and _distinct_epipolar_planes(e[k], X1)
                and _constraint_violation(e[k]) < _MAX_CONSTRAINT_RESIDUAL
            )


@kernel
def _null_space(A: np.ndarray, basis: np.ndarray) -> bool:
    """Orthonormal basis (3, 6) of the null space of the 3x6 system A, by Householder QR of its
    transpose: e = a N0 + b N1 + N2 with the rows N0, N1, N2 written into ``basis`` (the last three
    columns of Q). False when a row is (nearly) a combination of the others (rank below 3)."""
    M = np.empty((6, 3))  # A^T
    largest_row = 0.0
    for j in range(3):
        size = 0.0
        for r in range(6):
            M[r, j] = A[j, r]
            size += A[j, r] * A[j, r]
        largest_row = max(largest_row, math.sqrt(size))
    vs = np.zeros((3, 6))
    betas = np.zeros(3)
    smallest = largest_row
    for k in range(3):
        size = 0.0
        for r in range(k, 6):
            size += M[r, k] * M[r, k]
        size = math.sqrt(size)
        smallest = min(smallest, size)  # |R_kk|: the row's size after projecting out the rows before it
        for r in range(k, 6):
            vs[k, r] = M[r, k]
        vs[k, k] += size if M[k, k] >= 0.0 else -size  # x + sign(x0) |x| e0: no cancellation
        vv = 0.0
        for r in range(k, 6):
            vv += vs[k, r] * vs[k, r]
        betas[k] = 2.0 / vv if vv > 0.0 else 0.0
        for c in range(k + 1, 3):
            dot = 0.0
            for r in range(k, 6):
                dot += vs[k, r] * M[r, c]
            for r in range(k, 6):
                M[r, c] -= betas[k] * dot * vs[k, r]
    for c in range(3):  # Q = H0 H1 H2 applied to e3, e4, e5
        for r in range(6):
            basis[c, r] = 1.0 if r == 3 + c else 0.0
        for k in range(2, -1, -1):
            dot = 0.0
            for r in range(k, 6):
                dot += vs[k, r] * basis[c, r]
            for r in range(k, 6):
                basis[c, r] -= betas[k] * dot * vs[k, r]
    return smallest > _MIN_ROW_RANK_RATIO * largest_row


@kernel
def _constraint_values_at_padua(basis: np.ndarray) -> np.ndarray:
    """(40,) Q, D, Re T, Im T (10 each) of e(a, b) = a N0 + b N1 + N2 at the ten Padua points."""
    out = np.empty(40)
    for p in range(10):
        a, b = _PADUA[p, 0], _PADUA[p, 1]
        # e(a, b) entry by entry: no temporary arrays per point
        q, d, tr, ti = _qdt_of(
            a * basis[0, 0] + b * basis[1, 0] + basis[2, 0],
            a * basis[0, 1] + b * basis[1, 1] + basis[2, 1],
            a * basis[0, 2] + b * basis[1, 2] + basis[2, 2],
            a * basis[0, 3] + b * basis[1, 3] + basis[2, 3],
            a * basis[0, 4] + b * basis[1, 4] + basis[2, 4],
            a * basis[0, 5] + b * basis[1, 5] + basis[2, 5],
        )
        out[p], out[10 + p], out[20 + p], out[30 + p] = q, d, tr, ti
    return out


@kernel
def _qdt(e: np.ndarray) -> tuple[float, float, float, float]:
    """Q, D, Re T, Im T of e (6,) (:mod:`mavvo.geometry.essential`), in real arithmetic."""
    return _qdt_of(e[0], e[1], e[2], e[3], e[4], e[5])


@kernel(inline=True)
def _qdt_of(
    e13: float, e21: float, e22: float, e23: float, e31: float, e32: float
) -> tuple[float, float, float, float]:
    """:func:`_qdt` of the entries of e."""
    br, ar, ai, bi, gr, gi = (
        e13,
        e22,
        e21,
        e23,
        e31,
        e32,
    )  # beta = E13 + i E23, alpha = E22 + i E21, gamma = E31 + i E32
    q = br * br + bi * bi - gr * gr - gi * gi
    pr, pi = ar * gr - ai * gi, ar * gi + ai * gr  # alpha gamma
    d = pr * br + pi * bi  # Re(alpha gamma conj(beta))
    b2r, b2i = br * br - bi * bi, 2.0 * br * bi
    g2r, g2i = gr * gr - gi * gi, 2.0 * gr * gi
    tr = b2r * ar + b2i * ai + ar * g2r - ai * g2i  # beta^2 conj(alpha) + alpha gamma^2
    ti = b2i * ar - b2r * ai + ar * g2i + ai * g2r
    return q, d, tr, ti


@kernel
def _constraint_violation(e: np.ndarray) -> float:
    """Largest of |Q|, |D|, |T| at e (6,), as given (no scaling)."""
    q, d, tr, ti = _qdt(e)
    return max(abs(q), abs(d), math.sqrt(tr * tr + ti * ti))


@kernel
def _eliminate(C: np.ndarray, hi: np.ndarray) -> bool:
    """Gauss elimination with partial pivoting on the template C (6, 10), overwritten: rows <h> and
    <i> (written into hi (2, 4)) with ``ab + <h> . (b^3, b^2, b, 1) = 0`` and
    ``a + <i> . (b^3, b^2, b, 1) = 0``, the paper's (21) and (22); only these two rows are
    back-substituted. False for a singular template."""
    for k in range(6):
        piv = k
        for r in range(k + 1, 6):
            if abs(C[r, k]) > abs(C[piv, k]):
                piv = r
        if not abs(C[piv, k]) > 0.0:
            return False
        if piv != k:
            for c in range(k, 10):
                C[k, c], C[piv, c] = C[piv, c], C[k, c]
        for r in range(k + 1, 6):
            f = C[r, k] / C[k, k]
            for c in range(k + 1, 10):
                C[r, c] -= f * C[k, c]
    for c in range(4):
        hi[1, c] = C[5, 6 + c] / C[5, 5]
        hi[0, c] = (C[4, 6 + c] - C[4, 5] * hi[1, c]) / C[4, 4]
    return True


@kernel
def _unit_frobenius(e: np.ndarray) -> None:
    """e (6,) scaled in place so that its E has unit Frobenius norm (E11 = E22, E12 = -E21 count twice)."""
    n = math.sqrt(e[0] * e[0] + 2.0 * (e[1] * e[1] + e[2] * e[2]) + e[3] * e[3] + e[4] * e[4] + e[5] * e[5])
    if n > 0.0:
        e /= n


@kernel
def _is_finite(e: np.ndarray) -> bool:
    for v in e:
        if not math.isfinite(v):
            return False
    return True


@kernel
def _distinct_epipolar_planes(e: np.ndarray, X1: np.ndarray) -> bool:
    """Under e (6,) the three points X1 (3, 3) do not share one epipolar plane.

    Three points on a line coplanar with the baseline (the paper's line parallel to it, or one
    crossing it) lie in one epipolar plane: then the true yaw fits with any translation in that
    plane, and a solver may return a member of that continuum. Its epipolar lines E f1 coincide.
    """
    e13, e21, e22, e23, e31, e32 = e[0], e[1], e[2], e[3], e[4], e[5]
    u0 = e22 * X1[0, 0] - e21 * X1[0, 1] + e13 * X1[0, 2]  # E f1 of the first point
    u1 = e21 * X1[0, 0] + e22 * X1[0, 1] + e23 * X1[0, 2]
    u2 = e31 * X1[0, 0] + e32 * X1[0, 1]
    sq0 = u0 * u0 + u1 * u1 + u2 * u2
    for j in (1, 2):
        x, y, z = X1[j, 0], X1[j, 1], X1[j, 2]
        v0, v1, v2 = e22 * x - e21 * y + e13 * z, e21 * x + e22 * y + e23 * z, e31 * x + e32 * y
        # sin^2 of the angle between two lines is (|u|^2 |v|^2 - (u.v)^2) / (|u|^2 |v|^2); zero lines count as coincident.
        norms = sq0 * (v0 * v0 + v1 * v1 + v2 * v2)
        dot = u0 * v0 + u1 * v1 + u2 * v2
        if norms - dot * dot > _MIN_EPIPOLAR_PLANE_ANGLE**2 * norms:
            return True
    return False


@kernel
def _maybe_near_vertical(basis: np.ndarray) -> bool:
    """Cheap and conservative: the null space, basis (3, 6), may pass within ``_NEAR_VERTICAL`` of
    E13 = E23 = E31 = E32 = 0 (its 4x3 restriction has a small singular value)."""
    G = np.zeros((3, 3))  # Gram matrix of the rows' E13, E23, E31, E32; det = product of squared singular values
    for r in range(3):
        for c in range(3):
            for m in (0, 3, 4, 5):
                G[r, c] += basis[r, m] * basis[c, m]
    det = (
        G[0, 0] * (G[1, 1] * G[2, 2] - G[1, 2] * G[2, 1])
        - G[0, 1] * (G[1, 0] * G[2, 2] - G[1, 2] * G[2, 0])
        + G[0, 2] * (G[1, 0] * G[2, 1] - G[1, 1] * G[2, 0])
    )
    half_trace = 0.5 * (G[0, 0] + G[1, 1] + G[2, 2])
    return det <= (_NEAR_VERTICAL**2) * half_trace**2  # sigma_min^2 >= det / (trace/2)^2


@kernel
def _use_sheet_solutions(e: np.ndarray, valid: np.ndarray, basis: np.ndarray) -> None:
    """Near motion along gravity, put each sheet's solution in place of the template's roots there.

    The true E of motion along gravity has E13 = E23 = E31 = E32 = 0, where the two sheets of
    upright essential matrices, (yaw, tz) and (yaw + pi, -tz), cross. The template loses rank there
    and the solution becomes a double root; near it the template's roots are ill-conditioned. Each
    sheet alone is regular, so each is solved from the null space's nearest vertical point
    (:func:`_near_vertical_solutions`). Template roots within ``_SHEET_COPY_DISTANCE`` of them are
    ill-conditioned copies and are dropped; the two results take the slots of the two candidates
    nearest to them (free slots first), and the second is dropped where it equals the first (exactly
    vertical motion).

    e (4, 6) and valid (4,) are updated in place; basis (3, 6).
    """
    sheets = np.empty((2, 6))
    if not _near_vertical_solutions(basis, sheets):
        return
    for s in range(2):
        _unit_frobenius(sheets[s])
        if not _constraint_violation(sheets[s]) < _MAX_CONSTRAINT_RESIDUAL:
            return
    # Free slots first, then the candidates nearest to the sheets' solutions: the two largest keys.
    first, second, key_first, key_second = -1, -1, -1.0, -1.0
    for k in range(4):
        norm = 0.0
        dots = np.zeros(2)
        for m in range(6):
            norm += e[k, m] * e[k, m]
            dots[0] += e[k, m] * sheets[0, m]
            dots[1] += e[k, m] * sheets[1, m]
        norm = math.sqrt(norm)
        closest = max(abs(dots[0]), abs(dots[1])) / norm if norm > 0.0 else 0.0
        valid[k] = valid[k] and closest < 1.0 - 0.5 * _SHEET_COPY_DISTANCE**2  # ill-conditioned copies of them go
        key = closest if valid[k] else 2.0
        if key > key_first:
            first, second, key_first, key_second = k, first, key, key_first
        elif key > key_second:
            second, key_second = k, key
    same = 0.0
    sign = 1.0 if np.sum(sheets[0] * sheets[1]) >= 0.0 else -1.0
    for m in range(6):
        same += (sheets[0, m] - sign * sheets[1, m]) ** 2
        e[first, m] = sheets[0, m]
        e[second, m] = sheets[1, m]
    valid[first] = True
    valid[second] = not same < _SHEET_SAME_DISTANCE**2


@kernel
def _near_vertical_solutions(basis: np.ndarray, sheets: np.ndarray) -> bool:
    """Solutions near motion along gravity, one per sheet, iterated from the vertical point.

    Args:
        basis: (3, 6) orthonormal basis of the sample's null space.
        sheets: (2, 6) written: the solution on the sheet tz = +|alpha| and on tz = -|alpha|.

    Returns whether the null space passes within ``_NEAR_VERTICAL`` of E13 = E23 = E31 = E32 = 0 and
    each sheet has an isolated solution there (``sheets`` is meaningless otherwise).

    On sheet s the upright E satisfy ``s u gamma + i beta = 0`` with u = alpha / |alpha|: two real
    equations in the two coordinates of the null space, regular where alpha != 0, unlike the
    det/trace system whose equations are all quadratic in (beta, gamma). With u held at its current
    value they are linear; u varies slowly (beta and gamma are small here), so re-solving with the
    updated u converges by a factor of about the distance to the vertical point per step. Solutions
    farther than ``_SHEET_RADIUS`` are left to the template, whose roots are well separated there.
    """
    # Right singular vectors of the null space's E13, E23, E31, E32 part: the last, c, points to the
    # nearest vertical point; the other two span a local chart e = (c + x v1 + y v2) @ basis.
    # (Eigenvectors of its 3x3 Gram matrix, eigenvalues the squared singular values, ascending.)
    G = np.zeros((3, 3))
    for r in range(3):
        for c in range(3):
            for m in (0, 3, 4, 5):
                G[r, c] += basis[r, m] * basis[c, m]
    w, vecs = symmetric_eigen(G)
    if not (w[0] < _NEAR_VERTICAL**2 and w[1] > _NEAR_VERTICAL**2):
        return False
    e0, e1, e2 = np.zeros(6), np.zeros(6), np.zeros(6)
    for m in range(6):
        for r in range(3):
            e0[m] += vecs[r, 0] * basis[r, m]
            e1[m] += vecs[r, 2] * basis[r, m]
            e2[m] += vecs[r, 1] * basis[r, m]
    # In real arithmetic (alpha = E22 + i E21, beta = E13 + i E23, gamma = E31 + i E32 of each e_k):
    # c_k = s u gamma_k + i beta_k with u = alpha / |alpha|.
    E = (e0, e1, e2)
    for s in range(2):
        sheet = 1.0 if s == 0 else -1.0
        x = y = 0.0
        det = scale = 0.0
        c = np.zeros((3, 2))  # c_0, c_1, c_2 as (real, imaginary)
        for _ in range(_SHEET_STEPS):
            ar = e0[2] + x * e1[2] + y * e2[2]
            ai = e0[1] + x * e1[1] + y * e2[1]
            size = math.sqrt(ar * ar + ai * ai)
            if size == 0.0:
                return False
            ur, ui = sheet * ar / size, sheet * ai / size
            for k in range(3):
                gr, gi = E[k][4], E[k][5]
                br, bi = E[k][0], E[k][3]
                c[k, 0] = ur * gr - ui * gi - bi  # Re(u gamma + i beta)
                c[k, 1] = ur * gi + ui * gr + br  # Im(u gamma + i beta)
            # c1 x + c2 y + c0 = 0 in complex numbers: two real equations in x, y.
            det = c[1, 0] * c[2, 1] - c[2, 0] * c[1, 1]
            if det == 0.0:
                return False
            x = (c[2, 0] * c[0, 1] - c[0, 0] * c[2, 1]) / det
            y = (c[0, 0] * c[1, 1] - c[1, 0] * c[0, 1]) / det
            scale = c[1, 0] ** 2 + c[1, 1] ** 2 + c[2, 0] ** 2 + c[2, 1] ** 2
        # Isolated roots only: a pure rotation makes one sheet's equations vanish on a whole region.
        if not (abs(det) > _MIN_ISOLATION * scale and x * x + y * y < _SHEET_RADIUS**2):
            return False
        sheets[s] = e0 + x * e1 + y * e2
    return True


def solve_upright_3pt(f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """The 3-point minimal solver (section 3.3) for one sample.

    Args:
        f1, f2: (3, 3) level-frame bearings, row i of f1 matching row i of f2.

    Returns:
        (k, 3, 3) essential matrices with unit Frobenius norm, 0 <= k <= 4.
    """
    a, b = np.ascontiguousarray(f1, dtype=float), np.ascontiguousarray(f2, dtype=float)
    if a.shape == (3, 3) and b.shape == (3, 3):
        # The rows scaled by the kernel as_sample_batch uses: a sample solves alone as in a batch.
        X = np.empty((2, 1, 3, 3))
        if unit_rows(a, X[0, 0]) == -1 and unit_rows(b, X[1, 0]) == -1:
            e, valid = solve_samples(X[0], X[1])
            return essential_from_vector(e[0, valid[0]])
    as_bearing_pair(f1, f2, 3, exact_rows=3)  # raises, naming what is wrong (the same kernel's verdict)
    raise AssertionError("unreachable: the input was valid")
