"""Relative pose with known roll and pitch: the solvers of Fraundorfer, Tanskanen and Pollefeys (2010).

All functions take bearings in *level* frames (z along gravity, see :mod:`mavvo.frames`), points as
rows, and use the convention ``x_2 = R_2_1 @ x_1 + t_2_1``, ``E = [t_2_1]x @ R_2_1``,
``f2 @ E @ f1 = 0``. Between level frames ``R_2_1`` is a rotation about z, so E has the paper's
structure E33 = 0, E11 = E22, E12 = -E21 (equations 7-9) and is fixed by the six entries

    e = (E13, E21, E22, E23, E31, E32)                       (the paper's equation 12)

Each point pair gives one linear equation ``row @ e = 0`` (equation 11, :func:`epipolar_rows`).

Writing alpha = E22 + i E21, beta = E13 + i E23, gamma = E31 + i E32, the det (14) and trace (15)
constraints on such an E reduce to

    Q = |beta|^2 - |gamma|^2 = 0                               (trace, entries 13 23 31 32)
    D = Re(alpha gamma conj(beta)) = 0                         (det, and trace entry 33)
    T = beta^2 conj(alpha) + alpha gamma^2 = 0                 (trace, entries 11 12 21 22)

The paper's four trace equations of entries 13, 23, 31, 32 are Q times E13, E23, E31, E32; we use Q
times the monomials 1, a, b instead, which spans the same cubics in general and keeps full rank where
E13..E32 vanish together (motion along gravity). ``docs/geometry.md`` has the derivation and the
failure analysis behind every guard in this module.

Solvers return no solution on degenerate input rather than raising; they raise ``ValueError`` only
for malformed input (wrong shape, non-finite values, zero-length bearings, too few points).
"""

from __future__ import annotations

import numpy as np

from mavvo.frames import rot_z, skew
from mavvo.polyroots import cubic_real_roots, quartic_real_roots

__all__ = [
    "epipolar_rows",
    "essential_from_vector",
    "essential_to_vector",
    "alpha_beta_gamma",
    "upright_constraint_residual",
    "solve_upright_3pt",
    "solve_upright_3pt_batch",
    "solve_upright_4pt",
    "solve_upright_linear5pt",
    "upright_pose_from_essential",
    "solve_ground_2pt_batch",
    "ground_pose_from_homography",
    "as_bearing_pair",
]

# Row and column of each entry of e in E.
_E_ROW = np.array([0, 1, 1, 1, 2, 2])
_E_COL = np.array([2, 0, 1, 2, 0, 1])

# A candidate whose constraint residual (E scaled to unit Frobenius norm) exceeds this is not an
# essential matrix of the upright form: it comes from an ill-conditioned elimination, not the data.
_MAX_CONSTRAINT_RESIDUAL = 1e-7
# The 3x6 system counts as rank-deficient (repeated or degenerate points) below this relative size.
_MIN_ROW_RANK_RATIO = 1e-9
# The elimination template of a pure rotation or of a degenerate line vanishes identically.
_MIN_TEMPLATE_NORM = 1e-9
# Below this angle (rad) between the epipolar planes of the three points they count as one plane.
_MIN_EPIPOLAR_PLANE_ANGLE = 1e-3
# Where the null space passes within this distance of E13 = E23 = E31 = E32 = 0 (motion nearly
# along gravity) the two roots near the vertical point are solved sheet by sheet, with this many
# steps, if they lie within the radius; a sheet's equations whose 2x2 system has sigma_min /
# sigma_max below the isolation ratio hold on a continuum.
_NEAR_VERTICAL = 1e-3
_SHEET_STEPS = 5
_SHEET_RADIUS = 1e-2
_MIN_ISOLATION = 1e-6
# The two sheets' solutions closer than this (unit-norm e) are one: motion exactly along gravity.
# Template roots closer than the copy distance to either are ill-conditioned copies of them.
_SHEET_SAME_DISTANCE = 1e-8
_SHEET_COPY_DISTANCE = 1e-2
# The det cubic of the 4-point, or the 5th singular value of the linear 5-point, vanishes on a
# horizontal plane (rank 4). Relative to the largest coefficient / singular value.
_MIN_DEGENERACY_RATIO = 1e-9


# --------------------------------------------------------------------------- input checks


def _as_bearings(name: str, f: object, min_rows: int, exact_rows: int | None = None) -> np.ndarray:
    """Validate (N,3) bearings and return them as unit float64 rows."""
    arr = np.asarray(f, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name}: expected an (N,3) array of bearings, got shape {arr.shape}")
    n = arr.shape[0]
    if exact_rows is not None and n != exact_rows:
        raise ValueError(f"{name}: expected exactly {exact_rows} bearings, got {n}")
    if n < min_rows:
        raise ValueError(f"{name}: expected at least {min_rows} bearings, got {n}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: bearings must be finite, got NaN or inf")
    norms = np.linalg.norm(arr, axis=1)
    if np.any(norms < 1e-12):
        raise ValueError(f"{name}: bearings must have non-zero length, row {int(np.argmin(norms))} is zero")
    return arr / norms[:, None]


def as_bearing_pair(
    f1: object, f2: object, min_rows: int = 0, exact_rows: int | None = None, names: tuple[str, str] = ("f1", "f2")
) -> tuple[np.ndarray, np.ndarray]:
    """Validate two matching (N,3) bearing arrays and return them as unit float64 rows.

    Raises ValueError naming the argument for a wrong shape, a row count outside the bounds,
    non-finite values or zero-length bearings.
    """
    a = _as_bearings(names[0], f1, min_rows, exact_rows)
    b = _as_bearings(names[1], f2, min_rows, exact_rows)
    if a.shape != b.shape:
        raise ValueError(f"{names[0]} and {names[1]}: expected the same number of bearings, got {a.shape[0]} and {b.shape[0]}")
    return a, b


def _as_sample_batch(name: str, F: object) -> np.ndarray:
    """Validate (B, 3, 3) sample bearings; return them unit length and component-major, (3, 3, B):
    component, point, sample."""
    arr = np.asarray(F, dtype=float)
    if arr.ndim != 3 or arr.shape[1:] != (3, 3):
        raise ValueError(f"{name}: expected a (B,3,3) array (B samples of 3 bearings), got shape {arr.shape}")
    X = np.ascontiguousarray(arr.transpose(2, 1, 0))
    if not np.isfinite(X).all():
        raise ValueError(f"{name}: bearings must be finite, got NaN or inf")
    norms = np.sqrt(X[0] * X[0] + X[1] * X[1] + X[2] * X[2])  # (3 points, B)
    if (norms < 1e-12).any():
        i, b = np.unravel_index(int(np.argmin(norms)), norms.shape)
        raise ValueError(f"{name}: bearings must have non-zero length, sample {b} row {i} is zero")
    return X / norms


# --------------------------------------------------------------------------- the linear system


def epipolar_rows(f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """Rows of the paper's system (11)/(13): ``epipolar_rows(f1, f2) @ e == f2 @ E @ f1``.

    Args:
        f1, f2: (..., N, 3) level-frame bearings of view 1 and view 2.

    Returns:
        (..., N, 6) coefficients of e = (E13, E21, E22, E23, E31, E32).
    """
    return np.moveaxis(_epipolar_coefficients(np.moveaxis(f1, -1, 0), np.moveaxis(f2, -1, 0)), 0, -1)


def _epipolar_coefficients(X1: np.ndarray, X2: np.ndarray) -> np.ndarray:
    """:func:`epipolar_rows` on component-major bearings X1, X2 (3, ...): returns (6, ...)."""
    x, y, z = X1
    xp, yp, zp = X2
    return np.stack([xp * z, yp * x - xp * y, xp * x + yp * y, yp * z, zp * x, zp * y])


def essential_from_vector(e: np.ndarray) -> np.ndarray:
    """(..., 6) vector e = (E13, E21, E22, E23, E31, E32) to the (..., 3, 3) structured E."""
    e = np.asarray(e, dtype=float)
    E = np.zeros(e.shape[:-1] + (3, 3))
    E[..., _E_ROW, _E_COL] = e
    E[..., 0, 0] = e[..., 2]
    E[..., 0, 1] = -e[..., 1]
    return E


def essential_to_vector(E: np.ndarray) -> np.ndarray:
    """(..., 3, 3) E to its (..., 6) vector, projecting orthogonally onto the upright structure."""
    E = np.asarray(E, dtype=float)
    e = E[..., _E_ROW, _E_COL].copy()
    e[..., 1] = 0.5 * (E[..., 1, 0] - E[..., 0, 1])
    e[..., 2] = 0.5 * (E[..., 0, 0] + E[..., 1, 1])
    return e


def _complex_entries(
    e13: np.ndarray, e21: np.ndarray, e22: np.ndarray, e23: np.ndarray, e31: np.ndarray, e32: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return e22 + 1j * e21, e13 + 1j * e23, e31 + 1j * e32


def alpha_beta_gamma(e: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """alpha = E22 + i E21, beta = E13 + i E23, gamma = E31 + i E32 from (..., 6) vectors e."""
    return _complex_entries(*np.moveaxis(e, -1, 0))


def _constraint_values(al: np.ndarray, be: np.ndarray, ga: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Q (real), D (real) and T (complex) of the module docstring, elementwise."""
    return (be * np.conj(be)).real - (ga * np.conj(ga)).real, (al * ga * np.conj(be)).real, be * be * np.conj(al) + al * ga * ga


def _violation(e: np.ndarray) -> np.ndarray:
    """Largest of |Q|, |D|, |T| at component-major vectors e (6, ...), as given (no scaling)."""
    q, d, t = _constraint_values(*_complex_entries(*e))
    return np.maximum(np.maximum(np.abs(q), np.abs(d)), np.abs(t))


def upright_constraint_residual(E: np.ndarray) -> np.ndarray:
    """Largest violation of the det/trace constraints (Q, D, T above) for E scaled to unit norm.

    Zero exactly when E is ``[t]x Rz(yaw)`` (or its negative). Args: E (..., 3, 3). Returns (...).
    """
    E = np.asarray(E, dtype=float)
    n = np.linalg.norm(E, axis=(-2, -1))
    return _violation(np.moveaxis(essential_to_vector(E) / np.where(n > 0, n, 1.0)[..., None], -1, 0))


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


def _null_space(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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


def _template(basis: np.ndarray) -> np.ndarray:
    """The row-mixed template (6 equations, 10 monomials, B) of null spaces ``basis`` (3, 6, B)."""
    B = basis.shape[2]
    at_points = (_PADUA_AB1 @ basis.reshape(3, -1)).reshape(10, 6, B)  # e(a, b) at the Padua points
    q, d, t = _constraint_values(*_complex_entries(*at_points.transpose(1, 0, 2)))  # (10, B) each
    return (_TEMPLATE_FROM_VALUES @ np.stack([q, d, t.real, t.imag]).reshape(40, B)).reshape(6, 10, B)


def _solve_template(C: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss elimination on the template C (6, 10, B), component-major; C is overwritten.

    Returns rows <h> and <i> (4, B) each: ``ab + <h> . (b^3, b^2, b, 1) = 0`` and
    ``a + <i> . (b^3, b^2, b, 1) = 0``, the paper's (21) and (22); only these two rows are
    back-substituted. Without row exchanges the elimination is a few whole-batch operations; it
    also returns the indices of the samples with a small pivot (``_MIN_PIVOT_RATIO``), whose rows
    are to be taken from :func:`_solve_template_pivoted` instead. Singular templates (degenerate
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


def _solve_template_pivoted(C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
    F1 = _as_sample_batch("F1", F1)
    F2 = _as_sample_batch("F2", F2)
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
        A = _epipolar_coefficients(X1, X2)  # (6 entries, 3 points, B)
        basis, sizes = _null_space(A)  # (3 basis vectors, 6 entries, B): e = a N0 + b N1 + N2
        full_rank = sizes.min(axis=0) > _MIN_ROW_RANK_RATIO * np.sqrt((A * A).sum(axis=0)).max(axis=0)

        template = _template(basis)
        usable = full_rank & (np.abs(template).max(axis=(0, 1)) > _MIN_TEMPLATE_NORM)
        template[:, :, ~usable] = np.eye(6, 10)[:, :, None]  # solvable dummy; its solutions are discarded below

        h, i, redo = _solve_template(template)  # (4, B) each
        if redo.size:
            h[:, redo], i[:, redo] = _solve_template_pivoted(_template(basis[:, :, redo]))
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
        valid &= _violation(np.where(valid, e, 0.0)) < _MAX_CONSTRAINT_RESIDUAL
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
    ok = near & np.all(_violation(sheets) < _MAX_CONSTRAINT_RESIDUAL, axis=0)
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
    (a0, b0, g0), (a1, b1, g1), (a2, b2, g2) = (_complex_entries(*v) for v in (e0, e1, e2))
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


# --------------------------------------------------------------------------- 4-point and linear 5-point


def _right_singular(f1: np.ndarray, f2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Singular values (6,) (zero-padded) and right singular vectors (6, 6) of the N x 6 system."""
    A = epipolar_rows(f1, f2)
    _, s, vt = np.linalg.svd(A, full_matrices=True)
    return np.pad(s, (0, 6 - s.size)), vt


def _homogeneous_real_roots_cubic(c: np.ndarray) -> np.ndarray:
    """Real roots (lam, mu) of c0 lam^3 + c1 lam^2 mu + c2 lam mu^2 + c3 mu^3 = 0 as rows (k, 2).

    Solved in whichever chart keeps the leading coefficient large, so a root at infinity of one
    chart is an ordinary root of the other.
    """
    if abs(c[0]) >= abs(c[3]):
        x, ok = cubic_real_roots(c[None])
        return np.stack([x[0][ok[0]], np.ones(int(ok[0].sum()))], axis=1)
    x, ok = cubic_real_roots(c[None, ::-1])
    return np.stack([np.ones(int(ok[0].sum())), x[0][ok[0]]], axis=1)


def solve_upright_4pt(f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """The 4-point solver (section 3.2): 2-dim null space and the det(E) = 0 cubic.

    Args:
        f1, f2: (N, 3) level-frame bearings, N >= 4; with N > 4 the null space is the least-squares one.

    Returns:
        (k, 3, 3) essential matrices with unit Frobenius norm, 0 <= k <= 3. None where the cubic
        vanishes identically (all points on a horizontal plane: the system has rank 4 there).
    """
    a, b = as_bearing_pair(f1, f2, 4)
    s, vt = _right_singular(a, b)
    E1, E2 = essential_from_vector(vt[4]), essential_from_vector(vt[5])
    if s[3] <= _MIN_DEGENERACY_RATIO * s[0]:
        return np.zeros((0, 3, 3))  # rank < 4: fewer independent equations than the solver needs
    # det(lam E1 + mu E2) is a binary cubic; sample it at four (lam, mu) and interpolate.
    lm = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [1.0, -1.0]])
    dets = np.linalg.det(lm[:, 0, None, None] * E1 + lm[:, 1, None, None] * E2)
    basis = np.stack([lm[:, 0] ** 3, lm[:, 0] ** 2 * lm[:, 1], lm[:, 0] * lm[:, 1] ** 2, lm[:, 1] ** 3], axis=1)
    coeffs = np.linalg.solve(basis, dets)
    if np.abs(coeffs).max() <= _MIN_DEGENERACY_RATIO:
        return np.zeros((0, 3, 3))  # det vanishes on the whole pencil: horizontal plane
    roots = _homogeneous_real_roots_cubic(coeffs)
    E = roots[:, 0, None, None] * E1 + roots[:, 1, None, None] * E2
    return E / np.linalg.norm(E, axis=(1, 2), keepdims=True)


def solve_upright_linear5pt(f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """The linear 5-point solver (section 3.1): least squares on the six entries, then correction.

    The paper corrects the singular values; on this six-entry structure the equivalent that keeps
    E upright is the nearest ``[t]x Rz(yaw)`` in Frobenius norm (:func:`_nearest_upright`).

    Args:
        f1, f2: (N, 3) level-frame bearings, N >= 5.

    Returns:
        (k, 3, 3) with k in {0, 1}: none when the system has rank < 5 (all points on a horizontal
        plane, where it has rank 4 and the solution is a one-parameter family).
    """
    a, b = as_bearing_pair(f1, f2, 5)
    s, vt = _right_singular(a, b)
    if s[4] <= _MIN_DEGENERACY_RATIO * s[0]:
        return np.zeros((0, 3, 3))
    yaw, t = _nearest_upright(vt[5])
    E = skew(t) @ rot_z(yaw)
    return (E / np.linalg.norm(E))[None]


# --------------------------------------------------------------------------- decomposition


def _translation_for_yaw(e: np.ndarray, yaw: float) -> np.ndarray:
    """Least-squares t with ``[t]x Rz(yaw)`` closest to e (6,): the columns are orthogonal."""
    c, s = np.cos(yaw), np.sin(yaw)
    e13, e21, e22, e23, e31, e32 = e
    return np.array([(-e23 + s * e31 + c * e32) / 2.0, (e13 - c * e31 + s * e32) / 2.0, c * e21 - s * e22])


def _yaw_candidates(e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Stationary yaws of the fit of ``[t]x Rz(yaw)`` to e, and the fitted energy at each.

    For fixed yaw the best t (Frobenius norm on E) is linear least squares, leaving the energy
    f(yaw) = K + P sin + Q cos + U cos 2yaw + V sin 2yaw to maximise; with u = tan(yaw/2) its
    stationary points are the roots of a quartic (plus yaw = pi, the quartic's root at infinity).
    """
    e13, e21, e22, e23, e31, e32 = e
    P = e13 * e32 - e23 * e31
    Q = -(e23 * e32 + e13 * e31)
    U = e21**2 - e22**2  # E21 and E22 each stand twice in E, hence twice the weight
    V = -2.0 * e21 * e22
    quartic = np.array([2 * V - P, 8 * U - 2 * Q, -12 * V, -2 * Q - 8 * U, P + 2 * V])
    roots = np.roots(quartic) if np.any(quartic != 0) else np.zeros(0)
    u = roots.real[np.abs(roots.imag) <= 1e-8 * (1.0 + np.abs(roots))]
    yaws = np.concatenate([2.0 * np.arctan(u), [np.pi]])
    for _ in range(2):  # Newton on f'(yaw) = 0: the quartic's roots carry only ~1e-8 precision
        d1 = P * np.cos(yaws) - Q * np.sin(yaws) - 2 * U * np.sin(2 * yaws) + 2 * V * np.cos(2 * yaws)
        d2 = -P * np.sin(yaws) - Q * np.cos(yaws) - 4 * U * np.cos(2 * yaws) - 4 * V * np.sin(2 * yaws)
        yaws = yaws - np.where(np.abs(d2) > 1e-12, d1 / np.where(np.abs(d2) > 1e-12, d2, 1.0), 0.0)
    energy = P * np.sin(yaws) + Q * np.cos(yaws) + U * np.cos(2 * yaws) + V * np.sin(2 * yaws)
    return yaws, energy


def _nearest_upright(e: np.ndarray) -> tuple[float, np.ndarray]:
    """Yaw and t of the upright essential matrix nearest to e (6,) in Frobenius norm."""
    yaws, energy = _yaw_candidates(e)
    yaw = float(yaws[int(np.argmax(energy))])
    return yaw, _translation_for_yaw(e, yaw)


def _count_in_front(R: np.ndarray, t: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> int:
    """Points whose midpoint triangulation lies in front of both views."""
    a = f1 @ R.T
    aa = np.sum(a * a, axis=1)
    bb = np.sum(f2 * f2, axis=1)
    ab = np.sum(a * f2, axis=1)
    at = a @ t
    bt = f2 @ t
    det = aa * bb - ab * ab
    ok = det > 1e-12
    lam1 = (-at * bb + ab * bt) / np.where(ok, det, 1.0)
    lam2 = (aa * bt - ab * at) / np.where(ok, det, 1.0)
    return int(np.sum(ok & (lam1 > 0) & (lam2 > 0)))


def upright_pose_from_essential(E: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Decompose an upright essential matrix into the pose that puts the points in front of both views.

    E is first fitted by the nearest ``[t]x Rz(yaw)`` (exact for a solver's output). When t is
    vertical the twisted pair (yaw + pi, -t) is upright too and cheirality decides between them.

    Args:
        E: (3, 3) essential matrix with the upright structure (any scale).
        f1, f2: (N, 3) level-frame bearings used for the cheirality test, N >= 1.

    Returns:
        R_2_1 (3, 3), a rotation about z, and t_2_1 (3,), a unit vector.
    """
    E = np.asarray(E, dtype=float)
    if E.shape != (3, 3) or not np.all(np.isfinite(E)):
        raise ValueError(f"E: expected a finite (3,3) matrix, got shape {E.shape}")
    a, b = as_bearing_pair(f1, f2, 1)
    e = essential_to_vector(E)
    if np.linalg.norm(e) < 1e-300:
        raise ValueError("E: expected a non-zero essential matrix")
    e = e / np.linalg.norm(e)
    yaws, energy = _yaw_candidates(e)
    keep = energy >= energy.max() - 1e-9 * (1.0 + abs(energy.max()))
    best: tuple[int, float, np.ndarray, np.ndarray] | None = None
    for yaw, en in zip(yaws[keep], energy[keep]):
        t = _translation_for_yaw(e, float(yaw))
        t = t / np.linalg.norm(t)
        R = rot_z(float(yaw))
        for sign in (1.0, -1.0):
            score = (_count_in_front(R, sign * t, a, b), float(en))
            if best is None or score > best[:2]:
                best = (score[0], score[1], R, sign * t)
    assert best is not None
    return best[2], best[3]


# --------------------------------------------------------------------------- ground plane, 2-point
#
# With gravity known and every point on the horizontal ground plane ``z_lvl1 = d1`` below view 1,
# ``x_2 = (Rz(yaw) + (t_2_1 / d1) [0 0 1]) x_1``: a homography with 4 degrees of freedom (Saurer,
# Vasseur, Demonceaux and Fraundorfer, ACCV 2014). On the level image planes ``u = (x/z, y/z)`` it is
# a similarity, which in complex numbers reads ``u2 = m u1 + tau`` with ``m = exp(i yaw) / w``,
# ``w = 1 + tz/d1`` and ``tau = (tx + i ty) / (d1 w)``. Two points fix m and tau.

# Bearings closer than this (z of a unit bearing) to the horizon cannot lie on the ground below.
_MIN_GROUND_Z = 1e-3


def ground_homography_from_similarity(m: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """(..., 3, 3) ground homographies ``Rz(yaw) + (t/d1) e_z^T`` from complex similarity parameters (...)."""
    w = 1.0 / np.abs(m)
    rot = m * w  # exp(i yaw)
    tt = tau * w
    H = np.zeros(np.shape(m) + (3, 3))
    H[..., 0, 0] = H[..., 1, 1] = rot.real
    H[..., 0, 1] = -rot.imag
    H[..., 1, 0] = rot.imag
    H[..., 0, 2] = tt.real
    H[..., 1, 2] = tt.imag
    H[..., 2, 2] = w
    return H


def solve_ground_2pt_batch(F1: np.ndarray, F2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The known-gravity ground-plane homography from 2 points, for B samples at once.

    Args:
        F1, F2: (B, 2, 3) level-frame bearings; both points of a sample on the ground below the views.

    Returns:
        H (B, 3, 3) with ``x_2 ~ H @ x_1``, ``H = Rz(yaw_2_1) + (t_2_1 / d1) @ [0, 0, 1]`` where d1 is the
        height of view 1 above the plane (NaN where invalid), and valid (B,) bool. At most one
        solution per sample. Invalid: a bearing at or above the horizon, or two coincident points.
    """
    F1 = np.asarray(F1, dtype=float)
    F2 = np.asarray(F2, dtype=float)
    for name, F in (("F1", F1), ("F2", F2)):
        if F.ndim != 3 or F.shape[1:] != (2, 3):
            raise ValueError(f"{name}: expected a (B,2,3) array (B samples of 2 bearings), got shape {F.shape}")
        if not np.all(np.isfinite(F)):
            raise ValueError(f"{name}: bearings must be finite, got NaN or inf")
    if F1.shape != F2.shape:
        raise ValueError(f"F1 and F2: expected the same shape, got {F1.shape} and {F2.shape}")
    n1 = np.linalg.norm(F1, axis=-1)
    n2 = np.linalg.norm(F2, axis=-1)
    valid = np.all((F1[..., 2] > _MIN_GROUND_Z * n1) & (F2[..., 2] > _MIN_GROUND_Z * n2), axis=1)
    with np.errstate(all="ignore"):
        u1 = (F1[..., 0] + 1j * F1[..., 1]) / F1[..., 2]
        u2 = (F2[..., 0] + 1j * F2[..., 1]) / F2[..., 2]
        du1 = u1[:, 0] - u1[:, 1]
        m = (u2[:, 0] - u2[:, 1]) / du1
        tau = u2[:, 0] - m * u1[:, 0]
        valid &= (np.abs(du1) > 1e-12) & (np.abs(m) > 1e-12) & np.isfinite(m) & np.isfinite(tau)
        H = ground_homography_from_similarity(np.where(valid, m, 1.0), np.where(valid, tau, 0.0))
    H[~valid] = np.nan
    return H, valid


def ground_pose_from_homography(H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation per height of a ground homography (3, 3) of the form above.

    Returns:
        R_2_1 (3, 3), a rotation about z, and ``t_2_1 / d1`` (3,): the translation divided by the
        height of view 1 above the ground plane, so a rangefinder's height makes it metric.
    """
    H = np.asarray(H, dtype=float)
    if H.shape != (3, 3) or not np.all(np.isfinite(H)):
        raise ValueError(f"H: expected a finite (3,3) matrix, got shape {H.shape}")
    k = np.hypot(H[0, 0], H[1, 0])
    if k < 1e-12:
        raise ValueError("H: expected a ground homography, the rotation block is zero")
    H = H / k
    yaw = float(np.arctan2(H[1, 0], H[0, 0]))
    return rot_z(yaw), np.array([H[0, 2], H[1, 2], H[2, 2] - 1.0])
