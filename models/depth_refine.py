"""Depth refinement of network poses: point-to-plane ICP of the object's mesh against the
registered depth frame of an RGB-D camera, around the object's predicted projection (the
refinement RGB-D pose pipelines commonly put after a network, as PoseCNN + ICP does).

A keypoint network places the object well across the image but poorly along the viewing ray:
a corner off by a few pixels changes the object's apparent size, hence its distance, by several
per cent, and tilts it. A depth frame registered to the RGB image measures both directly.
:class:`DepthRefiner` starts from a detection's pose and

1. moves the object along its viewing ray (its projection barely changes) by the median
   difference between the measured depth and the mesh's depth at the pixels where the mesh's
   camera-facing surface samples project (differences beyond ``max_translation_m`` ignored):
   the network's largest error, its distance, is gone before the fit starts;
2. takes the depth pixels in the bounding box of the mesh's projection at that pose, grown by
   ``search_margin`` of its size on every side (``scene points``, at most
   ``max_scene_points`` by an even pixel stride);
3. iterates point-to-plane ICP: each camera-facing surface sample ``m`` (normal ``n``) pairs
   with its nearest scene point ``s`` within a gate that shrinks geometrically from ``gate_m``
   to ``final_gate_m`` (the background and other objects drop out as the fit tightens); the
   residuals ``n · (s - m)``, Huber-weighted (``huber_m``), give a damped Gauss-Newton step of
   a rigid motion about the object's centre; until a step moves the object less than
   ``tolerance_m`` (translation, plus rotation times the object's radius) at the final gate.
   The gate tightens only once a step moves the object less than a quarter of it, so that a
   face still far off is not cut loose before the others pull it in. Pairing each model
   sample with the *dense* depth (not each depth pixel with the sparse samples) keeps the fit
   free of the samples' spacing, and finds a face wherever it is within the gate, not only
   where the current pose projects it;
4. accepts the result when enough samples fit (``min_points`` within the final gate, and at
   least ``min_inlier_fraction`` of the camera-facing samples that see a depth at their
   pixel) and the correction is plausible (under ``max_translation_m`` and
   ``max_rotation_deg``); otherwise it returns the input pose unchanged, with
   ``refined=False`` and the reason.

Views that leave directions unconstrained (one flat face seen head-on: sliding within the
face and turning about its normal) keep the network's estimate there: the step is damped by
``damping`` times the number of points (translation, m², and rotation, rad² times the radius²),
a prior on no change that only matters where the depth says nothing.

Convexity: model points are "visible" when their normal faces the camera; on a non-convex
mesh, parts hidden behind the object's own front also count, which biases the fit slightly.
Depth is in metres with 0 or NaN for missing pixels, registered to the RGB camera whose
intrinsics (and optional OpenCV distortion) the caller passes. On the simulator's depth (noise
independent per pixel) the fit reaches a fraction of a millimetre; a real sensor's correlated
errors (flying pixels at edges, ripple on planes, a scale bias) do not average out and leave
millimetres.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import torch
from scipy.spatial import cKDTree

from evtrack.errors import ConfigError

__all__ = ["DepthRefineConfig", "DepthRefiner", "RefineResult"]


@dataclass(frozen=True)
class DepthRefineConfig:
    """Settings of :class:`DepthRefiner` (see the module docstring for their roles).

    Attributes:
        model_points: mesh surface samples (area-uniform, seeded); about half face the camera.
        max_scene_points: most depth pixels used (an even pixel stride keeps fewer).
        search_margin: the scene is the depth in the projection's bounding box grown by this
            fraction of its size on every side.
        gate_m: first association gate (metres): the largest error the fit can pull in.
        final_gate_m: the gate after shrinking (metres); also the inlier distance.
        gate_decay: factor per iteration by which the gate shrinks.
        huber_m: Huber threshold of the residuals, metres.
        damping: weight of the prior on no change per point (see the module docstring).
        iterations: most Gauss-Newton steps.
        tolerance_m: stop when a step moves the object less than this (metres).
        min_points: fewest samples within the final gate for a refined pose.
        min_inlier_fraction: fewest samples within the final gate, as a fraction of the
            camera-facing samples that see a depth.
        max_translation_m, max_rotation_deg: larger corrections are refused (the network's
            pose was too far off for the depth to be trusted, or the depth shows something
            else).
        seed: seed of the surface sampling.
    """

    model_points: int = 3000
    max_scene_points: int = 8000
    search_margin: float = 0.3
    gate_m: float = 0.06
    final_gate_m: float = 0.01
    gate_decay: float = 0.7
    huber_m: float = 0.004
    damping: float = 1e-4
    iterations: int = 40
    tolerance_m: float = 1e-4
    min_points: int = 50
    min_inlier_fraction: float = 0.4
    max_translation_m: float = 0.3
    max_rotation_deg: float = 60.0
    seed: int = 0

    def __post_init__(self) -> None:
        positive = ("model_points", "max_scene_points", "gate_m", "final_gate_m", "huber_m",
                    "iterations", "tolerance_m", "min_points", "max_translation_m",
                    "max_rotation_deg")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"depth refinement: {name} must be positive, got "
                                  f"{getattr(self, name)}")
        if self.final_gate_m > self.gate_m:
            raise ConfigError(f"depth refinement: final_gate_m {self.final_gate_m} exceeds "
                              f"gate_m {self.gate_m}")
        if not 0 < self.gate_decay <= 1:
            raise ConfigError(f"depth refinement: gate_decay must be in (0, 1], got "
                              f"{self.gate_decay}")
        if self.damping < 0 or self.search_margin < 0:
            raise ConfigError("depth refinement: damping and search_margin must be >= 0")
        if not 0 <= self.min_inlier_fraction <= 1:
            raise ConfigError(f"depth refinement: min_inlier_fraction must be in [0, 1], got "
                              f"{self.min_inlier_fraction}")


@dataclass(frozen=True)
class RefineResult:
    """The outcome of one refinement.

    Attributes:
        pose: (4, 4) float64 object-to-camera pose: refined, or the input when refused.
        refined: whether the depth refined the pose.
        inliers: camera-facing surface samples within the final gate at the final pose.
        visible: camera-facing surface samples that see a depth at their pixel.
        rmse_m: RMS point-to-plane residual of the inliers, metres (NaN without inliers).
        iterations: Gauss-Newton steps taken.
        reason: why the pose was not refined ("" when it was).
        information: (6, 6) Gauss-Newton normal matrix ``Σ w a aᵀ`` of the inliers at the
            final pose (m⁻² per m² of residual variance), for a rigid motion ``[δv, δω]`` about
            ``centre``: ``residual variance × information⁻¹`` is the fit's covariance.
            Directions the depth leaves unconstrained (sliding within a face seen head-on,
            turning a can about its axis) have eigenvalues near zero. ``None`` when refused.
        centre: (3,) the camera-frame point the motion is about (the object's bounding-box
            centre at the final pose); ``None`` when refused.
        refusal: the kind of refusal, for counting: ``""`` (refined), ``"few depth pixels"``
            (too few depth pixels around the object or near the mesh), ``"few fit"`` (too few
            of them fit the mesh at the final pose) or ``"correction too large"``.
    """

    pose: np.ndarray
    refined: bool
    inliers: int
    visible: int
    rmse_m: float
    iterations: int
    reason: str = ""
    information: np.ndarray | None = None
    centre: np.ndarray | None = None
    refusal: str = ""


def _rodrigues(w: np.ndarray) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(w, np.float64).reshape(3, 1))
    return R


class DepthRefiner:
    """Refines object poses with a registered depth frame (see the module docstring).

    Args:
        vertices: (V, 3) mesh vertices in the object frame, metres.
        faces: (F, 3) triangle indices.
        config: settings.

    Example::

        refiner = DepthRefiner.from_mesh(sequence.mesh_file)
        result = refiner.refine(detection.pose.numpy(), depth, camera.K().numpy())
        poses = refiner.refine_detections(estimator(rgb), depth, camera.K().numpy())
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray,
                 config: DepthRefineConfig | None = None) -> None:
        import trimesh

        self.config = config or DepthRefineConfig()
        vertices = np.asarray(vertices, np.float64)
        faces = np.asarray(faces, np.int64)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
            raise ConfigError(f"depth refinement needs (V, 3) vertices and (F, 3) faces, got "
                              f"{vertices.shape} and {faces.shape}")
        mesh = trimesh.Trimesh(vertices, faces, process=False)
        if not mesh.area > 0:
            raise ConfigError("depth refinement: the mesh has no surface area")
        points, face_index = trimesh.sample.sample_surface(
            mesh, self.config.model_points, seed=self.config.seed)
        self.points = np.asarray(points, np.float64)
        self.normals = np.asarray(mesh.face_normals[face_index], np.float64)
        self.hull_points = np.asarray(mesh.vertices, np.float64)
        self.centre = 0.5 * (vertices.min(0) + vertices.max(0))
        self.radius = float(np.linalg.norm(vertices - self.centre, axis=1).max())

    @classmethod
    def from_mesh(cls, mesh, config: DepthRefineConfig | None = None) -> DepthRefiner:
        """From a mesh file path or a ``trimesh.Trimesh`` (object frame, metres).

        A BOP model file (``obj_XXXXXX.ply`` beside ``models_info.json``) is in millimetres:
        it is scaled to metres and checked against its recorded diameter.
        """
        import trimesh

        if isinstance(mesh, (str, Path)):
            from evtrack.datasets.bop import MM, check_bop_model_size, is_bop_model_file

            if not Path(mesh).is_file():
                raise ConfigError(f"depth refinement: mesh file {mesh} not found")
            path, mesh = mesh, trimesh.load(mesh, force="mesh")
            if is_bop_model_file(path):
                mesh.apply_scale(MM)
                check_bop_model_size(path, np.asarray(mesh.vertices))
        return cls(np.asarray(mesh.vertices), np.asarray(mesh.faces), config)

    # ------------------------------------------------------------------ geometry
    @staticmethod
    def _pixel_rays(K: np.ndarray, dist: np.ndarray | None, shape: tuple[int, int]):
        """``rays(px) -> (N, 2)`` normalised image coordinates of integer pixels (undistorted
        when ``dist`` has non-zero terms)."""
        if dist is None or not np.any(np.asarray(dist) != 0):
            f, c = np.array([K[0, 0], K[1, 1]]), K[:2, 2]
            return lambda px: (px - c) / f
        h, w = shape
        grid = np.stack(np.meshgrid(np.arange(w, dtype=np.float64),
                                    np.arange(h, dtype=np.float64)), -1).reshape(-1, 1, 2)
        table = cv2.undistortPoints(grid, K, np.asarray(dist, np.float64)).reshape(h, w, 2)
        return lambda px: table[px[:, 1].astype(np.int64), px[:, 0].astype(np.int64)]

    def scene_points(self, pose: np.ndarray, depth: np.ndarray, K: np.ndarray,
                     dist: np.ndarray | None = None, rays=None) -> np.ndarray:
        """(N, 3) camera-frame points of the valid depth pixels in the bounding box of the
        mesh's projection at ``pose``, grown by ``search_margin`` of its size on every side
        (the fit's reach), strided evenly to at most ``max_scene_points``."""
        h, w = depth.shape
        rays = rays or self._pixel_rays(K, dist, depth.shape)
        P = self.hull_points @ pose[:3, :3].T + pose[:3, 3]
        P = P[P[:, 2] > 1e-3]
        if len(P) < 3:
            return np.zeros((0, 3))
        uv, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, dist)
        uv = uv.reshape(-1, 2)
        lo, hi = uv.min(0), uv.max(0)
        grow = self.config.search_margin * (hi - lo) + 2.0
        x0, y0 = np.maximum(np.floor(lo - grow), 0).astype(int)
        x1, y1 = np.minimum(np.ceil(hi + grow), [w - 1, h - 1]).astype(int)
        if x1 < x0 or y1 < y0:
            return np.zeros((0, 3))
        stride = max(1, math.ceil(math.sqrt((x1 - x0 + 1) * (y1 - y0 + 1)
                                            / self.config.max_scene_points)))
        ys, xs = np.mgrid[y0:y1 + 1:stride, x0:x1 + 1:stride]
        z = depth[ys, xs].astype(np.float64).ravel()
        ok = np.isfinite(z) & (z > 0)
        px = np.stack([xs.ravel(), ys.ravel()], 1)[ok].astype(np.float64)
        return np.column_stack([rays(px) * z[ok, None], z[ok]])

    def _facing(self, R: np.ndarray, t: np.ndarray):
        """Camera-frame surface samples facing the camera at ``(R, t)`` and their normals."""
        P = self.points @ R.T + t
        N = self.normals @ R.T
        keep = ((N * P).sum(1) < 0) & (P[:, 2] > 1e-3)
        return P[keep], N[keep]

    def _measured(self, P: np.ndarray, depth: np.ndarray, K: np.ndarray,
                  dist: np.ndarray | None, rays) -> tuple[np.ndarray, np.ndarray]:
        """For camera-frame points ``P`` (N, 3): the measured surface point at the pixel each
        projects to (back-projected depth, (N, 3)) and whether there is one (N,) bool."""
        h, w = depth.shape
        if dist is None or not np.any(np.asarray(dist) != 0):
            uv = (P[:, :2] / P[:, 2:3]) * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]
        else:
            uv, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, dist)
            uv = uv.reshape(-1, 2)
        px = np.round(uv)
        ok = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        S = np.full(P.shape, np.nan)
        pi = px[ok].astype(np.int64)
        z = depth[pi[:, 1], pi[:, 0]].astype(np.float64)
        S[ok] = np.column_stack([rays(pi.astype(np.float64)) * z[:, None], z])
        ok &= np.isfinite(S[:, 2]) & (S[:, 2] > 0)
        return S, ok

    def align_along_ray(self, pose: np.ndarray, depth: np.ndarray, K: np.ndarray,
                        dist: np.ndarray | None = None, rays=None) -> np.ndarray:
        """``pose`` moved along the ray through the object's centre by the median of
        (measured - mesh) depth at the pixels of the camera-facing surface samples (the input
        pose when fewer than ``min_points`` see a depth within ``max_translation_m``)."""
        rays = rays or self._pixel_rays(K, dist, depth.shape)
        R, t = pose[:3, :3], pose[:3, 3]
        P, _ = self._facing(R, t)
        S, ok = self._measured(P, depth, K, dist, rays)
        diff = S[ok, 2] - P[ok, 2]
        diff = diff[np.abs(diff) <= self.config.max_translation_m]
        if len(diff) < self.config.min_points:
            return pose
        centre = R @ self.centre + t
        out = pose.copy()
        out[:3, 3] = t + float(np.median(diff)) / centre[2] * centre  # slide along the ray
        return out

    # ------------------------------------------------------------------ refinement
    def refine(self, pose: np.ndarray | torch.Tensor, depth: np.ndarray,
               K: np.ndarray | torch.Tensor, dist: np.ndarray | None = None) -> RefineResult:
        """Refine one object-to-camera pose.

        Args:
            pose: (4, 4) object-to-camera transform (metres).
            depth: (H, W) float depth in metres registered to the camera ``K``; 0 or NaN where
                missing.
            K: (3, 3) intrinsics of that camera.
            dist: its OpenCV distortion coefficients, if any.

        Raises:
            ValueError: a pose that is not a finite (4, 4) matrix, integer depth (raw sensor
                units: convert to metres first), or a K that is not (3, 3).
        """
        cfg = self.config
        T0 = np.asarray(pose.detach().cpu() if isinstance(pose, torch.Tensor) else pose,
                        np.float64)
        if T0.shape != (4, 4) or not np.isfinite(T0).all():
            raise ValueError(f"depth refinement: pose must be a finite (4, 4) matrix, got "
                             f"shape {T0.shape}")
        K = np.asarray(K.detach().cpu() if isinstance(K, torch.Tensor) else K, np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"depth refinement: K must be (3, 3), got {K.shape}")
        depth = np.asarray(depth)
        if depth.ndim != 2:
            raise ValueError(f"depth refinement: depth must be (H, W), got {depth.shape}")
        if not np.issubdtype(depth.dtype, np.floating):
            raise ValueError(f"depth refinement: depth must be float metres, got {depth.dtype} "
                             "(convert raw sensor units, e.g. millimetres, to metres)")
        rays = self._pixel_rays(K, dist, depth.shape)
        T_start = self.align_along_ray(T0, depth, K, dist, rays)
        scene = self.scene_points(T_start, depth, K, dist, rays)
        if len(scene) < cfg.min_points:
            return RefineResult(T0, False, 0, 0, float("nan"), 0,
                                f"{len(scene)} depth pixels around the object, fewer than "
                                f"min_points={cfg.min_points}", refusal="few depth pixels")
        tree = cKDTree(scene)
        R, t = T_start[:3, :3].copy(), T_start[:3, 3].copy()
        gate = cfg.gate_m
        steps = 0
        for steps in range(1, cfg.iterations + 1):
            m, n, s, _ = self._associate(R, t, tree, scene, depth, K, dist, rays, gate)
            if len(m) < cfg.min_points:
                return RefineResult(T0, False, len(m), 0, float("nan"), steps,
                                    f"{len(m)} depth pixels meet the mesh near the pose, fewer "
                                    f"than min_points={cfg.min_points}",
                                    refusal="few depth pixels")
            c = R @ self.centre + t
            r = ((s - m) * n).sum(1)
            a = np.hstack([n, np.cross(m - c, n)])
            wts = np.where(np.abs(r) <= cfg.huber_m, 1.0,
                           cfg.huber_m / np.maximum(np.abs(r), 1e-12))
            H = (a * wts[:, None]).T @ a
            g = (a * wts[:, None]).T @ r
            prior = cfg.damping * len(s) * np.r_[np.ones(3), np.full(3, self.radius ** 2)]
            delta = np.linalg.solve(H + np.diag(prior), g)
            dR = _rodrigues(delta[3:])
            R = dR @ R
            t = dR @ (t - c) + c + delta[:3]
            moved = np.linalg.norm(delta[:3]) + np.linalg.norm(delta[3:]) * self.radius
            if gate > cfg.final_gate_m:
                if moved < 0.25 * gate:  # settled at this gate: tighten it
                    gate = max(cfg.final_gate_m, gate * cfg.gate_decay)
            elif moved < cfg.tolerance_m:
                break
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        m, n, s, seen = self._associate(R, t, tree, scene, depth, K, dist, rays,
                                        cfg.final_gate_m)
        inliers = len(m)
        r = ((s - m) * n).sum(1)
        rmse = float(np.sqrt(np.mean(r ** 2))) if inliers else float("nan")
        refusal, reason = self._refusal(T0, T, inliers, seen)
        if reason:
            return RefineResult(T0, False, inliers, seen, rmse, steps, reason, refusal=refusal)
        c = R @ self.centre + t
        a = np.hstack([n, np.cross(m - c, n)])
        wts = np.where(np.abs(r) <= cfg.huber_m, 1.0, cfg.huber_m / np.maximum(np.abs(r), 1e-12))
        information = (a * wts[:, None]).T @ a
        return RefineResult(T, True, inliers, seen, rmse, steps, "", information, c)

    def _associate(self, R: np.ndarray, t: np.ndarray, tree, scene: np.ndarray,
                   depth: np.ndarray, K: np.ndarray, dist: np.ndarray | None, rays,
                   gate: float):
        """Each camera-facing surface sample ``m`` (normal ``n``) with its nearest scene point
        ``s`` within ``gate``. Returns ``(m, n, s)`` (k, 3) each, and how many of the samples
        see a depth at the pixel they project to (the denominator of the inlier fraction)."""
        P, N = self._facing(R, t)
        _, seen = self._measured(P, depth, K, dist, rays)
        d, idx = tree.query(P, distance_upper_bound=gate)
        ok = np.isfinite(d)
        return P[ok], N[ok], scene[idx[ok]], int(seen.sum())

    def _refusal(self, T0: np.ndarray, T: np.ndarray, inliers: int, visible: int
                 ) -> tuple[str, str]:
        """``(kind, reason)`` of a refusal (see :class:`RefineResult`), ``("", "")`` if none."""
        cfg = self.config
        if inliers < cfg.min_points:
            return "few fit", (f"{inliers} depth pixels fit the mesh, fewer than min_points="
                               f"{cfg.min_points}")
        if inliers < cfg.min_inlier_fraction * visible:
            return "few fit", (
                f"only {inliers} of the {visible} visible surface samples with a depth fit "
                f"it (min_inlier_fraction={cfg.min_inlier_fraction}): something else is "
                "in front of the object, or it is not there")
        dt = float(np.linalg.norm(T[:3, 3] - T0[:3, 3]))
        cos = np.clip((np.trace(T[:3, :3] @ T0[:3, :3].T) - 1) / 2, -1.0, 1.0)
        dr = math.degrees(math.acos(cos))
        if dt > cfg.max_translation_m or dr > cfg.max_rotation_deg:
            return "correction too large", (
                f"the correction ({dt * 100:.1f} cm, {dr:.1f} deg) exceeds max_translation_m="
                f"{cfg.max_translation_m} / max_rotation_deg={cfg.max_rotation_deg}")
        return "", ""

    def refine_detections(self, detections: Sequence, depth: np.ndarray,
                          K: np.ndarray | torch.Tensor, dist: np.ndarray | None = None) -> list:
        """The detections (:class:`~evtrack.models.PoseDetection`) with depth-refined poses;
        a detection the depth cannot refine keeps its pose."""
        out = []
        for det in detections:
            res = self.refine(det.pose, depth, K, dist)
            if res.refined:
                det = replace(det, pose=torch.as_tensor(res.pose, dtype=torch.float64))
            out.append(det)
        return out
