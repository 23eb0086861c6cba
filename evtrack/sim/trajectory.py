"""Smooth random 6-DoF trajectories of an object in front of a static camera.

A trajectory passes through waypoints ``(t_i, r_i)`` at knot times. Between knots both the
translation ``t(s)`` and the rotation vector ``r(s)`` follow quintic Hermite curves with the
knot velocities given and zero knot accelerations, so the motion is C² (continuous
acceleration). At a *reversal* knot the velocities are zero: the object slows down, stops and
moves off in a new direction, as a hand-moved object does; at other knots it passes through
with a Catmull-Rom velocity.

Orientation: ``R(s) = exp([r(s)]×) R_ref`` with a random reference rotation ``R_ref`` per
sequence. The pose is object-to-camera, ``T = [R | t]``.

Twist (the package's convention, camera frame, ``Ṗ = v_o + ω × P``): computed analytically,
``ω = J_l(r) ṙ`` with ``J_l`` the left Jacobian of SO(3), and ``v_o = ṫ - ω × t``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evtrack.camera import PinholeCamera
from evtrack.sim.config import TrajectoryConfig

__all__ = ["Trajectory", "random_trajectory", "static_trajectory", "rotvec_to_matrix",
           "left_jacobian", "random_rotation"]

_SMALL_ANGLE = 1e-6
_MAX_FIT_ROUNDS = 30        # halvings of knot velocities to keep the object in view
_CHECK_STEP_S = 0.002        # the view check samples the trajectory this often
_MIN_SEGMENT_S = 0.08        # shortest time between waypoints
_MAX_WAYPOINT_TRIES = 200


def _skew(w: np.ndarray) -> np.ndarray:
    z = np.zeros_like(w[..., 0])
    wx, wy, wz = w[..., 0], w[..., 1], w[..., 2]
    return np.stack([z, -wz, wy, wz, z, -wx, -wy, wx, z], -1).reshape(*w.shape[:-1], 3, 3)


def rotvec_to_matrix(r: np.ndarray) -> np.ndarray:
    """Rodrigues: (..., 3) rotation vectors -> (..., 3, 3) rotation matrices (float64)."""
    r = np.asarray(r, np.float64)
    theta = np.linalg.norm(r, axis=-1)[..., None, None]
    K = _skew(r)
    small = theta < _SMALL_ANGLE
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta ** 2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta ** 2 / 24.0, (1.0 - np.cos(safe)) / safe ** 2)
    return np.eye(3) + a * K + b * (K @ K)


def left_jacobian(r: np.ndarray) -> np.ndarray:
    """Left Jacobian of SO(3): ``d/ds exp([r]×) · exp([r]×)^T = [J_l(r) ṙ]×``.

    ``J_l = I + (1 - cos θ)/θ² [r]× + (θ - sin θ)/θ³ [r]×²``; (..., 3) -> (..., 3, 3).
    """
    r = np.asarray(r, np.float64)
    theta = np.linalg.norm(r, axis=-1)[..., None, None]
    K = _skew(r)
    small = theta < _SMALL_ANGLE
    safe = np.where(small, 1.0, theta)
    b = np.where(small, 0.5 - theta ** 2 / 24.0, (1.0 - np.cos(safe)) / safe ** 2)
    c = np.where(small, 1.0 / 6.0 - theta ** 2 / 120.0, (safe - np.sin(safe)) / safe ** 3)
    return np.eye(3) + b * K + c * (K @ K)


def _hermite(tau: np.ndarray, h: np.ndarray):
    """Quintic Hermite basis (zero end accelerations) and derivatives w.r.t. time.

    Returns ``(b, db)``, each (N, 4) for ``(p0, v0, v1, p1)`` where the velocity terms are
    already multiplied by the segment duration ``h`` and ``db`` is divided by ``h``.
    """
    t2, t3, t4, t5 = tau ** 2, tau ** 3, tau ** 4, tau ** 5
    h0 = 1 - 10 * t3 + 15 * t4 - 6 * t5
    h1 = tau - 6 * t3 + 8 * t4 - 3 * t5
    h2 = -4 * t3 + 7 * t4 - 3 * t5
    h3 = 10 * t3 - 15 * t4 + 6 * t5
    d0 = -30 * t2 + 60 * t3 - 30 * t4
    d1 = 1 - 18 * t2 + 32 * t3 - 15 * t4
    d2 = -12 * t2 + 28 * t3 - 15 * t4
    d3 = 30 * t2 - 60 * t3 + 30 * t4
    b = np.stack([h0, h1 * h, h2 * h, h3], -1)
    db = np.stack([d0 / h, d1, d2, d3 / h], -1)
    return b, db


@dataclass(frozen=True)
class Trajectory:
    """A smooth object trajectory: knots with positions, rotation vectors and their rates.

    Attributes:
        knot_times: (K,) seconds, increasing; the trajectory is defined on
            ``[knot_times[0], knot_times[-1]]`` and held constant outside.
        positions: (K, 3) translations of the object->camera pose, metres.
        velocities: (K, 3) translation rates at the knots, m/s.
        rotvecs: (K, 3) rotation vectors ``r_i`` (``R_i = exp([r_i]×) R_ref``), radians.
        rotvec_rates: (K, 3) ``ṙ`` at the knots, rad/s.
        R_ref: (3, 3) reference rotation.
        reversals: (K,) bool, knots where the object comes to rest.
    """

    knot_times: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray
    rotvecs: np.ndarray
    rotvec_rates: np.ndarray
    R_ref: np.ndarray
    reversals: np.ndarray

    def _locate(self, t: np.ndarray):
        kt = self.knot_times
        t = np.clip(np.asarray(t, np.float64), kt[0], kt[-1])
        i = np.clip(np.searchsorted(kt, t, side="right") - 1, 0, len(kt) - 2)
        h = kt[i + 1] - kt[i]
        tau = (t - kt[i]) / h
        return i, tau, h, np.asarray(t)

    def _curves(self, t):
        scalar = np.ndim(t) == 0
        tt = np.atleast_1d(np.asarray(t, np.float64))
        outside = (tt < self.knot_times[0]) | (tt > self.knot_times[-1])
        i, tau, h, _ = self._locate(tt)
        b, db = _hermite(tau, h)

        def interp(p, v, basis):
            return (basis[:, :1] * p[i] + basis[:, 1:2] * v[i] + basis[:, 2:3] * v[i + 1]
                    + basis[:, 3:] * p[i + 1])

        pos = interp(self.positions, self.velocities, b)
        vel = interp(self.positions, self.velocities, db)
        r = interp(self.rotvecs, self.rotvec_rates, b)
        rdot = interp(self.rotvecs, self.rotvec_rates, db)
        vel[outside] = 0.0
        rdot[outside] = 0.0
        return scalar, pos, vel, r, rdot

    def pose(self, t: float | np.ndarray) -> np.ndarray:
        """Object-to-camera pose(s) at ``t`` seconds: (4, 4) or (N, 4, 4) float64."""
        scalar, pos, _, r, _ = self._curves(t)
        T = np.zeros((len(pos), 4, 4))
        T[:, :3, :3] = rotvec_to_matrix(r) @ self.R_ref
        T[:, :3, 3] = pos
        T[:, 3, 3] = 1.0
        return T[0] if scalar else T

    def twist(self, t: float | np.ndarray) -> np.ndarray:
        """Camera-frame twist ``[v_o, ω]`` at ``t`` seconds: (6,) or (N, 6) float64.

        Every object point moves as ``Ṗ = v_o + ω × P`` (the package's convention).
        """
        scalar, pos, vel, r, rdot = self._curves(t)
        omega = (left_jacobian(r) @ rdot[..., None])[..., 0]
        v_o = vel - np.cross(omega, pos)
        out = np.concatenate([v_o, omega], -1)
        return out[0] if scalar else out

    @property
    def start(self) -> float:
        return float(self.knot_times[0])

    @property
    def end(self) -> float:
        return float(self.knot_times[-1])

    def to_dict(self) -> dict:
        """Plain lists (for metadata)."""
        return {k: np.asarray(getattr(self, k)).tolist() for k in (
            "knot_times", "positions", "velocities", "rotvecs", "rotvec_rates", "R_ref",
            "reversals")}


def static_trajectory(pose: np.ndarray, duration: float) -> Trajectory:
    """A trajectory that holds ``pose`` (4, 4) for ``duration`` seconds."""
    pose = np.asarray(pose, np.float64)
    z = np.zeros((2, 3))
    return Trajectory(np.array([0.0, float(duration)]), np.stack([pose[:3, 3]] * 2), z.copy(),
                      z.copy(), z.copy(), pose[:3, :3].copy(), np.array([True, True]))


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly distributed random rotation matrix (3, 3) from ``rng``."""
    q = rng.standard_normal(4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _full_image(camera: PinholeCamera) -> tuple[float, float, float, float]:
    return 0.0, camera.width - 1.0, 0.0, camera.height - 1.0


def _in_view(p: np.ndarray, camera: PinholeCamera, radius: float, cfg: TrajectoryConfig,
             region: tuple[float, float, float, float] | None = None) -> np.ndarray:
    """(N, 3) object centres -> (N,) bool: in the depth range and inside the view margin of
    ``region`` (``(u_lo, u_hi, v_lo, v_hi)`` pixels; default the whole image)."""
    u_lo, u_hi, v_lo, v_hi = region or _full_image(camera)
    z = p[:, 2]
    ok = (z >= cfg.z_range[0] - 1e-9) & (z <= cfg.z_range[1] + 1e-9)
    zs = np.where(z > 0, z, np.inf)
    u = camera.fx * p[:, 0] / zs + camera.cx
    v = camera.fy * p[:, 1] / zs + camera.cy
    mu = cfg.view_margin * camera.fx * radius / zs
    mv = cfg.view_margin * camera.fy * radius / zs
    half_u, half_v = (u_hi - u_lo) / 2.0, (v_hi - v_lo) / 2.0
    mu, mv = np.minimum(mu, half_u), np.minimum(mv, half_v)
    return ok & (u >= u_lo + mu - 1e-9) & (u <= u_hi - mu + 1e-9) & (
        v >= v_lo + mv - 1e-9) & (v <= v_hi - mv + 1e-9)


def _sample_position(rng: np.random.Generator, camera: PinholeCamera, radius: float,
                     cfg: TrajectoryConfig,
                     region: tuple[float, float, float, float] | None = None) -> np.ndarray:
    u_lo, u_hi, v_lo, v_hi = region or _full_image(camera)
    z = rng.uniform(*cfg.z_range)
    mu = min(cfg.view_margin * camera.fx * radius / z, (u_hi - u_lo) / 2.0)
    mv = min(cfg.view_margin * camera.fy * radius / z, (v_hi - v_lo) / 2.0)
    u = rng.uniform(u_lo + mu, u_hi - mu)
    v = rng.uniform(v_lo + mv, v_hi - mv)
    return np.array([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z])


def _next_waypoint(rng, prev_p, prev_r, camera, radius, cfg, region=None):
    """A waypoint at a distance in ``waypoint_step`` and rotation in ``rotation_step``."""
    lo, hi = cfg.waypoint_step
    p = None
    for _ in range(_MAX_WAYPOINT_TRIES):
        cand = _sample_position(rng, camera, radius, cfg, region)
        if lo <= np.linalg.norm(cand - prev_p) <= hi:
            p = cand
            break
    if p is None:  # the view volume is small: take a point on the chord towards a sample
        cand = _sample_position(rng, camera, radius, cfg, region)
        d = cand - prev_p
        p = prev_p + d * min(1.0, hi / max(np.linalg.norm(d), 1e-12))
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    r = prev_r + axis * rng.uniform(*cfg.rotation_step)
    norm = np.linalg.norm(r)
    if norm > cfg.max_rotation:  # fold back into the allowed ball
        r = r * (2.0 * cfg.max_rotation - norm) / norm
    return p, r


def random_trajectory(duration: float, camera: PinholeCamera, object_radius: float,
                      config: TrajectoryConfig | None = None,
                      seed: int | np.random.SeedSequence = 0,
                      region: tuple[float, float, float, float] | None = None) -> Trajectory:
    """A random smooth trajectory covering ``[0, duration]`` seconds.

    The object's centre stays at ``z`` in ``config.z_range`` and projects inside the image
    with a margin of ``config.view_margin`` times its projected bounding radius. Knot
    velocities that would carry it out of view are halved until it stays in view (a knot with
    zero velocities moves along the straight chord, which stays in the convex view volume).

    Args:
        duration: seconds to cover.
        camera: the camera (for the view constraint).
        object_radius: bounding-sphere radius of the object, metres.
        config: speeds and limits (default: the ``regular`` preset).
        seed: the same seed gives the same trajectory.
        region: ``(u_lo, u_hi, v_lo, v_hi)``, the pixel rectangle the view constraint keeps
            the object in (default: the whole image).
    """
    cfg = config or TrajectoryConfig()
    rng = np.random.default_rng(seed)
    R_ref = random_rotation(rng)
    p = [_sample_position(rng, camera, object_radius, cfg, region)]
    r = [np.zeros(3)]
    seg = []
    t_first = None
    total = 0.0
    while True:
        pn, rn = _next_waypoint(rng, p[-1], r[-1], camera, object_radius, cfg, region)
        h = max(np.linalg.norm(pn - p[-1]) / cfg.linear_speed,
                np.linalg.norm(rn - r[-1]) / cfg.angular_speed, _MIN_SEGMENT_S)
        h *= rng.uniform(1.0 - cfg.duration_jitter, 1.0 + cfg.duration_jitter)
        p.append(pn)
        r.append(rn)
        seg.append(h)
        if t_first is None:  # start inside the first segment: the object is already moving
            t_first = -rng.uniform(0.0, h)
        total += h
        if t_first + total >= duration + _MIN_SEGMENT_S:
            break
    P, Rv, H = np.array(p), np.array(r), np.array(seg)
    times = t_first + np.concatenate([[0.0], np.cumsum(H)])
    reversal = rng.random(len(P)) < cfg.reversal_probability
    reversal[0] = reversal[-1] = True
    V, W = np.zeros_like(P), np.zeros_like(Rv)
    for i in range(1, len(P) - 1):
        if not reversal[i]:
            V[i] = (P[i + 1] - P[i - 1]) / (H[i - 1] + H[i])
            W[i] = (Rv[i + 1] - Rv[i - 1]) / (H[i - 1] + H[i])
    traj = Trajectory(times, P, V, Rv, W, R_ref, reversal)
    return _fit_in_view(traj, camera, object_radius, cfg, region)


def _fit_in_view(traj: Trajectory, camera, radius, cfg, region=None) -> Trajectory:
    """Halve knot velocities next to segments that leave the view until none does."""
    V = traj.velocities.copy()
    kt = traj.knot_times
    for _ in range(_MAX_FIT_ROUNDS):
        cur = Trajectory(kt, traj.positions, V, traj.rotvecs, traj.rotvec_rates, traj.R_ref,
                         traj.reversals)
        ts = np.arange(kt[0], kt[-1], _CHECK_STEP_S)
        bad = ~_in_view(cur.pose(ts)[:, :3, 3], camera, radius, cfg, region)
        if not bad.any():
            return cur
        segs = np.unique(np.clip(np.searchsorted(kt, ts[bad], side="right") - 1, 0, len(kt) - 2))
        V[segs] *= 0.5
        V[segs + 1] *= 0.5
    V[:] = 0.0  # straight chords: always inside the (convex) view volume
    return Trajectory(kt, traj.positions, V, traj.rotvecs, traj.rotvec_rates, traj.R_ref,
                      np.ones(len(kt), bool))
