"""The interaction matrix: how a camera-frame twist moves the image of a point, in px/s.

Derivation (the convention ``Ṗ = v_o + ω × P``, OpenCV axes). For ``P = (X, Y, Z)`` with
normalised coordinates ``x = X/Z``, ``y = Y/Z`` and pixels ``u = fx x + cx``, ``v = fy y + cy``::

    Ẋ = v_x + ω_y Z − ω_z Y,   Ẏ = v_y + ω_z X − ω_x Z,   Ż = v_z + ω_x Y − ω_y X
    ẋ = Ẋ/Z − x Ż/Z = v_x/Z − x v_z/Z − x y ω_x + (1 + x²) ω_y − y ω_z
    ẏ = Ẏ/Z − y Ż/Z = v_y/Z − y v_z/Z − (1 + y²) ω_x + x y ω_y + x ω_z

and ``u̇ = fx ẋ``, ``v̇ = fy ẏ``. The flow is ``J V`` in px/s (not ``J V Δt``, which is a
displacement: the paper's printed form mixes the two, and prints the sign of ``(1 + y²) ω_x``
wrongly). ``tests/filters/test_interaction.py`` pins this against finite differences of the
projection.

Distortion: :func:`interaction_matrix` works in the camera's measured (distorted) pixels: it
undistorts ``uv`` and chains the ideal-pinhole matrix with the 2x2 Jacobian of the distortion.
The filters work in ideal pinhole pixels instead; :func:`undistort_flow` maps measured flows
there, constraint for constraint. Its per-pixel part (the iterative undistortion and the
Jacobian, ~5 ms a call on a CPU whatever the number of points) depends on the pixel only; an
:class:`UndistortionTable` keeps it for the pixels seen (a tracker's RoI centres are a fixed
grid), with the same values.
"""

from __future__ import annotations

import torch
from torch import Tensor

from evtrack.camera import PinholeCamera

__all__ = [
    "UndistortionTable",
    "interaction_matrix",
    "interaction_matrix_pinhole",
    "distortion_jacobian",
    "undistort_flow",
]


def interaction_matrix_pinhole(
    x: Tensor, y: Tensor, inv_depth: Tensor, fx: Tensor, fy: Tensor
) -> Tensor:
    """The interaction matrix from normalised coordinates (ideal pinhole, no checks).

    Args:
        x, y: (*) normalised image coordinates ``(u - cx)/fx``, ``(v - cy)/fy``.
        inv_depth: (*) ``1/Z`` in 1/m.
        fx, fy: focal lengths in pixels, broadcastable to ``(*)``.

    Returns:
        (*, 2, 6) px/s per unit twist ``[v_o (m/s), ω (rad/s)]``.
    """
    xy = x * y
    zero = torch.zeros_like(x)
    row_u = torch.stack([inv_depth, zero, -x * inv_depth, -xy, 1.0 + x * x, -y], dim=-1)
    row_v = torch.stack([zero, inv_depth, -y * inv_depth, -1.0 - y * y, xy, x], dim=-1)
    return torch.stack([row_u * fx[..., None], row_v * fy[..., None]], dim=-2)


def distortion_jacobian(camera: PinholeCamera, uv_ideal: Tensor) -> Tensor:
    """∂(distorted pixel)/∂(ideal pixel) at ideal pixels (*,2) -> (*,2,2) (identity if none)."""
    eye = torch.eye(2, dtype=uv_ideal.dtype, device=uv_ideal.device)
    if camera.dist is None:
        return eye.expand(*uv_ideal.shape[:-1], 2, 2).clone()
    with torch.enable_grad():
        p = uv_ideal.detach().clone().requires_grad_(True)
        out = camera.distort_points(p)
        # Each output point depends on its own input only, so one gradient per output
        # coordinate gives that row of every point's 2x2 Jacobian.
        rows = [torch.autograd.grad(out[..., i].sum(), p, retain_graph=i == 0)[0] for i in range(2)]
    return torch.stack(rows, dim=-2).detach()


def interaction_matrix(uv: Tensor, depth: Tensor, camera: PinholeCamera) -> Tensor:
    """Pixel velocity per unit twist at pixels with known depth.

    Args:
        uv: (*, 2) pixel coordinates as measured (distorted if the camera has distortion).
        depth: (*) z-depth in metres of the point seen at ``uv``.
        camera: the camera that measured ``uv``.

    Returns:
        (*, 2, 6) ``J`` with ``flow = J @ [v_o, ω]`` in px/s (``v_o`` m/s, ``ω`` rad/s, camera
        frame, ``Ṗ = v_o + ω × P``). Rows at a non-positive or non-finite depth are NaN: the
        filters skip such RoIs and count them.

    Example:
        >>> cam = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)
        >>> J = interaction_matrix(torch.tensor([[320.0, 240.0]]), torch.tensor([2.0]), cam)
        >>> J[0, 0, 0].item()  # fx / Z
        250.0
    """
    if uv.shape[-1] != 2 or depth.shape != uv.shape[:-1]:
        raise ValueError(
            f"interaction_matrix: uv must be (*, 2) and depth (*), got {tuple(uv.shape)} "
            f"and {tuple(depth.shape)}"
        )
    dtype = uv.dtype if uv.is_floating_point() else torch.float64
    uv = uv.to(dtype)
    depth = depth.to(dtype=dtype, device=uv.device)
    uv_ideal = camera.undistort_points(uv)
    fx = torch.tensor(camera.fx, dtype=dtype, device=uv.device)
    fy = torch.tensor(camera.fy, dtype=dtype, device=uv.device)
    x = (uv_ideal[..., 0] - camera.cx) / fx
    y = (uv_ideal[..., 1] - camera.cy) / fy
    ok = torch.isfinite(depth) & (depth > 0)
    inv_depth = torch.where(ok, 1.0 / torch.where(ok, depth, torch.ones_like(depth)), torch.nan)
    J = interaction_matrix_pinhole(x, y, inv_depth, fx.expand_as(x), fy.expand_as(x))
    J = torch.where(ok[..., None, None], J, torch.nan)
    if camera.dist is not None:
        J = distortion_jacobian(camera, uv_ideal) @ J
    return J


class UndistortionTable:
    """The ideal pixel and the distortion Jacobian of each measured pixel a camera has been
    asked for, computed once (by :meth:`PinholeCamera.undistort_points
    <evtrack.camera.PinholeCamera.undistort_points>` and :func:`distortion_jacobian`, on the
    new pixels of a call together) and looked up afterwards: the values of the direct
    computation (each point's arithmetic does not depend on the others'), without its cost.

    Args:
        camera: a camera with distortion.
        max_points: the table starts afresh beyond this many pixels.

    Only float64 CPU pixels that are all finite, without gradients, are looked up
    (:meth:`applies`).
    """

    def __init__(self, camera: PinholeCamera, max_points: int = 1 << 16) -> None:
        self.camera = camera
        self.max_points = int(max_points)
        self._points: dict[tuple[float, float], tuple[list[float], list[list[float]]]] = {}

    @staticmethod
    def applies(uv: Tensor) -> bool:
        """Whether :meth:`lookup` takes ``uv``: float64 on the CPU, all finite, no
        gradient asked for."""
        return (uv.dtype == torch.float64 and uv.device.type == "cpu" and not uv.requires_grad
                and bool(torch.isfinite(uv).all()))

    def __len__(self) -> int:
        return len(self._points)

    def lookup(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        """``(uv_ideal (*, 2), D (*, 2, 2))`` of measured pixels ``uv`` (*, 2) (see
        :meth:`applies`), as ``camera.undistort_points(uv)`` and
        ``distortion_jacobian(camera, uv_ideal)`` give them."""
        keys = [(u, v) for u, v in uv.reshape(-1, 2).tolist()]
        points = self._points
        new = [k for k in dict.fromkeys(keys) if k not in points]
        if new:
            if len(points) + len(new) > self.max_points:  # afresh, with all of this call's
                points.clear()
                new = list(dict.fromkeys(keys))
            ideal = self.camera.undistort_points(torch.tensor(new, dtype=torch.float64))
            jac = distortion_jacobian(self.camera, ideal)
            points.update(zip(new, zip(ideal.tolist(), jac.tolist(), strict=True), strict=True))
        found = [points[k] for k in keys]
        shape = uv.shape[:-1]
        ideal = torch.tensor([f[0] for f in found], dtype=torch.float64).reshape(*shape, 2)
        jac = torch.tensor([f[1] for f in found], dtype=torch.float64).reshape(*shape, 2, 2)
        return ideal, jac


def undistort_flow(
    camera: PinholeCamera, uv: Tensor, flow: Tensor, normal_only: Tensor,
    table: UndistortionTable | None = None,
) -> tuple[Tensor, Tensor]:
    """Map measured pixels and flows to the ideal pinhole image, constraint for constraint.

    With ``D`` the distortion Jacobian at the ideal pixel, a full flow maps to ``D⁻¹ F``; a
    normal flow ``F = m n`` (constraint ``nᵀ f_d = m``) maps to the normal flow ``(m/|g|) g/|g|``
    with ``g = Dᵀ n``, which states the same constraint on the ideal-image flow. Without
    distortion the inputs come back unchanged.

    Args:
        uv: (*, 2) measured pixels; flow: (*, 2) px/s; normal_only: (*) bool.
        table: the camera's :class:`UndistortionTable`, used where it applies: the same
            results, the per-pixel part computed once per pixel.

    Returns:
        ``(uv_ideal, flow_ideal)``, both (*, 2).
    """
    if camera.dist is None:
        return uv, flow
    if table is not None and table.applies(uv):
        uv_ideal, D = table.lookup(uv)
    else:
        uv_ideal = camera.undistort_points(uv)
        D = distortion_jacobian(camera, uv_ideal)
    full = torch.linalg.solve(D, flow.unsqueeze(-1)).squeeze(-1)
    m = flow.norm(dim=-1, keepdim=True)
    n = flow / m.clamp_min(torch.finfo(flow.dtype).tiny)
    g = (D.transpose(-1, -2) @ n.unsqueeze(-1)).squeeze(-1)
    g2 = (g * g).sum(-1, keepdim=True).clamp_min(torch.finfo(flow.dtype).tiny)
    normal = g * (m / g2)
    return uv_ideal, torch.where(normal_only[..., None], normal, full)
