"""Global registration: an object's pose found once on one RGB-D frame from its textured mesh,
given where in the image it is, with nothing trained: the start pose that
``TrackerConfig.pose_source: model`` needs.

:func:`register_mesh` takes a box around the object in the colour image (a user's click, a
detector's box, a BOP ``scene_gt_info`` box) and

1. places the object's centre on the ray through the box's centre, at the box's nearest depth
   layer (a low quantile of the valid depths inside the box) plus the mesh's radius behind it
   (the camera sees the object's front);
2. tries ``rotations`` orientations spread evenly over SO(3) (a seeded uniform sample, plus
   the identity) from there, each aligned with the depth frame by
   :class:`~evtrack.models.DepthRefiner` (ICP: the depth pins the position and the shape's
   orientation);
3. keeps the fits nearly as good as the best (the share of the mesh's visible samples within
   the final gate), ``candidates`` of them spread over rotation, aligns each with the colour
   image by :class:`~evtrack.models.AppearanceRefiner` (the texture pins what the shape does
   not: a can's spin about its axis, a box's faces that look alike in depth; a prior keeps the
   depth's position), and returns the fit whose frame and render correlate best.

Without a box, :func:`find_mesh` looks for one: the regions of the depth frame that stand out
of the scene's dominant planes (a table, a wall) with the object's size
(:mod:`~evtrack.models.depth_regions`), each registered as above, the best kept.

When the colour image confirms none of the candidates, it raises rather than guess: a shape
the depth fits in many orientations (a box-like can whose faces look alike in depth) may leave
none of them within the colour fit's reach. The result says how sure it is:
:attr:`Registration.runner_up` is the best fit that lies more than ``distinct_deg`` away in
rotation, with its correlation; a runner-up nearly as good (a symmetric object, a plain
texture) means the frame could not tell the two apart.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError
from evtrack.models.appearance_refine import AppearanceRefiner
from evtrack.models.depth_refine import DepthRefiner
from evtrack.models.depth_regions import RegionConfig, object_regions

__all__ = ["RegistrationConfig", "Registration", "find_mesh", "register_mesh"]


@dataclass(frozen=True)
class RegistrationConfig:
    """Settings of :func:`register_mesh`.

    Attributes:
        rotations: orientations tried (a seeded uniform sample of SO(3), plus the identity).
        candidates: depth fits aligned with the colour image, spread over rotation among those
            within ``good_share`` of the best fit's inlier share.
        good_share: see ``candidates``.
        near_quantile: the box's depth layer the object's front is taken at (a quantile of the
            valid depths inside the box; the background lies behind it).
        distinct_deg: a runner-up must lie at least this far in rotation from the best.
        position_std_m: the colour image's fit keeps the depth fit's position within about this
            (a prior, m): an image sees the distance along the viewing ray poorly.
        seed: seed of the rotation sample.
    """

    rotations: int = 96
    candidates: int = 24
    good_share: float = 0.9
    near_quantile: float = 0.1
    distinct_deg: float = 20.0
    position_std_m: float = 0.01
    seed: int = 0

    def __post_init__(self) -> None:
        if self.rotations < 1 or self.candidates < 1:
            raise ConfigError("registration: rotations and candidates must be >= 1")
        if not 0 <= self.near_quantile <= 1:
            raise ConfigError(f"registration: near_quantile must be in [0, 1], got "
                              f"{self.near_quantile}")


@dataclass(frozen=True)
class Registration:
    """The outcome of :func:`register_mesh`.

    Attributes:
        pose: (4, 4) float64 object-to-camera pose of the colour camera.
        correlation: the frame's and the render's correlation at that pose.
        inlier_fraction: the share of the mesh's visible samples its depth fit explains.
        runner_up: ``(correlation, degrees from the best)`` of the best fit more than
            ``distinct_deg`` away, or ``None`` without one.
        tried: orientations tried; fitted: of those, the depth fits accepted.
        box: the box it was registered in (given, or found by :func:`find_mesh`).
    """

    pose: np.ndarray
    correlation: float
    inlier_fraction: float
    runner_up: tuple[float, float] | None = None
    tried: int = 0
    fitted: int = 0
    box: tuple[int, int, int, int] | None = None


def _rotation_deg(A: np.ndarray, B: np.ndarray) -> float:
    """The angle (deg) between the rotations of two (4, 4) poses."""
    return math.degrees(Rotation.from_matrix(A[:3, :3].T @ B[:3, :3]).magnitude())


def _start_position(depth: np.ndarray, box: tuple[int, int, int, int], K: np.ndarray,
                    radius: float, quantile: float) -> np.ndarray:
    """The object's centre guessed from the depths inside ``box`` (see the module docstring).

    Raises:
        ValueError: no valid depth inside the box.
    """
    u0, v0, u1, v1 = box
    patch = np.asarray(depth[v0:v1, u0:u1], np.float64)
    valid = patch[np.isfinite(patch) & (patch > 0)]
    if valid.size < 16:
        raise ValueError(f"registration: {valid.size} valid depth pixels inside the box "
                         f"{box}; the object's depth is needed to place it")
    front = float(np.quantile(valid, quantile))
    ray = np.linalg.solve(K, [(u0 + u1 - 1) / 2.0, (v0 + v1 - 1) / 2.0, 1.0])
    return ray * (front + radius) / ray[2]


def _spread(fits: list, cfg: RegistrationConfig) -> list:
    """The candidates for the colour image: of the depth fits nearly as good as the best
    (``good_share`` of its inlier share), ``candidates`` spread over rotation (the best first,
    then each time the one farthest from those taken). A shape the depth cannot orient (a
    can's spin, a box's faces) fits equally well in many orientations; spreading them leaves
    the colour image one within its reach."""
    good = [f for f in fits if f[0] >= cfg.good_share * fits[0][0]]
    taken = [good[0]]
    rest = good[1:]
    while rest and len(taken) < cfg.candidates:
        far = max(rest, key=lambda f: min(_rotation_deg(f[2], t[2]) for t in taken))
        taken.append(far)
        rest.remove(far)
    return taken


def register_mesh(mesh, camera: PinholeCamera, rgb: np.ndarray, depth: np.ndarray,
                  box: tuple[int, int, int, int],
                  config: RegistrationConfig | None = None,
                  depth_refiner: DepthRefiner | None = None,
                  appearance: AppearanceRefiner | None = None) -> Registration:
    """Find the object's pose on one RGB-D frame (see the module docstring).

    Args:
        mesh: the object's textured :class:`~evtrack.sim.objects.ObjectMesh` (metres).
        camera: the colour camera (the depth registered to it).
        rgb: (H, W, 3) uint8 colour image.
        depth: (H, W) float depth in metres, 0 or NaN where missing.
        box: ``(u0, v0, u1, v1)`` pixels around the object (``u1``, ``v1`` exclusive).
        config: settings.
        depth_refiner, appearance: the aligners (default: made from the mesh and camera).

    Raises:
        ValueError: a box outside the image or empty, no valid depth inside it, no
            orientation the depth could fit, or none the colour image confirms.
    """
    cfg = config or RegistrationConfig()
    W, H = camera.width, camera.height
    u0, v0, u1, v1 = (int(round(float(b))) for b in box)
    u0, v0, u1, v1 = max(0, u0), max(0, v0), min(W, u1), min(H, v1)
    if u1 - u0 < 2 or v1 - v0 < 2:
        raise ValueError(f"registration: the box {tuple(box)} holds no part of the "
                         f"{W}x{H} image")
    depth = np.asarray(depth)
    if depth.shape != (H, W):
        raise ValueError(f"registration: depth must be ({H}, {W}), got {depth.shape}")
    verts = np.asarray(mesh.vertices, np.float64)
    centre_obj = 0.5 * (verts.min(0) + verts.max(0))
    radius = float(np.linalg.norm(verts - centre_obj, axis=1).max())
    K = camera.K().numpy()
    dist = None if camera.dist is None else camera.dist.numpy()
    centre = _start_position(depth, (u0, v0, u1, v1), K, radius, cfg.near_quantile)
    icp = depth_refiner or DepthRefiner(verts, np.asarray(mesh.faces))
    rotations = np.concatenate([np.eye(3)[None], Rotation.random(
        cfg.rotations - 1, random_state=cfg.seed).as_matrix()]) if cfg.rotations > 1 \
        else np.eye(3)[None]
    fits = []
    for R in rotations:
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = centre - R @ centre_obj  # the mesh's centre on the guessed point
        res = icp.refine(T, depth.astype(np.float32, copy=False), K, dist)
        if res.refined:
            fits.append((res.inliers / max(res.visible, 1), -res.rmse_m, res.pose))
    if not fits:
        raise ValueError(f"registration: none of {len(rotations)} orientations fitted the depth "
                         f"inside the box {(u0, v0, u1, v1)}")
    fits.sort(key=lambda f: (f[0], f[1]), reverse=True)
    looks = appearance or AppearanceRefiner(mesh, camera)
    scored = []
    for share, _, pose in _spread(fits, cfg):
        res = looks.refine(pose, rgb, translation_std_m=cfg.position_std_m)
        if res.refined:
            scored.append((res.correlation, share, res.pose))
    if not scored:
        raise ValueError(f"registration: the colour image confirms none of the "
                         f"{len(fits)} orientations the depth fitted inside the box "
                         f"{(u0, v0, u1, v1)} (none aligned with a correlation of at least "
                         f"{looks.config.min_correlation}); give the start pose instead, or a "
                         "frame where the object is seen whole and sharp")
    scored.sort(key=lambda s: s[0], reverse=True)
    best_corr, best_share, best = scored[0]
    runner = next(((c, _rotation_deg(best, p)) for c, _, p in scored[1:]
                   if _rotation_deg(best, p) > cfg.distinct_deg), None)
    return Registration(best, best_corr, best_share, runner, len(rotations), len(fits),
                        (u0, v0, u1, v1))


def find_mesh(mesh, camera: PinholeCamera, rgb: np.ndarray, depth: np.ndarray,
              config: RegistrationConfig | None = None, regions: RegionConfig | None = None,
              max_regions: int = 3, depth_refiner: DepthRefiner | None = None,
              appearance: AppearanceRefiner | None = None) -> Registration:
    """Find the object's pose on one RGB-D frame without a box: the regions of the depth
    that stand out of the scene's dominant planes and fit the object's size
    (:func:`~evtrack.models.depth_regions.object_regions`), the best ``max_regions`` of them
    registered as :func:`register_mesh` does, and the registration whose colour image
    correlates best kept (:attr:`Registration.box` says where).

    Raises:
        ValueError: no valid depth, no region of the object's size, or no region the
            registration confirms (each region's reason is given).
    """
    if max_regions < 1:
        raise ConfigError(f"find_mesh: max_regions must be >= 1, got {max_regions}")
    verts = np.asarray(mesh.vertices, np.float64)
    if len(verts) == 0:
        raise ValueError("find_mesh: the mesh has no vertices")
    centre_obj = 0.5 * (verts.min(0) + verts.max(0))
    radius = float(np.linalg.norm(verts - centre_obj, axis=1).max())
    found = object_regions(depth, camera, radius, regions)
    if not found:
        raise ValueError(f"find_mesh: no region of the depth frame stands out of its dominant "
                         f"planes with the size of the object (radius {radius * 100:.1f} cm); "
                         "is the object in view, and the mesh in metres? Give a box around it "
                         "instead (register_mesh, evtrack track --start-box)")
    icp = depth_refiner or DepthRefiner(verts, np.asarray(mesh.faces))
    looks = appearance or AppearanceRefiner(mesh, camera)
    best: Registration | None = None
    reasons = []
    for region in found[:max_regions]:
        try:
            reg = register_mesh(mesh, camera, rgb, depth, region.box, config, icp, looks)
        except ValueError as exc:
            reasons.append(f"{region.box}: {exc}")
            continue
        if best is None or reg.correlation > best.correlation:
            best = reg
    if best is None:
        raise ValueError("find_mesh: no region was registered: " + "; ".join(reasons))
    return best
