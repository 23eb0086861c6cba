"""Quaternion and SE(3) kernels for the filters: a few tensor ops each, exportable to ONNX.

Conventions (DESIGN.md):
    * Quaternions are ``(w, x, y, z)``; ``q`` and ``-q`` are the same rotation.
    * A rotation vector ``φ`` (rad) maps to ``exp(φ) = [cos(|φ|/2), sin(|φ|/2) φ/|φ|]``.
    * Twists are ``[v_o, ω]`` in the camera frame; ``se3_exp(dt·V)`` is the exact motion under a
      constant twist: ``P' = R_Δ P + p_Δ`` (``Ṗ = v_o + ω × P``).
    * Pose perturbations are on the left, in the camera frame: ``q = exp(δθ) ⊗ q̄``, ``t = t̄ + δt``.

Why not kornia's ``So3``/``Se3`` here: they wrap every result in ``nn.Parameter`` and take about
100 tensor ops (``Se3.exp`` costs ~0.5 ms at batch 1), and their ``log`` uses ``atan2``, which
onnxruntime does not implement in float64. These kernels are pinned to kornia in
``tests/filters/test_lie.py``.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "atan2_precise",
    "quat_mul",
    "quat_conj",
    "quat_rotate",
    "quat_exp",
    "quat_log",
    "se3_exp",
    "pose_boxplus",
    "pose_boxminus",
]

# |v|/|q| below which log uses its series 2/w (error ~|v|^2/3, below float64 resolution).
_LOG_SMALL = 1e-8
# θ² below which the SE(3) left-Jacobian coefficients use their series (truncation < 1e-14).
_SE3_SERIES_SQ = 1e-2


def atan2_precise(y: Tensor, x: Tensor) -> Tensor:
    """``atan2(y, x)`` for ``y >= 0, x >= 0``, at full precision in float64 too.

    onnxruntime has no float64 ``Atan``; so in float64 the angle is taken in float32 and refined
    by one Newton step with float64 ``sin``/``cos`` (error ~c³/6 for a float32 error c ~ 1e-7).

    Args:
        y, x: (*) non-negative (the first quadrant, as in :func:`quat_log`).

    Returns:
        (*) radians in ``[0, π/2]``.
    """
    if y.dtype != torch.float64:
        return torch.atan2(y, x)
    a = torch.atan2(y.float(), x.float()).to(y.dtype)
    r = torch.sqrt(x * x + y * y).clamp_min(torch.finfo(y.dtype).tiny)
    return a + (y * torch.cos(a) - x * torch.sin(a)) / r


def _left_matrix(q: Tensor) -> Tensor:
    """(*,4) -> (*,4,4) ``L(q)`` with ``q ⊗ p == L(q) @ p``."""
    w, x, y, z = q.unbind(-1)
    nx, ny, nz = (-q[..., 1:]).unbind(-1)
    rows = (w, nx, ny, nz, x, w, nz, y, y, z, w, nx, z, ny, x, w)
    return torch.stack(rows, dim=-1).unflatten(-1, (4, 4))


def quat_mul(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product ``a ⊗ b`` (wxyz); shapes broadcast: (*,4), (*,4) -> (*,4)."""
    return (_left_matrix(a) @ b.unsqueeze(-1)).squeeze(-1)


def quat_conj(q: Tensor) -> Tensor:
    """Conjugate (the inverse of a unit quaternion): (*,4) -> (*,4)."""
    return torch.cat([q[..., :1], -q[..., 1:]], dim=-1)


def quat_rotate(q: Tensor, p: Tensor) -> Tensor:
    """Rotate vectors by unit quaternions: ``R(q) p``; (*,4), (*,3) -> (*,3) (broadcast)."""
    w, v = q[..., :1], q[..., 1:]
    if v.ndim != p.ndim:  # linalg.cross broadcasts only between equal ranks
        v, p = torch.broadcast_tensors(v, p)
    c = torch.linalg.cross(v, p, dim=-1)
    return p + 2.0 * (w * c + torch.linalg.cross(v, c, dim=-1))


def quat_exp(phi: Tensor) -> Tensor:
    """Rotation vector (*,3) rad -> unit quaternion (*,4) wxyz."""
    theta_sq = (phi * phi).sum(-1, keepdim=True)
    nonzero = theta_sq > 0
    theta = torch.sqrt(torch.where(nonzero, theta_sq, torch.ones_like(theta_sq)))
    half = 0.5 * theta
    k = torch.where(nonzero, torch.sin(half) / theta, torch.full_like(theta, 0.5))
    w = torch.where(nonzero, torch.cos(half), torch.ones_like(theta))
    return torch.cat([w, k * phi], dim=-1)


def quat_log(q: Tensor) -> Tensor:
    """Unit quaternion (*,4) -> the shortest rotation vector (*,3) rad, ``|φ| <= π``.

    ``q`` and ``-q`` give the same result (the double cover is resolved by taking ``w >= 0``).
    """
    q = torch.where(q[..., :1] < 0, -q, q)
    w, v = q[..., :1], q[..., 1:]
    s = torch.sqrt((v * v).sum(-1, keepdim=True))
    small = s < _LOG_SMALL
    s_safe = torch.where(small, torch.ones_like(s), s)
    ratio = torch.where(small, 2.0 / w, 2.0 * atan2_precise(s_safe, w) / s_safe)
    return ratio * v


def se3_exp(xi: Tensor) -> tuple[Tensor, Tensor]:
    """The rigid motion of a constant twist: ``exp([ρ, φ])`` as ``(q_Δ, p_Δ)``.

    Args:
        xi: (*,6) ``[ρ, φ] = dt·[v_o, ω]`` (metres, radians), camera frame.

    Returns:
        ``q_Δ`` (*,4) and ``p_Δ`` (*,3) with ``P' = R(q_Δ) P + p_Δ`` the exact solution of
        ``Ṗ = v_o + ω × P`` after ``dt``; ``p_Δ = V(φ) ρ`` with the SO(3) left Jacobian ``V``.
    """
    rho, phi = xi[..., :3], xi[..., 3:]
    q = quat_exp(phi)
    th2 = (phi * phi).sum(-1, keepdim=True)
    series = th2 < _SE3_SERIES_SQ
    th2_safe = torch.where(series, torch.ones_like(th2), th2)
    th = torch.sqrt(th2_safe)
    a_closed = (1.0 - torch.cos(th)) / th2_safe
    b_closed = (th - torch.sin(th)) / (th2_safe * th)
    # Taylor series of (1 - cos θ)/θ² and (θ - sin θ)/θ³ through θ⁶, in nested form whose
    # constants are exact in float32 (exported graphs store Python floats as float32):
    # 1/2 - θ²/24 + θ⁴/720 - θ⁶/40320  and  (1 - θ²/20 + θ⁴/840 - θ⁶/60480) / 6.
    a_series = 0.5 - th2 / 24.0 * (1.0 - th2 / 30.0 * (1.0 - th2 / 56.0))
    b_series = (1.0 - th2 / 20.0 * (1.0 - th2 / 42.0 * (1.0 - th2 / 72.0))) / 6.0
    a = torch.where(series, a_series, a_closed)
    b = torch.where(series, b_series, b_closed)
    c1 = torch.linalg.cross(phi, rho, dim=-1)
    c2 = torch.linalg.cross(phi, c1, dim=-1)
    return q, rho + a * c1 + b * c2


def pose_boxplus(t: Tensor, q: Tensor, delta: Tensor) -> tuple[Tensor, Tensor]:
    """``(t, q) ⊞ δ = (t + δt, exp(δθ) ⊗ q)``; t (*,3), q (*,4), δ (*,6) -> ((*,3), (*,4))."""
    return t + delta[..., :3], quat_mul(quat_exp(delta[..., 3:]), q)


def pose_boxminus(t1: Tensor, q1: Tensor, t0: Tensor, q0: Tensor) -> Tensor:
    """``(t1, q1) ⊟ (t0, q0) = [t1 - t0, log(q1 ⊗ q0⁻¹)]`` (*,6), the inverse of ⊞."""
    return torch.cat([t1 - t0, quat_log(quat_mul(q1, quat_conj(q0)))], dim=-1)
