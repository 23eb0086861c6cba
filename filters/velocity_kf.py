"""The 6-DoF velocity Kalman filter: RoI optical flow + depth -> object twist (paper III-B).

State: the twist ``V = [v_o (m/s), ω (rad/s)]`` of B tracks in the camera frame (the
convention ``Ṗ = v_o + ω × P``) and its 6x6 covariance.

Predict over ``dt`` seconds (decaying velocity model, rate-independent)::

    a = alpha ** (dt / alpha_dt)          # the paper's alpha = 0.5 per 1 ms step, per second
    V = a V,   P = a² P + Q dt            # Q: process-noise density, (m/s)²/s and (rad/s)²/s

Update from RoI flows ``F_k`` (px/s) at ideal pinhole pixels ``uv_k`` with depths ``Z_k``: the
predicted flow is ``J_k V`` (:mod:`interaction`). Each flow is written in its own flow-aligned
frame, ``n = F/|F|`` and ``n⊥``: the along row measures ``nᵀ J V = |F|`` and the across row
``n⊥ᵀ J V = 0``. A normal-only flow (aperture problem) keeps only the along row: the predicted
flow projected on the measured direction against the measured magnitude, the paper's residual
``r_k = (F·F̂/|F|) F/|F| − F`` written as the scalar it is a multiple of. A full flow keeps both
rows, which with an isotropic ``R_F`` equals the plain 2-D flow measurement. The model is linear
in ``V`` (``n`` comes from the measurement), so the update is an exact Kalman update.

Rows are weighted by :func:`weighting.laplacian_weights` (noise ``R_F/ρ_j``) and fused in
information form, O(N) in the number of RoIs plus fixed 6x6 algebra::

    Λ = P⁻¹ + Hᵀ W H,   P⁺ = Λ⁻¹,   V⁺ = V + P⁺ Hᵀ W (z − H V),   W = diag(ρ_j / σ_F²)

The weights' residuals are taken against a reference twist (by default the last posterior,
see :class:`VelocityKFConfig.weighting_reference`) and refined over
``weighting_iterations`` passes, each against the previous pass's posterior.

One track (B = 1) of float64 on CPU runs the stateful methods on a single-track backend
(:mod:`backends`: numba, or NumPy; equal to the torch steps to rounding), unless
``fast_path=False`` (or ``backend="torch"``).

Tracks with different numbers of RoIs share a batch through padding and a ``mask``. A RoI
whose depth is missing, zero, negative or NaN is skipped and counted in ``skipped_depth``; one
whose flow or pixel is not finite, or whose normal flow is zero (no direction), is skipped and
counted in ``skipped_flow``. Skipped values never reach the arithmetic.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from evtrack.camera import PinholeCamera
from evtrack.filters.backend_base import FilterBackend, RoiRows, VelocityModel
from evtrack.filters.backends import as_array, as_bool_array
from evtrack.filters.base import TrackFilter, checked
from evtrack.filters.config import VelocityKFConfig
from evtrack.filters.interaction import UndistortionTable, undistort_flow
from evtrack.filters.lie import pivot_map
from evtrack.filters.velocity_model import measurement_rows, weighted_update

__all__ = ["VelocityKF"]


class VelocityKF(TrackFilter):
    """Batched 6-DoF velocity Kalman filter from event optical flow (paper III-B).

    Args:
        camera: the event camera (its intrinsics become buffers; distortion, if any, is undone
            by :meth:`update` before the flows enter the filter, see
            :func:`interaction.undistort_flow`).
        batch_size: number of tracks B.
        config: the filter's parameters; defaults to :class:`VelocityKFConfig`.
        dtype: float64 by default. A float32 filter keeps its state and the per-RoI work in
            float32 but sums the information and does the 6x6 algebra in float64.
        device: where the state lives (``.to(device)`` moves it later too).
        fast_path: let :meth:`predict`, :meth:`update`, :meth:`forward` and
            :meth:`forward_run` run one float64 CPU track on a single-track backend (equal to
            the torch steps to rounding, several times faster at B = 1); also settable later as
            the attribute ``fast_path``. Batches, other dtypes and devices, gradients and
            compiled steps always run torch.
        backend: the preferred backend where ``fast_path`` holds (:mod:`backends`:
            ``"auto"``, ``"numba"``, ``"numpy"`` or ``"torch"``); also the attribute
            ``backend``.

    Buffers (all in ``state_dict``): the state ``twist`` (B,6), ``cov`` (B,6,6) and
    ``reference`` (B,6) (the last posterior twist, which the weighting compares flows with);
    cumulative counts ``skipped_depth`` and ``skipped_flow`` (B,); constants ``focal``
    ``[fx, fy]``, ``principal`` ``[cx, cy]``, ``q_density`` (6,) and
    ``q_matrix`` (its 6x6 diagonal),
    ``init_var`` (6,) and ``consts`` (6,).

    Example:
        >>> cam = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)
        >>> kf = VelocityKF(cam, batch_size=2)
        >>> uv = torch.tensor([[[300.0, 200.0], [350.0, 260.0]]]).expand(2, 2, 2)
        >>> depth, flow = torch.ones(2, 2), torch.full((2, 2, 2), 100.0)
        >>> kf(1e-3, uv, depth, flow).shape
        torch.Size([2, 6])
    """

    _STEP_NAMES = ("predict_state", "update_state", "step")
    _STATE = ("twist", "cov", "reference")

    twist: Tensor
    cov: Tensor
    reference: Tensor
    skipped_depth: Tensor
    skipped_flow: Tensor
    focal: Tensor
    principal: Tensor
    q_density: Tensor
    q_matrix: Tensor
    init_var: Tensor
    consts: Tensor

    def __init__(
        self,
        camera: PinholeCamera,
        batch_size: int = 1,
        config: VelocityKFConfig | None = None,
        dtype: torch.dtype = torch.float64,
        device: str | torch.device | None = None,
        fast_path: bool = True,
        backend: str = "auto",
    ) -> None:
        super().__init__()
        self.config = config if config is not None else VelocityKFConfig()
        self.camera = camera
        # the per-pixel part of the undistortion, kept for the pixels seen (the same values)
        self._undistortion = None if camera.dist is None else UndistortionTable(camera)
        self._init_backend(backend, fast_path)
        cfg = self.config
        kw: dict[str, Any] = {"dtype": dtype, "device": device}
        self.register_buffer("focal", torch.tensor([camera.fx, camera.fy], **kw))
        self.register_buffer("principal", torch.tensor([camera.cx, camera.cy], **kw))
        self.register_buffer(
            "q_density", torch.tensor([cfg.q_linear] * 3 + [cfg.q_angular] * 3, **kw)
        )
        self.register_buffer("q_matrix", torch.diag(self.q_density))
        var = [cfg.init_std_linear**2] * 3 + [cfg.init_std_angular**2] * 3
        self.register_buffer("init_var", torch.tensor(var, **kw))
        for name, shape, dt in (
            ("twist", (0, 6), dtype),
            ("cov", (0, 6, 6), dtype),
            ("reference", (0, 6), dtype),
            ("skipped_depth", (0,), torch.int64),
            ("skipped_flow", (0,), torch.int64),
        ):
            self.register_buffer(name, torch.zeros(shape, dtype=dt, device=device))
        # Scalars as tensors of the filter's dtype: an exported graph would store Python floats
        # as float32 constants. [ln(alpha)/alpha_dt (1/s), 1/R_F ((px/s)⁻²), b or 0, b_min, floor,
        # 1/R of a normal-only row ((px/s)⁻²)]
        normal_std = cfg.flow_std if cfg.normal_flow_std is None else cfg.normal_flow_std
        consts = [
            math.log(cfg.alpha) / cfg.alpha_dt,
            1.0 / cfg.flow_std**2,
            cfg.laplace_scale or 0.0,
            cfg.laplace_scale_min,
            cfg.weight_floor,
            1.0 / normal_std**2,
        ]
        self.register_buffer("consts", torch.tensor(consts, **kw))
        self.reset(batch_size)

    def prepare_pixels(self, uv: Tensor) -> None:
        """With a distorted camera, undistort the measured pixels ``uv`` (N, 2) px now (e.g. a
        flow's RoI centres, where every later flow lies), so that the updates there only look
        their undistortion up (:class:`~evtrack.filters.interaction.UndistortionTable`: the
        same values); nothing without distortion."""
        table = self._undistortion
        if table is not None and uv.numel():
            uv = uv.detach().to(device="cpu", dtype=torch.float64).reshape(-1, 2)
            if table.applies(uv):
                table.lookup(uv)

    # ------------------------------------------------------------------ state
    def reset(
        self, batch_size: int | None = None, twist: Tensor | None = None, cov: Tensor | None = None
    ) -> None:
        """Start over: twist (B,6) (default 0), covariance (B,6,6) (default the initial one),
        counters zeroed. ``batch_size`` defaults to the current one."""
        B = self.batch_size if batch_size is None else int(batch_size)
        kw = {"dtype": self.init_var.dtype, "device": self.init_var.device}
        self.twist = (
            torch.zeros(B, 6, **kw) if twist is None else checked(twist, (B, 6), "twist", kw)
        )
        if cov is None:
            self.cov = torch.diag_embed(self.init_var).expand(B, 6, 6).clone()
        else:
            self.cov = checked(cov, (B, 6, 6), "cov", kw)
        self.reference = self.twist.clone()
        self.skipped_depth = torch.zeros(B, dtype=torch.int64, device=kw["device"])
        self.skipped_flow = torch.zeros(B, dtype=torch.int64, device=kw["device"])

    def set_pivot(self, pivot: Tensor | None) -> None:
        """Make the process noise independent in the object's own motion about ``pivot``.

        The state ``[v_o, ω]`` is the camera-frame twist (``v_o``: velocity of the point at the
        camera's origin). With a pivot ``p`` (3,) metres, camera frame (the object's centre),
        ``q_linear`` becomes the spread of the pivot's velocity ``v = v_o + ω × p`` and the
        noise is ``A Q Aᵀ`` with ``A = [[I, [p]×], [0, I]]``: an unexpected turn of the object
        about itself no longer has to be explained by a velocity of the camera-origin point.
        ``None`` restores the diagonal noise of the config. One pivot for all tracks.
        """
        backend = None if pivot is None else self._single_track((pivot,))
        if backend is not None:  # the tracker's call at every step
            self._buffers["q_matrix"] = torch.from_numpy(backend.pivot_noise(
                self._buffers["q_density"].numpy(), as_array(pivot).reshape(3)))
            return
        Q = torch.diag(self.q_density)
        if pivot is not None:
            A = pivot_map(torch.as_tensor(pivot, dtype=Q.dtype, device=Q.device).reshape(3))
            Q = A @ Q @ A.T
            Q = 0.5 * (Q + Q.T)
        self.q_matrix = Q

    # ------------------------------------------------------------------ stateful steps
    def predict(self, dt: float | Tensor) -> Tensor:
        """Decay the twist over ``dt`` seconds (float or (B,)); returns the prediction (B,6)."""
        backend = self._single_track((dt,))
        if backend is not None:
            twist, cov = self._predicted(backend, dt)
            V = torch.from_numpy(twist[None])
            self._buffers.update(twist=V, cov=torch.from_numpy(cov[None]))
            return V
        self.twist, self.cov = self.step_function("predict_state")(
            self.twist, self.cov, self._dt(dt)
        )
        return self.twist

    def update(
        self,
        uv: Tensor,
        depth: Tensor,
        flow: Tensor,
        normal_only: Tensor | None = None,
        mask: Tensor | None = None,
    ) -> Tensor:
        """Correct the twist with RoI flows; returns the posterior twist (B,6).

        Args:
            uv: (B,N,2) RoI pixel coordinates as measured by the camera.
            depth: (B,N) z-depth in metres at the RoIs (NaN, 0, negative or inf: missing).
            flow: (B,N,2) RoI flows in px/s.
            normal_only: (B,N) bool, True where a flow is only the component normal to an edge
                (aperture problem); default: ``config.assume_normal`` for every RoI.
            mask: (B,N) bool, False on padding; default all True.
        """
        backend = self._single_track((uv, depth, flow, normal_only, mask))
        if backend is not None:
            try:
                return self._update_single(backend, uv, depth, flow, normal_only, mask)
            except np.linalg.LinAlgError:  # a 6x6 not positive definite: torch gives its NaNs
                pass
        return self._update_torch(uv, depth, flow, normal_only, mask)

    def _update_torch(
        self,
        uv: Tensor,
        depth: Tensor,
        flow: Tensor,
        normal_only: Tensor | None,
        mask: Tensor | None,
    ) -> Tensor:
        """:meth:`update` through the torch step (any batch, device and dtype)."""
        uv, depth, flow, normal_only, mask = self._inputs(uv, depth, flow, normal_only, mask)
        if self.camera.dist is not None:
            uv, flow = undistort_flow(self.camera, uv, flow, normal_only, self._undistortion)
        V, P, skipped = self.step_function("update_state")(
            self.twist, self.cov, self.reference, uv, depth, flow, normal_only, mask
        )
        self.twist, self.cov, self.reference = V, P, V
        self.skipped_depth = self.skipped_depth + skipped[:, 0]
        self.skipped_flow = self.skipped_flow + skipped[:, 1]
        return V

    def forward(
        self,
        dt: float | Tensor,
        uv: Tensor,
        depth: Tensor,
        flow: Tensor,
        normal_only: Tensor | None = None,
        mask: Tensor | None = None,
    ) -> Tensor:
        """One predict over ``dt`` seconds then one update (arguments as in :meth:`update`)."""
        backend = self._single_track((dt, uv, depth, flow, normal_only, mask))
        if backend is not None:
            # one track: the predicted state goes to the update as arrays, not through the
            # buffers (same arithmetic as predict() then update(); a bad input raises in
            # _update_single before the state changes)
            twist, cov = self._predicted(backend, dt)
            try:
                return self._update_single(backend, uv, depth, flow, normal_only, mask,
                                           (twist, cov))
            except np.linalg.LinAlgError:  # the torch update from the predicted state
                self._buffers.update(twist=torch.from_numpy(twist[None]),
                                     cov=torch.from_numpy(cov[None]))
                return self._update_torch(uv, depth, flow, normal_only, mask)
        self.predict(dt)
        return self.update(uv, depth, flow, normal_only, mask)

    def forward_run(
        self,
        dts: Sequence[float],
        bounds: Sequence[int],
        uv: Tensor,
        depth: Tensor,
        flow: Tensor,
        normal_only: Tensor | None = None,
    ) -> Tensor | None:
        """``len(dts)`` calls of :meth:`forward` in one backend call, with the same
        arithmetic: step ``k`` predicts over ``dts[k]`` s and updates with the rows
        ``bounds[k]:bounds[k+1]`` of the RoIs (a step without rows only predicts, as
        :meth:`predict`). For a tracker's group of velocity steps, where one call per step
        costs more than its arithmetic.

        Args:
            dts: (n,) seconds. bounds: (n+1,) non-decreasing row offsets into the RoIs.
            uv: (N,2) RoI pixel coordinates; depth: (N,) m; flow: (N,2) px/s;
                normal_only: (N,) bool or ``None`` (``config.assume_normal``): the rows of
                all the steps, as :meth:`update` takes one step's (without the batch).

        Returns:
            The twist after each step done, (m,1,6) with ``m <= n``; the filter holds the
            state after step ``m - 1``. ``m < n`` when the update of step ``m`` meets a
            matrix that is not positive definite: nothing of that step is done, and it is
            left to :meth:`forward` (whose torch path reports it). ``None``, with the filter
            unchanged, when :meth:`forward` would not run on a single-track backend with runs
            (a batch, CUDA, float32, gradients, the NumPy or torch backend, no numba...): then
            call :meth:`forward` per step.

        With a distorted camera the rows of all the steps are mapped to the ideal pinhole image
        at once (:func:`~evtrack.filters.interaction.undistort_flow`, as :meth:`update` maps
        each step's), then run as an undistorted camera's: the same states as per step, to
        rounding (the per-point arithmetic is the same; only the tensors' sizes differ).
        """
        n = len(dts)
        if len(bounds) != n + 1:
            raise ValueError(f"forward_run: {n} steps need {n + 1} row bounds, got {len(bounds)}")
        N = depth.shape[0] if isinstance(depth, Tensor) and depth.ndim == 1 else -1
        if N < 0 or uv.shape != (N, 2) or flow.shape != (N, 2) or (
                normal_only is not None and (normal_only.shape != (N,)
                                             or normal_only.dtype is not torch.bool)):
            raise ValueError(
                "forward_run: uv (N,2), depth (N,), flow (N,2) and normal_only (N,) bool, got "
                f"{tuple(uv.shape)}, {tuple(getattr(depth, 'shape', ()))}, {tuple(flow.shape)}"
                f", {None if normal_only is None else tuple(normal_only.shape)}")
        b = np.asarray(bounds, dtype=np.int64)
        if n and (b[0] < 0 or b[-1] > N or (np.diff(b) < 0).any()):
            raise ValueError(f"forward_run: row bounds must rise within [0, {N}], got {b}")
        backend = (self._single_track((uv, depth, flow, normal_only, *(float(dt) for dt in dts)))
                   if n else None)
        if backend is None or not backend.runs:
            return None
        if self.camera.dist is not None:
            uv, flow, normal_only = self._undistorted_rows(uv, flow, normal_only)
        buf = self._buffers
        rois = RoiRows(as_array(uv), as_array(depth), as_array(flow),
                       None if normal_only is None else as_bool_array(normal_only), None)
        done, twists, covs, refs, skipped = backend.velocity_run(
            self._model(), buf["q_matrix"].numpy(), buf["twist"].numpy()[0],
            buf["cov"].numpy()[0], buf["reference"].numpy()[0],
            np.array([float(dt) for dt in dts], dtype=np.float64), b, rois,
        )
        if done:
            last = done - 1
            self._store(twists[last:done].copy(), covs[last:done].copy(), refs[last:done].copy(),
                        *(int(v) for v in skipped[:done].sum(0)))
        return torch.from_numpy(twists[:done]).unsqueeze(1)

    def _undistorted_rows(self, uv: Tensor, flow: Tensor, normal_only: Tensor | None
                          ) -> tuple[Tensor, Tensor, Tensor]:
        """The rows of :meth:`forward_run` in the ideal pinhole image: ``uv`` (N,2) px and
        ``flow`` (N,2) px/s of the filter's dtype, mapped by
        :func:`~evtrack.filters.interaction.undistort_flow` constraint for constraint, and
        ``normal_only`` (N,) bool (``config.assume_normal`` where ``None``), as :meth:`update`
        maps one step's."""
        kw = {"dtype": self.twist.dtype, "device": self.twist.device}
        if normal_only is None:
            normal_only = torch.full((uv.shape[0],), self.config.assume_normal, dtype=torch.bool,
                                     device=kw["device"])
        uv, flow = undistort_flow(self.camera, uv.to(**kw), flow.to(**kw), normal_only,
                                  self._undistortion)
        return uv, flow, normal_only

    # ------------------------------------------------------------------ single track (B = 1)
    # Buffers are read from and written to ``_buffers`` directly: nn.Module's attribute
    # access and assignment cost ~1 and ~3 µs per buffer, as much as the arithmetic here.
    def _model(self) -> VelocityModel:
        """The constants of the update as a backend takes them."""
        buf = self._buffers
        return VelocityModel(self.config, buf["consts"].tolist(), buf["focal"].numpy(),
                             buf["principal"].numpy())

    def _predicted(self, backend: FilterBackend, dt: float | Tensor
                   ) -> tuple[np.ndarray, np.ndarray]:
        """The one track's predicted (6,) twist and (6,6) covariance (buffers unchanged)."""
        buf = self._buffers
        return backend.velocity_predict(
            buf["twist"].numpy()[0],
            buf["cov"].numpy()[0],
            self._single_dt(dt),
            buf["consts"].tolist()[0],
            buf["q_matrix"].numpy(),
        )

    def _update_single(
        self,
        backend: FilterBackend,
        uv: Tensor,
        depth: Tensor,
        flow: Tensor,
        normal_only: Tensor | None,
        mask: Tensor | None,
        prior: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> Tensor:
        """:meth:`update` of one float64 CPU track on ``backend``; ``prior``: the (6,) twist
        and (6,6) covariance to update instead of the buffers' (a predict not yet stored)."""
        self._check_inputs(uv, depth, flow, normal_only, mask)
        if self.camera.dist is not None:
            uv, depth, flow, normal_only, mask = self._inputs(uv, depth, flow, normal_only, mask)
            uv, flow = undistort_flow(self.camera, uv, flow, normal_only, self._undistortion)
        buf = self._buffers
        twist, cov = prior if prior is not None else (buf["twist"].numpy()[0],
                                                       buf["cov"].numpy()[0])
        rois = RoiRows(
            as_array(uv)[0],
            as_array(depth)[0],
            as_array(flow)[0],
            None if normal_only is None else as_bool_array(normal_only)[0],
            None if mask is None else as_bool_array(mask)[0],
        )
        twist, cov, skipped_depth, skipped_flow = backend.velocity_update(
            self._model(), twist, cov, buf["reference"].numpy()[0], rois
        )
        V = twist[None]
        self._store(V, cov[None], V, skipped_depth, skipped_flow)
        return buf["twist"]

    def _store(self, twist: np.ndarray, cov: np.ndarray, reference: np.ndarray,
               skipped_depth: int, skipped_flow: int) -> None:
        """Store one track's posterior, twist (1,6), cov (1,6,6), reference (1,6) (the same
        array as ``twist`` gives the same tensor), and add to the skip counters."""
        buf = self._buffers
        V = torch.from_numpy(twist)
        buf.update(twist=V, cov=torch.from_numpy(cov),
                   reference=V if reference is twist else torch.from_numpy(reference))
        if skipped_depth or skipped_flow:
            buf.update(
                skipped_depth=buf["skipped_depth"] + skipped_depth,
                skipped_flow=buf["skipped_flow"] + skipped_flow,
            )

    @property
    def skipped_measurements(self) -> Tensor:
        """(B,) RoIs skipped so far for a bad depth or a bad flow."""
        return self.skipped_depth + self.skipped_flow

    # ------------------------------------------------------------------ functional core
    def predict_state(self, twist: Tensor, cov: Tensor, dt: Tensor) -> tuple[Tensor, Tensor]:
        """Pure predict: twist (B,6), cov (B,6,6), dt (B,) seconds -> (twist, cov)."""
        decay = torch.exp(dt * self.consts[0])  # alpha ** (dt / alpha_dt)
        twist = twist * decay.unsqueeze(-1)
        # P = a² P + Q dt
        cov = cov * (decay * decay)[:, None, None] + dt[:, None, None] * self.q_matrix
        return twist, cov

    def update_state(
        self,
        twist: Tensor,
        cov: Tensor,
        reference: Tensor,
        uv: Tensor,
        depth: Tensor,
        flow: Tensor,
        normal_only: Tensor,
        mask: Tensor,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Pure update in ideal pinhole pixels; no Python branches on tensor values.

        Args:
            twist: (B, 6) the prior twist.
            cov: (B, 6, 6) the prior covariance.
            reference: (B, 6) the twist the first weighting pass compares flows with (used
                when ``weighting_reference == "previous"``).
            uv: (B, N, 2) RoI pixel coordinates (ideal pinhole), px.
            depth: (B, N) depths at the RoIs, m.
            flow: (B, N, 2) RoI flows, px/s.
            normal_only: (B, N) bool, True where a RoI's flow is normal-only.
            mask: (B, N) bool, False on padding.

        Returns:
            ``(twist, cov, skipped (B,2))``, ``skipped`` counting this update's RoIs skipped
            for a bad depth (column 0) and for a bad flow or pixel (column 1).
        """
        H, z, rows_ok, skipped = measurement_rows(
            uv, depth, flow, normal_only, mask, self.focal, self.principal, self.config.normal_flow
        )
        V, P = weighted_update(self.config, self.consts, twist, cov, reference, H, z, rows_ok,
                               normal_only)
        return V, P, skipped

    def step(
        self,
        twist: Tensor,
        cov: Tensor,
        reference: Tensor,
        dt: Tensor,
        uv: Tensor,
        depth: Tensor,
        flow: Tensor,
        normal_only: Tensor,
        mask: Tensor,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Pure predict + update (the step exported to ONNX); returns ``(twist, cov, skipped)``.

        The new ``reference`` is the returned twist (the posterior).
        """
        twist, cov = self.predict_state(twist, cov, dt)
        return self.update_state(twist, cov, reference, uv, depth, flow, normal_only, mask)

    # ------------------------------------------------------------------ input handling
    def _check_inputs(
        self,
        uv: Tensor,
        depth: Tensor,
        flow: Tensor,
        normal_only: Tensor | None,
        mask: Tensor | None,
    ) -> None:
        """Raise ValueError unless the shapes (and the bool flags' dtype) fit :meth:`update`."""
        B = self._buffers["twist"].shape[0]
        if depth.ndim != 2 or depth.shape[0] != B:
            raise ValueError(
                f"VelocityKF.update: depth must be (B={B}, N), got {tuple(depth.shape)}"
            )
        N = depth.shape[1]
        for name, t in (("uv", uv), ("flow", flow)):
            if t.shape != (B, N, 2):
                raise ValueError(
                    f"VelocityKF.update: {name} must be ({B}, {N}, 2), got {tuple(t.shape)}"
                )
        for name, t in (("normal_only", normal_only), ("mask", mask)):
            if t is not None and (t.shape != (B, N) or t.dtype is not torch.bool):
                raise ValueError(
                    f"VelocityKF.update: {name} must be a ({B}, {N}) bool tensor, "
                    f"got {tuple(t.shape)} {t.dtype}"
                )

    def _inputs(
        self,
        uv: Tensor,
        depth: Tensor,
        flow: Tensor,
        normal_only: Tensor | None,
        mask: Tensor | None,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        self._check_inputs(uv, depth, flow, normal_only, mask)
        B, N = depth.shape
        kw = {"dtype": self.twist.dtype, "device": self.twist.device}
        dev = self.twist.device
        if normal_only is None:
            normal_only = torch.full(
                (B, N), self.config.assume_normal, dtype=torch.bool, device=dev
            )
        if mask is None:
            mask = torch.ones(B, N, dtype=torch.bool, device=dev)
        return uv.to(**kw), depth.to(**kw), flow.to(**kw), normal_only.to(dev), mask.to(dev)

