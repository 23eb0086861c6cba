"""The ``ge`` baseline: a velocity filter on the 1-DoF generative event model.

The group's earlier hybrid tracker measured the object's motion with a generative event model:
an event is a log-brightness change of one contrast step, and a moving brightness pattern
changes the log brightness at a pixel at the rate ``∂L/∂t = −∇L · u`` (brightness constancy),
``u = J(x, z) V`` the pixel velocity of the twist (:func:`evtrack.filters.interaction_matrix`).
An event of polarity ``p`` at pixel ``x``, ``Δt`` after the previous event of that pixel, then
gives one number (1 degree of freedom), the residual between the observed and the predicted
brightness change::

    r = p C − (−Δt ∇L(x)ᵀ J(x, z) V)

Linear in ``V``: each event is one Kalman row ``h = −Δt ∇Lᵀ J``, measurement ``p C``, noise
``residual_std²``. The gradient ``∇L`` comes from the latest RGB frame (log luminance, Gaussian
smoothed) carried to the present with the tracker's pose estimates: the event's surface point
(depth from the depth source) is moved from the current predicted pose to the pose at the frame
time and projected there; the gradient there is mapped back by the transpose of that warp's
2x2 Jacobian (chain rule). The velocity state uses the same decaying model as
:class:`~evtrack.filters.VelocityKF` (``alpha`` per ``alpha_dt``, process-noise densities).

This is the velocity front end only; the pose fusion is the tracker's, as for ``full``.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch
from torch import Tensor

from evtrack.camera import PinholeCamera
from evtrack.events import Events
from evtrack.filters.config import VelocityKFConfig
from evtrack.filters.interaction import interaction_matrix_pinhole
from evtrack.tracking.config import GEConfig

__all__ = ["GEVelocity", "log_gradient"]

_LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)  # Rec. 709, linear RGB


def log_gradient(rgb: np.ndarray, sigma: float, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """Gradient (1/px) of the smoothed log luminance of an 8-bit sRGB image.

    Returns:
        ``(gx, gy)``, each (H, W) float32: ``∂L/∂u`` and ``∂L/∂v`` with ``L = log(Y + eps)``.
    """
    x = np.asarray(rgb, np.float32) / 255.0
    lin = np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
    L = np.log(lin @ _LUMA + eps).astype(np.float32)
    L = cv2.GaussianBlur(L, (0, 0), sigma)
    gx = cv2.Sobel(L, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 8.0)
    gy = cv2.Sobel(L, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 8.0)
    return gx, gy


class GEVelocity:
    """Twist from events through the generative event model (see the module docstring).

    Args:
        camera: the event camera (ideal pinhole pixels are used; distortion is undone).
        config: :class:`~evtrack.tracking.config.GEConfig`.
        kf_config: the decaying-velocity model and initial covariance (``alpha``,
            ``alpha_dt``, ``q_linear``, ``q_angular``, ``init_std_*``).
        device: where the state lives.
    """

    def __init__(self, camera: PinholeCamera, config: GEConfig,
                 kf_config: VelocityKFConfig, device: str | torch.device = "cpu") -> None:
        self.camera = camera
        self.config = config
        self.kf_config = kf_config
        self.device = torch.device(device)
        kw = {"dtype": torch.float64, "device": self.device}
        self._q = torch.tensor([kf_config.q_linear] * 3 + [kf_config.q_angular] * 3, **kw)
        self._init_var = torch.tensor([kf_config.init_std_linear ** 2] * 3
                                      + [kf_config.init_std_angular ** 2] * 3, **kw)
        self._log_alpha_rate = math.log(kf_config.alpha) / kf_config.alpha_dt
        self.reset()

    def reset(self) -> None:
        """Zero twist, initial covariance, no pixel history, no frame."""
        kw = {"dtype": torch.float64, "device": self.device}
        self.twist = torch.zeros(1, 6, **kw)
        self.cov = torch.diag(self._init_var).unsqueeze(0).clone()
        self.last_t = np.full((self.camera.height, self.camera.width), -(1 << 62), np.int64)
        self._grad: tuple[np.ndarray, np.ndarray] | None = None
        self._frame_pose: np.ndarray | None = None
        self.last_rows = 0
        self.rows_total = 0

    def set_frame(self, t_us: int, rgb: np.ndarray, pose_at_frame: np.ndarray | None) -> None:
        """Take the gradient of a new RGB frame and the object's pose at its time (4, 4);
        without a pose (not initialised) the frame cannot be carried and is not used."""
        if pose_at_frame is None or not np.isfinite(pose_at_frame).all():
            self._grad, self._frame_pose = None, None
            return
        self._grad = log_gradient(rgb, self.config.blur_sigma_px, self.config.log_eps)
        self._frame_pose = np.asarray(pose_at_frame, np.float64)

    # ------------------------------------------------------------------ filter
    def predict(self, dt: float) -> None:
        """``V = a V``, ``P = a² P + Q dt`` with ``a = alpha ** (dt / alpha_dt)``."""
        a = math.exp(self._log_alpha_rate * dt)
        self.twist = self.twist * a
        self.cov = self.cov * (a * a) + torch.diag(self._q * dt).unsqueeze(0)

    def update(self, H: Tensor, z: Tensor) -> None:
        """Information-form update with rows ``H`` (N, 6) and values ``z`` (N,)."""
        info = 1.0 / self.config.residual_std ** 2
        prior_info = torch.linalg.inv(self.cov[0])
        lam = prior_info + info * H.T @ H
        cov = torch.linalg.inv(lam)
        cov = 0.5 * (cov + cov.T)
        V = cov @ (prior_info @ self.twist[0] + info * H.T @ z)
        self.twist, self.cov = V.unsqueeze(0), cov.unsqueeze(0)

    # ------------------------------------------------------------------ one step
    def step(self, dt: float, events: Events, pose: np.ndarray | None,
             depth_fn) -> Tensor:
        """Predict over ``dt`` s, then update with the step's events on the object.

        Args:
            dt: step length, seconds.
            events: the step's events inside the predicted silhouette (time-sorted).
            pose: the predicted pose (4, 4) now, or ``None`` (no update).
            depth_fn: ``depth_fn(uv (N,2)) -> (N,)`` metres at event pixels (never NaN).

        Returns:
            the twist (1, 6).
        """
        self.predict(dt)
        self.last_rows = 0
        if not len(events):
            return self.twist
        x = events.x.numpy().astype(np.int64)
        y = events.y.numpy().astype(np.int64)
        t = events.t.numpy()
        p = events.p.numpy().astype(np.float64)
        prev = self._previous_times(x, y, t)
        if pose is None or self._grad is None:
            return self.twist
        cfg = self.config
        dt_e = (t - prev) * 1e-6
        ok = (dt_e > 0) & (dt_e <= cfg.max_dt_ms * 1e-3)
        idx = np.nonzero(ok)[0]
        if len(idx) > cfg.max_events:
            idx = idx[np.linspace(0, len(idx) - 1, cfg.max_events).astype(np.int64)]
        if len(idx) == 0:
            return self.twist
        uv = np.stack([x[idx], y[idx]], 1).astype(np.float64)
        if self.camera.dist is not None:
            uv = self.camera.undistort_points(torch.from_numpy(uv)).numpy()
        z = np.asarray(depth_fn(uv), np.float64)
        g = self._carried_gradient(uv, z, pose)
        keep = np.isfinite(g).all(1) & (np.linalg.norm(g, axis=1) >= cfg.min_gradient)
        if not keep.any():
            return self.twist
        uv, z, g, idx = uv[keep], z[keep], g[keep], idx[keep]
        cam = self.camera
        xn = torch.from_numpy((uv[:, 0] - cam.cx) / cam.fx)
        yn = torch.from_numpy((uv[:, 1] - cam.cy) / cam.fy)
        J = interaction_matrix_pinhole(xn, yn, torch.from_numpy(1.0 / z),
                                       torch.full_like(xn, cam.fx), torch.full_like(xn, cam.fy))
        G = torch.from_numpy(g)
        H = -torch.from_numpy(dt_e[idx]).unsqueeze(1) * (G.unsqueeze(1) @ J).squeeze(1)
        meas = torch.from_numpy(p[idx] * cfg.contrast)
        self.update(H.to(self.device), meas.to(self.device))
        self.last_rows = len(idx)
        self.rows_total += len(idx)
        return self.twist

    def _previous_times(self, x: np.ndarray, y: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Time of the previous event at each event's pixel (any polarity); updates the map."""
        flat = y * self.camera.width + x
        order = np.lexsort((np.arange(len(t)), flat))  # by pixel, then stream order
        f_sorted = flat[order]
        t_sorted = t[order]
        prev_sorted = np.empty_like(t_sorted)
        first = np.ones(len(order), bool)
        first[1:] = f_sorted[1:] != f_sorted[:-1]
        prev_sorted[first] = self.last_t.reshape(-1)[f_sorted[first]]
        prev_sorted[~first] = t_sorted[np.nonzero(~first)[0] - 1]
        prev = np.empty_like(t)
        prev[order] = prev_sorted
        last = np.ones(len(order), bool)
        last[:-1] = f_sorted[1:] != f_sorted[:-1]
        self.last_t.reshape(-1)[f_sorted[last]] = t_sorted[last]
        return prev

    def _carried_gradient(self, uv: np.ndarray, z: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """∇L at the present pixels: warp to the frame (pose now -> pose at the frame), read the
        frame's gradient there, map it back with the warp's Jacobian transposed."""
        cam = self.camera
        D = self._frame_pose @ np.linalg.inv(pose)  # present camera point -> frame camera point

        def warp(u: np.ndarray, v: np.ndarray) -> np.ndarray:
            P = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], 1)
            Q = P @ D[:3, :3].T + D[:3, 3]
            return np.stack([cam.fx * Q[:, 0] / Q[:, 2] + cam.cx,
                             cam.fy * Q[:, 1] / Q[:, 2] + cam.cy], 1)

        w0 = warp(uv[:, 0], uv[:, 1])
        du = warp(uv[:, 0] + 1.0, uv[:, 1]) - w0  # columns of the 2x2 Jacobian
        dv = warp(uv[:, 0], uv[:, 1] + 1.0) - w0
        gx, gy = self._grad
        h, w = gx.shape
        ui = np.rint(w0[:, 0]).astype(np.int64)
        vi = np.rint(w0[:, 1]).astype(np.int64)
        inside = (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
        ui, vi = np.clip(ui, 0, w - 1), np.clip(vi, 0, h - 1)
        gf = np.stack([gx[vi, ui], gy[vi, ui]], 1).astype(np.float64)
        # ∇_x L_now = Wᵀ ∇L_frame, W = [du dv]
        g = np.stack([(du * gf).sum(1), (dv * gf).sum(1)], 1)
        g[~inside] = np.nan
        return g
