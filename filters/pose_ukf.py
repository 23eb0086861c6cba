"""Quaternion pose UKFs (paper III-C): the pose driven by a measured twist, and the
constant-velocity variant with the twist in the state (as ROFT).

State of B tracks: translation ``t`` (m) and unit quaternion ``q`` (wxyz) of the
object-to-camera pose, with a covariance in the tangent ``[δt, δθ]`` (m, rad; camera-frame
left perturbation ``q = exp(δθ) ⊗ q̄``, see :mod:`ukf`). :class:`PoseTwistUKF` appends the twist
``V = [v_o, ω]`` to the state (12-D tangent).

Predict: each sigma point moves by the exact constant-twist motion (the convention
``Ṗ = v_o + ω × P``): ``t' = R_Δ t + p_Δ``, ``q' = q_Δ ⊗ q`` with ``(q_Δ, p_Δ) = exp(dt·V)``
(:func:`lie.se3_exp`), then ``P += Q·dt`` (``Q`` a noise density, so the filter does not depend
on the update rate). The paper's first-order form ``(I + [ω]× dt) t + v_o dt`` is the same to
first order in ``dt``.

Update with a pose ``(t_m, q_m)`` and its 6x6 tangent covariance ``R``: the unscented update
with measurement ``h(x) = pose`` and innovation ``ν = (t_m, q_m) ⊟ (z̄_t, z̄_q)``. A pose whose
Mahalanobis distance ``νᵀ S⁻¹ ν`` exceeds ``gate_chi2`` is rejected and counted; after
``reinit_after`` consecutive rejections the filter re-initialises on the pose (state = pose,
covariance = ``R``), as it does on the first pose of a track that has none yet.

By default (``sigma_points=False``) the pose UKF evaluates its unscented transforms in closed
form: a known twist moves every sigma point by one rigid motion, linear on the tangent
(``δt' = R_Δ δt``, ``δθ' = R_Δ δθ``), and ``h(x) = pose`` is the identity, so the sigma-point
results are exactly ``P' = A P Aᵀ + Q dt`` and ``S = P + R`` (pinned to the sigma-point path in
``tests/filters/test_pose_ukf.py``). ``sigma_points=True`` propagates the 2n+1 points; the
constant-velocity filter always does in its predict, which is nonlinear in the state.

Every step is branch-free on tensor values (``torch.where``), so it exports to ONNX
(:mod:`onnx_export`); :meth:`compile_steps` opts into ``torch.compile``. One track (B = 1) of
float64 on CPU runs the closed-form steps (``PoseUKF.predict`` and the pose update of both
filters) on a single-track backend (:mod:`backends`: numba, or NumPy; equal to the torch steps
to rounding), unless ``fast_path=False`` (or ``backend="torch"``). The shared state and
measurement updates are in :mod:`pose_filter` and :mod:`pose_measurements`, the predicts in
:mod:`pose_motion`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from evtrack.filters.backend_base import FilterBackend
from evtrack.filters.backends import as_array
from evtrack.filters.base import checked
from evtrack.filters.config import PoseTwistUKFConfig, PoseUKFConfig
from evtrack.filters.lie import pivot_map
from evtrack.filters.linalg import symmetrize
from evtrack.filters.pose_filter import PoseFilterBase
from evtrack.filters.pose_measurements import twist_update
from evtrack.filters.pose_motion import closed_form_predict

__all__ = ["PoseUKF", "PoseTwistUKF"]


class PoseUKF(PoseFilterBase):
    """Quaternion pose UKF driven by a measured twist (paper III-C), batched over B tracks.

    Args:
        batch_size: number of tracks B.
        config: :class:`PoseUKFConfig` (defaults documented there).
        dtype: float64 by default. device: where the state lives.
        fast_path: let :meth:`predict`, :meth:`predict_run`, :meth:`update` and
            :meth:`forward` of one float64 CPU track run on a single-track backend (closed form
            only; equal to the torch steps to rounding); also the attribute ``fast_path``.
        backend: the preferred backend where ``fast_path`` holds (:mod:`backends`:
            ``"auto"``, ``"numba"``, ``"numpy"`` or ``"torch"``); also the attribute
            ``backend``.

    Buffers (all in ``state_dict``): ``t`` (B,3), ``q`` (B,4), ``cov`` (B,6,6),
    ``initialized`` (B,) bool, ``rejected_run`` (B,) consecutive rejections, and cumulative
    counts ``rejected`` and ``reinitialised`` (B,). With ``config.velocity_bias`` also
    ``bias`` (B,3), the estimated bias of the twists' velocity per unit of the object's speed
    (m/s per m/s, camera frame): each predict moves the pose by the twist and the position
    further by ``b s dt``, ``s = |v_o + ω × t|`` the speed of the object's origin under the
    twist (at the prior mean ``t``), so the track does not drift at rest; ``cov`` is (B,9,9)
    over ``[δt, δθ, δb]``. The pose updates estimate ``b`` through its correlation with the
    position, the only measurement it has.

    Example:
        >>> ukf = PoseUKF(batch_size=1)
        >>> ukf.reset(t=torch.tensor([[0.0, 0.0, 1.0]]), q=torch.tensor([[1.0, 0.0, 0.0, 0.0]]))
        >>> ukf.predict(torch.tensor([[0.5, 0.0, 0.0, 0.0, 0.0, 0.0]]), 0.5)[0].tolist()
        [[0.25, 0.0, 1.0]]
    """

    _STEP_NAMES = ("predict_state", "update_pose_state", "step")

    bias: Tensor

    def __init__(
        self,
        batch_size: int = 1,
        config: PoseUKFConfig | None = None,
        dtype: torch.dtype = torch.float64,
        device: str | torch.device | None = None,
        fast_path: bool = True,
        backend: str = "auto",
    ) -> None:
        cfg = config if config is not None else PoseUKFConfig()
        qd = [cfg.q_translation] * 3 + [cfg.q_rotation] * 3
        var = [cfg.init_std_translation**2] * 3 + [cfg.init_std_rotation**2] * 3
        if cfg.velocity_bias:
            qd += [cfg.q_velocity_bias] * 3
            var += [cfg.init_std_velocity_bias**2] * 3
        super().__init__(cfg, len(qd), qd, var, batch_size, dtype, device, fast_path, backend)
        if cfg.velocity_bias:
            self._extra_name = "bias"
            self.register_buffer("bias", torch.zeros(0, 3, dtype=dtype, device=device))
        self.reset(batch_size)

    def reset(
        self,
        batch_size: int | None = None,
        t: Tensor | None = None,
        q: Tensor | None = None,
        cov: Tensor | None = None,
    ) -> None:
        """Start over with B tracks: at pose ``(t (B,3), q (B,4))`` (initialised), or without a
        pose (the first pose update initialises each track). Counters are zeroed, and a
        velocity bias (``config.velocity_bias``) is zero with its initial spread again."""
        B = self.batch_size if batch_size is None else int(batch_size)
        self._reset_pose(B, t, q, cov)
        if self._extra_name:
            self.bias = torch.zeros(B, 3, dtype=self.t.dtype, device=self.t.device)

    def predict(self, twist: Tensor, dt: float | Tensor) -> tuple[Tensor, Tensor]:
        """Move the pose by the twist (B,6) ``[v_o, ω]`` (and the velocity bias, if the
        filter has one) over ``dt`` s; returns ``(t, q)``."""
        buf = self._buffers
        bias = buf["bias"] if self._extra_name else None
        if not isinstance(twist, Tensor):
            twist = checked(twist, (self.batch_size, 6), "twist", self._kw(), copy=False)
        backend = self._single_track((twist, dt)) if twist.shape == (1, 6) else None
        if backend is not None:  # one track: the backend's predict on the state's arrays
            t, q, cov = backend.pose_predict(
                buf["t"].numpy(),
                buf["q"].numpy(),
                buf["cov"].numpy(),
                as_array(twist),
                self._single_dt(dt),
                buf["q_matrix"].numpy(),
                None if bias is None else bias.numpy(),
            )
            self._set_state_single(t, q, cov)
            return buf["t"], buf["q"]
        twist = checked(twist, (self.batch_size, 6), "twist", self._kw(), copy=False)
        self.t, self.q, self.cov = self.step_function("predict_state")(
            self.t, self.q, self.cov, twist, self._dt(dt), bias
        )
        return self.t, self.q

    def predict_run(
        self, twists: Sequence[Tensor], dts: Sequence[float]
    ) -> tuple[Tensor, Tensor, Tensor] | None:
        """``len(twists)`` predicts in a row in one compiled call: step ``k`` moves the pose
        by ``twists[k]`` (1,6) over ``dts[k]`` s, with the same arithmetic as
        :meth:`predict` (bit for bit). For a replay of many steps (a late measurement's,
        :class:`~evtrack.tracking.pose_timeline.PoseTimeline`), where one call per step costs more
        than the step.

        Returns:
            the states after each step, ``t`` (n,1,3), ``q`` (n,1,4), ``cov`` (n,1,6,6)
            ((n,1,9,9) with a velocity bias, which a predict leaves as it is), the last of
            which is now the filter's; or ``None``, with the filter unchanged, when
            :meth:`predict` would not run on a single-track backend with runs (a batch, CUDA,
            float32, gradients, sigma points, no numba...): then call :meth:`predict` per step.
        """
        if len(twists) != len(dts):
            raise ValueError(f"predict_run: {len(twists)} twists but {len(dts)} time steps")
        if not (twists and all(isinstance(w, Tensor) and w.shape == (1, 6) and w.is_cpu
                               for w in twists)):
            return None
        backend = self._single_track((*twists, *(float(dt) for dt in dts)))
        if backend is None or not backend.runs:
            return None
        buf = self._buffers
        t, q, cov = backend.pose_predict_run(
            buf["t"].numpy(),
            buf["q"].numpy(),
            buf["cov"].numpy(),
            np.concatenate([as_array(w) for w in twists]),
            np.array([self._single_dt(dt) for dt in dts], dtype=np.float64),
            buf["q_matrix"].numpy(),
            buf["bias"].numpy() if self._extra_name else None,
        )
        buf.update(t=torch.from_numpy(t[-1].copy()), q=torch.from_numpy(q[-1].copy()),
                   cov=torch.from_numpy(cov[-1].copy()))
        return torch.from_numpy(t), torch.from_numpy(q), torch.from_numpy(cov)

    def predict_state(
        self, t: Tensor, q: Tensor, cov: Tensor, twist: Tensor, dt: Tensor,
        bias: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Pure predict: (B,3), (B,4), (B,n,n), twist (B,6), dt (B,) -> (t, q, cov); ``bias``
        (B,3) m/s per m/s of speed: the velocity bias of a filter with one (n = 9), else
        ``None`` (n = 6)."""
        if self.config.sigma_points:
            extra = t[:, :0] if bias is None else bias
            t, q, _, cov = self._propagate(t, q, extra, cov, twist, dt)
            return t, q, cov
        return closed_form_predict(t, q, cov, twist, dt, self.q_matrix, bias)

    def forward(
        self,
        twist: Tensor,
        dt: float | Tensor,
        t_meas: Tensor,
        q_meas: Tensor,
        cov_meas: Tensor | None = None,
        valid: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Predict with ``twist`` over ``dt`` then fuse the pose (see :meth:`update`);
        returns the posterior ``(t, q)``."""
        self.predict(twist, dt)
        self.update(t_meas, q_meas, cov_meas, valid)
        return self.t, self.q

    def step(
        self,
        t: Tensor,
        q: Tensor,
        cov: Tensor,
        initialized: Tensor,
        rejected_run: Tensor,
        twist: Tensor,
        dt: Tensor,
        t_meas: Tensor,
        q_meas: Tensor,
        cov_meas: Tensor,
        valid: Tensor,
        bias: Tensor | None = None,
    ) -> tuple[Tensor, ...]:
        """Pure predict + gated update (the step exported to ONNX); ``bias`` (B,3): the
        velocity bias of a filter with one (``cov`` (B,9,9)).

        Returns:
            ``(t, q, cov, initialized, rejected_run, used, rejected, reinitialised)``, and the
            new ``bias`` after them where one was given.
        """
        t, q, cov = self.predict_state(t, q, cov, twist, dt, bias)
        extra = t[:, :0] if bias is None else bias
        t, q, extra, cov, initialized, run, used, rej, reinit = self.update_pose_state(
            t, q, extra, cov, initialized, rejected_run, t_meas, q_meas, cov_meas, valid
        )
        out = (t, q, cov, initialized, run, used, rej, reinit)
        return out if bias is None else (*out, extra)


class PoseTwistUKF(PoseFilterBase):
    """Constant-velocity pose UKF with the twist in the state (as ROFT), batched.

    State ``[t, q, V]`` with a 12-D tangent covariance ``[δt, δθ, δv_o, δω]``; predict moves
    every sigma point by its own twist (then decays it by ``alpha ** (dt / alpha_dt)``; the
    default ``alpha = 1`` is the constant-velocity model); :meth:`update` fuses poses (gated as
    :class:`PoseUKF`), :meth:`update_twist` fuses twist measurements (e.g. the output of
    :class:`VelocityKF`, ungated). Arguments as :class:`PoseUKF`; ``fast_path`` concerns the
    closed-form pose update only (the predict always propagates sigma points in torch).

    The twist ``V = [v_o, ω]`` is the camera-frame twist of :func:`evtrack.geometry.integrate_twist`
    (``Ṗ = v_o + ω × P``: ``v_o`` is the velocity of the point at the camera's origin). With
    ``config.object_centred`` (default) its initial spread and its random walk are independent
    for the object's own motion, the velocity ``v`` of the object's origin and ``ω``, and enter
    the state through ``v_o = v + t × ω``, i.e. ``Σ_V = A Σ A^T`` with ``A(t) = [[I, [t]×],
    [0, I]]`` at the current position ``t``. Independent spreads of ``v_o`` and ``ω`` (the
    alternative) make an unknown rotation swing the object about the camera: the sigma points
    fan out on a circle of radius ``|t|`` and the predicted mean is pulled towards the camera
    (with the default spreads, 0.2 s of predicts from a fresh pose at 0.49 m moved it to 0.22 m).

    Buffers: those of :class:`PoseUKF` plus ``twist`` (B,6); ``cov`` is (B,12,12).
    """

    _STEP_NAMES = ("predict_state", "update_pose_state", "update_twist_state", "step")
    _extra_name = "twist"

    twist: Tensor
    decay_rate: Tensor
    twist_meas_cov: Tensor

    def __init__(
        self,
        batch_size: int = 1,
        config: PoseTwistUKFConfig | None = None,
        dtype: torch.dtype = torch.float64,
        device: str | torch.device | None = None,
        fast_path: bool = True,
        backend: str = "auto",
    ) -> None:
        cfg = config if config is not None else PoseTwistUKFConfig()
        qd = (
            [cfg.q_translation] * 3
            + [cfg.q_rotation] * 3
            + [cfg.q_linear] * 3
            + [cfg.q_angular] * 3
        )
        var = (
            [cfg.init_std_translation**2] * 3
            + [cfg.init_std_rotation**2] * 3
            + [cfg.init_std_linear**2] * 3
            + [cfg.init_std_angular**2] * 3
        )
        super().__init__(cfg, 12, qd, var, batch_size, dtype, device, fast_path, backend)
        tw = [cfg.meas_std_linear**2] * 3 + [cfg.meas_std_angular**2] * 3
        self.register_buffer(
            "decay_rate",
            torch.tensor(math.log(cfg.alpha) / cfg.alpha_dt, dtype=dtype, device=device),
        )
        self.register_buffer(
            "twist_meas_cov", torch.diag(torch.tensor(tw, dtype=dtype, device=device))
        )
        self.register_buffer("twist", torch.zeros(0, 6, dtype=dtype, device=device))
        self.reset(batch_size)

    def reset(
        self,
        batch_size: int | None = None,
        t: Tensor | None = None,
        q: Tensor | None = None,
        twist: Tensor | None = None,
        cov: Tensor | None = None,
    ) -> None:
        """Start over (see :meth:`PoseUKF.reset`); ``twist`` (B,6) defaults to zero."""
        B = self.batch_size if batch_size is None else int(batch_size)
        self._reset_pose(B, t, q, cov)
        kw = {"dtype": self.t.dtype, "device": self.t.device}
        self.twist = (
            torch.zeros(B, 6, **kw) if twist is None else checked(twist, (B, 6), "twist", kw)
        )
        if cov is None and t is not None and self.config.object_centred:
            self.cov = self._with_object_twist_cov(self.cov, self.t)

    def _twist_block(self, diag: Tensor, t: Tensor) -> Tensor:
        """(B,6,6) covariance in ``[v_o, ω]`` of independent object-frame spreads ``diag`` (6,)."""
        A = pivot_map(t)
        D = torch.eye(6, dtype=diag.dtype, device=diag.device) * diag  # diag_embed: no ONNX op
        return symmetrize(A @ D.expand_as(A) @ A.transpose(-1, -2))

    def _with_object_twist_cov(self, cov: Tensor, t: Tensor) -> Tensor:
        """``cov`` with its twist block set to the initial spread at ``t``, no cross terms."""
        top = torch.cat([cov[:, :6, :6], torch.zeros_like(cov[:, :6, 6:])], dim=-1)
        bottom = torch.cat(
            [torch.zeros_like(cov[:, 6:, :6]), self._twist_block(self.init_var[6:], t)], dim=-1
        )
        return torch.cat([top, bottom], dim=-2)

    def predict(self, dt: float | Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Constant-velocity predict over ``dt`` s; returns ``(t, q, twist)``."""
        self.t, self.q, self.twist, self.cov = self.step_function("predict_state")(
            self.t, self.q, self.twist, self.cov, self._dt(dt)
        )
        return self.t, self.q, self.twist

    def predict_state(
        self, t: Tensor, q: Tensor, twist: Tensor, cov: Tensor, dt: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Pure unscented predict: (B,3), (B,4), (B,6), (B,12,12), dt (B,) -> (t, q, twist, cov)."""
        if not self.config.object_centred:
            return self._propagate(t, q, twist, cov, None, dt, decay_rate=self.decay_rate)
        B = t.shape[0]
        pose_q = self.q_matrix[:6, :6].expand(B, 6, 6)
        top = torch.cat([pose_q, torch.zeros_like(pose_q)], dim=-1)
        bottom = torch.cat([torch.zeros_like(pose_q), self._twist_block(self.q_density[6:], t)],
                           dim=-1)
        return self._propagate(t, q, twist, cov, None, dt, torch.cat([top, bottom], dim=-2),
                               self.decay_rate)

    def update_pose_state(self, t: Tensor, q: Tensor, extra: Tensor, cov: Tensor,
                          initialized: Tensor, *args: Tensor,
                          reinit_after: int | None = None) -> tuple[Tensor, ...]:
        """As :meth:`PoseUKF.update_pose_state`; a track that starts on this pose gets its
        twist spread at the pose's position (``config.object_centred``)."""
        out = super().update_pose_state(t, q, extra, cov, initialized, *args,
                                        reinit_after=reinit_after)
        if not self.config.object_centred:
            return out
        started = (~initialized & out[4])[:, None, None]
        cov_new = torch.where(started, self._with_object_twist_cov(out[3], out[0]), out[3])
        return (*out[:3], cov_new, *out[4:])

    def _update_single(self, backend: FilterBackend, t_meas: Tensor, q_meas: Tensor,
                       R: Tensor, valid: Tensor, reinit_after: int | None = None) -> Tensor:
        was_initialized = bool(self._buffers["initialized"].tolist()[0])
        used = super()._update_single(backend, t_meas, q_meas, R, valid, reinit_after)
        if self.config.object_centred and not was_initialized and bool(used.tolist()[0]):
            buf = self._buffers
            buf["cov"] = self._with_object_twist_cov(buf["cov"], buf["t"])
        return used

    def update_twist(
        self, twist_meas: Tensor, cov_meas: Tensor | None = None, valid: Tensor | None = None
    ) -> None:
        """Fuse a twist measurement (B,6) with covariance (B,6,6) or (6,6) (default from the
        config); ``valid`` (B,) bool marks the tracks that have one (non-finite ones are
        skipped)."""
        B, kw = self.batch_size, self._kw()
        z = checked(twist_meas, (B, 6), "twist_meas", kw, copy=False)
        R = self._checked_cov(cov_meas, self.twist_meas_cov, B, kw)
        valid = self._checked_valid(valid, B, kw["device"])
        self.t, self.q, self.twist, self.cov = self.step_function("update_twist_state")(
            self.t, self.q, self.twist, self.cov, z, R, valid
        )

    def update_twist_state(
        self,
        t: Tensor,
        q: Tensor,
        twist: Tensor,
        cov: Tensor,
        twist_meas: Tensor,
        cov_meas: Tensor,
        valid: Tensor,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Pure update with ``h(x) = V``
        (:func:`~evtrack.filters.pose_measurements.twist_update`): (B,3), (B,4), (B,6),
        (B,12,12), twist_meas (B,6), cov_meas (B,6,6), valid (B,) -> (t, q, twist, cov)."""
        return twist_update((t, q, twist, cov), twist_meas, cov_meas, valid, self.twist_meas_cov)

    def forward(
        self,
        dt: float | Tensor,
        t_meas: Tensor,
        q_meas: Tensor,
        cov_meas: Tensor | None = None,
        valid: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Predict over ``dt`` then fuse the pose; returns ``(t, q, twist)``."""
        self.predict(dt)
        self.update(t_meas, q_meas, cov_meas, valid)
        return self.t, self.q, self.twist

    def step(
        self,
        t: Tensor,
        q: Tensor,
        twist: Tensor,
        cov: Tensor,
        initialized: Tensor,
        rejected_run: Tensor,
        dt: Tensor,
        t_meas: Tensor,
        q_meas: Tensor,
        cov_meas: Tensor,
        valid: Tensor,
    ) -> tuple[Tensor, ...]:
        """Pure predict + gated pose update (exported to ONNX).

        Returns:
            ``(t, q, twist, cov, initialized, rejected_run, used, rejected, reinitialised)``.
        """
        t, q, twist, cov = self.predict_state(t, q, twist, cov, dt)
        return self.update_pose_state(
            t, q, twist, cov, initialized, rejected_run, t_meas, q_meas, cov_meas, valid
        )
