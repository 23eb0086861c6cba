"""Rigid-body helpers over kornia: poses as (R, t), 4x4 matrices and (t, q), and twists.

Conventions (docs/architecture.md, "Conventions"):
    * A pose is object-to-camera: ``P_c = R @ P_o + t``.
    * Quaternions are ``(w, x, y, z)``, unit norm, as in kornia; the sign is not canonicalised
      except by :func:`canonical_quaternion`.
    * A twist ``V = [v_o, ω]`` (m/s, rad/s) lives in the camera frame: every object point moves
      as ``Ṗ = v_o + ω × P``; hence ``ṫ = v_o + ω × t`` and ``Ṙ = [ω]× R``.

All functions take any leading batch shape ``(*)`` and do not modify their inputs.
"""

from __future__ import annotations

import torch
from kornia.geometry.conversions import (
    quaternion_to_rotation_matrix,
    rotation_matrix_to_quaternion,
)
from kornia.geometry.liegroup import Se3
from kornia.geometry.quaternion import Quaternion
from torch import Tensor

__all__ = [
    "skew",
    "pose_to_matrix",
    "matrix_to_pose",
    "tq_to_matrix",
    "matrix_to_tq",
    "quaternion_to_rotation_matrix",
    "rotation_matrix_to_quaternion",
    "canonical_quaternion",
    "compose",
    "inverse",
    "transform_points",
    "integrate_twist",
    "integrate_twist_tq",
    "twist_between",
]


def skew(w: Tensor) -> Tensor:
    """Skew-symmetric matrix ``[w]×`` so that ``[w]× @ p == w × p``.

    Args:
        w: (*, 3).

    Returns:
        (*, 3, 3).
    """
    zero = torch.zeros_like(w[..., 0])
    wx, wy, wz = w.unbind(-1)
    return torch.stack(
        [zero, -wz, wy, wz, zero, -wx, -wy, wx, zero], dim=-1
    ).reshape(*w.shape[:-1], 3, 3)


def pose_to_matrix(R: Tensor, t: Tensor) -> Tensor:
    """(R (*,3,3), t (*,3)) -> homogeneous (*,4,4)."""
    T = torch.zeros(*R.shape[:-2], 4, 4, dtype=R.dtype, device=R.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1
    return T


def matrix_to_pose(T: Tensor) -> tuple[Tensor, Tensor]:
    """Homogeneous (*,4,4) -> (R (*,3,3), t (*,3))."""
    return T[..., :3, :3].clone(), T[..., :3, 3].clone()


def canonical_quaternion(q: Tensor) -> Tensor:
    """Normalise and pick the sign with ``w >= 0`` (q and -q are the same rotation)."""
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def tq_to_matrix(t: Tensor, q: Tensor) -> Tensor:
    """(t (*,3) metres, q (*,4) wxyz) -> (*,4,4). ``q`` is normalised first."""
    q = q / q.norm(dim=-1, keepdim=True)
    return pose_to_matrix(quaternion_to_rotation_matrix(q), t)


def matrix_to_tq(T: Tensor) -> tuple[Tensor, Tensor]:
    """(*,4,4) -> (t (*,3), q (*,4) wxyz with w >= 0)."""
    R, t = matrix_to_pose(T)
    return t, canonical_quaternion(rotation_matrix_to_quaternion(R.contiguous()))


def compose(T_ab: Tensor, T_bc: Tensor) -> Tensor:
    """``T_ac = T_ab @ T_bc`` for homogeneous (*,4,4) transforms."""
    return T_ab @ T_bc


def inverse(T: Tensor) -> Tensor:
    """Inverse of a rigid (*,4,4) transform, using ``R^T`` (no general matrix inverse)."""
    R, t = matrix_to_pose(T)
    Rt = R.transpose(-1, -2)
    return pose_to_matrix(Rt, -(Rt @ t.unsqueeze(-1)).squeeze(-1))


def transform_points(T: Tensor, P: Tensor) -> Tensor:
    """Apply (*,4,4) to points (*,N,3) -> (*,N,3)."""
    return P @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]


def _se3_exp(xi: Tensor) -> Tensor:
    """exp of the se(3) element ``[ρ, φ]`` (*,6) as a (*,4,4) matrix (via kornia's Se3)."""
    M = Se3.exp(xi.reshape(-1, 6)).matrix()
    if not xi.requires_grad:  # kornia wraps the result in Parameters
        M = M.detach()
    return M.reshape(*xi.shape[:-1], 4, 4).to(xi.dtype)


def integrate_twist(T: Tensor, twist: Tensor, dt: float | Tensor) -> Tensor:
    """Move an object-to-camera pose by a constant camera-frame twist for ``dt`` seconds.

    Solves ``Ṗ = v_o + ω × P`` exactly: ``T(dt) = exp(dt·[ω× v_o; 0 0]) @ T``.

    Args:
        T: (*,4,4) object-to-camera pose at the start.
        twist: (*,6) ``[v_o (m/s), ω (rad/s)]`` in the camera frame.
        dt: seconds, a float or a tensor broadcastable to ``(*)``.

    Returns:
        (*,4,4) the pose after ``dt``.
    """
    dt = torch.as_tensor(dt, dtype=twist.dtype, device=twist.device)
    xi = twist * dt.unsqueeze(-1) if dt.ndim else twist * dt
    return _se3_exp(xi) @ T


def integrate_twist_tq(
    t: Tensor, q: Tensor, twist: Tensor, dt: float | Tensor
) -> tuple[Tensor, Tensor]:
    """:func:`integrate_twist` on a ``(t (*,3), q (*,4) wxyz)`` pose; returns ``(t', q')``."""
    return matrix_to_tq(integrate_twist(tq_to_matrix(t, q), twist, dt))


def twist_between(T0: Tensor, T1: Tensor, dt: float) -> Tensor:
    """The constant camera-frame twist that moves ``T0`` to ``T1`` in ``dt`` seconds.

    Inverse of :func:`integrate_twist`: ``log(T1 @ T0^-1) / dt`` (via kornia's Se3.log).

    Returns:
        (*,6) ``[v_o, ω]``.
    """
    D = T1 @ inverse(T0)
    flat = D.reshape(-1, 4, 4)
    R = flat[:, :3, :3]
    g = Se3(Quaternion(rotation_matrix_to_quaternion(R.contiguous())), flat[:, :3, 3])
    xi = g.log().detach().to(T0.dtype)
    return xi.reshape(*T0.shape[:-2], 6) / dt
