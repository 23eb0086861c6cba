"""Quaternion and SE(3) algebra of one track on Python floats (tuples): the float64 form of
:mod:`lie`, for the single-track backends and the tracker.

The same formulas as the batched tensor forms of :mod:`lie` (units: radians, metres;
quaternions ``wxyz``, unit norm), written for one track on tuples of floats: a call costs a
microsecond, not the dispatch of tensor ops. Each function runs as plain Python in the NumPy
backend (:mod:`fast_path`) and, unchanged, inside the compiled kernels of :mod:`fast_compiled`
(numba ``register_jitable``: numba compiles it where a kernel calls it; without numba it is
plain Python only).
"""

from __future__ import annotations

import math

from evtrack.filters.lie import _LOG_SMALL, _TINY_ANGLE

try:  # numba is a dependency; without it these stay plain Python
    from numba.extending import register_jitable as _jitable
except ImportError:  # pragma: no cover - exercised only where numba is missing

    def _jitable(fn):
        return fn


__all__ = [
    "Quat",
    "Vec3",
    "cross",
    "normalized",
    "quat_exp",
    "quat_log",
    "quat_mul",
    "quat_rotate",
    "rotation_matrix",
    "se3_exp",
]

Quat = tuple[float, float, float, float]
Vec3 = tuple[float, float, float]


@_jitable
def quat_mul(a: Quat, b: Quat) -> Quat:
    """Hamilton product ``a ⊗ b`` (wxyz)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        ax * bw + aw * bx - az * by + ay * bz,
        ay * bw + az * bx + aw * by - ax * bz,
        az * bw - ay * bx + ax * by + aw * bz,
    )


@_jitable
def cross(a: Vec3, b: Vec3) -> Vec3:
    """``a × b``."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@_jitable
def quat_rotate(q: Quat, p: Vec3) -> Vec3:
    """``R(q) p`` as ``p + 2 (w c + v × c)``, ``c = v × p``."""
    w, v = q[0], q[1:]
    c = cross(v, p)  # type: ignore[arg-type]
    d = cross(v, c)  # type: ignore[arg-type]
    return (
        p[0] + 2.0 * (w * c[0] + d[0]),
        p[1] + 2.0 * (w * c[1] + d[1]),
        p[2] + 2.0 * (w * c[2] + d[2]),
    )


@_jitable
def rotation_matrix(q: Quat) -> tuple[Vec3, Vec3, Vec3]:
    """The 3x3 rotation matrix of a unit quaternion, by rows."""
    w, x, y, z = q
    return (
        (1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)),
        (2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)),
        (2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)),
    )


@_jitable
def normalized(q: Quat) -> Quat:
    """``q / |q|``."""
    w, x, y, z = q
    n = math.sqrt(w * w + x * x + y * y + z * z)
    return (w / n, x / n, y / n, z / n)


@_jitable
def _exp_parts(phi: Vec3) -> tuple[Quat, float, float, float]:
    """``exp(φ)``, ``θ``, ``sin(θ/2)/θ`` and ``θ`` safe to divide by (as in :mod:`lie`)."""
    theta = math.sqrt(phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2])
    half = 0.5 * theta
    if theta > _TINY_ANGLE:
        theta_safe, k = theta, math.sin(half) / theta
    else:
        theta_safe, k = 1.0, 0.5
    return (math.cos(half), k * phi[0], k * phi[1], k * phi[2]), theta, k, theta_safe


@_jitable
def quat_exp(phi: Vec3) -> Quat:
    """Rotation vector (rad) -> unit quaternion."""
    return _exp_parts(phi)[0]


@_jitable
def quat_log(q: Quat) -> Vec3:
    """Unit quaternion -> the shortest rotation vector (either sign of ``q``)."""
    w, x, y, z = q
    s = math.sqrt(x * x + y * y + z * z)
    aw = abs(w)
    ratio = 2.0 / aw if s < _LOG_SMALL else 2.0 * math.atan2(s, aw) / s
    if w < 0:
        ratio = -ratio
    return (ratio * x, ratio * y, ratio * z)


@_jitable
def se3_exp(rho: Vec3, phi: Vec3) -> tuple[Quat, Vec3]:
    """The rigid motion ``(q_Δ, p_Δ)`` of the constant twist ``[ρ, φ] = dt·[v_o, ω]``."""
    q, theta, k, theta_safe = _exp_parts(phi)
    a = 2.0 * k * k
    b = (theta - math.sin(theta)) / (theta_safe * theta_safe * theta_safe)
    c1 = cross(phi, rho)
    c2 = cross(phi, c1)
    return q, (
        rho[0] + a * c1[0] + b * c2[0],
        rho[1] + a * c1[1] + b * c2[1],
        rho[2] + a * c1[2] + b * c2[2],
    )


