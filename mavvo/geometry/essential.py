"""Relative pose with known roll and pitch: the solvers of Fraundorfer, Tanskanen and Pollefeys (2010).

All functions take bearings in *level* frames (z along gravity, see :mod:`mavvo.geometry.frames`), points as
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

The solvers (one per module: :mod:`mavvo.geometry.upright_3pt`, :mod:`~mavvo.geometry.upright_4pt`,
:mod:`~mavvo.geometry.upright_pose`, :mod:`~mavvo.geometry.ground_2pt`) return no solution on degenerate input rather than raising; they raise ``ValueError`` only
for malformed input (wrong shape, non-finite values, zero-length bearings, too few points).
"""

from __future__ import annotations

import math

import numpy as np

from mavvo.jit import kernel

# The det cubic of the 4-point, or the 5th singular value of the linear 5-point, vanishes on a
# horizontal plane (rank 4). Relative to the largest coefficient / singular value.
MIN_DEGENERACY_RATIO = 1e-9

# Row and column of each entry of e in E.
_E_ROW = np.array([0, 1, 1, 1, 2, 2])
_E_COL = np.array([2, 0, 1, 2, 0, 1])


# --------------------------------------------------------------------------- input checks


def as_bearings(name: str, f: object, min_rows: int, exact_rows: int | None = None) -> np.ndarray:
    """Validate (N,3) bearings and return them as unit float64 rows."""
    arr = np.asarray(f, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name}: expected an (N,3) array of bearings, got shape {arr.shape}")
    n = arr.shape[0]
    if exact_rows is not None and n != exact_rows:
        raise ValueError(f"{name}: expected exactly {exact_rows} bearings, got {n}")
    if n < min_rows:
        raise ValueError(f"{name}: expected at least {min_rows} bearings, got {n}")
    unit = np.empty((n, 3))
    bad = unit_rows(np.ascontiguousarray(arr), unit)
    if bad == -2:
        raise ValueError(f"{name}: bearings must be finite, got NaN or inf")
    if bad >= 0:
        raise ValueError(f"{name}: bearings must have non-zero length, row {bad} is zero")
    return unit


@kernel
def unit_rows(f: np.ndarray, out: np.ndarray) -> int:
    """Rows of f (N, 3) scaled to unit length into out; -1 when all are finite and non-zero, else -2
    for a non-finite value, or the index of the first row shorter than 1e-12."""
    zero = -1
    for i in range(f.shape[0]):
        x, y, z = f[i, 0], f[i, 1], f[i, 2]
        if not (abs(x) < np.inf and abs(y) < np.inf and abs(z) < np.inf):
            return -2
        norm = math.sqrt(x * x + y * y + z * z)
        if norm == np.inf:  # finite but their squares overflow: a direction all the same
            m = max(abs(x), abs(y), abs(z))
            x, y, z = x / m, y / m, z / m
            norm = math.sqrt(x * x + y * y + z * z)
        if norm < 1e-12:
            zero = i if zero < 0 else zero
            continue
        out[i, 0], out[i, 1], out[i, 2] = x / norm, y / norm, z / norm
    return zero


def as_bearing_pair(
    f1: object, f2: object, min_rows: int = 0, exact_rows: int | None = None, names: tuple[str, str] = ("f1", "f2")
) -> tuple[np.ndarray, np.ndarray]:
    """Validate two matching (N,3) bearing arrays and return them as unit float64 rows.

    Raises ValueError naming the argument for a wrong shape, a row count outside the bounds,
    non-finite values or zero-length bearings.
    """
    a = as_bearings(names[0], f1, min_rows, exact_rows)
    b = as_bearings(names[1], f2, min_rows, exact_rows)
    if a.shape != b.shape:
        raise ValueError(
            f"{names[0]} and {names[1]}: expected the same number of bearings, got {a.shape[0]} and {b.shape[0]}"
        )
    return a, b


def as_sample_batch(name: str, F: object) -> np.ndarray:
    """Validate (B, 3, 3) sample bearings (sample, point, component); return them unit length, C-contiguous."""
    arr = np.asarray(F, dtype=float)
    if arr.ndim != 3 or arr.shape[1:] != (3, 3):
        raise ValueError(f"{name}: expected a (B,3,3) array (B samples of 3 bearings), got shape {arr.shape}")
    # Scaled as :func:`as_bearings` scales one sample's rows, to the last bit: a batch and the same
    # samples one at a time then solve the same numbers (a near-degenerate sample can turn on one ulp).
    unit = np.empty((arr.shape[0] * 3, 3))
    bad = unit_rows(np.ascontiguousarray(arr.reshape(-1, 3)), unit)
    if bad == -2:
        raise ValueError(f"{name}: bearings must be finite, got NaN or inf")
    if bad >= 0:
        b, i = divmod(bad, 3)
        raise ValueError(f"{name}: bearings must have non-zero length, sample {b} row {i} is zero")
    return unit.reshape(arr.shape)


# --------------------------------------------------------------------------- the linear system


def epipolar_rows(f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """Rows of the paper's system (11)/(13): ``epipolar_rows(f1, f2) @ e == f2 @ E @ f1``.

    Args:
        f1, f2: (..., N, 3) level-frame bearings of view 1 and view 2.

    Returns:
        (..., N, 6) coefficients of e = (E13, E21, E22, E23, E31, E32).
    """
    return np.moveaxis(epipolar_coefficients(np.moveaxis(f1, -1, 0), np.moveaxis(f2, -1, 0)), 0, -1)


def epipolar_coefficients(X1: np.ndarray, X2: np.ndarray) -> np.ndarray:
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


def complex_entries(
    e13: np.ndarray, e21: np.ndarray, e22: np.ndarray, e23: np.ndarray, e31: np.ndarray, e32: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return e22 + 1j * e21, e13 + 1j * e23, e31 + 1j * e32


def alpha_beta_gamma(e: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """alpha = E22 + i E21, beta = E13 + i E23, gamma = E31 + i E32 from (..., 6) vectors e."""
    return complex_entries(*np.moveaxis(e, -1, 0))


def constraint_values(al: np.ndarray, be: np.ndarray, ga: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Q (real), D (real) and T (complex) of the module docstring, elementwise."""
    return (
        (be * np.conj(be)).real - (ga * np.conj(ga)).real,
        (al * ga * np.conj(be)).real,
        be * be * np.conj(al) + al * ga * ga,
    )


def constraint_violation(e: np.ndarray) -> np.ndarray:
    """Largest of |Q|, |D|, |T| at component-major vectors e (6, ...), as given (no scaling)."""
    q, d, t = constraint_values(*complex_entries(*e))
    return np.maximum(np.maximum(np.abs(q), np.abs(d)), np.abs(t))


def upright_constraint_residual(E: np.ndarray) -> np.ndarray:
    """Largest violation of the det/trace constraints (Q, D, T above) for E scaled to unit norm.

    Zero exactly when E is ``[t]x Rz(yaw)`` (or its negative). Args: E (..., 3, 3). Returns (...).
    """
    E = np.asarray(E, dtype=float)
    n = np.linalg.norm(E, axis=(-2, -1))
    return constraint_violation(np.moveaxis(essential_to_vector(E) / np.where(n > 0, n, 1.0)[..., None], -1, 0))


def singular_system(f1: np.ndarray, f2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Singular values (6,) (zero-padded) and right singular vectors (6, 6) of the N x 6 system."""
    A = epipolar_rows(f1, f2)
    _, s, vt = np.linalg.svd(A, full_matrices=True)
    return np.pad(s, (0, 6 - s.size)), vt
