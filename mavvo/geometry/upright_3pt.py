"""The 3-point solver (section 3.3), single and batched: null space, elimination template, quartic.

Conventions: see :mod:`mavvo.geometry.essential`.
"""

from __future__ import annotations

import numpy as np

from mavvo.geometry.essential import (
    as_bearing_pair,
    as_sample_batch,
    complex_entries,
    constraint_values,
    constraint_violation,
    epipolar_coefficients,
    essential_from_vector,
)
from mavvo.geometry.polyroots import quartic_real_roots

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
    return np.array([(np.cos(j * np.pi / 3), np.cos(k * np.pi / 4)) for j in range(4) for k in range(5) if (j + k) % 2 == 0])


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


# The batched 3-point works on component-major arrays: a (6, B) array holds one 6-vector per
# sample in its columns, so every arithmetic step is one numpy call over contiguous rows of B values.
# (Sample-major (B, 3, 6) arrays make numpy loop over tiny inner axes and cost several times more.)
# The template is filled by evaluating Q, D and T on the null space at the Padua points, e(a, b) =
# a N0 + b N1 + N2, and mapping those values to the row-mixed template in one product.
_PADUA_AB1 = np.column_stack([_padua_points(), np.ones(10)])  # (10 points, 3): (a, b, 1)
_TEMPLATE_FROM_VALUES = _template_map()
# Elimination runs without row exchanges; a sample whose pivot is below this fraction of the
# largest entry left in its column (where partial pivoting would exchange rows) is solved by LAPACK.
_MIN_PIVOT_RATIO = 1e-2


def null_space_batch(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal bases of the null spaces of B 3x6 systems, by Householder QR of their transposes.

    Args:
        A: (6 entries, 3 rows, B), component-major.

    Returns:
        basis (3, 6, B): N0, N1, N2 with e = a N0 + b N1 + N2 (the last three columns of Q), and
        |R_kk| (3, B): the size of each row after projecting out the rows before it (rank test).
    """
    X = A.copy()
    reflectors = []
    sizes = []
    for k in range(3):
        x = X[k:, k]  # (6 - k, B)
        size = np.sqrt((x * x).sum(axis=0))
        v = x.copy()
        v[0] += np.where(x[0] >= 0.0, size, -size)  # x + sign(x0) |x| e0: no cancellation
        vv = (v * v).sum(axis=0)
        beta = 2.0 / np.where(vv > 0.0, vv, 1.0)
        if k < 2:
            rest = X[k:, k + 1 :]
            rest -= v[:, None] * (beta * (v[:, None] * rest).sum(axis=0))
        reflectors.append((k, v, beta))
        sizes.append(size)
    Z = np.zeros((6, 3, A.shape[2]))
    Z[3, 0] = Z[4, 1] = Z[5, 2] = 1.0
    for k, v, beta in reversed(reflectors):  # Q = H0 H1 H2 applied to e3, e4, e5
        part = Z[k:]
        part -= v[:, None] * (beta * (v[:, None] * part).sum(axis=0))
    return np.ascontiguousarray(Z.transpose(1, 0, 2)), np.stack(sizes)


def elimination_template(basis: np.ndarray) -> np.ndarray:
    """The row-mixed template (6 equations, 10 monomials, B) of null spaces ``basis`` (3, 6, B)."""
    B = basis.shape[2]
    at_points = (_PADUA_AB1 @ basis.reshape(3, -1)).reshape(10, 6, B)  # e(a, b) at the Padua points
    q, d, t = constraint_values(*complex_entries(*at_points.transpose(1, 0, 2)))  # (10, B) each
    return (_TEMPLATE_FROM_VALUES @ np.stack([q, d, t.real, t.imag]).reshape(40, B)).reshape(6, 10, B)


def solve_template(C: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss elimination on the template C (6, 10, B), component-major, without row exchanges; C is
    overwritten.

    Returns rows <h> and <i> (4, B) each: ``ab + <h> . (b^3, b^2, b, 1) = 0`` and
    ``a + <i> . (b^3, b^2, b, 1) = 0``, the paper's (21) and (22); only these two rows are
    back-substituted. Without row exchanges the elimination is a few whole-batch operations; it
    also returns the indices of the samples with a small pivot (``_MIN_PIVOT_RATIO``), whose rows
    are to be taken from :func:`solve_template_pivoted` instead. Singular templates (degenerate
    data) give non-finite rows.
    """
    small_pivot = np.zeros(C.shape[2], dtype=bool)
    for k in range(5):
        column = C[k:, k]
        small_pivot |= np.abs(column[0]) < _MIN_PIVOT_RATIO * np.abs(column).max(axis=0)
        C[k + 1 :, k + 1 :] -= (column[1:] / column[0])[:, None] * C[k, k + 1 :]
    i = C[5, 6:] / C[5, 5]
    h = (C[4, 6:] - C[4, 5] * i) / C[4, 4]
    return h, i, np.nonzero(small_pivot)[0]


def solve_template_pivoted(C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows <h> and <i> of templates C (6, 10, n) by LAPACK with partial pivoting."""
    left, right = C[:, :6].transpose(2, 0, 1), C[:, 6:].transpose(2, 0, 1)
    try:
        X = np.linalg.solve(left, right)
    except np.linalg.LinAlgError:
        X = np.full(right.shape, np.nan)
        for n in range(len(X)):
            try:
                X[n] = np.linalg.solve(left[n], right[n])
            except np.linalg.LinAlgError:
                pass
    return X[:, 4].T, X[:, 5].T


def solve_upright_3pt_batch(F1: np.ndarray, F2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 3-point minimal solver for B samples in one vectorised call.

    Args:
        F1, F2: (B, 3, 3) level-frame bearings; sample b is the three pairs ``F1[b, i] <-> F2[b, i]``.

    Returns:
        E (B, 4, 3, 3) essential matrices with unit Frobenius norm (NaN in unused slots) and
        valid (B, 4) bool. Each sample has 0 to 4 valid solutions.
    """
    F1 = as_sample_batch("F1", F1)
    F2 = as_sample_batch("F2", F2)
    if F1.shape != F2.shape:
        raise ValueError(f"F1 and F2: expected the same shape, got {F1.shape} and {F2.shape}")
    e, valid = _upright_3pt(F1, F2)
    E = essential_from_vector(e.T)  # (B, 4, 3, 3)
    E[~valid.T] = np.nan
    return E, valid.T


def _upright_3pt(X1: np.ndarray, X2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 3-point on validated unit bearings X1, X2, component-major (3 components, 3 points, B).

    Returns e (6, 4, B), component-major and scaled so that E has unit Frobenius norm, and
    valid (4, B).
    """
    with np.errstate(all="ignore"):
        A = epipolar_coefficients(X1, X2)  # (6 entries, 3 points, B)
        basis, sizes = null_space_batch(A)  # (3 basis vectors, 6 entries, B): e = a N0 + b N1 + N2
        full_rank = sizes.min(axis=0) > _MIN_ROW_RANK_RATIO * np.sqrt((A * A).sum(axis=0)).max(axis=0)

        template = elimination_template(basis)
        usable = full_rank & (np.abs(template).max(axis=(0, 1)) > _MIN_TEMPLATE_NORM)
        template[:, :, ~usable] = np.eye(6, 10)[:, :, None]  # solvable dummy; its solutions are discarded below

        h, i, redo = solve_template(template)  # (4, B) each
        if redo.size:
            h[:, redo], i[:, redo] = solve_template_pivoted(elimination_template(basis[:, :, redo]))
        del template  # 60 values per sample: not kept through the rest, for the batch's peak memory
        # <k> = <h> - b <i>  (23): a quartic in b; a from <i>  (22).
        b, valid = quartic_real_roots(np.stack([i[0], i[1] - h[0], i[2] - h[1], i[3] - h[2], -h[3]]), axis=0)  # (4 roots, B)
        a = -(((i[0] * b + i[1]) * b + i[2]) * b + i[3])
        e = a * basis[0][:, None] + b * basis[1][:, None] + basis[2][:, None]  # (6, 4, B)

        _use_sheet_solutions(e, valid, basis, usable)
        e = _unit_frobenius(e)
        valid &= usable
        valid &= np.isfinite(e).all(axis=0)
        valid &= _distinct_epipolar_planes(e, X1)
        valid &= constraint_violation(np.where(valid, e, 0.0)) < _MAX_CONSTRAINT_RESIDUAL
    return e, valid


def _unit_frobenius(e: np.ndarray) -> np.ndarray:
    """Component-major e (6, ...) scaled so that its E has unit Frobenius norm (E11 = E22, E12 = -E21 count twice)."""
    return e / np.sqrt(e[0] * e[0] + 2.0 * (e[1] * e[1] + e[2] * e[2]) + e[3] * e[3] + e[4] * e[4] + e[5] * e[5])


def _distinct_epipolar_planes(e: np.ndarray, X1: np.ndarray) -> np.ndarray:
    """(4, B) bool: under e (6, 4, B) the three points X1 (3, 3, B) do not share one epipolar plane.

    Three points on a line coplanar with the baseline (the paper's line parallel to it, or one
    crossing it) lie in one epipolar plane: then the true yaw fits with any translation in that
    plane, and a solver may return a member of that continuum. Its epipolar lines E f1 coincide.
    """
    x, y, z = X1[:, :, None]  # (3 points, 1, B) each
    e13, e21, e22, e23, e31, e32 = e
    lines = np.stack([e22 * x - e21 * y + e13 * z, e21 * x + e22 * y + e23 * z, e31 * x + e32 * y])  # (3, 3 points, 4, B)
    sq = (lines * lines).sum(axis=0)  # (3 points, 4, B)
    dots = (lines[:, :1] * lines[:, 1:]).sum(axis=0)  # line 0 against lines 1 and 2
    # sin^2 of the angle between two lines is (|u|^2 |v|^2 - (u.v)^2) / (|u|^2 |v|^2); zero lines count as coincident.
    norms = sq[0] * sq[1:]
    return np.any(norms - dots * dots > _MIN_EPIPOLAR_PLANE_ANGLE**2 * norms, axis=0)


def _use_sheet_solutions(e: np.ndarray, valid: np.ndarray, basis: np.ndarray, usable: np.ndarray) -> None:
    """Near motion along gravity, put each sheet's solution in place of the template's roots there.

    The true E of motion along gravity has E13 = E23 = E31 = E32 = 0, where the two sheets of
    upright essential matrices, (yaw, tz) and (yaw + pi, -tz), cross. The template loses rank there
    and the solution becomes a double root; near it the template's roots are ill-conditioned. Each
    sheet alone is regular, so each is solved from the null space's nearest vertical point
    (:func:`_near_vertical_solutions`). Template roots within ``_SHEET_COPY_DISTANCE`` of them are
    ill-conditioned copies and are dropped; the two results take the slots of the two candidates
    nearest to them (free slots first), and the second is dropped where it equals the first (exactly
    vertical motion).

    e (6, 4, B) and valid (4, B) are updated in place; basis (3, 6, B); usable (B,).
    """
    rows = np.nonzero(_maybe_near_vertical(basis) & usable)[0]
    if rows.size == 0:
        return
    near, sheets = _near_vertical_solutions(basis[:, :, rows])  # (n,), (6, 2, n)
    sheets = _unit_frobenius(sheets)
    ok = near & np.all(constraint_violation(sheets) < _MAX_CONSTRAINT_RESIDUAL, axis=0)
    rows, sheets = rows[ok], sheets[:, :, ok]
    candidates = e[:, :, rows] / np.sqrt((e[:, :, rows] ** 2).sum(axis=0))  # (6, 4, n)
    cosines = np.abs(np.einsum("ikn,ijn->jkn", candidates, sheets))  # (2 sheets, 4, n)
    closest = np.maximum(cosines[0], cosines[1])
    valid[:, rows] &= closest < 1.0 - 0.5 * _SHEET_COPY_DISTANCE**2  # ill-conditioned copies of them go
    slots = np.argsort(-np.where(valid[:, rows], closest, 2.0), axis=0)[:2]  # free slots first
    sign = np.where((sheets[:, 0] * sheets[:, 1]).sum(axis=0) < 0.0, -1.0, 1.0)
    gap = sheets[:, 0] - sign * sheets[:, 1]
    same = (gap * gap).sum(axis=0) < _SHEET_SAME_DISTANCE**2
    e[:, slots[0], rows] = sheets[:, 0]
    e[:, slots[1], rows] = sheets[:, 1]
    valid[slots[0], rows] = True
    valid[slots[1], rows] = ~same


def _maybe_near_vertical(basis: np.ndarray) -> np.ndarray:
    """(B,) bool, cheap and conservative: the null space, basis (3, 6, B), may pass within
    ``_NEAR_VERTICAL`` of E13 = E23 = E31 = E32 = 0 (its 4x3 restriction has a small singular value)."""
    V = basis[:, [0, 3, 4, 5]]
    G = (V[:, None] * V[None]).sum(axis=2)  # (3, 3, B) Gram matrix; det = product of squared singular values
    det = (
        G[0, 0] * (G[1, 1] * G[2, 2] - G[1, 2] * G[2, 1])
        - G[0, 1] * (G[1, 0] * G[2, 2] - G[1, 2] * G[2, 0])
        + G[0, 2] * (G[1, 0] * G[2, 1] - G[1, 1] * G[2, 0])
    )
    half_trace = 0.5 * (G[0, 0] + G[1, 1] + G[2, 2])
    return det <= (_NEAR_VERTICAL**2) * half_trace**2  # sigma_min^2 >= det / (trace/2)^2


def _near_vertical_solutions(basis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solutions near motion along gravity, one per sheet, iterated from the vertical point.

    Args:
        basis: (3, 6, n) orthonormal basis of each sample's null space.

    Returns:
        near (n,) bool: the null space passes within ``_NEAR_VERTICAL`` of E13 = E23 = E31 = E32 = 0
        and each sheet has an isolated solution there; e (6, 2, n): the solution on the sheet
        tz = +|alpha| and on tz = -|alpha| (columns where ``near`` is false are meaningless).

    On sheet s the upright E satisfy ``s u gamma + i beta = 0`` with u = alpha / |alpha|: two real
    equations in the two coordinates of the null space, regular where alpha != 0, unlike the
    det/trace system whose equations are all quadratic in (beta, gamma). With u held at its current
    value they are linear; u varies slowly (beta and gamma are small here), so re-solving with the
    updated u converges by a factor of about the distance to the vertical point per step. Solutions
    farther than ``_SHEET_RADIUS`` are left to the template, whose roots are well separated there.
    """
    # Right singular vectors of the null space's E13, E23, E31, E32 part: the last, c, points to the
    # nearest vertical point; the other two span a local chart e = (c + x v1 + y v2) @ basis.
    _, sv, vt = np.linalg.svd(basis[:, [0, 3, 4, 5]].transpose(2, 1, 0))  # (n, 4, 3)
    e0, e1, e2 = (np.einsum("nk,kin->in", vt[:, r], basis) for r in (2, 0, 1))  # (6, n) each
    (a0, b0, g0), (a1, b1, g1), (a2, b2, g2) = (complex_entries(*v) for v in (e0, e1, e2))
    ib0, ib1, ib2 = 1j * b0, 1j * b1, 1j * b2
    sheet = np.array([[1.0], [-1.0]])
    x = np.zeros((2, e0.shape[1]))
    y = np.zeros_like(x)
    for _ in range(_SHEET_STEPS):
        alpha = a0 + x * a1 + y * a2
        su = sheet * alpha / np.abs(alpha)
        # c1 x + c2 y + c0 = 0 in complex numbers: two real equations in x, y.
        c0, c1, c2 = su * g0 + ib0, su * g1 + ib1, su * g2 + ib2
        det = c1.real * c2.imag - c2.real * c1.imag
        x = (c2.real * c0.imag - c0.real * c2.imag) / det
        y = (c0.real * c1.imag - c1.real * c0.imag) / det
    # Isolated roots only: a pure rotation makes one sheet's equations vanish on a whole region.
    scale = (c1 * np.conj(c1)).real + (c2 * np.conj(c2)).real
    near = (sv[:, 2] < _NEAR_VERTICAL) & (sv[:, 1] > _NEAR_VERTICAL)
    near &= np.all((np.abs(det) > _MIN_ISOLATION * scale) & (x * x + y * y < _SHEET_RADIUS**2), axis=0)
    return near, e0[:, None] + x * e1[:, None] + y * e2[:, None]


def solve_upright_3pt(f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """The 3-point minimal solver (section 3.3) for one sample.

    Args:
        f1, f2: (3, 3) level-frame bearings, row i of f1 matching row i of f2.

    Returns:
        (k, 3, 3) essential matrices with unit Frobenius norm, 0 <= k <= 4.
    """
    a, b = as_bearing_pair(f1, f2, 3, exact_rows=3)
    e, valid = _upright_3pt(a.T[:, :, None], b.T[:, :, None])
    return essential_from_vector(e[:, valid[:, 0], 0].T)


