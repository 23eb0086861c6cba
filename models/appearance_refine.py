"""Appearance refinement: a pose corrected by aligning the textured mesh's render with an RGB
frame (render-and-compare), with nothing trained.

:class:`AppearanceRefiner` renders the object's textured mesh at a predicted pose, keeps the
rendered pixels inside the silhouette (eroded by ``erode_px``, so the background at the rim
does not count) where the render's texture has the strongest gradients, lifts them to 3-D with
the render's depth, and finds the rigid motion that makes the RGB frame, sampled where those
points project, look like the render:

    minimise over [δt, δθ]   Σᵢ ρ( a · I(π(exp(δθ) R Xᵢ + t + δt)) + b − Tᵢ )

with ``Xᵢ`` the points in the object frame, ``(R, t)`` the pose, ``π`` the pinhole projection,
``I`` the frame's luminance (linear RGB), ``Tᵢ`` the render's, ``a, b`` a gain and offset solved
at every step from the two's means and spreads (the frame's exposure and light are not the
render's), and ``ρ``
Huber's loss on a scale from the residuals' median absolute deviation. Gauss-Newton steps run
coarse to fine over Gaussian blurs of ``levels`` pixels (the coarse ones reach corrections of
tens of degrees and take the frame's motion blur), then the mesh is rendered again at the
result (``renders``) so that what is visible matches the new pose.

It measures what a depth frame cannot: the turn of a can about its own axis, or of a box
about the normal of the face in view, shows only in the texture. It measures poorly what the
depth measures well, the distance along the viewing ray; :attr:`AppearanceResult.information`
says which is which, so a filter weighs each direction by what the image saw.

The perturbation is the pose filter's: ``[δt, δθ]`` (m, rad) in the camera frame, the rotation
about the object's origin (``R ← exp(δθ) R``, ``t ← t + δt``). The renderer is a pinhole; a
frame of a distorted camera is undistorted first (onto the same intrinsics).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError

__all__ = ["AppearanceRefineConfig", "AppearanceResult", "AppearanceRefiner"]

MESH_SIZE_M = (0.005, 3.0)
"""The diagonal of the mesh's bounding box must lie in this range (metres): anything else is a
mesh in other units."""


@dataclass(frozen=True)
class AppearanceRefineConfig:
    """Settings of :class:`AppearanceRefiner`.

    Attributes:
        levels: Gaussian blurs (standard deviation, px) of the coarse-to-fine passes; the first
            sets how far the fit reaches (a few times its blur, in pixels of motion).
        iterations: Gauss-Newton steps per pass at most.
        renders: renders per refinement: the first at the given pose, fitted at every blur of
            ``levels``; each next one at the previous result (what is visible follows the
            pose), fitted at the finest blur only.
        max_pixels: template pixels of a pass at most (the strongest render gradients).
        min_pixels: fewest template pixels to fit (fewer: refused, ``"few pixels"``).
        min_gradient: template pixels need a render gradient at least this strong (linear
            luminance per pixel, at the pass's blur): a flat, evenly lit face has nothing to
            align.
        erode_px: template pixels lie deeper than this inside the silhouette, plus the pass's
            blur: the frame's background blurs into the rim.
        margin_px: the frame is cropped to the render's bounding box grown by this (pixels):
            the farthest the object may appear from its predicted place.
        huber: Huber's threshold in units of the residuals' robust scale.
        min_correlation: the correlation of the frame's and the render's luminance at the
            template pixels after the fit (finest pass) below which the fit is refused
            (``"low correlation"``): the frame does not show the rendered texture there.
        max_rotation_deg, max_translation_m: larger corrections are refused
            (``"correction too large"``).
        tolerance: a pass stops when a step turns less than this (rad) and moves less than
            this times the object's distance.
    """

    levels: tuple[float, ...] = (4.0, 2.0, 1.0)
    iterations: int = 10
    renders: int = 2
    max_pixels: int = 3000
    min_pixels: int = 100
    min_gradient: float = 1e-3
    erode_px: int = 2
    margin_px: int = 48
    huber: float = 1.345
    min_correlation: float = 0.5
    max_rotation_deg: float = 60.0
    max_translation_m: float = 0.2
    tolerance: float = 1e-5

    def __post_init__(self) -> None:
        if not self.levels or any(not (s > 0) for s in self.levels):
            raise ConfigError(f"appearance refinement: levels must be positive blurs (px), got "
                              f"{self.levels}")
        for name in ("iterations", "renders", "max_pixels", "min_pixels", "huber",
                     "max_rotation_deg", "max_translation_m", "tolerance"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"appearance refinement: {name} must be positive, got "
                                  f"{getattr(self, name)}")
        if self.erode_px < 0 or self.margin_px < 0 or self.min_gradient < 0:
            raise ConfigError("appearance refinement: erode_px, margin_px and min_gradient "
                              "must be >= 0")
        if not -1 <= self.min_correlation <= 1:
            raise ConfigError(f"appearance refinement: min_correlation must be in [-1, 1], got "
                              f"{self.min_correlation}")


@dataclass(frozen=True)
class AppearanceResult:
    """The outcome of one appearance refinement.

    Attributes:
        pose: (4, 4) float64 object-to-camera pose: refined, or the input when refused.
        refined: whether the frame refined the pose.
        pixels: template pixels of the finest pass.
        correlation: correlation of the frame's and the render's luminance at those pixels
            after the fit (NaN when not fitted).
        residual_std: robust standard deviation of the luminance residuals of the finest pass
            (linear luminance units, NaN when not fitted).
        information: (6, 6) Gauss-Newton normal matrix ``Σ w J Jᵀ`` of the finest pass at
            the final pose, per unit residual variance, for ``[δt, δθ]`` (m, rad, see the
            module docstring): ``residual_std² · information⁻¹`` is the fit's covariance if the
            pixels' errors were independent. ``None`` when refused.
        refusal: ``""`` (refined), ``"not visible"`` (the mesh at the pose covers too few
            pixels of the image), ``"few pixels"``, ``"low correlation"``, ``"correction too
            large"`` or ``"diverged"`` (the fit left the image or the numbers).
        reason: the refusal in words (``""`` when refined).
    """

    pose: np.ndarray
    refined: bool
    pixels: int = 0
    correlation: float = float("nan")
    residual_std: float = float("nan")
    information: np.ndarray | None = None
    refusal: str = ""
    reason: str = ""


def luminance(rgb: np.ndarray) -> np.ndarray:
    """(H, W) float32 linear luminance of a uint8 sRGB image (decoded to linear first) or of a
    float linear RGB image, (H, W, 3)."""
    from evtrack.sim.frames import luminance as linear_luminance
    from evtrack.sim.frames import srgb_to_linear

    lin = srgb_to_linear(rgb) if rgb.dtype == np.uint8 else rgb
    return np.ascontiguousarray(linear_luminance(lin))


class _Refused(Exception):
    """A fit given up: ``refusal`` (the kind) and ``reason`` (in words)."""

    def __init__(self, refusal: str, reason: str) -> None:
        super().__init__(reason)
        self.refusal, self.reason = refusal, reason


_DIVERGED = ("diverged", "the fit left the image or became non-finite")


def _rotation(w: np.ndarray) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(w, np.float64).reshape(3, 1))
    return R


def _rotation_angle(R: np.ndarray) -> float:
    return math.acos(max(-1.0, min(1.0, (float(np.trace(R)) - 1.0) / 2.0)))


class AppearanceRefiner:
    """Refines object poses on RGB frames against the textured mesh (see the module docstring).

    Args:
        mesh: the object's textured :class:`~evtrack.sim.objects.ObjectMesh` (object frame,
            metres), e.g. from :func:`evtrack.sim.objects.load_mesh`.
        camera: the RGB camera (intrinsics, size, optional distortion).
        config: settings.
        renderer_factory: ``(pinhole camera) -> renderer`` with ``set_object(mesh)`` and
            ``render(pose) -> RenderOutput`` (default :class:`evtrack.sim.renderer.Renderer`,
            headless OpenGL). One renderer is made per calling thread (a GL context belongs to
            the thread that made it).

    Example::

        refiner = AppearanceRefiner(load_mesh("object.glb", recenter=False), camera)
        result = refiner.refine(predicted_pose, rgb)      # rgb: uint8 (H, W, 3)
        if result.refined:
            pose, information = result.pose, result.information
    """

    def __init__(self, mesh, camera: PinholeCamera, config: AppearanceRefineConfig | None = None,
                 renderer_factory: Callable[[PinholeCamera], object] | None = None) -> None:
        faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))))
        if faces.ndim != 2 or faces.shape[0] == 0:
            raise ConfigError("appearance refinement needs a textured mesh with faces; got one "
                              "without faces")
        verts = np.asarray(mesh.vertices, np.float64)
        size = float(np.linalg.norm(verts.max(0) - verts.min(0))) if len(verts) else 0.0
        if not MESH_SIZE_M[0] <= size <= MESH_SIZE_M[1]:
            raise ConfigError(f"appearance refinement: the mesh is {size:.4g} across, outside "
                              f"{MESH_SIZE_M[0]}-{MESH_SIZE_M[1]} m: its vertices must be in "
                              "metres (a mesh in millimetres: scale it by 0.001, or load it "
                              "with evtrack.sim.objects.load_mesh(path, scale=0.001))")
        self.mesh = mesh
        self.config = config or AppearanceRefineConfig()
        self.camera = camera
        self.pinhole = PinholeCamera(camera.fx, camera.fy, camera.cx, camera.cy, camera.width,
                                     camera.height)
        self.K = self.pinhole.K().numpy()
        self._undistort = None
        if camera.dist is not None:
            self._undistort = cv2.initUndistortRectifyMap(
                self.K, camera.dist.numpy(), None, self.K, (camera.width, camera.height),
                cv2.CV_32FC1)
        self._factory = renderer_factory
        self._renderers: dict[int, object] = {}
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ parts
    def _renderer(self):
        key = threading.get_ident()
        with self._lock:
            renderer = self._renderers.get(key)
            if renderer is None:
                if self._factory is None:
                    from evtrack.sim.renderer import Renderer

                    renderer = Renderer(self.pinhole)
                else:
                    renderer = self._factory(self.pinhole)
                renderer.set_object(self.mesh)
                self._renderers[key] = renderer
        return renderer

    def release(self) -> None:
        """Free the renderers (their GL contexts)."""
        with self._lock:
            for renderer in self._renderers.values():
                release = getattr(renderer, "release", None)
                if release is not None:
                    release()
            self._renderers = {}

    def _checked_frame(self, rgb: np.ndarray) -> np.ndarray:
        rgb = np.asarray(rgb)
        size = (self.camera.height, self.camera.width)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[:2] != size:
            raise ValueError(f"appearance refinement: the RGB frame must be (H, W, 3) = "
                             f"({size[0]}, {size[1]}, 3), got {rgb.shape}")
        return rgb

    def frame_luminance(self, rgb: np.ndarray, box: tuple[int, int, int, int] | None = None
                        ) -> np.ndarray:
        """Float32 linear luminance of an RGB frame undistorted onto the pinhole: the whole
        (H, W) image, or the rows ``r0:r1`` and columns ``c0:c1`` of ``box = (r0, r1, c0,
        c1)``.

        Raises:
            ValueError: not an (H, W, 3) image of the camera's size.
        """
        rgb = self._checked_frame(rgb)
        r0, r1, c0, c1 = box if box is not None else (0, rgb.shape[0], 0, rgb.shape[1])
        if self._undistort is None:
            return luminance(rgb[r0:r1, c0:c1])
        mx, my = (m[r0:r1, c0:c1] for m in self._undistort)
        return luminance(cv2.remap(rgb, mx, my, cv2.INTER_LINEAR))

    # ------------------------------------------------------------------ the fit
    def refine(self, pose: np.ndarray | torch.Tensor, rgb: np.ndarray,
               translation_std_m: float | None = None,
               ignore: np.ndarray | None = None) -> AppearanceResult:
        """Refine one object-to-camera pose on an RGB frame.

        Args:
            pose: (4, 4) object-to-camera transform (metres), e.g. a filter's prediction.
            rgb: (H, W, 3) frame of the camera: uint8 sRGB, or float linear RGB.
            translation_std_m: a Gaussian prior on the fit's move of the position (standard
                deviation, m), for a pose whose position is already known better than the
                image tells it (e.g. from a depth fit: an image sees the distance along the
                viewing ray poorly, and the fit may slide along it). ``None``: no prior. The
                returned information holds the image's part alone.
            ignore: (H, W) bool, pixels of the frame to leave out (e.g. where another object
                hides this one); ``None``: none.

        Raises:
            ValueError: a pose that is not a finite (4, 4) matrix, or a frame of another size.
        """
        T0 = np.asarray(pose.detach().cpu() if isinstance(pose, torch.Tensor) else pose,
                        np.float64)
        if T0.shape != (4, 4) or not np.isfinite(T0).all():
            raise ValueError(f"appearance refinement: pose must be a finite (4, 4) matrix, got "
                             f"shape {T0.shape}")
        frame = self._checked_frame(rgb)
        if ignore is not None:
            ignore = np.asarray(ignore, bool)
            if ignore.shape != frame.shape[:2]:
                raise ValueError(f"appearance refinement: ignore must be {frame.shape[:2]}, "
                                 f"got {ignore.shape}")
        cfg = self.config
        if T0[2, 3] <= 0:
            return AppearanceResult(T0, False, refusal="not visible",
                                    reason=f"the object's origin is not in front of the camera "
                                           f"(z = {T0[2, 3]:.3f} m)")
        if translation_std_m is not None and not translation_std_m > 0:
            raise ValueError(f"appearance refinement: translation_std_m must be positive, got "
                             f"{translation_std_m}")
        anchor = None if translation_std_m is None else (T0[:3, 3].copy(), translation_std_m)
        T = T0.copy()
        try:
            for k in range(cfg.renders):
                levels = cfg.levels if k == 0 else cfg.levels[-1:]
                T, pixels, corr, scale, info = self._fit_render(T, frame, levels, anchor,
                                                                ignore)
        except _Refused as refused:
            return AppearanceResult(T0, False, refusal=refused.refusal, reason=refused.reason)
        turned = math.degrees(_rotation_angle(T[:3, :3] @ T0[:3, :3].T))
        moved = float(np.linalg.norm(T[:3, 3] - T0[:3, 3]))
        if turned > cfg.max_rotation_deg or moved > cfg.max_translation_m:
            return AppearanceResult(T0, False, pixels, corr, scale, refusal="correction too large",
                                    reason=f"the fit turned the pose {turned:.1f}° and moved it "
                                           f"{moved:.3f} m (at most {cfg.max_rotation_deg}° and "
                                           f"{cfg.max_translation_m} m)")
        if not corr >= cfg.min_correlation:
            return AppearanceResult(T0, False, pixels, corr, scale, refusal="low correlation",
                                    reason=f"the frame correlates {corr:.2f} with the render "
                                           f"after the fit (min_correlation "
                                           f"{cfg.min_correlation})")
        return AppearanceResult(T, True, pixels, corr, scale, info)

    def _fit_render(self, T: np.ndarray, frame: np.ndarray, levels: tuple[float, ...],
                    anchor: tuple[np.ndarray, float] | None = None,
                    ignore: np.ndarray | None = None):
        """Render at ``T`` and fit at the blurs ``levels`` in turn: ``(pose, pixels,
        correlation, scale, information)``.

        Raises:
            _Refused: the object is not visible, too few pixels, or the fit diverged.
        """
        cfg = self.config
        out = self._renderer().render(T)
        mask = np.asarray(out.mask, bool)
        if ignore is not None:  # away from the ignored pixels as from the silhouette's rim
            mask = mask & ~ignore
        if int(mask.sum()) < cfg.min_pixels:
            raise _Refused("not visible", f"the mesh at the pose covers {int(mask.sum())} "
                                          f"pixels of the image (min_pixels {cfg.min_pixels})")
        rows, cols = np.nonzero(mask)
        H, W = mask.shape
        m = cfg.margin_px
        r0, r1 = max(0, rows.min() - m), min(H, rows.max() + m + 1)
        c0, c1 = max(0, cols.min() - m), min(W, cols.max() + m + 1)
        template = luminance(out.rgb[r0:r1, c0:c1])
        image = self.frame_luminance(frame, (r0, r1, c0, c1))
        inside = mask[r0:r1, c0:c1]
        # each pixel's distance from the silhouette's rim: a pass at blur s keeps the pixels
        # deeper than erode_px + s, whose blurred values the background barely reaches
        depth_px = cv2.distanceTransform(inside.astype(np.uint8), cv2.DIST_L2, 3)
        vs, us = np.nonzero(depth_px > cfg.erode_px)
        rim = depth_px[vs, us]
        if len(vs) < cfg.min_pixels:
            raise _Refused("few pixels", f"{len(vs)} pixels inside the eroded silhouette "
                                         f"(min_pixels {cfg.min_pixels})")
        z = np.asarray(out.depth, np.float64)[vs + r0, us + c0]
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        X_cam = np.stack([(us + c0 - cx) / fx * z, (vs + r0 - cy) / fy * z, z], 1)
        X_obj = (X_cam - T[:3, 3]) @ T[:3, :3]
        # crop coordinates: the camera's principal point moved by the crop's corner
        K = (fx, fy, cx - c0, cy - r0)
        fit = None
        for sigma in levels:
            deep = rim > cfg.erode_px + sigma
            fit = self._fit_level(T, X_obj[deep], us[deep], vs[deep], template, inside, image,
                                  sigma, K, anchor)
            T = fit[0]
        return fit

    def _fit_level(self, T: np.ndarray, X_obj: np.ndarray, us: np.ndarray, vs: np.ndarray,
                   template: np.ndarray, inside: np.ndarray, image: np.ndarray, sigma: float,
                   K: tuple[float, float, float, float],
                   anchor: tuple[np.ndarray, float] | None = None):
        """Gauss-Newton steps at one blur: ``(pose, pixels, correlation, scale, information)``;
        ``anchor`` ``(t0, σ)``: the translation prior (see :meth:`refine`).

        Raises:
            _Refused: too few textured pixels, or the fit diverged.
        """
        cfg = self.config
        fx, fy, cx, cy = K
        # the render blurred over the object alone (normalised convolution): no edge against
        # the render's empty background, which the frame's background does not share
        weight = cv2.GaussianBlur(inside.astype(np.float32), (0, 0), sigma)
        tb = cv2.GaussianBlur(template * inside, (0, 0), sigma) / np.maximum(weight, 1e-6)
        ib = cv2.GaussianBlur(image, (0, 0), sigma)
        tgx = cv2.Sobel(tb, cv2.CV_32F, 1, 0, ksize=3) / 8.0
        tgy = cv2.Sobel(tb, cv2.CV_32F, 0, 1, ksize=3) / 8.0
        gx = cv2.Sobel(ib, cv2.CV_32F, 1, 0, ksize=3) / 8.0
        gy = cv2.Sobel(ib, cv2.CV_32F, 0, 1, ksize=3) / 8.0
        strength = np.hypot(tgx[vs, us], tgy[vs, us])
        keep = np.argsort(-strength, kind="stable")[:cfg.max_pixels]
        keep = keep[strength[keep] >= max(cfg.min_gradient, 1e-12)]
        if len(keep) < cfg.min_pixels:
            raise _Refused("few pixels", f"{len(keep)} textured pixels inside the silhouette "
                                         f"(min_pixels {cfg.min_pixels})")
        Xo = X_obj[keep]
        target = tb[vs[keep], us[keep]].astype(np.float64)
        h, w = image.shape
        lin = (ib, gx, gy, (fx, fy, cx, cy), (w, h))
        r, J, _ = self._linearise(T, Xo, target, *lin)
        scale = self._scale(r)  # the robust scale, renewed at each accepted step

        def prior(T: np.ndarray, scale: float) -> tuple[float, np.ndarray]:
            """The prior's weight (residual units², per m²) and the position's move."""
            if anchor is None:
                return 0.0, np.zeros(3)
            return (scale / anchor[1]) ** 2, T[:3, 3] - anchor[0]

        def total_cost(r: np.ndarray, T: np.ndarray, scale: float) -> float:
            weight, moved = prior(T, scale)
            return self._cost(r, scale) + 0.5 * weight * float(moved @ moved) / len(r)

        cost = total_cost(r, T, scale)
        lam = 1e-4
        for _ in range(cfg.iterations):
            wts = self._weights(r, scale)
            A = (J * wts[:, None]).T @ J
            g = (J * wts[:, None]).T @ r
            weight, moved = prior(T, scale)
            A[:3, :3] += weight * np.eye(3)
            g[:3] += weight * moved
            step = None
            while lam < 1e6:  # Levenberg-Marquardt: damp until a step lowers the cost
                try:
                    candidate = -np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), g)
                except np.linalg.LinAlgError:
                    raise _Refused(*_DIVERGED) from None
                T_new = T.copy()
                T_new[:3, :3] = _rotation(candidate[3:]) @ T[:3, :3]
                T_new[:3, 3] = T[:3, 3] + candidate[:3]
                try:
                    r_new, J_new, _ = self._linearise(T_new, Xo, target, *lin)
                except _Refused:
                    r_new = None
                if r_new is not None and total_cost(r_new, T_new, scale) < cost:
                    step, lam = candidate, max(lam / 10.0, 1e-7)
                    break
                lam *= 10.0
            if step is None:
                break  # no step lowers the cost: converged
            T, r, J = T_new, r_new, J_new
            scale = self._scale(r)
            cost = total_cost(r, T, scale)
            if (np.linalg.norm(step[3:]) < cfg.tolerance
                    and np.linalg.norm(step[:3]) < cfg.tolerance * abs(T[2, 3])):
                break
        r, J, (sampled, tv) = self._linearise(T, Xo, target, *lin, values=True)
        scale = self._scale(r)
        wts = self._weights(r, scale)
        info = (J * wts[:, None]).T @ J
        corr = float(np.corrcoef(sampled, tv)[0, 1]) if sampled.std() > 0 and tv.std() > 0 \
            else float("nan")
        return T, len(r), corr, scale, info

    def _cost(self, r: np.ndarray, scale: float) -> float:
        """Mean Huber cost of residuals ``r`` at the robust ``scale`` (points that left the
        crop do not count)."""
        k = self.config.huber * scale
        a = np.abs(r)
        return float(np.mean(np.where(a <= k, 0.5 * a ** 2, k * (a - 0.5 * k))))

    def _weights(self, r: np.ndarray, scale: float) -> np.ndarray:
        """Huber's weights of residuals ``r`` at the robust ``scale``."""
        return np.minimum(1.0, self.config.huber * scale / (np.abs(r) + 1e-12))

    @staticmethod
    def _scale(r: np.ndarray) -> float:
        """The residuals' robust standard deviation (1.4826 x their median absolute
        deviation)."""
        return float(1.4826 * np.median(np.abs(r - np.median(r)))) + 1e-12

    def _linearise(self, T, Xo, target, image, gx, gy, K, size, values: bool = False):
        """Residuals ``a I + b − T`` at the points projected with ``T`` (those inside the
        crop) and their Jacobian (N, 6) for ``[δt, δθ]``; with ``values`` also the sampled
        frame and template values.

        Raises:
            _Refused: fewer than ``min_pixels`` points project into the crop (``"diverged"``),
                or the frame is uniform where they do (``"low correlation"``).
        """
        fx, fy, cx, cy = K
        w, h = size
        Rx = Xo @ T[:3, :3].T
        X = Rx + T[:3, 3]
        z = X[:, 2]
        front = z > 1e-6
        zs = np.where(front, z, 1.0)
        u = np.where(front, fx * X[:, 0] / zs + cx, -1.0)
        v = np.where(front, fy * X[:, 1] / zs + cy, -1.0)
        inside = front & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
        if int(inside.sum()) < self.config.min_pixels:
            raise _Refused(*_DIVERGED)
        X, Rx, u, v, tv = X[inside], Rx[inside], u[inside], v[inside], target[inside]
        mx = u.astype(np.float32).reshape(-1, 1)
        my = v.astype(np.float32).reshape(-1, 1)
        sampled = cv2.remap(image, mx, my, cv2.INTER_LINEAR).ravel().astype(np.float64)
        Gx = cv2.remap(gx, mx, my, cv2.INTER_LINEAR).ravel().astype(np.float64)
        Gy = cv2.remap(gy, mx, my, cv2.INTER_LINEAR).ravel().astype(np.float64)
        # the frame's gain and offset against the render: the ratio of their spreads and the
        # difference of their means (a least-squares gain would shrink towards 0 while the
        # two are misaligned, and with it the steps)
        spread = float(sampled.std())
        if not spread > 0:
            raise _Refused("low correlation", "the frame is uniform where the object should be")
        a = float(tv.std()) / spread
        b = float(tv.mean()) - a * float(sampled.mean())
        r = a * sampled + b - tv
        x, y, zz = X[:, 0], X[:, 1], X[:, 2]
        dIdX = a * np.stack([Gx * fx / zz, Gy * fy / zz,
                             -(Gx * fx * x + Gy * fy * y) / zz ** 2], 1)
        J = np.concatenate([dIdX, np.cross(Rx, dIdX)], 1)
        return (r, J, (sampled, tv)) if values else (r, J, None)
