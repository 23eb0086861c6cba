"""From belief maps and affinity fields to object poses.

1. Peaks of the 9 belief maps (:func:`evtrack.models.keypoints.find_peaks`).
2. Every centroid peak starts an instance. Every corner peak reads its affinity vector (the
   predicted direction towards its object's centroid) and joins the centroid whose direction
   from the corner makes the smallest angle with it, if that angle is below
   ``max_angle_deg``; per instance and corner the strongest peak wins (ties: the
   best-aligned). The affinity only says *which instance* a peak belongs to: every corner's
   field points at the centroid, so alignment cannot tell one corner of an object from
   another, while the belief value says how sure the network is that this is *this* corner.
3. PnP with OpenCV on the instance's keypoints and the object's cuboid: EPnP (inside RANSAC
   when asked) and SQPnP as a second start, each refined with Levenberg-Marquardt; the
   solution with the smaller reprojection error is kept.
   With ``correspondence="search"`` the corner identities come from a search instead
   (:mod:`evtrack.models.pose_search`): the instance's corner peaks of *every* corner map are
   pooled, poses are hypothesised from pairs of them and the centroid, and the pose whose
   projected corners the maps support best is refined on the nearest pooled points. Use it
   for networks that localise corners better than they name them. With
   ``search_below > 0`` the search runs only where the strongest peaks give no pose or one
   less confident than that, and the more confident of the two detections is kept.
4. ``confidence = mean over the 9 keypoints of the clipped peak value (0 if missing)
   * exp(-0.5 * (rms_reprojection_px / reprojection_scale_px)^2)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal

import cv2
import numpy as np
import torch
from torch import Tensor

from evtrack.configs import Config, setting
from evtrack.models.cuboid import CENTROID_INDEX, NUM_KEYPOINTS, Cuboid
from evtrack.models.keypoints import (
    find_peaks,
    grid_to_pixel,
    pixel_to_grid,
    sample_bilinear,
)
from evtrack.models.pose_search import merge_points, search_pose

__all__ = [
    "DecodeConfig",
    "SubpixelMethod",
    "PoseDetection",
    "InstanceKeypoints",
    "extract_instances",
    "solve_pose",
    "search_instance",
    "decode_poses",
    "with_alternatives",
]


SubpixelMethod = Literal["log_quadratic", "centroid", "none"]
"""The sub-cell peak refinements of :func:`~evtrack.models.keypoints.find_peaks`
(:data:`~evtrack.models.keypoints.SUBPIXEL_METHODS`)."""

_MIN_KEYPOINT_SPREAD_PX = 1.0
"""Keypoints spread over less than this (pixels, either axis) give no pose."""


@dataclass(frozen=True)
class DecodeConfig(Config):
    """How belief maps and affinity fields become poses.

    Attributes:
        peak_threshold: minimum belief value of a keypoint peak.
        nms_radius: peaks closer than this many cells to a stronger one are suppressed.
        subpixel: sub-cell refinement, ``"log_quadratic"``, ``"centroid"`` or ``"none"``.
        max_angle_deg: largest angle between a corner's affinity vector and the direction to
            a centroid for the corner to join that centroid's instance.
        min_affinity_norm: corners whose affinity vector is shorter than this are ignored
            (the field is ~unit length where the network is sure).
        min_points: fewest keypoints (corners + centroid) for a pose (>= 4).
        ransac: run EPnP inside RANSAC (needs >= 6 points, else plain EPnP). On by default:
            with the shipped demo weights, three held-out regular sequences gave ADD 0.85
            against 0.73 without it (median 0.81 cm / 2.55 deg against 1.06 / 2.91;
            ``benchmarks/bench_pose_accuracy.py --decode ransac --decode strongest``), in the
            same time per frame. OpenCV seeds its sampler on every call: the same keypoints give
            the same pose. Its choice of inliers can follow the last bits of the keypoints,
            so they reach it on a grid (:data:`PNP_GRID_PX`): torch and onnxruntime then give
            the same poses.
        ransac_reprojection_px: RANSAC inlier threshold, pixels.
        ransac_iterations: RANSAC iterations.
        refine: ``"lm"`` (Levenberg-Marquardt on the reprojection error) or ``"none"``.
        reprojection_scale_px: reprojection RMS at which the confidence falls by exp(-1/2).
        min_confidence: detections below this confidence are dropped.
        max_instances: at most this many centroid peaks (the strongest) are decoded.
        correspondence: ``"strongest"`` (each corner takes its map's strongest peak) or
            ``"search"`` (pose search over corner identities; see the module docstring).
        search_below: with ``correspondence="strongest"``, an instance whose strongest-peak
            pose is missing or less confident than this is decoded by the search as well, and
            the more confident detection is kept (0: never). A network that names the corners
            of an object poorly in some views (the shipped mustard bottle's seen end-on, the
            potted meat can's in a few) still has strong peaks there, at the right places
            under the wrong names: the strongest peaks then fit with a reprojection error of
            tens of pixels (confidence ~0, poses 0.4-5 m and 60-180 deg off), the search gives
            a pose. 0.1 by default: with the shipped YCB networks on the benchmark's `faster`
            sequences the tracker's rotation RMSE fell from 13.35 to 12.50 deg (paper-matched
            speeds) and from 13.74 to 12.92 deg (default presets; torch on 2 threads; on one:
            13.12 to 11.94 and 14.34 to 13.29), no object worse, `regular` unchanged. At 0.5
            the search also replaced the tomato can's fits of confidence 0.17-0.21, which were
            better than its answers (4.6 -> 15.9 deg), so its confidence is not comparable with
            the strongest peaks' above ~0.1. The search
            costs ~10-15 ms per instance (eight points, its P3P batched; it was ~35-45 ms
            with one ``cv2.solveP3P`` per problem: ``bench_pose_speed.py``), paid only where
            it runs.
        search_identity_weight: weight of a corner's own map against the best of all corner
            maps in the search's score, in [0, 1].
        search_max_points: the search hypothesises from at most this many pooled corner points.
        search_merge_cells: pooled corner points closer than this (cells) are merged.
        search_gate_cells: after the search, a projected corner takes the nearest pooled point
            within this distance (cells) for the refinement.
        crop_refine: a second network pass per detection, on a square crop centred on its
            projected cuboid and resized to this fraction of the network's input width
            (:mod:`evtrack.models.crop_refine`); the crop's pose replaces the first when the
            crop finds the object (the first joins the detection's ``alternatives``). 0: one
            pass. Used by :class:`PoseEstimator`, not by
            :func:`decode_poses`. 0.5 by default: with the shipped coded-box weights, six
            held-out sequences per preset (``bench_pose_accuracy.py --one-pass``) gave regular
            ADD 0.942 against 0.733 in one pass (median 0.62 cm / 2.20 deg against 0.91 /
            2.81), faster 0.792 against 0.756; the cracker box's weights (320x240) on the
            two benchmark sets' cracker sequences regular 0.838 against 0.796, faster 0.971
            against 0.854 (both networks' model cards, "Held-out accuracy"). Other sides were
            no better over both objects. It costs a network call on a quarter to a third
            of a 640x480 image's pixels.
        crop_blend_max_deg: where the crop's rotation and the first pass's differ by at most
            this (degrees), the detection's rotation turns halfway to the first pass's
            (:func:`~evtrack.models.crop_refine.halfway_rotation`; its position, keypoints,
            confidence and reprojection error stay the crop's; both passes' own poses join its
            ``alternatives``); 0 (the default): the crop's pose as it is. The two passes see
            the object at different sizes and err apart, so their mean can beat either, but
            only where the network's first pass is about as good as its crop. Median rotation
            error on held-out renders (``bench_pose_accuracy.py --crop-blend 45``, six
            sequences per preset, seeds 1000-1011, regular / faster, crop -> blended; 2 cores
            of an AMD EPYC, 2026-11-29): mustard bottle 6.86 -> 5.72 / 6.44 -> 5.83, tomato
            can 5.52 -> 6.10 / 7.01 -> 6.39, potted meat can 3.34 -> 5.03 / 4.33 -> 4.73 (its
            first pass errs 8.3 / 6.2 deg), cracker box 3.17 -> 3.63 / 3.47 -> 3.57, coded box
            2.20 -> 2.25 / 3.04 -> 2.82 (regular ADD 0.942 -> 0.925). No shipped record
            turns it on: the mustard bottle's gain did not carry over to the tracker on the
            benchmark's test split (its model card, "Decoding").
            Check a network on such renders before turning it on; beyond ~40 deg two poses are
            different answers (a half turn, a corner swap) and their mean is neither.
        crop_margin: side of that crop / longer side of the projected cuboid's bounding box
            (>= 1): 1.3 (1.5 was better on the coded box's regular sequences, 0.947, worse
            on its faster ones and on the cracker box).
        prior_recrop: with a prior pose (:meth:`~evtrack.models.PoseEstimator.estimate_near`,
            a tracker's prediction), the crop placed on the prior is placed again on its own
            detection, and the crop pass run once more there, unless the two crops nearly
            coincide: their centres within this fraction of the crop's side and their zooms
            within twice it. A tracker's prediction can be centimetres off, which puts the
            object off-centre and at another size in the crop than the network saw in
            training (at most 5 % off-centre there); a crop placed on a detection from the
            image itself does not. 0: always twice.
    """

    peak_threshold: float = setting(0.1, ge=0.0, le=1.0)
    nms_radius: int = setting(1, ge=1, unit="cells")
    subpixel: SubpixelMethod = "log_quadratic"
    max_angle_deg: float = setting(30.0, gt=0.0, le=180.0, unit="deg")
    min_affinity_norm: float = setting(0.2, ge=0.0, le=1.0)
    min_points: int = setting(5, ge=4, note="PnP needs 4")
    ransac: bool = True
    ransac_reprojection_px: float = setting(6.0, gt=0.0, unit="px")
    ransac_iterations: int = setting(100, ge=1)
    refine: Literal["lm", "none"] = "lm"
    reprojection_scale_px: float = setting(8.0, gt=0.0, unit="px")
    min_confidence: float = setting(0.0, ge=0.0, le=1.0)
    max_instances: int = setting(16, ge=1)
    correspondence: Literal["strongest", "search"] = "strongest"
    search_below: float = setting(0.1, ge=0.0, le=1.0, note="a confidence; 0: off")
    search_identity_weight: float = setting(0.5, ge=0.0, le=1.0)
    search_max_points: int = setting(8, ge=2)
    search_merge_cells: float = setting(1.0, gt=0.0, unit="cells")
    search_gate_cells: float = setting(1.5, gt=0.0, unit="cells")
    crop_refine: float = setting(0.5, ge=0.0, le=4.0,
                                 note="a fraction of the network input width; 0: off")
    crop_margin: float = setting(1.3, ge=1.0)
    prior_recrop: float = setting(0.05, ge=0.0, le=1.0, note="a fraction of the crop side")
    crop_blend_max_deg: float = setting(0.0, ge=0.0, le=180.0, unit="deg", note="0: off")

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None, source: str = "decode") -> DecodeConfig:
        """Build from a mapping of fields (``None``: the defaults); errors name ``source``
        and the field."""
        return super().from_dict(data, source)


@dataclass
class PoseDetection:
    """One detected object instance.

    Attributes:
        pose: (4, 4) float64 object-to-camera transform (metres).
        confidence: in [0, 1]; see the module docstring. After the estimator's crop pass
            (``DecodeConfig.crop_refine``), the better of its two passes' confidences.
        keypoints: (9, 2) float64 pixels in the input image (8 corners, centroid); NaN where
            missing.
        keypoint_scores: (9,) float64 belief peak values; 0 where missing.
        reprojection_error_px: RMS reprojection error over the keypoints used by PnP.
        num_points: keypoints used by PnP.
        object_name: the object the network was trained for ("" if unknown).
        alternatives: other poses the decoding found for the same instance and did not keep
            (the strongest peaks' fit where the search's was kept, or the reverse; the first
            pass's detection where the crop pass replaced it), most confident first, each
            without alternatives of its own. A tracker with depth can verify them where the
            kept pose fails (``TrackerConfig.pose_gate.alternatives``).
    """

    pose: Tensor
    confidence: float
    keypoints: Tensor
    keypoint_scores: Tensor
    reprojection_error_px: float
    num_points: int
    object_name: str = ""
    alternatives: tuple[PoseDetection, ...] = ()


@dataclass
class InstanceKeypoints:
    """Keypoints of one instance before PnP: (9, 2) pixels (NaN missing) and (9,) scores.

    ``candidates`` (N, 4) ``(x, y, score, corner map)`` holds every corner peak that joined the
    instance, pixels (the pose search pools them).
    """

    keypoints: np.ndarray
    scores: np.ndarray
    candidates: np.ndarray | None = None


def extract_instances(
    belief: np.ndarray, affinity: np.ndarray, stride: int, config: DecodeConfig | None = None
) -> list[InstanceKeypoints]:
    """Group belief peaks into instances through the affinity fields (steps 1-2).

    Args:
        belief: (9, h, w) belief maps.
        affinity: (16, h, w) affinity fields (x, y per corner).
        stride: the network's output stride (pixels per cell).

    Returns:
        One entry per centroid peak, strongest first; keypoints in input-image pixels.
    """
    cfg = config or DecodeConfig()
    belief = np.asarray(belief, dtype=np.float32)
    affinity = np.asarray(affinity, dtype=np.float32)
    if belief.shape[0] != NUM_KEYPOINTS or affinity.shape[0] != 2 * (NUM_KEYPOINTS - 1):
        raise ValueError(
            f"expected 9 belief maps and 16 affinity maps, got {belief.shape}, {affinity.shape}"
        )
    if belief.shape[1:] != affinity.shape[1:]:
        raise ValueError(f"belief {belief.shape} and affinity {affinity.shape} sizes differ")
    peaks = find_peaks(belief, cfg.peak_threshold, cfg.nms_radius, cfg.subpixel)
    centroids = peaks[CENTROID_INDEX][: cfg.max_instances]
    m = len(centroids)
    if m == 0:
        return []
    kp = np.full((m, NUM_KEYPOINTS, 2), np.nan)
    sc = np.zeros((m, NUM_KEYPOINTS))
    kp[:, CENTROID_INDEX] = centroids[:, :2]
    sc[:, CENTROID_INDEX] = centroids[:, 2]
    max_angle = math.radians(cfg.max_angle_deg)
    joined: list[list[tuple[float, float, float, int]]] = [[] for _ in range(m)]
    for k in range(NUM_KEYPOINTS - 1):
        best_angle = np.full(m, np.inf)
        for x, y, score in peaks[k]:
            a = sample_bilinear(affinity[2 * k: 2 * k + 2], x, y)
            a_norm = float(np.hypot(*a))
            if a_norm < cfg.min_affinity_norm:
                continue
            d = centroids[:, :2] - np.array([x, y])
            d_norm = np.hypot(d[:, 0], d[:, 1])
            with np.errstate(invalid="ignore", divide="ignore"):
                cos = (d @ a) / (d_norm * a_norm)
            cos = np.where(d_norm < 1e-9, 1.0, cos)  # a corner on its centroid agrees with any
            angle = np.arccos(np.clip(cos, -1.0, 1.0))
            j = int(np.argmin(angle))
            if angle[j] <= max_angle:
                joined[j].append((x, y, score, k))
            better = score > sc[j, k] or (score == sc[j, k] and angle[j] < best_angle[j])
            if angle[j] <= max_angle and better:
                best_angle[j] = angle[j]
                kp[j, k] = (x, y)
                sc[j, k] = score
    kp = grid_to_pixel(kp, stride)
    out = []
    for i in range(m):
        cand = np.array(joined[i], dtype=np.float64).reshape(-1, 4)
        cand[:, :2] = grid_to_pixel(cand[:, :2], stride)
        out.append(InstanceKeypoints(kp[i], sc[i], cand))
    return out


def _reprojection_rms(
    obj: np.ndarray, img: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, K: np.ndarray,
    dist: np.ndarray | None,
) -> float:
    uv, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    return float(np.sqrt(np.mean(np.sum((uv.reshape(-1, 2) - img) ** 2, axis=1))))


def _in_front(obj: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> bool:
    R, _ = cv2.Rodrigues(rvec)
    z = (obj @ R.T + tvec.reshape(1, 3))[:, 2]
    return bool(np.all(z > 0))


PNP_GRID_PX = 1.0 / 32.0
"""Keypoints go to PnP rounded to this grid (pixels). RANSAC's consensus is not a smooth
function of its input: EPnP on a five- or six-point sample is ill-conditioned, so keypoints
1e-5 px apart (the same network on torch and on onnxruntime) made it keep different inlier
sets, and poses 1-2 degrees apart, on a third of the frames of a test sequence. On the grid
the two backends give PnP the same numbers but where a keypoint lies within ~1e-5 px of a
grid line; 1/32 px is far below the keypoints' own error (~1 px)."""


def on_pnp_grid(points: np.ndarray) -> np.ndarray:
    """``points`` (pixels, float64) rounded to :data:`PNP_GRID_PX` (NaN stays NaN)."""
    return np.round(np.asarray(points, np.float64) / PNP_GRID_PX) * PNP_GRID_PX


def solve_pose(
    instance: InstanceKeypoints,
    cuboid: Cuboid,
    K: np.ndarray,
    dist: np.ndarray | None = None,
    config: DecodeConfig | None = None,
    object_name: str = "",
) -> PoseDetection | None:
    """PnP on one instance's keypoints (steps 3-4); ``None`` when no valid pose is found.

    Args:
        instance: keypoints in pixels of the image that ``K`` describes.
        cuboid: the object's cuboid.
        K: (3, 3) intrinsics; dist: OpenCV distortion coefficients or ``None``.
    """
    cfg = config or DecodeConfig()
    mask = np.all(np.isfinite(instance.keypoints), axis=1)
    n = int(mask.sum())
    if n < cfg.min_points:
        return None
    K = np.asarray(K, dtype=np.float64)
    dist = None if dist is None else np.asarray(dist, dtype=np.float64).reshape(-1)
    obj = np.ascontiguousarray(cuboid.points()[mask])
    img = np.ascontiguousarray(on_pnp_grid(instance.keypoints[mask]))
    if np.ptp(img, axis=0).max() < _MIN_KEYPOINT_SPREAD_PX:
        return None  # every keypoint on (nearly) one pixel: no pose, and OpenCV's solvers assert
    epnp, used = _epnp_start(obj, img, K, dist, cfg)
    obj_u, img_u = obj[used], img[used]
    starts = [s for s in (epnp, _sqpnp_start(obj_u, img_u, K, dist)) if s is not None]
    best = _best_refined(starts, obj_u, img_u, K, dist, cfg, cuboid.points())
    if best is None:
        return None
    err, rvec, tvec = best
    return _detection(rvec, tvec, instance.keypoints, instance.scores, err, int(used.sum()), cfg,
                      object_name)


_Start = tuple[np.ndarray, np.ndarray]
"""A PnP solution ``(rvec, tvec)``."""


def _epnp_start(obj: np.ndarray, img: np.ndarray, K: np.ndarray, dist: np.ndarray | None,
                cfg: DecodeConfig) -> tuple[_Start | None, np.ndarray]:
    """EPnP, inside RANSAC when ``cfg.ransac`` and there are >= 6 points: the solution (or
    ``None``) and the mask of the points it keeps (RANSAC's inliers, else all)."""
    n = len(obj)
    used = np.ones(n, dtype=bool)
    try:
        if cfg.ransac and n >= 6:
            ok, rvec, tvec, inliers = cv2.solvePnPRansac(
                obj, img, K, dist, iterationsCount=cfg.ransac_iterations,
                reprojectionError=cfg.ransac_reprojection_px, flags=cv2.SOLVEPNP_EPNP,
            )
            if ok and inliers is not None and len(inliers) >= cfg.min_points:
                used = np.zeros(n, dtype=bool)
                used[inliers.reshape(-1)] = True
                return (rvec, tvec), used
        else:
            ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_EPNP)
            if ok:
                return (rvec, tvec), used
    except cv2.error:
        pass  # a degenerate configuration: the SQPnP start may still succeed
    return None, used


def _sqpnp_start(obj: np.ndarray, img: np.ndarray, K: np.ndarray, dist: np.ndarray | None
                 ) -> _Start | None:
    """SQPnP's solution, or ``None``."""
    try:
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_SQPNP)
        if ok:
            return rvec, tvec
    except cv2.error:
        pass  # SQPnP asserts on (nearly) collinear or coincident points
    return None


def _best_refined(
    starts: Sequence[_Start], obj: np.ndarray, img: np.ndarray, K: np.ndarray,
    dist: np.ndarray | None, cfg: DecodeConfig, corners: np.ndarray,
) -> tuple[float, np.ndarray, np.ndarray] | None:
    """Each start refined (``cfg.refine``); the one with the smallest reprojection RMS (px)
    that puts every cuboid point in front of the camera, as ``(rms, rvec, tvec)``."""
    best: tuple[float, np.ndarray, np.ndarray] | None = None
    for rvec, tvec in starts:
        rvec, tvec = rvec.astype(np.float64).copy(), tvec.astype(np.float64).copy()
        if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
            continue
        if cfg.refine == "lm":
            try:
                rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
            except cv2.error:
                continue
        if not _in_front(corners, rvec, tvec):
            continue
        err = _reprojection_rms(obj, img, rvec, tvec, K, dist)
        if np.isfinite(err) and (best is None or err < best[0]):
            best = (err, rvec, tvec)
    return best


def _detection(
    rvec: np.ndarray, tvec: np.ndarray, keypoints: np.ndarray, scores: np.ndarray, err: float,
    num_points: int, cfg: DecodeConfig, object_name: str,
) -> PoseDetection | None:
    """The detection of a solved pose (step 4's confidence), or ``None`` below
    ``min_confidence``."""
    confidence = float(np.clip(scores, 0.0, 1.0).mean()
                       * math.exp(-0.5 * (err / cfg.reprojection_scale_px) ** 2))
    if confidence < cfg.min_confidence:
        return None
    pose = np.eye(4)
    pose[:3, :3] = cv2.Rodrigues(rvec)[0]
    pose[:3, 3] = np.asarray(tvec).reshape(3)
    return PoseDetection(
        pose=torch.from_numpy(pose),
        confidence=confidence,
        keypoints=torch.from_numpy(np.array(keypoints, dtype=np.float64)),
        keypoint_scores=torch.from_numpy(np.array(scores, dtype=np.float64)),
        reprojection_error_px=err,
        num_points=num_points,
        object_name=object_name,
    )


def search_instance(
    instance: InstanceKeypoints,
    belief: np.ndarray,
    cuboid: Cuboid,
    K: np.ndarray,
    dist: np.ndarray | None = None,
    *,
    stride: int = 8,
    config: DecodeConfig | None = None,
    pixel_scale: float | tuple[float, float] | np.ndarray = 1.0,
    object_name: str = "",
) -> PoseDetection | None:
    """Pose of one instance by the search over corner identities, then LM refinement.

    Args:
        instance: keypoints and pooled ``candidates`` in pixels of the image ``K`` describes.
        belief: (9, h, w) the maps the instance came from.
        cuboid, K, dist: as in :func:`solve_pose`.
        stride: network output stride; pixel_scale: the network input was the image resized by
            this factor (per axis).

    Returns:
        The detection, or ``None`` (no centroid, fewer than two corner peaks, no hypothesis,
        or fewer than ``min_points`` keypoints matched after the search).
    """
    cfg = config or DecodeConfig()
    scale = np.broadcast_to(np.asarray(pixel_scale, dtype=np.float64), (2,))
    centroid = instance.keypoints[CENTROID_INDEX]
    cand = instance.candidates
    if cand is None or not np.all(np.isfinite(centroid)):
        return None
    cell_px = stride / float(scale.min())  # one cell in pixels of K's image (the larger axis)
    points = merge_points(cand[:, :3], cfg.search_merge_cells * cell_px)
    K = np.asarray(K, dtype=np.float64)
    dist = None if dist is None else np.asarray(dist, dtype=np.float64).reshape(-1)

    def to_grid(uv: np.ndarray) -> np.ndarray:
        return pixel_to_grid((uv + 0.5) * scale - 0.5, stride)

    found = search_pose(points, centroid, belief, cuboid, K, dist, to_grid,
                        identity_weight=cfg.search_identity_weight,
                        max_points=cfg.search_max_points)
    if found is None:
        return None
    obj = cuboid.points()
    uv, _ = cv2.projectPoints(obj, found.rvec, found.tvec, K, dist)
    uv = uv.reshape(-1, 2)
    keypoints = np.full((NUM_KEYPOINTS, 2), np.nan)
    scores = np.zeros(NUM_KEYPOINTS)
    keypoints[CENTROID_INDEX] = centroid
    scores[CENTROID_INDEX] = instance.scores[CENTROID_INDEX]
    gate = cfg.search_gate_cells * cell_px
    dists = np.linalg.norm(uv[:CENTROID_INDEX, None, :] - points[None, :, :2], axis=2)
    taken = np.zeros(len(points), dtype=bool)
    for c in np.argsort(dists.min(axis=1), kind="stable"):
        # corners nearest to a point choose first; each point serves one corner
        d = np.where(taken, np.inf, dists[c])
        j = int(np.argmin(d))
        if d[j] <= gate:
            taken[j] = True
            keypoints[c] = points[j, :2]
            scores[c] = points[j, 2]
    mask = np.all(np.isfinite(keypoints), axis=1)
    if int(mask.sum()) < cfg.min_points:
        return None
    obj_u = np.ascontiguousarray(obj[mask])
    img_u = np.ascontiguousarray(keypoints[mask])
    rvec, tvec = found.rvec.copy(), found.tvec.copy()
    if cfg.refine == "lm":
        try:
            rvec, tvec = cv2.solvePnPRefineLM(obj_u, img_u, K, dist, rvec, tvec)
        except cv2.error:
            rvec, tvec = found.rvec.copy(), found.tvec.copy()
    if not _in_front(obj, rvec, tvec):
        return None
    err = _reprojection_rms(obj_u, img_u, rvec, tvec, K, dist)
    if not np.isfinite(err):
        return None
    return _detection(rvec, tvec, keypoints, scores, err, int(mask.sum()), cfg, object_name)


def _keep_more_confident(a: PoseDetection | None, b: PoseDetection | None
                         ) -> PoseDetection | None:
    """The more confident of two detections of one instance (``a`` on ties), the other one
    among its :attr:`~PoseDetection.alternatives`."""
    if a is None or b is None:
        return a if b is None else b
    kept, other = (b, a) if b.confidence > a.confidence else (a, b)
    return with_alternatives(kept, (other,))


def with_alternatives(det: PoseDetection, others: Sequence[PoseDetection]) -> PoseDetection:
    """``det`` with ``others`` (and their own alternatives, flattened) added to its
    alternatives, most confident first."""
    flat = list(det.alternatives)
    for o in others:
        flat.append(replace(o, alternatives=()))
        flat.extend(o.alternatives)
    flat.sort(key=lambda d: -d.confidence)
    return replace(det, alternatives=tuple(flat))


def decode_poses(
    belief: np.ndarray,
    affinity: np.ndarray,
    cuboid: Cuboid,
    K: np.ndarray,
    dist: np.ndarray | None = None,
    *,
    stride: int = 8,
    config: DecodeConfig | None = None,
    pixel_scale: float | tuple[float, float] = 1.0,
    object_name: str = "",
) -> list[PoseDetection]:
    """Poses of every instance in one image's maps, most confident first.

    Args:
        belief: (9, h, w); affinity: (16, h, w) for one image.
        cuboid: the object's cuboid; K: (3, 3) intrinsics of the *original* image.
        dist: distortion coefficients of the original image, or ``None``.
        stride: network output stride.
        pixel_scale: the network saw the image resized by this factor (or by ``(sx, sy)``);
            keypoints are mapped back with ``p_orig = (p + 0.5) / scale - 0.5`` per axis.
    """
    cfg = config or DecodeConfig()
    scale = np.broadcast_to(np.asarray(pixel_scale, dtype=np.float64), (2,))
    out = []
    for inst in extract_instances(belief, affinity, stride, cfg):
        if np.any(scale != 1.0):
            cand = None
            if inst.candidates is not None:
                cand = inst.candidates.copy()
                cand[:, :2] = (cand[:, :2] + 0.5) / scale - 0.5
            inst = InstanceKeypoints((inst.keypoints + 0.5) / scale - 0.5, inst.scores, cand)
        search = cfg.correspondence == "search"
        det = None if search else solve_pose(inst, cuboid, K, dist, cfg, object_name)
        if search or (cfg.search_below > 0
                      and (det is None or det.confidence < cfg.search_below)):
            found = search_instance(inst, belief, cuboid, K, dist, stride=stride, config=cfg,
                                    pixel_scale=scale, object_name=object_name)
            det = _keep_more_confident(det, found)
        if det is not None:
            out.append(det)
    out.sort(key=lambda d: -d.confidence)
    return out
