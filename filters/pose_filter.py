"""The base of the pose UKFs: their shared state, reset, measurement updates and gating.

State of B tracks: translation ``t`` (m) and unit quaternion ``q`` (wxyz) of the
object-to-camera pose, further state ``extra`` (B,k) (a velocity bias, or the twist of the
constant-velocity filter) and a covariance (B,n,n), n = 6 + k, in the tangent
``[δt, δθ, δextra]`` (m, rad; camera-frame left perturbation ``q = exp(δθ) ⊗ q̄``, see
:mod:`ukf`). The measurement models are in :mod:`pose_measurements`, the predicts in
:mod:`pose_motion`; the filters are :class:`~evtrack.filters.PoseUKF` and
:class:`~evtrack.filters.PoseTwistUKF`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from evtrack.errors import ConfigError
from evtrack.filters.backend_base import FilterBackend
from evtrack.filters.base import TrackFilter, checked
from evtrack.filters.config import PoseUKFConfig
from evtrack.filters.pose_measurements import (
    PoseState,
    aligned_update,
    gated_pose_update,
    range_update,
)
from evtrack.filters.pose_motion import propagate_sigma_points
from evtrack.filters.ukf import UnscentedParams, merwe_weights

__all__ = ["PoseFilterBase"]

_NO_EXTRA = np.zeros(0)  # the further state of a filter without one, on a single-track backend


class PoseFilterBase(TrackFilter):
    """Shared state, reset, pose update and gating of the pose UKFs (tangent size ``n``)."""

    _STATE = ("t", "q", "cov")

    t: Tensor
    q: Tensor
    cov: Tensor
    initialized: Tensor
    rejected_run: Tensor
    rejected: Tensor
    reinitialised: Tensor
    w_mean: Tensor
    w_cov: Tensor
    q_density: Tensor
    q_matrix: Tensor
    meas_cov: Tensor
    init_var: Tensor
    gamma: Tensor
    gate: Tensor
    _extra_name: str | None = None  # the buffer of the state beyond the pose, if any

    def __init__(
        self,
        config: PoseUKFConfig,
        n: int,
        q_density: list[float],
        init_var: list[float],
        batch_size: int,
        dtype: torch.dtype,
        device: str | torch.device | None,
        fast_path: bool = True,
        backend: str = "auto",
    ) -> None:
        super().__init__()
        self.config = config
        self.n = n
        self._init_backend(backend, fast_path)
        kw: dict[str, Any] = {"dtype": dtype, "device": device}
        w = merwe_weights(n, config.sigma_alpha, config.sigma_beta, config.sigma_kappa)
        # Scalars as tensors: exported graphs would keep Python floats as float32 constants.
        self.register_buffer("gamma", torch.tensor(w.gamma, **kw))
        self.register_buffer("gate", torch.tensor(config.gate_chi2, **kw))
        self.register_buffer("w_mean", torch.tensor(w.mean, **kw))
        self.register_buffer("w_cov", torch.tensor(w.cov, **kw))
        self.register_buffer("q_density", torch.tensor(q_density, **kw))
        self.register_buffer("q_matrix", torch.diag(self.q_density))
        meas = [config.meas_std_translation**2] * 3 + [config.meas_std_rotation**2] * 3
        self.register_buffer("meas_cov", torch.diag(torch.tensor(meas, **kw)))
        self.register_buffer("init_var", torch.tensor(init_var, **kw))
        for name, shape, dt in (
            ("t", (0, 3), dtype),
            ("q", (0, 4), dtype),
            ("cov", (0, n, n), dtype),
            ("initialized", (0,), torch.bool),
            ("rejected_run", (0,), torch.int64),
            ("rejected", (0,), torch.int64),
            ("reinitialised", (0,), torch.int64),
        ):
            self.register_buffer(name, torch.zeros(shape, dtype=dt, device=device))

    # ------------------------------------------------------------------ state
    def _reset_pose(self, B: int, t: Tensor | None, q: Tensor | None, cov: Tensor | None) -> None:
        kw = {"dtype": self.init_var.dtype, "device": self.init_var.device}
        if (t is None) != (q is None):
            raise ValueError("reset: give both t and q, or neither")
        if t is None:
            self.t = torch.zeros(B, 3, **kw)
            self.q = torch.zeros(B, 4, **kw)
            self.q[:, 0] = 1
            self.initialized = torch.zeros(B, dtype=torch.bool, device=kw["device"])
        else:
            assert q is not None
            t = checked(t, (B, 3), "t", kw)
            q = checked(q, (B, 4), "q", kw)
            norm = q.norm(dim=-1, keepdim=True)
            if not bool((torch.isfinite(t).all() & torch.isfinite(norm) & (norm > 0)).all()):
                raise ValueError("reset: t and q must be finite and each q a non-zero "
                                 "quaternion (w, x, y, z)")
            self.t, self.q = t, q / norm
            self.initialized = torch.ones(B, dtype=torch.bool, device=kw["device"])
        n = self.n
        self.cov = (
            torch.diag_embed(self.init_var).expand(B, n, n).clone()
            if cov is None
            else checked(cov, (B, n, n), "cov", kw)
        )
        for name in ("rejected_run", "rejected", "reinitialised"):
            setattr(self, name, torch.zeros(B, dtype=torch.int64, device=kw["device"]))

    def _state(self) -> PoseState:
        """``(t, q, extra, cov)`` (``extra`` (B,0) for a filter without further state)."""
        extra = self._buffers[self._extra_name] if self._extra_name else self.t[:, :0]
        return self.t, self.q, extra, self.cov

    def _set_state(self, t: Tensor, q: Tensor, extra: Tensor, cov: Tensor) -> None:
        self.t, self.q, self.cov = t, q, cov
        if self._extra_name:
            setattr(self, self._extra_name, extra)

    def _single_track_allowed(self) -> bool:
        return not self.config.sigma_points

    def _sigma(self) -> UnscentedParams:
        """The sigma-point parameters (buffers of the filter's dtype)."""
        return UnscentedParams(self.gamma, self.w_mean, self.w_cov, self.config.mean_iterations)

    # ------------------------------------------------------------------ pose update
    def update(
        self,
        t_meas: Tensor,
        q_meas: Tensor,
        cov_meas: Tensor | None = None,
        valid: Tensor | None = None,
        reinit_after: int | None = None,
    ) -> Tensor:
        """Fuse a pose measurement; returns (B,) bool, True where the pose was used.

        Args:
            t_meas: (B,3) metres. q_meas: (B,4) wxyz (normalised here; either sign).
            cov_meas: (B,6,6) or (6,6) tangent covariance ``[δt, δθ]`` (m², rad²); default
                from the config.
            valid: (B,) bool, False for tracks without a pose this time (default all True).
                Non-finite poses or covariances, and all-zero quaternions, count as missing.
            reinit_after: ``config.reinit_after`` for this update only (``1``: a rejected
                pose re-initialises the filter); ``None`` keeps the config's.
        """
        if reinit_after is not None and reinit_after < 1:
            raise ConfigError(f"reinit_after must be >= 1, got {reinit_after}")
        t_meas, q_meas, R, valid = self._update_inputs(t_meas, q_meas, cov_meas, valid)
        backend = self._single_track((t_meas, q_meas, R, valid))
        if backend is not None:
            try:
                return self._update_single(backend, t_meas, q_meas, R, valid, reinit_after)
            except np.linalg.LinAlgError:  # S not positive definite: torch gives its NaNs
                pass
        t, q, extra, P = self._state()
        t, q, extra, P, self.initialized, self.rejected_run, used, rejected, reinit = (
            self.step_function("update_pose_state")(
                t, q, extra, P, self.initialized, self.rejected_run, t_meas, q_meas, R, valid,
                reinit_after=reinit_after,
            )
        )
        self._set_state(t, q, extra, P)
        self.rejected = self.rejected + rejected
        self.reinitialised = self.reinitialised + reinit
        return used

    def update_range(
        self,
        direction: Tensor,
        distance: Tensor,
        variance: Tensor | float,
        valid: Tensor | None = None,
    ) -> Tensor:
        """Fuse a measurement of the position's component along a direction: ``z = uᵀ t``
        (metres) with noise variance ``r``, e.g. the object's range along its viewing ray from
        a depth frame. Returns (B,) bool, True where it was used.

        The measurement is linear in the state (``H = [uᵀ, 0]``), so the Kalman update is
        exact: ``S = H P Hᵀ + r``, ``K = P Hᵀ / S``, state ``⊞ K ν`` with ``ν = z − uᵀ t``
        (the rotation and a twist in the state move through their covariance with ``t``),
        covariance in Joseph form ``(I − K H) P (I − K H)ᵀ + r K Kᵀ``. Only initialised
        tracks are updated; a range with ``ν² / S`` above ``config.range_gate_chi2`` is
        rejected (not counted in ``rejected``, which counts poses, and never a reason to
        re-initialise).

        Args:
            direction: (B,3) direction ``u`` (normalised here), camera frame.
            distance: (B,) measured ``uᵀ t``, metres.
            variance: (B,) or a float: ``r``, m².
            valid: (B,) bool, False for tracks without a measurement (default all True).
                Non-finite inputs or a non-positive variance count as missing.
        """
        B, kw = self.batch_size, self._kw()
        u = checked(direction, (B, 3), "direction", kw, copy=False)
        z = checked(distance, (B,), "distance", kw, copy=False)
        r = torch.as_tensor(variance, **kw)
        r = checked(r.expand(B) if r.ndim == 0 else r, (B,), "variance", kw, copy=False)
        valid = self._checked_valid(valid, B, kw["device"])
        *state, passed = range_update(self._state(), self.initialized, u, z, r, valid,
                                      self.config.range_gate_chi2)
        self._set_state(*state)
        return passed

    def update_aligned(
        self,
        t_meas: Tensor,
        q_meas: Tensor,
        cov_meas: Tensor,
        valid: Tensor | None = None,
    ) -> Tensor:
        """Fuse a pose fitted from the filter's own pose, e.g. the object's mesh aligned with a
        depth frame (:class:`~evtrack.models.DepthRefiner`) from the predicted pose. Returns
        (B,) bool, True where it was used.

        Unlike :meth:`update` such a pose is not an independent detection: it is gated
        (``νᵀ S⁻¹ ν`` against ``config.gate_chi2``) but a rejection is not counted in
        ``rejected`` nor in the run that re-initialises the filter, and an uninitialised track
        is left alone. Its covariance may be nearly singular in the other direction: huge
        along what the fit could not see (a can turning about its axis), so the update leaves
        the state there to the other measurements.

        The pose measures the state's pose part directly (``H = [I₆, 0]`` on the tangent), so
        the update is the exact linear one: ``ν = (t_m, q_m) ⊟ (t, q)``, ``S = P₆₆ + R``,
        ``K = P H ᵀ S⁻¹``, state ``⊞ K ν``, covariance in Joseph form
        ``(I − K H) P (I − K H)ᵀ + K R Kᵀ``.

        Args:
            t_meas: (B,3) metres. q_meas: (B,4) wxyz (normalised here; either sign).
            cov_meas: (B,6,6) or (6,6) tangent covariance ``[δt, δθ]`` (m², rad²).
            valid: (B,) bool, False for tracks without a pose this time (default all True).
                Non-finite inputs count as missing.
        """
        t_meas, q_meas, R, valid = self._update_inputs(t_meas, q_meas, cov_meas, valid)
        *state, passed = aligned_update(self._state(), self.initialized, t_meas, q_meas, R,
                                        valid, self.gate)
        self._set_state(*state)
        return passed

    def _update_inputs(
        self, t_meas: Tensor, q_meas: Tensor, cov_meas: Tensor | None, valid: Tensor | None
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Checked :meth:`update` inputs of the filter's dtype and device, defaults filled in."""
        B, kw = self.batch_size, self._kw()
        t_meas = checked(t_meas, (B, 3), "t_meas", kw, copy=False)
        q_meas = checked(q_meas, (B, 4), "q_meas", kw, copy=False)
        R = self._checked_cov(cov_meas, self.meas_cov, B, kw)
        valid = self._checked_valid(valid, B, kw["device"])
        if q_meas.is_cpu and not bool((q_meas != 0).any(dim=-1).all()):
            valid = valid & (q_meas != 0).any(dim=-1)  # a zero quaternion: no pose, as NaN
        return t_meas, q_meas, R, valid

    def _kw(self) -> dict[str, Any]:
        """The state's dtype and device, as keyword arguments."""
        t = self._buffers["t"]
        return {"dtype": t.dtype, "device": t.device}

    @staticmethod
    def _checked_cov(cov_meas: Tensor | None, default: Tensor, B: int, kw: dict[str, Any]
                     ) -> Tensor:
        """A measurement covariance (B,6,6) of dtype and device ``kw`` from ``cov_meas`` (B,6,6)
        or (6,6), or ``None``: ``default`` (6,6)."""
        R = default if cov_meas is None else cov_meas.to(**kw)
        if R.shape == (6, 6):
            R = R.expand(B, 6, 6)
        return checked(R, (B, 6, 6), "cov_meas", kw, copy=False)

    @staticmethod
    def _checked_valid(valid: Tensor | None, B: int, device: torch.device) -> Tensor:
        """The (B,) bool flags on ``device`` of the tracks that have a measurement (``None``:
        all)."""
        if valid is None:
            valid = torch.ones(B, dtype=torch.bool, device=device)
        return checked(valid, (B,), "valid", {"device": device}, copy=False)

    # ------------------------------------------------------------------ single track (B = 1)
    # Buffers are read from and written to ``_buffers`` directly: nn.Module's attribute
    # access and assignment cost ~1 and ~3 µs per buffer, as much as the arithmetic here.
    def _update_single(self, backend: FilterBackend, t_meas: Tensor, q_meas: Tensor,
                       R: Tensor, valid: Tensor, reinit_after: int | None = None) -> Tensor:
        """:meth:`update` of one float64 CPU track on ``backend``."""
        buf = self._buffers
        extra = buf[self._extra_name].numpy()[0] if self._extra_name else _NO_EXTRA
        out = backend.pose_update(
            tuple(buf["t"].tolist()[0]),
            tuple(buf["q"].tolist()[0]),
            extra,
            buf["cov"].numpy()[0],
            buf["initialized"].tolist()[0],
            buf["rejected_run"].tolist()[0],
            tuple(t_meas.tolist()[0]),
            tuple(q_meas.tolist()[0]),
            R.numpy()[0],
            bool(valid.tolist()[0]),
            buf["gate"].tolist(),
            self.config.reinit_after if reinit_after is None else reinit_after,
        )
        self._set_state_single(np.array([out.t]), np.array([out.q]), out.cov[None],
                               out.extra[None] if self._extra_name else None)
        buf.update(
            initialized=torch.from_numpy(np.array([out.initialized])),
            rejected_run=torch.from_numpy(np.array([out.rejected_run], dtype=np.int64)),
        )
        if out.rejected or out.reinitialised:
            buf.update(
                rejected=buf["rejected"] + out.rejected,
                reinitialised=buf["reinitialised"] + out.reinitialised,
            )
        return torch.from_numpy(np.array([out.used]))

    def _set_state_single(
        self, t: np.ndarray, q: np.ndarray, cov: np.ndarray, extra: np.ndarray | None = None
    ) -> None:
        """Store one track's state from a backend's arrays: ``t`` (1,3), ``q`` (1,4), ``cov``
        (1,n,n) and ``extra`` (1,k) (the twist of :class:`PoseTwistUKF` or the velocity bias of
        a :class:`PoseUKF` with one; ``None``: unchanged)."""
        self._buffers.update(
            t=torch.from_numpy(t), q=torch.from_numpy(q), cov=torch.from_numpy(cov)
        )
        if extra is not None:
            self._buffers[self._extra_name] = torch.from_numpy(extra)

    # ------------------------------------------------------------------ pure steps
    def update_pose_state(
        self,
        t: Tensor,
        q: Tensor,
        extra: Tensor,
        cov: Tensor,
        initialized: Tensor,
        rejected_run: Tensor,
        t_meas: Tensor,
        q_meas: Tensor,
        cov_meas: Tensor,
        valid: Tensor,
        reinit_after: int | None = None,
    ) -> tuple[Tensor, ...]:
        """Pure, gated unscented pose update.

        Args:
            t (B,3), q (B,4), extra (B,k), cov (B,n,n): the prior; initialized (B,) bool;
            rejected_run (B,) int64; t_meas (B,3), q_meas (B,4), cov_meas (B,6,6), valid (B,).
            reinit_after: overrides ``config.reinit_after`` (see :meth:`update`).

        Returns:
            ``(t, q, extra, cov, initialized, rejected_run, used, rejected, reinitialised)``,
            the last three (B,) int64 flags of this update.
        """
        limit = self.config.reinit_after if reinit_after is None else reinit_after
        sigma = self._sigma() if self.config.sigma_points else None
        return gated_pose_update((t, q, extra, cov), initialized, rejected_run, t_meas, q_meas,
                                 cov_meas, valid, self.gate, limit, sigma)

    def _propagate(
        self,
        t: Tensor,
        q: Tensor,
        extra: Tensor,
        cov: Tensor,
        twist: Tensor | None,
        dt: Tensor,
        q_matrix: Tensor | None = None,
        decay_rate: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Unscented predict under a constant twist
        (:func:`~evtrack.filters.pose_motion.propagate_sigma_points`): the track's ``twist``
        (B,6) for the pose-only filter, or each sigma point's own (``twist=None``: from
        ``extra``, decayed at ``decay_rate``). ``q_matrix``: (B,n,n) process-noise densities
        (default: the config's, diagonal)."""
        return propagate_sigma_points(
            t, q, extra, cov, twist, dt, self._sigma(),
            self.q_matrix if q_matrix is None else q_matrix, decay_rate,
        )
