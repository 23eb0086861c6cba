"""Pose sources: what gives :class:`evtrack.Tracker` its low-rate absolute poses.

A pose source is called on an RGB frame and returns at most one :class:`PoseMeasurement` in the
event camera frame::

    measurement = source(t_us, rgb, depth)      # PoseMeasurement | None

* :class:`NetworkPoseSource` wraps a pose network estimator (:mod:`evtrack.models`:
  ``TorchPoseEstimator``, ``OnnxPoseEstimator``): the most confident detection, refined on
  the frame's depth when given a :class:`~evtrack.models.DepthRefiner`, carried from the RGB
  camera into the event camera with ``T_event_rgb``.
* :class:`OraclePoseSource` is **not an estimator**: it returns the ground-truth pose of a
  simulated sequence with synthetic noise, outliers and dropouts. It exists to test the tracker
  and to measure the filtering side independently of any network; results obtained with it say
  nothing about a real pose network.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from torch import Tensor

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError
from evtrack.geometry import inverse

__all__ = [
    "ROTATION_TOLERANCE",
    "checked_pose",
    "PoseMeasurement",
    "PoseSource",
    "NetworkPoseSource",
    "OraclePoseSource",
]


ROTATION_TOLERANCE = 1e-3
"""Largest ``|RᵀR - I|`` entry (and ``|det R - 1|``) of a pose's rotation block accepted by
:class:`PoseMeasurement`: float32 round-off passes, a scaled or sheared matrix does not."""


def checked_pose(pose: Tensor | np.ndarray, where: str) -> Tensor:
    """``pose`` as a float64 (4, 4) tensor, if it is a rigid transform: finite, a rotation
    block within :data:`ROTATION_TOLERANCE`, last row ``[0, 0, 0, 1]``.

    Raises:
        ValueError: naming ``where`` and what is wrong.
    """
    try:
        pose = torch.as_tensor(pose, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"{where}: pose must be a (4, 4) array of numbers ({exc})") from exc
    if pose.shape != (4, 4):
        raise ValueError(f"{where}: pose must be (4, 4), got {tuple(pose.shape)}")
    if not bool(torch.isfinite(pose).all()):
        raise ValueError(f"{where}: pose is not finite")
    R = pose[:3, :3]
    ortho = float((R.T @ R - torch.eye(3, dtype=torch.float64)).abs().max())
    det = float(torch.linalg.det(R))
    if ortho > ROTATION_TOLERANCE or abs(det - 1.0) > ROTATION_TOLERANCE:
        raise ValueError(f"{where}: the rotation block is not a rotation "
                         f"(max |RᵀR - I| = {ortho:.2g}, det = {det:.4g})")
    bottom = pose[3].tolist()
    if bottom != [0.0, 0.0, 0.0, 1.0]:
        raise ValueError(f"{where}: last row must be [0, 0, 0, 1], got {bottom}")
    return pose


@dataclass
class PoseMeasurement:
    """One absolute pose.

    Attributes:
        t_us: time of the image it was computed from (µs).
        pose: (4, 4) float64 object-to-event-camera transform: finite, a rotation block
            (within :data:`ROTATION_TOLERANCE`) and last row ``[0, 0, 0, 1]``.
        cov: (6, 6) float64 covariance of ``[δt (m), δθ (rad)]``, finite and symmetric, or
            ``None`` for the filter's default measurement noise.
        confidence: the detector's confidence (1 when unknown).
        alternatives: other poses the detector found for the object in the same image and
            ranked lower (e.g. :attr:`evtrack.models.PoseDetection.alternatives`), most
            confident first; the tracker tries them, in that order, where this pose fails its
            depth check (``TrackerConfig.pose_gate.alternatives``). Each is a measurement of the
            same
            ``t_us`` without alternatives of its own.

    Raises:
        ValueError: a pose or covariance of the wrong shape, not finite, or not a rigid
            transform (one NaN pose would otherwise poison the filter state for good).
    """

    t_us: int
    pose: Tensor
    cov: Tensor | None = None
    confidence: float = 1.0
    alternatives: tuple[PoseMeasurement, ...] = ()

    def __post_init__(self) -> None:
        self.t_us = int(self.t_us)
        self.alternatives = tuple(self.alternatives)
        for alt in self.alternatives:
            if not isinstance(alt, PoseMeasurement) or alt.t_us != self.t_us or alt.alternatives:
                raise ValueError(f"pose measurement at t={self.t_us} µs: each alternative must "
                                 "be a PoseMeasurement of the same t_us without alternatives")
        where = f"pose measurement at t={self.t_us} µs"
        self.pose = checked_pose(self.pose, where)
        if self.cov is not None:
            self.cov = torch.as_tensor(self.cov, dtype=torch.float64)
            if self.cov.shape != (6, 6):
                raise ValueError(f"{where}: covariance must be (6, 6), got "
                                 f"{tuple(self.cov.shape)}")
            if not bool(torch.isfinite(self.cov).all()):
                raise ValueError(f"{where}: covariance is not finite")
            if not torch.allclose(self.cov, self.cov.T, rtol=1e-9, atol=1e-12):
                raise ValueError(f"{where}: covariance is not symmetric")


@runtime_checkable
class PoseSource(Protocol):
    """Anything callable as ``source(t_us, rgb, depth) -> PoseMeasurement | None``.

    The tracker passes the frame's depth map (metres, registered to ``rgb``) only to sources
    whose ``uses_depth`` attribute is true (it then loads the depth frames for them), and
    ``None`` otherwise. With ``TrackerConfig.pose_prior`` on, a source whose
    ``accepts_prior`` attribute is true is also given ``prior=``, the track's (4, 4) pose
    (event camera frame) at ``t_us``, while the track holds.
    """

    def __call__(self, t_us: int, rgb: np.ndarray, depth: np.ndarray | None
                 ) -> PoseMeasurement | None: ...


class NetworkPoseSource:
    """Poses from a pose network estimator (:class:`evtrack.models.PoseEstimator`).

    Args:
        estimator: callable ``estimator(rgb) -> list[PoseDetection]`` (most confident first or
            not; the most confident detection is taken). Detection poses are object-to-RGB-camera.
        T_event_rgb: (4, 4) maps RGB-camera points into the event camera (identity default).
        min_confidence: detections below it are ignored.
        cov: (6, 6) measurement covariance handed to the filter, or ``None`` for its default.
        refiner: a :class:`~evtrack.models.DepthRefiner`: when a frame comes with a depth map
            (registered to the RGB image), the detection's pose is refined on it first; a pose
            the depth cannot refine is used as the network gave it (counted in
            :attr:`refine_refused`).
        camera: the RGB camera (intrinsics, distortion) for the refiner; default: the
            estimator's ``camera``.

    A detection whose pose is not a finite rigid transform (see :class:`PoseMeasurement`)
    gives no measurement (the tracker counts the call as a miss) and is counted in
    :attr:`invalid`; so is such an alternative, which is left out of the measurement's
    ``alternatives``.
    """

    def __init__(self, estimator: Callable[[np.ndarray], Sequence],
                 T_event_rgb: Tensor | None = None, min_confidence: float = 0.0,
                 cov: Tensor | None = None, refiner=None, camera=None) -> None:
        self.estimator = estimator
        self.T_event_rgb = (torch.eye(4, dtype=torch.float64) if T_event_rgb is None
                            else torch.as_tensor(T_event_rgb, dtype=torch.float64))
        if self.T_event_rgb.shape != (4, 4):
            raise ConfigError(f"T_event_rgb must be (4, 4), got {tuple(self.T_event_rgb.shape)}")
        self.min_confidence = float(min_confidence)
        self.cov = cov
        self.refiner = refiner
        self.camera = camera if camera is not None else getattr(estimator, "camera", None)
        if refiner is not None and self.camera is None:
            raise ConfigError("a depth refiner needs the RGB camera: pass camera=...")
        self.invalid = 0
        self.refined = 0
        self.refine_refused = 0

    @property
    def uses_depth(self) -> bool:
        """Whether the source reads the depth frames (the tracker loads them for it)."""
        return self.refiner is not None

    def _refine(self, pose: np.ndarray, depth: np.ndarray) -> np.ndarray:
        cam = self.camera
        if isinstance(cam, PinholeCamera):
            K = cam.K().numpy()
            dist = None if cam.dist is None else cam.dist.numpy()
        else:
            K, dist = np.asarray(cam, np.float64), None
        res = self.refiner.refine(pose, np.asarray(depth), K, dist)
        self.refined += int(res.refined)
        self.refine_refused += int(not res.refined)
        return res.pose

    accepts_prior = True
    """:meth:`__call__` takes ``prior=`` (the tracker passes its pose when
    ``TrackerConfig.pose_prior`` is on)."""

    def __call__(self, t_us: int, rgb: np.ndarray, depth: np.ndarray | None = None,
                 prior: np.ndarray | Tensor | None = None) -> PoseMeasurement | None:
        """The most confident detection in ``rgb`` as a measurement at ``t_us``, or ``None``.

        Args:
            t_us: the frame's time (µs). rgb: uint8 (H, W, 3). depth: the registered depth
                map for the refiner, or ``None``.
            prior: (4, 4) object-to-event-camera pose expected in the frame, or ``None``: with
                one, an estimator that has ``estimate_near``
                (:meth:`~evtrack.models.PoseEstimator.estimate_near`) looks there first; a
                plain callable estimator ignores it.
        """
        near = getattr(self.estimator, "estimate_near", None)
        if prior is not None and near is not None:
            prior_rgb = inverse(self.T_event_rgb) @ torch.as_tensor(
                np.asarray(prior, np.float64))
            found = near(rgb, prior_rgb.numpy())
        else:
            found = self.estimator(rgb)
        detections = [d for d in found if d.confidence >= self.min_confidence]
        if not detections:
            return None
        best = max(detections, key=lambda d: d.confidence)
        pose = np.asarray(best.pose, np.float64)
        if self.refiner is not None and depth is not None and np.isfinite(pose).all():
            pose = self._refine(pose, depth)
        try:
            return PoseMeasurement(t_us, self.T_event_rgb @ torch.as_tensor(pose),
                                   self.cov, float(best.confidence),
                                   self._alternatives(t_us, best))
        except ValueError:
            self.invalid += 1
            return None

    def _alternatives(self, t_us: int, detection) -> tuple[PoseMeasurement, ...]:
        """The detection's :attr:`~evtrack.models.PoseDetection.alternatives` at or above
        ``min_confidence`` as measurements (not depth-refined; invalid poses left out)."""
        out = []
        for alt in getattr(detection, "alternatives", ()):
            if alt.confidence < self.min_confidence:
                continue
            try:
                out.append(PoseMeasurement(t_us, self.T_event_rgb @ torch.as_tensor(
                    np.asarray(alt.pose, np.float64)), self.cov, float(alt.confidence)))
            except ValueError:
                self.invalid += 1
                continue
        return tuple(out)


class OraclePoseSource:
    """Ground-truth poses with synthetic errors — for tests and diagnostics only.

    **Not a pose estimator.** It reads the true pose of a simulated sequence at the frame time
    and perturbs it; use it to test the tracker and to measure the filters without a network.

    Every frame time gets its own random draws, from ``(seed, t_us)``: the same frame always
    gives the same measurement, whatever the order or chunking of the calls.

    Args:
        pose_at: the true pose at a time, ``pose_at(t_us) -> (4, 4)`` (e.g.
            ``sequence.ground_truth.pose_at``).
        std_translation: metres, Gaussian noise per axis on the translation.
        std_rotation: radians, Gaussian noise per axis of a rotation vector applied in the
            camera frame (``R' = exp(δθ) R``).
        outlier_rate: probability that the pose is replaced by a random one: a uniformly random
            rotation and the true translation moved uniformly within ``±outlier_translation``
            per axis.
        outlier_translation: metres, see ``outlier_rate``.
        dropout_rate: probability of returning nothing (a missed detection).
        report_cov: hand the filter the covariance of the inlier noise (else ``None``: the
            filter's default).
        seed: seed of all draws.
    """

    def __init__(self, pose_at: Callable[[int], Tensor], std_translation: float = 0.0,
                 std_rotation: float = 0.0, outlier_rate: float = 0.0,
                 outlier_translation: float = 0.3, dropout_rate: float = 0.0,
                 report_cov: bool = False, seed: int = 0) -> None:
        for name, value in (("std_translation", std_translation), ("std_rotation", std_rotation),
                            ("outlier_translation", outlier_translation)):
            if not value >= 0:
                raise ConfigError(f"OraclePoseSource: {name} must be >= 0, got {value}")
        for name, value in (("outlier_rate", outlier_rate), ("dropout_rate", dropout_rate)):
            if not 0 <= value <= 1:
                raise ConfigError(f"OraclePoseSource: {name} must be in [0, 1], got {value}")
        self.pose_at = pose_at
        self.std_translation = float(std_translation)
        self.std_rotation = float(std_rotation)
        self.outlier_rate = float(outlier_rate)
        self.outlier_translation = float(outlier_translation)
        self.dropout_rate = float(dropout_rate)
        self.report_cov = bool(report_cov)
        self.seed = int(seed)
        self.outliers: list[int] = []  # frame times given an outlier (for tests)

    @classmethod
    def from_sequence(cls, sequence, **kwargs) -> OraclePoseSource:
        """The oracle of a sequence with ground truth (raises if it has none)."""
        gt = sequence.ground_truth
        if gt is None:
            raise ConfigError(f"{sequence.root or sequence.meta.name}: the oracle pose source "
                              "needs ground truth (groundtruth.h5)")
        return cls(gt.pose_at, **kwargs)

    def _cov(self) -> Tensor | None:
        if not self.report_cov:
            return None
        var = [max(self.std_translation, 1e-6) ** 2] * 3 + [max(self.std_rotation, 1e-6) ** 2] * 3
        return torch.diag(torch.tensor(var, dtype=torch.float64))

    def __call__(self, t_us: int, rgb: np.ndarray | None = None,
                 depth: np.ndarray | None = None) -> PoseMeasurement | None:
        rng = np.random.default_rng([self.seed, int(t_us)])
        drop, outlier = rng.random(2)
        noise = rng.standard_normal(6)
        random_rot = Rotation.random(random_state=rng).as_matrix()
        offset = rng.uniform(-1.0, 1.0, 3) * self.outlier_translation
        if drop < self.dropout_rate:
            return None
        pose = self.pose_at(int(t_us))
        T = (pose.detach().cpu().numpy() if isinstance(pose, Tensor) else np.asarray(pose)
             ).astype(np.float64, copy=True)
        if outlier < self.outlier_rate:
            self.outliers.append(int(t_us))
            T[:3, :3] = random_rot
            T[:3, 3] += offset
        else:
            T[:3, 3] += noise[:3] * self.std_translation
            T[:3, :3] = Rotation.from_rotvec(noise[3:] * self.std_rotation).as_matrix() @ T[:3, :3]
        return PoseMeasurement(int(t_us), torch.from_numpy(T), self._cov(), 1.0)
