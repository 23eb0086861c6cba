"""Configuration of the synthetic data engine: dataclasses with documented defaults, from YAML.

Every section is a dataclass whose defaults are the values used by the benchmark set
(640x480, 500 FPS renders, 60 FPS RGB-D). :func:`load_config` reads a YAML file with the
same nesting (``camera``, ``scene``, ``render``, ``trajectory``, ``events``, ``frames``,
``ground_truth``) with :mod:`evtrack.configs`: unknown, mistyped or out-of-range fields raise
:class:`~evtrack.errors.ConfigError` naming the file and the field.

Example:
    >>> cfg = SimConfig.from_dict({"duration": 0.5, "trajectory": {"preset": "faster"}})
    >>> cfg.trajectory.linear_speed, cfg.render.render_hz
    (0.8, 500.0)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from evtrack.camera import PinholeCamera
from evtrack.configs import Config, FieldError, setting
from evtrack.errors import ConfigError

__all__ = [
    "CameraConfig",
    "SceneConfig",
    "RenderConfig",
    "TrajectoryConfig",
    "EventConfig",
    "FrameConfig",
    "GroundTruthConfig",
    "SimConfig",
    "TRAJECTORY_PRESETS",
    "TrajectoryPreset",
    "load_config",
]

#: Mean speeds of the two motion presets: translation (m/s) and rotation (rad/s) along the
#: waypoint path. ``faster`` is the paper's fast-motion setting with visible motion blur.
TRAJECTORY_PRESETS: dict[str, dict[str, float]] = {
    "regular": {"linear_speed": 0.3, "angular_speed": 1.0},
    "faster": {"linear_speed": 0.8, "angular_speed": 2.5},
}

TrajectoryPreset = Literal["regular", "faster"]
"""The names of :data:`TRAJECTORY_PRESETS`."""


@dataclass
class CameraConfig(Config):
    """The simulated camera (event camera and RGB-D camera share it: identical optics).

    Attributes:
        width, height: image size in pixels.
        fx, fy: focal lengths in pixels (RealSense D415 colour at 640x480 is about 615).
        cx, cy: principal point in pixels (pixel centres at integer coordinates);
            ``None`` puts it at the image centre ``((width-1)/2, (height-1)/2)``.
    """

    width: int = 640
    height: int = 480
    fx: float = 615.0
    fy: float = 615.0
    cx: float | None = None
    cy: float | None = None

    def camera(self) -> PinholeCamera:
        """The :class:`~evtrack.PinholeCamera` (no distortion: the renderer is a pinhole)."""
        cx = (self.width - 1) / 2.0 if self.cx is None else self.cx
        cy = (self.height - 1) / 2.0 if self.cy is None else self.cy
        return PinholeCamera(self.fx, self.fy, cx, cy, self.width, self.height)

    def resized(self, width: int, height: int) -> CameraConfig:
        """The same field of view at another resolution (focal lengths scaled with width)."""
        s = width / self.width
        cx = None if self.cx is None else (self.cx + 0.5) * s - 0.5
        cy = None if self.cy is None else (self.cy + 0.5) * height / self.height - 0.5
        return CameraConfig(width, height, self.fx * s, self.fy * height / self.height, cx, cy)


@dataclass
class SceneConfig(Config):
    """What surrounds the object: background, lighting, distractors.

    Attributes:
        background_depth: z of the background plane facing the camera, metres.
        background_brightness: linear radiance scale of the (unlit) background texture.
        background_contrast: contrast of the procedural background texture in [0, 1].
        light_direction: direction *towards* the light in the camera frame (normalised).
        ambient: ambient term of the Lambertian shading (linear units).
        diffuse: diffuse term: ``albedo * (ambient + diffuse * max(0, n·l))``.
        randomize: for training data: random background texture, light direction and
            strength, and ``0..max_distractors`` static distractor objects.
        max_distractors: most distractors when ``randomize`` is set.
        distractor_depth: z range of distractors, metres (behind or among the object's range).
        distractor_kinds: procedural kinds distractors are drawn from (``box``, ``can``,
            ``bottle``); training data for a procedural object leaves its own kind out, so that
            no look-alike of the object is in view.
    """

    background_depth: float = 2.0
    background_brightness: float = 0.6
    background_contrast: float = 0.35
    light_direction: tuple[float, float, float] = (-0.3, -0.5, -1.0)
    ambient: float = 0.35
    diffuse: float = 0.65
    randomize: bool = False
    max_distractors: int = 4
    distractor_depth: tuple[float, float] = (0.9, 1.8)
    distractor_kinds: tuple[str, ...] = ("box", "can", "bottle")


@dataclass
class RenderConfig(Config):
    """Render timing and clipping.

    Attributes:
        render_hz: base render rate in Hz (the paper renders at 500 FPS).
        adaptive: if set, an interval between two renders is split (midpoint renders, up to
            ``max_subdivisions`` times) while some pixel's log intensity changes by more than
            ``max_log_change`` contrast thresholds. Pixels where the visible surface changes
            (object coverage flips, or depth jumps by more than ``depth_jump``) are excluded:
            such steps do not shrink with a shorter interval.
        max_log_change: see ``adaptive``; fraction of the smaller contrast threshold.
        max_subdivisions: see ``adaptive``; at most ``2**max_subdivisions`` renders per interval.
        depth_jump: see ``adaptive``; metres.
        near, far: clipping distances, metres.
    """

    render_hz: float = 500.0
    adaptive: bool = False
    max_log_change: float = 0.5
    max_subdivisions: int = 3
    depth_jump: float = 0.01
    near: float = 0.05
    far: float = 20.0


@dataclass
class TrajectoryConfig(Config):
    """Random smooth 6-DoF trajectories (see :mod:`evtrack.sim.trajectory`).

    Attributes:
        preset: ``"regular"`` or ``"faster"``; fills ``linear_speed``/``angular_speed``
            when those are not given explicitly.
        linear_speed: mean translation speed between waypoints, m/s.
        angular_speed: mean rotation speed between waypoints, rad/s.
        z_range: distance range (z of the object centre), metres.
        view_margin: fraction of the object's projected bounding radius that must stay inside
            the image around the projected centre (0: the centre stays in view; 1: the whole
            bounding sphere does).
        waypoint_step: range of distances between consecutive waypoints, metres.
        rotation_step: range of rotation between consecutive waypoints, radians.
        max_rotation: largest rotation away from the sequence's reference orientation, rad.
        reversal_probability: chance that the object comes to rest at a waypoint before moving
            on (a speed reversal); at other waypoints it passes through.
        duration_jitter: segment durations are scaled by a uniform factor in
            ``[1 - jitter, 1 + jitter]``.
        layout: how several objects share the view (:mod:`evtrack.sim.layout`):
            ``"crossing"``, each in its own depth band, all moving about the middle of the
            image, so that they pass in front of one another; ``"apart"``, each in its own
            cell of the image with its whole bounding sphere inside, so that none occludes
            another. One object ignores it.
    """

    preset: TrajectoryPreset = "regular"
    linear_speed: float | None = setting(None, gt=0, unit="m/s")
    angular_speed: float | None = setting(None, gt=0, unit="rad/s")
    z_range: tuple[float, float] = (0.4, 1.2)
    view_margin: float = 0.5
    waypoint_step: tuple[float, float] = (0.08, 0.35)
    rotation_step: tuple[float, float] = (0.3, 1.2)
    max_rotation: float = 2.0
    reversal_probability: float = 0.5
    duration_jitter: float = 0.3
    layout: Literal["crossing", "apart"] = "crossing"

    def __post_init__(self) -> None:
        super().__post_init__()
        preset = TRAJECTORY_PRESETS[self.preset]
        if self.linear_speed is None:
            self.linear_speed = preset["linear_speed"]
        if self.angular_speed is None:
            self.angular_speed = preset["angular_speed"]
        if not 0 < self.z_range[0] < self.z_range[1]:
            raise FieldError(self, "z_range", f"must be 0 < near < far, got {self.z_range}")


@dataclass
class EventConfig(Config):
    """The event-camera model (see :mod:`evtrack.sim.esim`).

    Attributes:
        threshold_on, threshold_off: nominal contrast thresholds (log-intensity steps).
        threshold_mismatch: per-pixel relative standard deviation of the thresholds.
        min_threshold: thresholds are clipped below at this value.
        refractory_us: after an event, a pixel emits nothing for this long (µs); threshold
            crossings in that time are lost (the reference still follows them).
        log_eps: the simulator works on ``log(L + log_eps)`` with ``L`` the linear luminance
            (1 = white), which tames dark pixels.
        shot_noise_hz: rate of random ON/OFF noise events per pixel (Hz); 0 disables.
        leak_noise_hz: rate of leak ON events per pixel in a static scene (Hz); 0 disables.
        leak_mismatch: per-pixel relative standard deviation of the leak rate.
        device: torch device of the simulator (``"cpu"``, ``"cuda"``).
    """

    threshold_on: float = setting(0.2, gt=0)
    threshold_off: float = setting(0.2, gt=0)
    threshold_mismatch: float = setting(0.03, ge=0)
    min_threshold: float = setting(0.01, gt=0)
    refractory_us: float = setting(100.0, ge=0, unit="µs")
    log_eps: float = setting(0.01, gt=0)
    shot_noise_hz: float = setting(0.0, ge=0, unit="Hz")
    leak_noise_hz: float = setting(0.0, ge=0, unit="Hz")
    leak_mismatch: float = setting(0.1, ge=0)
    device: str = "cpu"


@dataclass
class FrameConfig(Config):
    """The RGB-D camera: exposure (motion blur), sensor noise, depth noise.

    Attributes:
        rgb_hz: frame rate of RGB and depth (aligned streams, as a RealSense gives them).
        exposure: exposure time as a fraction of the frame period; the renders whose time is in
            ``[start, start + exposure / rgb_hz)`` are averaged into the frame.
        read_noise: standard deviation of additive Gaussian noise (linear units; 1 = white).
        shot_noise: signal-dependent noise: variance ``shot_noise**2 * I``.
        depth_noise: RealSense-like axial noise, ``sigma = depth_noise * z**2`` (m, z in m);
            0 disables.
        depth_dropout: probability that a depth pixel is missing at random.
        depth_shadow_baseline: stereo baseline in metres for occlusion shadows (pixels the
            second imager cannot see are missing); 0 disables.
        depth_range: valid depth range, metres; outside it depth is missing.
    """

    rgb_hz: float = setting(60.0, gt=0, unit="Hz")
    exposure: float = setting(1.0, gt=0, le=1)
    read_noise: float = 0.004
    shot_noise: float = 0.01
    depth_noise: float = 0.0024
    depth_dropout: float = 0.005
    depth_shadow_baseline: float = 0.055
    depth_range: tuple[float, float] = (0.2, 10.0)

    @classmethod
    def noiseless(cls, **overrides: Any) -> FrameConfig:
        """A configuration with every noise source off."""
        base = {"read_noise": 0.0, "shot_noise": 0.0, "depth_noise": 0.0, "depth_dropout": 0.0,
                "depth_shadow_baseline": 0.0}
        base.update(overrides)
        return cls(**base)


@dataclass
class GroundTruthConfig(Config):
    """Which ground truth to store.

    Attributes:
        event_flow: store the optical flow (px/s) at each event (NaN off the object).
        velocity_samples: mesh vertices used for the pixel-velocity statistics.
    """

    event_flow: bool = True
    velocity_samples: int = 256


@dataclass
class SimConfig(Config):
    """Everything one simulated sequence needs besides the object.

    Attributes:
        duration: sequence length, seconds.
        seed: master seed; trajectory, scene, thresholds and noise use independent streams
            spawned from it, so the same seed gives the same bytes (on the same device).
        torch_threads: CPU threads torch uses while simulating (restored afterwards); 0
            leaves torch's setting. One thread is the default: the per-frame tensors are small
            (0.3 M pixels) and extra threads mostly wait on a busy machine (measured 40x slower
            element-wise ops with 2 threads on 2 loaded cores).
    """

    duration: float = setting(2.0, gt=0, unit="s")
    seed: int = 0
    torch_threads: int = 1
    camera: CameraConfig = field(default_factory=CameraConfig)
    scene: SceneConfig = field(default_factory=SceneConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    events: EventConfig = field(default_factory=EventConfig)
    frames: FrameConfig = field(default_factory=FrameConfig)
    ground_truth: GroundTruthConfig = field(default_factory=GroundTruthConfig)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.render.render_hz < self.frames.rgb_hz:
            raise ConfigError(
                f"render.render_hz ({self.render.render_hz}) must be at least frames.rgb_hz "
                f"({self.frames.rgb_hz})"
            )


def load_config(path: str | Path) -> SimConfig:
    """Read a :class:`SimConfig` from a YAML file (``yaml.safe_load``; never evaluated)."""
    return SimConfig.from_yaml(path)
