"""Filter configurations: dataclasses with documented defaults, loadable from YAML.

``configs/filters.yaml`` holds the defaults below in three sections (``velocity_kf``,
``pose_ukf``, ``pose_twist_ukf``); :func:`load_filters_config` reads such a file. Units are SI
(metres, seconds, radians) and pixels; process noises are spectral densities, so the noise added
by a predict over ``dt`` is ``Q·dt`` whatever the update rate.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import yaml

from evtrack import configs
from evtrack.errors import ConfigError

__all__ = [
    "VelocityKFConfig",
    "PoseUKFConfig",
    "PoseTwistUKFConfig",
    "load_filters_config",
]

WEIGHTING_REFERENCES = ("previous", "predicted")

# The 0.999 quantile of the χ² distribution with 6 degrees of freedom.
CHI2_6DOF_999 = 22.457744484825326
# The 0.999 quantile of the χ² distribution with 1 degree of freedom.
CHI2_1DOF_999 = 10.827566170662733


@dataclass
class VelocityKFConfig:
    """The 6-DoF velocity Kalman filter (paper III-B).

    Attributes:
        alpha: fraction of the velocity kept over one reference step ``alpha_dt`` (paper: 0.5).
            Over any ``dt`` the velocity is multiplied by ``alpha ** (dt / alpha_dt)``.
        alpha_dt: seconds, the reference step of ``alpha`` (the paper's ~1 ms update period).
        q_linear: (m/s)²/s, process-noise density on ``v_o``.
        q_angular: (rad/s)²/s, process-noise density on ``ω``. The decay pulls the prediction
            towards zero; these must be large enough that the flows, not the shrunk prediction,
            set the estimate (the shrinkage of the posterior is about
            ``(1 − a) / (1 + I·Q·dt)`` for flow information ``I``).
        flow_std: px/s, standard deviation ``σ_F`` of one flow component (``R_F = σ_F²``).
        normal_flow_std: px/s, the standard deviation of the one row of a RoI flagged
            normal-only (under ``normal_flow``), or ``None``: ``flow_std`` (the paper: one
            noise for every row). The tracker's normal-only flows are much more precise than
            its full flows (residual RMS ~19 px/s along their direction against ~140 for full
            flows on the paper-matched mustard bottle `faster`, 2026-11-28), so a smaller value
            weighs them by what they know. With 15-25 px/s the tracker's rotation error fell
            by 3-9 % on all four benchmark columns (oracle poses) while its position error rose
            by up to 9 % on three of them; with the shipped pose networks only the
            paper-matched `faster` column gained: off by default.
        init_std_linear: m/s, initial standard deviation of ``v_o`` (initial mean zero).
        init_std_angular: rad/s, initial standard deviation of ``ω``.
        normal_flow: apply the normal-flow constraint (paper III-B.4) to RoIs flagged normal-only;
            off, every flow is used as a full 2-D flow (the paper's ablation).
        assume_normal: flag used for every RoI when an update gets no per-RoI flag (the paper
            treats every RoI flow as a normal flow).
        weighting: Laplacian weighting of residuals (paper III-B.5); off, every row weighs 1.
        laplace_scale: px/s, the Laplacian scale ``b``; ``None`` estimates it per update as the
            mean absolute deviation of the residuals around their median (its maximum-likelihood
            value).
        laplace_scale_min: px/s, lower bound on an estimated ``b`` (keeps ``b > 0`` when all
            residuals agree).
        weight_floor: the floor on the Laplacian density ``L_k`` (paper: 1e-6), in 1/(px/s).
        weighting_reference: the twist the first pass's residuals are taken against:
            ``"previous"``, the last posterior (before the decay of the predict), or
            ``"predicted"``, the decayed prediction (the paper's literal reading). With
            ``alpha = 0.5`` per ms the prediction is half the current motion, so its residuals
            measure the decay as much as the outliers (``tests/filters`` shows the difference).
        weighting_iterations: passes of the weighting within one update; each pass after the
            first re-weights against the previous pass's posterior and re-estimates ``b`` with
            the previous weights (iteratively reweighted least squares).
        object_centred: the tracker sets the object's position as the filter's pivot each step
            (:meth:`~evtrack.filters.VelocityKF.set_pivot`): ``q_linear`` then spreads the
            velocity of the object's centre, independent of ``ω``. Off: the paper's noise,
            independent in ``v_o`` and ``ω``. On by default: oracle poses, the four YCB
            ``faster`` sequences rendered at 4 kHz, the full method's rotation RMSE 28.5° ->
            23.4° (cracker box 13.0 -> 10.3, tomato can 32.5 -> 23.1, mustard 38.3 -> 28.8,
            potted meat 30.1 -> 31.6) for a position RMSE of 6.38 -> 6.63 cm.
    """

    alpha: float = 0.5
    alpha_dt: float = 1e-3
    q_linear: float = 1000.0
    q_angular: float = 10000.0
    flow_std: float = 50.0
    normal_flow_std: float | None = None
    init_std_linear: float = 1.0
    init_std_angular: float = 3.0
    normal_flow: bool = True
    assume_normal: bool = True
    weighting: bool = True
    laplace_scale: float | None = None
    laplace_scale_min: float = 1.0
    weight_floor: float = 1e-6
    weighting_reference: str = "previous"
    weighting_iterations: int = 2
    object_centred: bool = True

    def __post_init__(self) -> None:
        if self.weighting_reference not in WEIGHTING_REFERENCES:
            raise ConfigError(
                f"field 'weighting_reference' must be one of {WEIGHTING_REFERENCES}, "
                f"got {self.weighting_reference!r}"
            )
        _check_range(self, "alpha", 0.0, 1.0, low_open=True)
        for name in (
            "alpha_dt",
            "flow_std",
            "init_std_linear",
            "init_std_angular",
            "laplace_scale_min",
            "weight_floor",
        ):
            _check_positive(self, name)
        for name in ("q_linear", "q_angular"):
            _check_positive(self, name, allow_zero=True)
        if self.laplace_scale is not None:
            _check_positive(self, "laplace_scale")
        if self.normal_flow_std is not None:
            _check_positive(self, "normal_flow_std")
        if (
            int(self.weighting_iterations) != self.weighting_iterations
            or self.weighting_iterations < 1
        ):
            raise ConfigError(
                f"weighting_iterations must be an integer >= 1, got {self.weighting_iterations}"
            )


@dataclass
class PoseUKFConfig:
    """The quaternion pose UKF driven by a twist (paper III-C).

    Attributes:
        q_translation: m²/s, process-noise density on the translation.
        q_rotation: rad²/s, process-noise density on the rotation (tangent, camera frame).
        meas_std_translation: m, default pose-measurement noise when an update gets no
            covariance.
        meas_std_rotation: rad, default pose-measurement rotation noise.
        init_std_translation: m, standard deviation after :meth:`reset` with a pose.
        init_std_rotation: rad, likewise for the rotation.
        gate_chi2: Mahalanobis gate: a pose with ``νᵀ S⁻¹ ν`` above it is rejected (default: the
            0.999 quantile of χ² with 6 degrees of freedom); ``inf`` disables gating.
        reinit_after: after this many consecutive rejected poses the filter re-initialises on
            the next rejected one (it takes the pose and its covariance as the state).
        range_gate_chi2: gate of :meth:`~evtrack.filters.PoseUKF.update_range` (a position
            component along a direction, e.g. the object's range on a depth frame): rejected
            above ``ν² / S`` (default: the 0.999 quantile of χ² with 1 degree of freedom).
            Rejected ranges never re-initialise the filter.
        sigma_alpha, sigma_beta, sigma_kappa: van der Merwe's scaled sigma-point parameters. The
            defaults (1, 2, 0) put the 2n outer points at ``±√n σ`` with a zero-weight centre.
        mean_iterations: Gauss–Newton iterations of the weighted Karcher mean of the sigma
            quaternions, started at the centre point. It converges linearly, faster the smaller
            the spread; after a short predict the points are nearly symmetric about the centre,
            which is then almost the mean already.
        sigma_points: propagate 2n+1 sigma points through every predict and pose update.
            ``False`` uses the closed form of the same unscented transform: the pose measurement
            is the state itself and a known twist moves every sigma point by one rigid motion,
            which maps tangent offsets linearly (``δt' = R_Δ δt``, ``δθ' = R_Δ δθ``), so the
            transform is exact and equals ``P' = A P Aᵀ``, ``S = P + R`` to rounding (while
            the rotation spread ``γσ_θ`` stays below π; tests pin both paths together). The
            constant-velocity filter always propagates sigma points in its predict, which is
            nonlinear in the state.
        velocity_bias: estimate a bias of the driving twist's velocity that grows with the
            object's speed: a camera-frame vector ``b`` (m/s per m/s) in the state, the
            position moving by ``ṫ = v_o + ω × t + b |v_o + ω × t|`` (the speed of the
            object's origin under the twist, so nothing moves at rest), a random walk learnt
            from the pose updates (their innovations are its only measurement), as an inertial
            navigation filter learns its sensors' errors from GPS. Off by default (the paper's
            filter); :class:`~evtrack.filters.PoseUKF` only.
        q_velocity_bias: 1/s, random-walk density of ``b`` (its variance grows by this per
            second).
        init_std_velocity_bias: standard deviation of ``b`` (zero) after :meth:`reset`,
            dimensionless (m/s per m/s).
    """

    q_translation: float = 1e-3
    q_rotation: float = 1e-2
    meas_std_translation: float = 0.01
    meas_std_rotation: float = 0.05
    init_std_translation: float = 0.05
    init_std_rotation: float = 0.2
    gate_chi2: float = CHI2_6DOF_999
    reinit_after: int = 5
    range_gate_chi2: float = CHI2_1DOF_999
    sigma_alpha: float = 1.0
    sigma_beta: float = 2.0
    sigma_kappa: float = 0.0
    mean_iterations: int = 2
    sigma_points: bool = False
    velocity_bias: bool = False
    q_velocity_bias: float = 0.01
    init_std_velocity_bias: float = 0.05

    def __post_init__(self) -> None:
        _check_ukf_common(self)
        _check_positive(self, "q_velocity_bias", allow_zero=True)
        _check_positive(self, "init_std_velocity_bias")


@dataclass
class PoseTwistUKFConfig(PoseUKFConfig):
    """The constant-velocity variant with the twist in the state (as ROFT).

    Attributes (in addition to :class:`PoseUKFConfig`):
        q_linear: (m/s)²/s, random-walk density on ``v_o``.
        q_angular: (rad/s)²/s, random-walk density on ``ω``.
        init_std_linear: m/s, initial standard deviation of ``v_o``.
        init_std_angular: rad/s, initial standard deviation of ``ω``.
        meas_std_linear: m/s, default noise of a twist measurement.
        meas_std_angular: rad/s, likewise for ``ω``.
        alpha, alpha_dt: the twist is multiplied by ``alpha ** (dt / alpha_dt)`` in each
            predict; 1 (default) is the constant-velocity model, < 1 the decaying model of
            :class:`VelocityKFConfig`.
        object_centred: ``q_linear``/``init_std_linear`` are spreads of the velocity of the
            object's origin, independent of ``ω`` (default; the object turns about itself), and
            are mapped into the camera-frame ``v_o`` at the current position (see
            :class:`~evtrack.filters.PoseTwistUKF`); False: spreads of ``v_o`` itself.
    """

    q_linear: float = 10.0
    q_angular: float = 100.0
    init_std_linear: float = 1.0
    init_std_angular: float = 3.0
    meas_std_linear: float = 0.05
    meas_std_angular: float = 0.2
    alpha: float = 1.0
    alpha_dt: float = 1e-3
    object_centred: bool = True

    def __post_init__(self) -> None:
        _check_ukf_common(self)
        if self.velocity_bias:
            raise ConfigError("PoseTwistUKFConfig.velocity_bias: the constant-velocity filter "
                              "has no driving twist to correct; set it on the PoseUKF's config")
        _check_range(self, "alpha", 0.0, 1.0, low_open=True)
        _check_positive(self, "alpha_dt")
        for name in ("init_std_linear", "init_std_angular", "meas_std_linear", "meas_std_angular"):
            _check_positive(self, name)
        for name in ("q_linear", "q_angular"):
            _check_positive(self, name, allow_zero=True)


def load_filters_config(
    path: str | Path,
) -> tuple[VelocityKFConfig, PoseUKFConfig, PoseTwistUKFConfig]:
    """Read ``velocity_kf``, ``pose_ukf`` and ``pose_twist_ukf`` sections from a YAML file.

    Absent sections and fields keep their defaults. Raises :class:`ConfigError` naming the
    file and field on a malformed file.
    """
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read filter config: {exc}") from exc
    data = {} if data is None else data
    if not isinstance(data, Mapping):
        raise ConfigError(f"{path}: expected a mapping with filter sections")
    sections = {
        "velocity_kf": VelocityKFConfig,
        "pose_ukf": PoseUKFConfig,
        "pose_twist_ukf": PoseTwistUKFConfig,
    }
    unknown = sorted(set(data) - set(sections))
    if unknown:
        raise ConfigError(f"{path}: unknown section(s) {unknown}; expected {sorted(sections)}")
    out = [configs.from_dict(cls, data.get(key), f"{path}: {key}")
           for key, cls in sections.items()]
    return out[0], out[1], out[2]  # type: ignore[return-value]


def _check_positive(cfg: object, name: str, allow_zero: bool = False) -> None:
    v = getattr(cfg, name)
    ok = math.isfinite(v) and (v >= 0 if allow_zero else v > 0)
    if not ok:
        need = "finite and >= 0" if allow_zero else "finite and > 0"
        raise ConfigError(f"field {name!r} must be {need}, got {v}")


def _check_range(cfg: object, name: str, low: float, high: float, low_open: bool = False) -> None:
    v = getattr(cfg, name)
    if not (math.isfinite(v) and (v > low if low_open else v >= low) and v <= high):
        raise ConfigError(
            f"field {name!r} must be in {'(' if low_open else '['}{low}, {high}], got {v}"
        )


def _check_ukf_common(cfg: PoseUKFConfig) -> None:
    for name in (
        "meas_std_translation",
        "meas_std_rotation",
        "init_std_translation",
        "init_std_rotation",
        "sigma_alpha",
    ):
        _check_positive(cfg, name)
    for name in ("q_translation", "q_rotation", "sigma_beta"):
        _check_positive(cfg, name, allow_zero=True)
    for name in ("gate_chi2", "range_gate_chi2"):
        if not getattr(cfg, name) > 0:
            raise ConfigError(
                f"field {name!r} must be > 0 (inf disables gating), got {getattr(cfg, name)}"
            )
    for name in ("reinit_after", "mean_iterations"):
        v = getattr(cfg, name)
        if int(v) != v or v < 1:
            raise ConfigError(f"field {name!r} must be an integer >= 1, got {v}")
    if not math.isfinite(cfg.sigma_kappa) or 6 + cfg.sigma_kappa <= 0:
        raise ConfigError(
            f"field 'sigma_kappa' must be finite with n + kappa > 0, got {cfg.sigma_kappa}"
        )
