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

import itertools

import numpy as np

from mavvo.frames import cross, rot_z, skew
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
# A solution whose constraint Jacobian has sigma_min / sigma_max below this lies on a continuum.
_MIN_ISOLATION = 1e-6
# Within this distance of E13 = E23 = E31 = E32 = 0 (motion nearly along gravity) the two roots
# near the vertical point are solved sheet by sheet, with this many Newton steps.
_NEAR_VERTICAL = 1e-3
_SHEET_NEWTON_STEPS = 4
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
    arr = np.asarray(F, dtype=float)
    if arr.ndim != 3 or arr.shape[1:] != (3, 3):
        raise ValueError(f"{name}: expected a (B,3,3) array (B samples of 3 bearings), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: bearings must be finite, got NaN or inf")
    norms = np.linalg.norm(arr, axis=2)
    if np.any(norms < 1e-12):
        b, i = np.unravel_index(int(np.argmin(norms)), norms.shape)
        raise ValueError(f"{name}: bearings must have non-zero length, sample {b} row {i} is zero")
    return arr / norms[..., None]


# --------------------------------------------------------------------------- the linear system


def epipolar_rows(f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """Rows of the paper's system (11)/(13): ``epipolar_rows(f1, f2) @ e == f2 @ E @ f1``.

    Args:
        f1, f2: (..., N, 3) level-frame bearings of view 1 and view 2.

    Returns:
        (..., N, 6) coefficients of e = (E13, E21, E22, E23, E31, E32).
    """
    x, y, z = f1[..., 0], f1[..., 1], f1[..., 2]
    xp, yp, zp = f2[..., 0], f2[..., 1], f2[..., 2]
    return np.stack([xp * z, yp * x - xp * y, xp * x + yp * y, yp * z, zp * x, zp * y], axis=-1)


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


def alpha_beta_gamma(e: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """alpha = E22 + i E21, beta = E13 + i E23, gamma = E31 + i E32 from (..., 6) vectors e."""
    return e[..., 2] + 1j * e[..., 1], e[..., 0] + 1j * e[..., 3], e[..., 4] + 1j * e[..., 5]


def upright_constraint_residual(E: np.ndarray) -> np.ndarray:
    """Largest violation of the det/trace constraints (Q, D, T above) for E scaled to unit norm.

    Zero exactly when E is ``[t]x Rz(yaw)`` (or its negative). Args: E (..., 3, 3). Returns (...).
    """
    E = np.asarray(E, dtype=float)
    n = np.linalg.norm(E, axis=(-2, -1))
    al, be, ga = alpha_beta_gamma(essential_to_vector(E) / np.where(n > 0, n, 1.0)[..., None])
    q = np.abs(be) ** 2 - np.abs(ga) ** 2
    d = (al * ga * np.conj(be)).real
    t = be * be * np.conj(al) + al * ga * ga
    return np.maximum(np.maximum(np.abs(q), np.abs(d)), np.abs(t))


# --------------------------------------------------------------------------- 3-point

# Linear forms over v = (a, b, 1); products of them are mapped to monomials by constant matrices.
_V_DEG = ((1, 0), (0, 1), (0, 0))
# Cubic monomials in the paper's elimination order: those with a first, (20)-(22).
_CUBIC = ((3, 0), (2, 1), (2, 0), (1, 2), (1, 1), (1, 0), (0, 3), (0, 2), (0, 1), (0, 0))
_QUADRATIC = ((2, 0), (1, 1), (1, 0), (0, 2), (0, 1), (0, 0))
_IDX_AB, _IDX_A = 4, 5  # rows <h> (21) and <i> (22) after elimination


def _product_map(n_factors: int, monomials: tuple[tuple[int, int], ...]) -> np.ndarray:
    index = {m: i for i, m in enumerate(monomials)}
    out = np.zeros((3**n_factors, len(monomials)))
    for row, combo in enumerate(itertools.product(range(3), repeat=n_factors)):
        out[row, index[(sum(_V_DEG[c][0] for c in combo), sum(_V_DEG[c][1] for c in combo))]] += 1.0
    return out


def _shift_map() -> np.ndarray:
    """(6, 30): quadratic coefficients -> the cubic coefficients of q*a, q*b and q*1."""
    index = {m: i for i, m in enumerate(_CUBIC)}
    out = np.zeros((len(_QUADRATIC), 3, len(_CUBIC)))
    for i, (da, db) in enumerate(_QUADRATIC):
        for k, (va, vb) in enumerate(_V_DEG):
            out[i, k, index[(da + va, db + vb)]] = 1.0
    return out.reshape(len(_QUADRATIC), 3 * len(_CUBIC))


_MAP2 = _product_map(2, _QUADRATIC)
_MAP3 = _product_map(3, _CUBIC)
_SHIFT = _shift_map()
# Three fixed directions projected onto each null space give its basis; any fixed set in general
# position works (the projection is rank-deficient only on a measure-zero set of inputs).
_NULL_SEEDS = np.linalg.qr(np.random.default_rng(2010).standard_normal((6, 3)))[0]


def _orthonormal_rows(M: np.ndarray, passes: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Gram-Schmidt on the rows of (B, k, n) with re-orthogonalisation; returns rows and the
    (B, k) norms each row had before it was normalised in the first pass."""
    Q = M.copy()
    k = M.shape[1]
    first = np.empty(M.shape[:2])
    for p in range(passes):
        for i in range(k):
            row = Q[:, i : i + 1]  # (B, 1, n)
            if i:
                done = Q[:, :i]  # (B, i, n), orthonormal
                row = row - (row @ np.swapaxes(done, 1, 2)) @ done
            nrm = np.sqrt((row @ np.swapaxes(row, 1, 2))[:, 0, 0])
            if p == 0:
                first[:, i] = nrm
            Q[:, i] = row[:, 0] / np.where(nrm > 0.0, nrm, 1.0)[:, None]
    return Q, first


def _real_map(p: np.ndarray, M: np.ndarray) -> np.ndarray:
    # Complex @ real in two real products: numpy has no fast mixed-type matmul.
    return p.real @ M + 1j * (p.imag @ M)


def _poly2(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return _real_map((x[:, :, None] * y[:, None, :]).reshape(x.shape[0], 9), _MAP2)


def _poly3(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    return _real_map((x[:, :, None, None] * y[:, None, :, None] * z[:, None, None, :]).reshape(x.shape[0], 27), _MAP3)


def _solve_template(C: np.ndarray) -> np.ndarray:
    """Gauss-Jordan on the (B, 6, 10) template: (B, 6, 4) with monomial_j + X_j . (b^3, b^2, b, 1) = 0.

    Exactly singular templates (degenerate data) come back as NaN instead of failing the batch.
    """
    left, right = C[:, :, :6], C[:, :, 6:]
    try:
        return np.linalg.solve(left, right)
    except np.linalg.LinAlgError:
        out = np.full(right.shape, np.nan)
        for i in range(C.shape[0]):
            try:
                out[i] = np.linalg.solve(left[i], right[i])
            except np.linalg.LinAlgError:
                pass
        return out


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
    B = F1.shape[0]
    with np.errstate(all="ignore"):
        A = epipolar_rows(F1, F2)  # (B, 3, 6)
        rows, first_norms = _orthonormal_rows(A)
        row_scale = np.linalg.norm(A, axis=-1).max(axis=-1)
        full_rank = first_norms.min(axis=-1) > _MIN_ROW_RANK_RATIO * row_scale
        # Fixed directions projected onto the null space, as rows: W^T - (rows W)^T rows.
        seeds = _NULL_SEEDS.T[None] - np.swapaxes(rows @ _NULL_SEEDS, 1, 2) @ rows
        N, _ = _orthonormal_rows(seeds)  # (B, 3, 6): e = a N0 + b N1 + N2

        # alpha, beta, gamma as complex linear forms over (a, b, 1): (B, 3) each.
        al, be, ga = alpha_beta_gamma(N)
        q = (_poly2(be, np.conj(be)) - _poly2(ga, np.conj(ga))).real
        d = _poly3(al, ga, np.conj(be)).real
        t = _poly3(be, be, np.conj(al)) + _poly3(al, ga, ga)
        template = np.concatenate(
            [(q @ _SHIFT).reshape(B, 3, 10), d[:, None], t.real[:, None], t.imag[:, None]], axis=1
        )
        usable = full_rank & (np.abs(template).max(axis=(1, 2)) > _MIN_TEMPLATE_NORM)
        template[~usable] = np.eye(6, 10)  # solvable dummy; its solutions are discarded below

        X = _solve_template(template)
        h, i = X[:, _IDX_AB], X[:, _IDX_A]
        # <k> = <h> - b <i>  (23): a quartic in b; a from <i>  (22).
        quartic = np.stack([i[:, 0], i[:, 1] - h[:, 0], i[:, 2] - h[:, 1], i[:, 3] - h[:, 2], -h[:, 3]], axis=-1)
        b, valid = quartic_real_roots(quartic)
        a = -(((i[:, None, 0] * b + i[:, None, 1]) * b + i[:, None, 2]) * b + i[:, None, 3])
        e = a[..., None] * N[:, None, 0] + b[..., None] * N[:, None, 1] + N[:, None, 2]  # (B, 4, 6)
        valid &= _isolated(e, al, be, ga)

        # Motion along gravity: the true E has E13 = E23 = E31 = E32 = 0, where the two sheets of
        # upright essential matrices, (yaw, tz) and (yaw + pi, -tz), cross. The template loses rank
        # there and the solution becomes a double root; near it the two roots are ill-conditioned.
        # Each sheet alone is regular, so solve each from the null space's nearest vertical point.
        # (A vanishing template means every point of the null space solves: a pure rotation.)
        rows_v = np.nonzero(_maybe_near_vertical(N) & usable)[0]
        near = np.zeros(B, dtype=bool)
        if rows_v.size:
            near_v, e_sheets = _near_vertical_solutions(N[rows_v])
            ok = near_v & np.all(upright_constraint_residual(essential_from_vector(e_sheets)) < _MAX_CONSTRAINT_RESIDUAL, axis=1)
            rows_v, e_sheets = rows_v[ok], e_sheets[ok]
            near[rows_v] = True
            e_v = e_sheets[:, 0]
            similarity = np.abs(np.einsum("bki,bi->bk", e[rows_v], e_v)) / np.linalg.norm(e[rows_v], axis=-1)
            slots = np.argsort(-np.where(valid[rows_v], similarity, 2.0), axis=1)[:, :2]
            e[rows_v[:, None], slots] = e_sheets
            valid[rows_v[:, None], slots] = True

        E = essential_from_vector(e)
        E /= np.linalg.norm(E, axis=(-2, -1), keepdims=True)
        valid &= usable[:, None]
        valid &= np.all(np.isfinite(E), axis=(-2, -1))
        valid &= _distinct_epipolar_planes(E, F1)
        valid &= upright_constraint_residual(np.where(valid[..., None, None], E, 0.0)) < _MAX_CONSTRAINT_RESIDUAL
    E[~valid] = np.nan
    return E, valid


def _distinct_epipolar_planes(E: np.ndarray, F1: np.ndarray) -> np.ndarray:
    """(B, 4) bool: under E (B, 4, 3, 3) the three points F1 (B, 3, 3) do not share one epipolar plane.

    Three points on a line coplanar with the baseline (the paper's line parallel to it, or one
    crossing it) lie in one epipolar plane: then the true yaw fits with any translation in that
    plane, and a solver may return a member of that continuum. Its epipolar lines E f1 coincide.
    """
    lines = np.swapaxes(E @ np.swapaxes(F1, 1, 2)[:, None], 2, 3)  # (B, 4, 3 points, 3): lines in view 2
    lines /= np.maximum(np.linalg.norm(lines, axis=-1, keepdims=True), 1e-300)
    c01 = np.linalg.norm(cross(lines[:, :, 0], lines[:, :, 1]), axis=-1)
    c02 = np.linalg.norm(cross(lines[:, :, 0], lines[:, :, 2]), axis=-1)
    return np.maximum(c01, c02) > _MIN_EPIPOLAR_PLANE_ANGLE


def _isolated(e: np.ndarray, al: np.ndarray, be: np.ndarray, ga: np.ndarray) -> np.ndarray:
    """(B, 4) bool: the candidates e (B, 4, 6) are isolated solutions of Q = D = T = 0 in the chart.

    A line of points coplanar with the baseline, or a pure rotation, leaves a continuum of upright
    essential matrices that fit; every point of it satisfies the constraints, so the residual test
    cannot reject it. There the constraints' Jacobian in (a, b) drops below rank 2.
    al, be, ga: (B, 3) linear forms over (a, b, 1).
    """
    A, Bt, G = alpha_beta_gamma(e)
    cols = []
    for k in (0, 1):  # d/da, d/db
        dA, dB, dG = al[:, None, k], be[:, None, k], ga[:, None, k]
        dQ = 2.0 * (np.conj(Bt) * dB).real - 2.0 * (np.conj(G) * dG).real
        dD = (dA * G * np.conj(Bt) + A * dG * np.conj(Bt) + A * G * np.conj(dB)).real
        dT = 2.0 * Bt * dB * np.conj(A) + Bt * Bt * np.conj(dA) + dA * G * G + 2.0 * A * G * dG
        cols.append(np.stack([dQ, dD, dT.real, dT.imag], axis=-1))
    gxx = np.sum(cols[0] * cols[0], axis=-1)
    gyy = np.sum(cols[1] * cols[1], axis=-1)
    gxy = np.sum(cols[0] * cols[1], axis=-1)
    # sigma_min^2 / sigma_max^2 of the 4x2 Jacobian, up to a factor <= 4.
    return (gxx * gyy - gxy * gxy) > _MIN_ISOLATION**2 * (gxx + gyy) ** 2


def _maybe_near_vertical(N: np.ndarray) -> np.ndarray:
    """(B,) bool, cheap and conservative: the null space (B, 3, 6) may pass within
    ``_NEAR_VERTICAL`` of E13 = E23 = E31 = E32 = 0 (its 4x3 restriction has a small singular value)."""
    V = N[:, :, [0, 3, 4, 5]]
    G = V @ np.swapaxes(V, 1, 2)  # (B, 3, 3) Gram matrix; det = product of squared singular values
    det = (
        G[:, 0, 0] * (G[:, 1, 1] * G[:, 2, 2] - G[:, 1, 2] * G[:, 2, 1])
        - G[:, 0, 1] * (G[:, 1, 0] * G[:, 2, 2] - G[:, 1, 2] * G[:, 2, 0])
        + G[:, 0, 2] * (G[:, 1, 0] * G[:, 2, 1] - G[:, 1, 1] * G[:, 2, 0])
    )
    half_trace = 0.5 * (G[:, 0, 0] + G[:, 1, 1] + G[:, 2, 2])
    return det <= (_NEAR_VERTICAL**2) * half_trace**2  # sigma_min^2 >= det / (trace/2)^2


def _near_vertical_solutions(N: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solutions near motion along gravity, one per sheet, by Newton from the vertical point.

    Args:
        N: (B, 3, 6) orthonormal basis of each sample's null space.

    Returns:
        near (B,) bool: the null space passes within ``_NEAR_VERTICAL`` of E13 = E23 = E31 = E32 = 0;
        e (B, 2, 6): the solution on the sheet tz = +|alpha| and on tz = -|alpha| (rows where
        ``near`` is false are meaningless).

    On sheet s the upright E satisfy ``s |alpha| gamma + i conj(alpha) beta = 0``: two real
    equations in the two coordinates of the null space, regular where alpha != 0, unlike the
    det/trace system whose equations are all quadratic in (beta, gamma).
    """
    B = N.shape[0]
    V = np.swapaxes(N[:, :, [0, 3, 4, 5]], 1, 2)  # (B, 4, 3): E13, E23, E31, E32 over the basis
    pairs = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
    crosses = np.stack([cross(V[:, i], V[:, j]) for i, j in pairs], axis=1)
    norms = np.linalg.norm(crosses, axis=-1)
    c = crosses[np.arange(B), np.argmax(norms, axis=1)]
    c /= np.maximum(np.linalg.norm(c, axis=-1), 1e-300)[:, None]
    near = (np.linalg.norm(np.einsum("bjk,bk->bj", V, c), axis=-1) < _NEAR_VERTICAL) & (norms.max(axis=1) > 1e-12)
    # Local chart e = (c + x u + y w) @ N with u, w completing c to an orthonormal frame.
    helper = np.where((np.abs(c[:, 0]) < 0.9)[:, None], np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    u = cross(c, helper)
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    w = cross(c, u)
    e0, eu, ew = (np.einsum("bk,bki->bi", v, N) for v in (c, u, w))

    (a0, b0, g0), (au, bu, gu), (aw, bw, gw) = (alpha_beta_gamma(v) for v in (e0, eu, ew))
    sheet = np.array([1.0, -1.0])[None, :]
    x = np.zeros((B, 2))
    y = np.zeros((B, 2))
    for _ in range(_SHEET_NEWTON_STEPS):
        al = a0[:, None] + x * au[:, None] + y * aw[:, None]
        be = b0[:, None] + x * bu[:, None] + y * bw[:, None]
        ga = g0[:, None] + x * gu[:, None] + y * gw[:, None]
        mod = np.maximum(np.abs(al), 1e-300)
        F = sheet * mod * ga + 1j * np.conj(al) * be
        Fx = sheet * ((np.conj(al) * au[:, None]).real / mod * ga + mod * gu[:, None]) + 1j * (
            np.conj(au)[:, None] * be + np.conj(al) * bu[:, None]
        )
        Fy = sheet * ((np.conj(al) * aw[:, None]).real / mod * ga + mod * gw[:, None]) + 1j * (
            np.conj(aw)[:, None] * be + np.conj(al) * bw[:, None]
        )
        det = Fx.real * Fy.imag - Fy.real * Fx.imag
        ok = np.abs(det) > 1e-300
        det = np.where(ok, det, 1.0)
        x = x - np.where(ok, (F.real * Fy.imag - Fy.real * F.imag) / det, 0.0)
        y = y - np.where(ok, (Fx.real * F.imag - F.real * Fx.imag) / det, 0.0)
    # Isolated roots only: a pure rotation makes one sheet's equations vanish on a whole region.
    scale = np.abs(Fx) ** 2 + np.abs(Fy) ** 2
    isolated = np.abs(det) > _MIN_ISOLATION * np.maximum(scale, 1e-300)
    near &= np.all(isolated, axis=1)
    e = e0[:, None] + x[..., None] * eu[:, None] + y[..., None] * ew[:, None]
    return near, e


def solve_upright_3pt(f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """The 3-point minimal solver (section 3.3) for one sample.

    Args:
        f1, f2: (3, 3) level-frame bearings, row i of f1 matching row i of f2.

    Returns:
        (k, 3, 3) essential matrices with unit Frobenius norm, 0 <= k <= 4.
    """
    a, b = as_bearing_pair(f1, f2, 3, exact_rows=3)
    E, valid = solve_upright_3pt_batch(a[None], b[None])
    return E[0][valid[0]]


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
