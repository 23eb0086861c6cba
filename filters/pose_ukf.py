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
filters) through :mod:`fast_path` (Python floats and NumPy, equal to the torch steps to
rounding), unless ``fast_path=False``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from evtrack.errors import ConfigError
from evtrack.filters import fast_compiled as _compiled
from evtrack.filters import fast_path as fp
from evtrack.filters.compiled import CompilableSteps
from evtrack.filters.config import PoseTwistUKFConfig, PoseUKFConfig
from evtrack.filters.lie import (
    pivot_map,
    pose_boxminus,
    pose_boxplus,
    quat_mul,
    quat_rotate,
    se3_exp,
)
from evtrack.filters.linalg import spd_inverse, spd_solve, symmetrize
from evtrack.filters.ukf import merwe_weights, quat_mean, sigma_offsets, weighted_cov

__all__ = ["PoseUKF", "PoseTwistUKF"]

_NO_EXTRA = np.zeros(0)  # the further state of PoseUKF in the fast path: none


class _PoseFilter(CompilableSteps, nn.Module):
    """Shared state, reset, pose update and gating of the pose UKFs (tangent size ``n``)."""

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
    ) -> None:
        super().__init__()
        self.config = config
        self.n = n
        self.fast_path = fast_path
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
    @property
    def batch_size(self) -> int:
        """Number of tracks B."""
        return self.t.shape[0]

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
            t = _checked(t, (B, 3), "t", kw)
            q = _checked(q, (B, 4), "q", kw)
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
            else _checked(cov, (B, n, n), "cov", kw)
        )
        for name in ("rejected_run", "rejected", "reinitialised"):
            setattr(self, name, torch.zeros(B, dtype=torch.int64, device=kw["device"]))

    def _load_from_state_dict(
        self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
    ):  # noqa: ANN001 - torch's signature
        # A saved filter may hold another number of tracks: take the saved batch size.
        key = prefix + "t"
        if key in state_dict and state_dict[key].shape[0] != self.batch_size:
            self.reset(state_dict[key].shape[0])  # type: ignore[attr-defined]
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )

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
        if self._fast((t_meas, q_meas, R, valid)):
            try:
                return self._update_fast(t_meas, q_meas, R, valid, reinit_after)
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
        B = self.batch_size
        kw = {"dtype": self.t.dtype, "device": self.t.device}
        u = _checked(direction, (B, 3), "direction", kw, copy=False)
        z = _checked(distance, (B,), "distance", kw, copy=False)
        r = torch.as_tensor(variance, **kw)
        r = _checked(r.expand(B) if r.ndim == 0 else r, (B,), "variance", kw, copy=False)
        if valid is None:
            valid = torch.ones(B, dtype=torch.bool, device=kw["device"])
        valid = _checked(valid, (B,), "valid", {"device": kw["device"]}, copy=False)
        norm = torch.linalg.vector_norm(u, dim=-1)
        ok = (valid & self.initialized & torch.isfinite(u).all(-1) & (norm > 0)
              & torch.isfinite(z) & torch.isfinite(r) & (r > 0))
        u = u / torch.where(norm > 0, norm, torch.ones_like(norm)).unsqueeze(-1)
        t, q, extra, P = self._state()
        n = P.shape[-1]
        H = torch.zeros(B, n, **kw)
        H[:, :3] = u
        PH = (P @ H.unsqueeze(-1)).squeeze(-1)  # (B,n) = P Hᵀ
        S = (H * PH).sum(-1) + r
        nu = z - (u * t).sum(-1)
        S_safe = torch.where(ok & (S > 0), S, torch.ones_like(S))
        passed = ok & (S > 0) & (nu * nu <= self.config.range_gate_chi2 * S_safe)
        K = PH / S_safe.unsqueeze(-1)
        delta = torch.where(passed.unsqueeze(-1), K * nu.unsqueeze(-1), torch.zeros_like(K))
        t_new, q_new = pose_boxplus(t, q, delta[:, :6])
        extra_new = extra + delta[:, 6:]
        IKH = torch.eye(n, **kw) - K.unsqueeze(-1) * H.unsqueeze(-2)
        P_new = symmetrize(IKH @ P @ IKH.transpose(-1, -2)
                           + r[:, None, None] * K.unsqueeze(-1) * K.unsqueeze(-2))
        keep = passed.unsqueeze(-1)
        self._set_state(t_new, torch.where(keep, q_new, q), torch.where(keep, extra_new, extra),
                        torch.where(keep.unsqueeze(-1), P_new, P))
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
        B = self.batch_size
        kw = {"dtype": self.t.dtype, "device": self.t.device}
        finite = torch.isfinite(t_meas.sum(-1) + q_meas.sum(-1) + R.sum((-2, -1)))
        ok = valid & finite & self.initialized
        t, q, extra, P = self._state()
        zeros6 = torch.zeros(B, 6, **kw)
        eye6 = torch.eye(6, **kw).expand(B, 6, 6)
        t_in = torch.where(ok.unsqueeze(-1), t_meas, t)  # no NaN reaches the arithmetic
        q_in = torch.where(ok.unsqueeze(-1), q_meas, q)
        R = torch.where(ok[:, None, None], R, eye6)
        q_in = q_in / torch.linalg.vector_norm(q_in, dim=-1, keepdim=True)
        n = P.shape[-1]
        nu = torch.where(ok.unsqueeze(-1), pose_boxminus(t_in, q_in, t, q), zeros6)
        S = symmetrize(P[:, :6, :6] + R)
        Pxz = P[:, :, :6]
        X = spd_solve(S, torch.cat([Pxz.transpose(-1, -2), nu.unsqueeze(-1)], dim=-1))
        K = X[..., :n].transpose(-1, -2)  # (B,n,6) = P Hᵀ S⁻¹
        d2 = (nu.unsqueeze(-2) @ X[..., n:]).reshape(-1)
        passed = ok & (d2 <= self.gate)
        delta = (K @ nu.unsqueeze(-1)).squeeze(-1)
        t_new, q_new = pose_boxplus(t, q, delta[:, :6])
        H = torch.zeros(B, 6, n, **kw)
        H[:, :, :6] = torch.eye(6, **kw)
        IKH = torch.eye(n, **kw) - K @ H
        P_new = symmetrize(IKH @ P @ IKH.transpose(-1, -2) + K @ R @ K.transpose(-1, -2))
        keep = passed.unsqueeze(-1)
        self._set_state(torch.where(keep, t_new, t), torch.where(keep, q_new, q),
                        torch.where(keep, extra + delta[:, 6:], extra),
                        torch.where(keep.unsqueeze(-1), P_new, P))
        return passed

    def _update_inputs(
        self, t_meas: Tensor, q_meas: Tensor, cov_meas: Tensor | None, valid: Tensor | None
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Checked :meth:`update` inputs of the filter's dtype and device, defaults filled in."""
        B = self.batch_size
        kw = {"dtype": self.t.dtype, "device": self.t.device}
        t_meas = _checked(t_meas, (B, 3), "t_meas", kw, copy=False)
        q_meas = _checked(q_meas, (B, 4), "q_meas", kw, copy=False)
        R = self.meas_cov if cov_meas is None else cov_meas.to(**kw)
        if R.shape == (6, 6):
            R = R.expand(B, 6, 6)
        R = _checked(R, (B, 6, 6), "cov_meas", kw, copy=False)
        if valid is None:
            valid = torch.ones(B, dtype=torch.bool, device=kw["device"])
        valid = _checked(valid, (B,), "valid", {"device": kw["device"]}, copy=False)
        if q_meas.is_cpu and not bool((q_meas != 0).any(dim=-1).all()):
            valid = valid & (q_meas != 0).any(dim=-1)  # a zero quaternion: no pose, as NaN
        return t_meas, q_meas, R, valid

    # ------------------------------------------------------------------ fast path (B = 1)
    # Buffers are read from and written to ``_buffers`` directly: nn.Module's attribute
    # access and assignment cost ~1 and ~3 µs per buffer, as much as the arithmetic here.
    def _fast(self, inputs: tuple[object, ...]) -> bool:
        if not self.fast_path or self.config.sigma_points or self.__dict__.get("_compiled_steps"):
            return False
        buf = self._buffers
        return fp.applies(buf["t"], (buf["q"], buf["cov"], *inputs))

    def _fast_dt(self, dt: float | Tensor) -> float:
        if isinstance(dt, Tensor) and dt.ndim > 0:
            self._dt(dt)  # raises unless (B,)
        value = float(dt)
        if not (math.isfinite(value) and value >= 0):
            raise ValueError(f"dt must be a finite number of seconds >= 0, got {value}")
        return value

    def _update_fast(self, t_meas: Tensor, q_meas: Tensor, R: Tensor, valid: Tensor,
                     reinit_after: int | None = None) -> Tensor:
        """:meth:`update` of one float64 CPU track through :func:`fast_path.pose_update`."""
        buf = self._buffers
        extra = buf[self._extra_name].numpy()[0] if self._extra_name else _NO_EXTRA
        out = fp.pose_update(
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
        self._set_state_fast(out.t, out.q, out.extra if self._extra_name else None, out.cov)
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

    def _set_state_fast(
        self, t: fp.Vec3, q: fp.Quat, extra: np.ndarray | None, cov: np.ndarray
    ) -> None:
        """Store one track's state from :mod:`fast_path` results (``extra``: the twist of
        :class:`PoseTwistUKF` or the velocity bias of a :class:`PoseUKF` with one, else
        ``None``)."""
        self._buffers.update(
            t=torch.from_numpy(np.array([t])),
            q=torch.from_numpy(np.array([q])),
            cov=torch.from_numpy(cov[None]),
        )
        if extra is not None:
            self._buffers[self._extra_name] = torch.from_numpy(extra[None])

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
        cfg = self.config
        # A pose is missing where not valid or not finite; nothing below selects from its
        # (possibly NaN) values then, so they need no masking.
        finite = torch.isfinite(t_meas.sum(-1) + q_meas.sum(-1) + cov_meas.sum((-2, -1)))
        ok = valid & finite
        q_meas = q_meas / torch.linalg.vector_norm(q_meas, dim=-1, keepdim=True)
        R = cov_meas
        if cfg.sigma_points:
            offs = sigma_offsets(cov, self.gamma)  # (B,S,n)
            ts, qs = pose_boxplus(t.unsqueeze(1), q.unsqueeze(1), offs[..., :6])
            zt = (self.w_mean.unsqueeze(-1) * ts).sum(1)
            zq, eq = quat_mean(qs, self.w_mean, q, cfg.mean_iterations)
            dz = torch.cat([ts - zt.unsqueeze(1), eq], dim=-1)  # Zᵢ ⊟ z̄, (B,S,6)
            S = weighted_cov(dz, dz, self.w_cov) + R
            Pxz = weighted_cov(offs, dz, self.w_cov)  # χᵢ ⊟ x̄ are the offsets themselves
        else:
            # h(x) = pose: symmetric sigma points give z̄ = x̄ and Zᵢ ⊟ z̄ = offsets, hence:
            zt, zq = t, q
            Pxz = cov if self.n == 6 else cov[:, :, :6]
            S = (cov if self.n == 6 else cov[:, :6, :6]) + R
        nu = pose_boxminus(t_meas, q_meas, zt, zq)  # (B,6)
        # One solve gives Kᵀ = S⁻¹ Pxzᵀ and S⁻¹ ν.
        X = spd_solve(S, torch.cat([Pxz.transpose(-1, -2), nu.unsqueeze(-1)], dim=-1))
        S_inv_nu = X[..., self.n :]
        d2 = (nu.unsqueeze(-2) @ S_inv_nu).reshape(-1)  # νᵀ S⁻¹ ν
        delta = (Pxz @ S_inv_nu).squeeze(-1)  # K ν
        cov_up = symmetrize(cov - Pxz @ X[..., : self.n])  # P − K S Kᵀ = P − Pxz S⁻¹ Pxzᵀ
        t_up, q_up = pose_boxplus(t, q, delta if self.n == 6 else delta[:, :6])
        extra_up = extra + delta[:, 6:]

        fresh = ~initialized
        accept = ok & (fresh | (d2 <= self.gate))
        reject = ok & ~accept
        limit = cfg.reinit_after if reinit_after is None else reinit_after
        reinit = reject & (rejected_run >= limit - 1)
        take = ok & fresh | reinit
        fuse = accept & ~fresh
        take1, fuse1 = take.unsqueeze(-1), fuse.unsqueeze(-1)
        take2, fuse2 = take1.unsqueeze(-1), fuse1.unsqueeze(-1)
        t_new = torch.where(take1, t_meas, torch.where(fuse1, t_up, t))
        q_new = torch.where(take1, q_meas, torch.where(fuse1, q_up, q))
        q_new = q_new / torch.linalg.vector_norm(q_new, dim=-1, keepdim=True)
        extra_new = torch.where(fuse1, extra_up, extra)
        cov_new = torch.where(take2, _reinit_cov(cov, R), torch.where(fuse2, cov_up, cov))
        run = torch.where(reject & ~reinit, rejected_run + 1, torch.where(ok, 0, rejected_run))
        used = fuse | take
        return (
            t_new,
            q_new,
            extra_new,
            cov_new,
            initialized | ok,
            run,
            used,
            reject.long(),
            reinit.long(),
        )

    # ------------------------------------------------------------------ predict helper
    def _propagate(
        self,
        t: Tensor,
        q: Tensor,
        extra: Tensor,
        cov: Tensor,
        twist: Tensor | None,
        dt: Tensor,
        q_matrix: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Unscented predict under a constant twist: the track's ``twist`` (B,6) for the
        pose-only filter, or each sigma point's own (``twist=None``: from ``extra``).
        ``q_matrix``: (B,n,n) process-noise densities (default: the config's, diagonal)."""
        offs = sigma_offsets(cov, self.gamma)
        ts, qs = pose_boxplus(t.unsqueeze(1), q.unsqueeze(1), offs[..., :6])
        es = extra.unsqueeze(1) + offs[..., 6:]
        if twist is None:
            xi = es * dt[:, None, None]  # each sigma point's own twist
            qd, pd = se3_exp(xi)
        else:
            qd, pd = se3_exp(twist * dt.unsqueeze(-1))
            qd, pd = qd.unsqueeze(1), pd.unsqueeze(1)
        ts = quat_rotate(qd, ts) + pd
        if twist is not None and es.shape[-1]:  # a velocity bias: t' = R t + p + b s dt
            ts = ts + es * (dt * _origin_speed(twist, t))[:, None, None]
        qs = quat_mul(qd, qs)
        if twist is None:
            es = es * self.decay_rate.mul(dt).exp()[:, None, None]  # V' = alpha^(dt/alpha_dt) V
        wm = self.w_mean.unsqueeze(-1)
        tm = (wm * ts).sum(1)
        qm, eq = quat_mean(qs, self.w_mean, qs[:, 0], self.config.mean_iterations)
        em = (wm * es).sum(1)
        dev = torch.cat([ts - tm.unsqueeze(1), eq, es - em.unsqueeze(1)], dim=-1)
        # P = Σ Wc devᵢ devᵢᵀ + Q dt
        Q = self.q_matrix if q_matrix is None else q_matrix
        P = symmetrize(weighted_cov(dev, dev, self.w_cov)) + dt[:, None, None] * Q
        return tm, qm, em, P

    def _dt(self, dt: float | Tensor) -> Tensor:
        d = torch.as_tensor(dt, dtype=self.t.dtype, device=self.t.device)
        fp.check_dt(d)
        if d.ndim == 0:
            return d.expand(self.batch_size)
        if tuple(d.shape) != (self.batch_size,):
            raise ValueError(f"dt must be a float or ({self.batch_size},), got {tuple(d.shape)}")
        return d

    def _state(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        raise NotImplementedError  # pragma: no cover - defined by both subclasses

    def _set_state(self, t: Tensor, q: Tensor, extra: Tensor, cov: Tensor) -> None:
        raise NotImplementedError  # pragma: no cover - defined by both subclasses


class PoseUKF(_PoseFilter):
    """Quaternion pose UKF driven by a measured twist (paper III-C), batched over B tracks.

    Args:
        batch_size: number of tracks B.
        config: :class:`PoseUKFConfig` (defaults documented there).
        dtype: float64 by default. device: where the state lives.
        fast_path: let :meth:`predict`, :meth:`update` and :meth:`forward` of one float64 CPU
            track run through :mod:`fast_path` (closed form only; equal to the torch steps to
            rounding); also the attribute ``fast_path``.

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
    ) -> None:
        cfg = config if config is not None else PoseUKFConfig()
        qd = [cfg.q_translation] * 3 + [cfg.q_rotation] * 3
        var = [cfg.init_std_translation**2] * 3 + [cfg.init_std_rotation**2] * 3
        if cfg.velocity_bias:
            qd += [cfg.q_velocity_bias] * 3
            var += [cfg.init_std_velocity_bias**2] * 3
        super().__init__(cfg, len(qd), qd, var, batch_size, dtype, device, fast_path)
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
        if (
            isinstance(twist, Tensor)
            and twist.shape == (1, 6)
            and twist.is_cpu
            and fp.COMPILED
            and _compiled.available()
            and self._fast((twist, dt))
        ):  # one track on CPU: the compiled kernel, no conversions of the state
            t, q, cov = _compiled.pose_predict(
                buf["t"].numpy(),
                buf["q"].numpy(),
                buf["cov"].numpy(),
                fp.as_array(twist),
                self._fast_dt(dt),
                buf["q_matrix"].numpy(),
                None if bias is None else bias.numpy(),
            )
            buf.update(t=torch.from_numpy(t), q=torch.from_numpy(q), cov=torch.from_numpy(cov))
            return buf["t"], buf["q"]
        twist = _checked(
            twist,
            (self.batch_size, 6),
            "twist",
            {"dtype": self.t.dtype, "device": self.t.device},
            copy=False,
        )
        if self._fast((twist, dt)):
            t, q, cov = fp.pose_predict(
                tuple(buf["t"].tolist()[0]),
                tuple(buf["q"].tolist()[0]),
                buf["cov"].numpy()[0],
                twist.tolist()[0],
                self._fast_dt(dt),
                buf["q_matrix"].numpy(),
                None if bias is None else bias.tolist()[0],
            )
            self._set_state_fast(t, q, None, cov)
            return self.t, self.q
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
            :meth:`predict` would not take its compiled single-track path (a batch, CUDA,
            float32, gradients, sigma points, no numba...): then call :meth:`predict` per step.
        """
        if len(twists) != len(dts):
            raise ValueError(f"predict_run: {len(twists)} twists but {len(dts)} time steps")
        if not (
            twists
            and fp.COMPILED
            and _compiled.available()
            and all(isinstance(w, Tensor) and w.shape == (1, 6) and w.is_cpu for w in twists)
            and self._fast((*twists, *(float(dt) for dt in dts)))
        ):
            return None
        buf = self._buffers
        t, q, cov = _compiled.pose_predict_run(
            buf["t"].numpy(),
            buf["q"].numpy(),
            buf["cov"].numpy(),
            np.concatenate([fp.as_array(w) for w in twists]),
            np.array([self._fast_dt(dt) for dt in dts], dtype=np.float64),
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
        # Every sigma point moves by the same rigid motion, which acts on the tangent linearly:
        # δt' = R_Δ δt (+ s dt δb), δθ' = R_Δ δθ (δb' = δb). The unscented transform is exact:
        # P' = A P Aᵀ + Q dt.
        qd, pd = se3_exp(twist * dt.unsqueeze(-1))
        t_prior = t
        t = quat_rotate(qd, t) + pd
        if bias is not None:
            db = dt * _origin_speed(twist, t_prior)  # the bias's share of the step: s dt
            t = t + bias * db.unsqueeze(-1)
        q = quat_mul(qd, q)
        q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
        # P' = A P Aᵀ with A = diag(R_Δ, R_Δ): rotate the 3-vector blocks of P's rows, then of
        # the columns (elementwise work: batched 6x6 matmuls are slow at large B).
        qb = qd[:, None, None, :]
        if bias is None:
            half = quat_rotate(qb, cov.unflatten(-1, (2, 3))).flatten(-2)  # P Aᵀ
            cov = quat_rotate(qb, half.transpose(-1, -2).unflatten(-1, (2, 3))).flatten(-2)
        else:
            half = _times_bias_transition(cov, qb, db)  # P Aᵀ
            cov = _times_bias_transition(half.transpose(-1, -2), qb, db)  # A P Aᵀ
        cov = symmetrize(cov) + dt[:, None, None] * self.q_matrix
        return t, q, cov

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

    def _state(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        return self.t, self.q, self.bias if self._extra_name else self.t[:, :0], self.cov

    def _set_state(self, t: Tensor, q: Tensor, extra: Tensor, cov: Tensor) -> None:
        self.t, self.q, self.cov = t, q, cov
        if self._extra_name:
            self.bias = extra


class PoseTwistUKF(_PoseFilter):
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
        super().__init__(cfg, 12, qd, var, batch_size, dtype, device, fast_path)
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
            torch.zeros(B, 6, **kw) if twist is None else _checked(twist, (B, 6), "twist", kw)
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
            return self._propagate(t, q, twist, cov, None, dt)
        B = t.shape[0]
        pose_q = self.q_matrix[:6, :6].expand(B, 6, 6)
        top = torch.cat([pose_q, torch.zeros_like(pose_q)], dim=-1)
        bottom = torch.cat([torch.zeros_like(pose_q), self._twist_block(self.q_density[6:], t)],
                           dim=-1)
        return self._propagate(t, q, twist, cov, None, dt, torch.cat([top, bottom], dim=-2))

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

    def _update_fast(self, t_meas: Tensor, q_meas: Tensor, R: Tensor, valid: Tensor,
                     reinit_after: int | None = None) -> Tensor:
        was_initialized = bool(self._buffers["initialized"].tolist()[0])
        used = super()._update_fast(t_meas, q_meas, R, valid, reinit_after)
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
        B = self.batch_size
        kw = {"dtype": self.t.dtype, "device": self.t.device}
        z = _checked(twist_meas, (B, 6), "twist_meas", kw, copy=False)
        R = self.twist_meas_cov if cov_meas is None else cov_meas.to(**kw)
        R = _checked(
            R.expand(B, 6, 6) if R.shape == (6, 6) else R, (B, 6, 6), "cov_meas", kw, copy=False
        )
        if valid is None:
            valid = torch.ones(B, dtype=torch.bool, device=kw["device"])
        valid = _checked(valid, (B,), "valid", {"device": kw["device"]}, copy=False)
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
        """Pure update with ``h(x) = V``: linear, so the unscented transform is exact and equals
        the Kalman update ``S = P_VV + R``, ``K = P_xV S⁻¹``."""
        ok = (
            valid & torch.isfinite(twist_meas).all(-1) & torch.isfinite(cov_meas).flatten(1).all(-1)
        )
        R = torch.where(ok[:, None, None], cov_meas, self.twist_meas_cov)
        S = cov[:, 6:, 6:] + R
        Pxz = cov[:, :, 6:]
        K = Pxz @ spd_inverse(S)
        nu = torch.where(ok.unsqueeze(-1), twist_meas, twist) - twist
        delta = (K @ nu.unsqueeze(-1)).squeeze(-1)
        t_up, q_up = pose_boxplus(t, q, delta[:, :6])
        cov_up = symmetrize(cov - K @ Pxz.transpose(-1, -2))
        m = ok.unsqueeze(-1)
        return (
            torch.where(m, t_up, t),
            torch.where(m, q_up / q_up.norm(dim=-1, keepdim=True), q),
            torch.where(m, twist + delta[:, 6:], twist),
            torch.where(m.unsqueeze(-1), cov_up, cov),
        )

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

    def _state(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        return self.t, self.q, self.twist, self.cov

    def _set_state(self, t: Tensor, q: Tensor, extra: Tensor, cov: Tensor) -> None:
        self.t, self.q, self.twist, self.cov = t, q, extra, cov


def _origin_speed(twist: Tensor, t: Tensor) -> Tensor:
    """(B,) speed (m/s) ``|v_o + ω × t|`` of the object's origin at ``t`` (B,3) under the
    camera-frame twist (B,6) (the cross product written out: it exports to ONNX)."""
    v, w = twist[:, :3], twist[:, 3:]
    c = torch.stack([w[:, 1] * t[:, 2] - w[:, 2] * t[:, 1],
                     w[:, 2] * t[:, 0] - w[:, 0] * t[:, 2],
                     w[:, 0] * t[:, 1] - w[:, 1] * t[:, 0]], dim=-1)
    return torch.linalg.vector_norm(v + c, dim=-1)


def _times_bias_transition(M: Tensor, qb: Tensor, db: Tensor) -> Tensor:
    """``M Aᵀ`` for ``M`` (B,9,9) and the transition of a pose filter with a velocity bias,
    ``A = [[R_Δ, 0, db I], [0, R_Δ, 0], [0, 0, I]]`` (``R_Δ`` the rotation of ``qb``
    (B,1,1,4), ``db = s dt`` (B,) s·m/s): each row's first two 3-blocks rotated, ``db`` times
    its bias block added to the first."""
    rotated = quat_rotate(qb, M[..., :6].unflatten(-1, (2, 3))).flatten(-2)
    bias_cols = M[..., 6:]
    return torch.cat([rotated[..., :3] + db[:, None, None] * bias_cols, rotated[..., 3:],
                      bias_cols], dim=-1)


def _reinit_cov(cov: Tensor, R: Tensor) -> Tensor:
    """The covariance after re-initialising on a pose: ``R`` for the pose block, the old
    covariance for any further state (the twist), no cross terms."""
    n = cov.shape[-1]
    if n == 6:
        return R
    top = torch.cat([R, torch.zeros_like(cov[:, :6, 6:])], dim=-1)
    bottom = torch.cat([torch.zeros_like(cov[:, 6:, :6]), cov[:, 6:, 6:]], dim=-1)
    return torch.cat([top, bottom], dim=-2)


def _checked(
    t: Tensor, shape: tuple[int, ...], name: str, kw: dict[str, Any], copy: bool = True
) -> Tensor:
    if not isinstance(t, Tensor):
        t = torch.as_tensor(t)
    if tuple(t.shape) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {tuple(t.shape)}")
    t = t.to(**kw)
    return t.clone() if copy else t
