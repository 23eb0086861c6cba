"""Quaternion and SE(3) kernels for the filters: a few tensor ops each, exportable to ONNX.

Conventions (docs/architecture.md, "Conventions"):
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

from evtrack.filters.linalg import use_portable

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
    "pivot_map",
]

# |v|/|q| below which log uses its series 2/w (error ~|v|^2/3, below float64 resolution).
_LOG_SMALL = 1e-8
# θ below which exp uses its limits (θ³ must not underflow; sin(θ/2)/θ = 1/2 to the last bit).
_TINY_ANGLE = 1e-20


def atan2_precise(y: Tensor, x: Tensor) -> Tensor:
    """``atan2(y, x)`` for ``y >= 0, x >= 0``, at full precision in float64 too.

    onnxruntime has no float64 ``Atan``; so while exporting, a float64 angle is taken in float32
    and refined by one Newton step with float64 ``sin``/``cos`` (error ~c³/6 for a float32
    error c ~ 1e-7). In eager mode this is ``torch.atan2``.

    Args:
        y, x: (*) non-negative (the first quadrant, as in :func:`quat_log`).

    Returns:
        (*) radians in ``[0, π/2]``.
    """
    if y.dtype != torch.float64 or not use_portable():
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
    return _exp_parts(phi)[0]


def _exp_parts(phi: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``exp(φ)`` and the pieces :func:`se3_exp` reuses: ``θ``, ``sin(θ/2)/θ``, ``θ`` made safe
    to divide by, even cubed (1 below ``_TINY_ANGLE``, where ``sin(θ/2)/θ`` is 1/2 exactly)."""
    theta = torch.linalg.vector_norm(phi, dim=-1, keepdim=True)
    half = 0.5 * theta
    nonzero = theta > _TINY_ANGLE
    theta_safe = torch.where(nonzero, theta, 1.0)
    k = torch.where(nonzero, torch.sin(half) / theta_safe, 0.5)  # sin(θ/2)/θ, 1/2 at θ = 0
    return torch.cat([torch.cos(half), k * phi], dim=-1), theta, k, theta_safe


def quat_log(q: Tensor) -> Tensor:
    """Unit quaternion (*,4) -> the shortest rotation vector (*,3) rad, ``|φ| <= π``.

    ``q`` and ``-q`` give the same result (the double cover is resolved by taking ``w >= 0``).
    """
    w, v = q[..., :1], q[..., 1:]
    s = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    aw = w.abs()  # the w >= 0 representative of ±q gives the shortest rotation
    small = s < _LOG_SMALL
    s_safe = torch.where(small, 1.0, s)
    ratio = torch.where(small, 2.0 / aw, 2.0 * atan2_precise(s_safe, aw) / s_safe)
    return torch.where(w < 0, -ratio, ratio) * v


def se3_exp(xi: Tensor) -> tuple[Tensor, Tensor]:
    """The rigid motion of a constant twist: ``exp([ρ, φ])`` as ``(q_Δ, p_Δ)``.

    Args:
        xi: (*,6) ``[ρ, φ] = dt·[v_o, ω]`` (metres, radians), camera frame.

    Returns:
        ``q_Δ`` (*,4) and ``p_Δ`` (*,3) with ``P' = R(q_Δ) P + p_Δ`` the exact solution of
        ``Ṗ = v_o + ω × P`` after ``dt``; ``p_Δ = V(φ) ρ`` with the SO(3) left Jacobian
        ``V = I + a [φ]× + b [φ]×²``, ``a = (1 − cos θ)/θ² = 2 (sin(θ/2)/θ)²`` and
        ``b = (θ − sin θ)/θ³``. ``b`` loses relative precision as ``θ → 0`` but multiplies a
        term of size ``θ² |ρ|``, so ``p_Δ`` keeps full precision (``b`` is unused below
        ``_TINY_ANGLE``).
    """
    rho, phi = xi[..., :3], xi[..., 3:]
    q, theta, k, theta_safe = _exp_parts(phi)
    a = 2.0 * k * k
    b = (theta - torch.sin(theta)) / (theta_safe * theta_safe * theta_safe)
    c1 = torch.linalg.cross(phi, rho, dim=-1)
    c2 = torch.linalg.cross(phi, c1, dim=-1)
    return q, rho + a * c1 + b * c2


def pose_boxplus(t: Tensor, q: Tensor, delta: Tensor) -> tuple[Tensor, Tensor]:
    """``(t, q) ⊞ δ = (t + δt, exp(δθ) ⊗ q)``; t (*,3), q (*,4), δ (*,6) -> ((*,3), (*,4))."""
    return t + delta[..., :3], quat_mul(quat_exp(delta[..., 3:]), q)


def pose_boxminus(t1: Tensor, q1: Tensor, t0: Tensor, q0: Tensor) -> Tensor:
    """``(t1, q1) ⊟ (t0, q0) = [t1 - t0, log(q1 ⊗ q0⁻¹)]`` (*,6), the inverse of ⊞."""
    return torch.cat([t1 - t0, quat_log(quat_mul(q1, quat_conj(q0)))], dim=-1)


def pivot_map(p: Tensor) -> Tensor:
    """``A = [[I, [p]×], [0, I]]`` (*,6,6) for pivots ``p`` (*,3), metres.

    Maps the twist ``[v, ω]`` of a motion about ``p`` (``v``: the velocity of the point ``p``)
    to the camera-frame twist ``[v_o, ω]`` of :func:`evtrack.geometry.integrate_twist`
    (``v_o = v − ω × p = v + p × ω``); a covariance ``Σ`` of ``[v, ω]`` becomes ``A Σ Aᵀ``.
    Built from stacks and concatenations only (ONNX-exportable).
    """
    zero = torch.zeros_like(p[..., 0])
    px, py, pz = p.unbind(-1)
    cross = torch.stack([zero, -pz, py, pz, zero, -px, -py, px, zero], dim=-1)
    cross = cross.reshape(*p.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=p.dtype, device=p.device).expand_as(cross)
    top = torch.cat([eye, cross], dim=-1)
    bottom = torch.cat([torch.zeros_like(eye), eye], dim=-1)
    return torch.cat([top, bottom], dim=-2)
