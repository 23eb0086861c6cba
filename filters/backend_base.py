"""The interface of the filters' single-track backends: one track's steps on NumPy arrays.

The torch modules (:class:`~evtrack.filters.VelocityKF`, :class:`~evtrack.filters.PoseUKF`,
:class:`~evtrack.filters.PoseTwistUKF`) are the specification: any batch, device and dtype,
gradients, ``torch.compile`` and ONNX export. A tracker steps one float64 track on CPU about a
thousand times a second, where a torch step costs the dispatch of ~150 tiny ops rather than
arithmetic; a backend runs the same model for that one track (B = 1) on float64 NumPy arrays
and Python floats. Backends are registered by name in :mod:`backends`, which also decides
which one runs a call.

Shapes drop the batch dimension unless stated: a twist ``[v_o (m/s), ω (rad/s)]`` is (6,), a
covariance (n, n), the RoI inputs (N, 2) and (N,). Quaternions are wxyz. A 6x6 (or n x n)
matrix that is not positive definite raises ``numpy.linalg.LinAlgError``, on which the
filters rerun the step in torch (which returns its NaNs instead of raising).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar, NamedTuple

import numpy as np

from evtrack.filters.config import VelocityKFConfig

__all__ = ["FilterBackend", "PoseUpdate", "RoiRows", "VelocityModel"]


class VelocityModel(NamedTuple):
    """The constants of a velocity filter's update, as one track's backend takes them.

    Attributes:
        config: the filter's config.
        consts: the filter's ``consts`` buffer as floats ``[ln(alpha)/alpha_dt (1/s),
            1/σ_F² ((px/s)⁻²), b or 0 (px/s), b_min (px/s), floor, 1/σ_N² ((px/s)⁻²)]``
            (``σ_N``: the noise of a normal-only row).
        focal: (2,) ``[fx, fy]`` px.
        principal: (2,) ``[cx, cy]`` px.
    """

    config: VelocityKFConfig
    consts: list[float]
    focal: np.ndarray
    principal: np.ndarray


class RoiRows(NamedTuple):
    """One track's RoI measurements of a velocity update.

    Attributes:
        uv: (N, 2) ideal pinhole pixels. depth: (N,) m. flow: (N, 2) px/s.
        normal_only: (N,) bool, or ``None`` (``config.assume_normal`` everywhere).
        mask: (N,) bool, or ``None`` (all True).
    """

    uv: np.ndarray
    depth: np.ndarray
    flow: np.ndarray
    normal_only: np.ndarray | None
    mask: np.ndarray | None


class PoseUpdate(NamedTuple):
    """The result of a backend's gated pose update (one track)."""

    t: tuple[float, float, float]  # m
    q: tuple[float, float, float, float]  # wxyz, unit
    extra: np.ndarray  # (k,) further state (the twist of PoseTwistUKF, a velocity bias), or (0,)
    cov: np.ndarray  # (n, n)
    initialized: bool
    rejected_run: int
    used: bool
    rejected: int
    reinitialised: int


class FilterBackend(ABC):
    """One track's float64 steps of the filters, equal to the torch steps to rounding.

    Subclasses set :attr:`name` (the key of the registry in :mod:`backends`) and, if they
    implement :meth:`velocity_run` and :meth:`pose_predict_run`, :attr:`runs`.
    """

    name: ClassVar[str]
    #: Whether :meth:`velocity_run` and :meth:`pose_predict_run` are implemented: many steps
    #: in one call, bit for bit the results of the single steps of this backend.
    runs: ClassVar[bool] = False

    def available(self) -> bool:
        """Whether this backend can run here (its dependencies are installed)."""
        return True

    # ------------------------------------------------------------------ VelocityKF
    @abstractmethod
    def velocity_predict(
        self, twist: np.ndarray, cov: np.ndarray, dt: float, log_rate: float,
        q_matrix: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """``V' = a V``, ``P' = a² P + Q dt`` with ``a = exp(dt · log_rate)``.

        Args:
            twist: (6,). cov: (6, 6). dt: seconds. log_rate: ``ln(alpha)/alpha_dt`` (1/s).
            q_matrix: (6, 6) process-noise density.

        Returns:
            The predicted twist (6,) and covariance (6, 6), new arrays.
        """

    @abstractmethod
    def velocity_update(
        self, model: VelocityModel, twist: np.ndarray, cov: np.ndarray, reference: np.ndarray,
        rois: RoiRows,
    ) -> tuple[np.ndarray, np.ndarray, int, int]:
        """The weighted information-form update of :meth:`VelocityKF.update_state`.

        Args:
            model: the filter's constants. twist (6,), cov (6, 6): the prior.
            reference: (6,) the last posterior twist (the weighting's reference).
            rois: the RoI measurements.

        Returns:
            ``(twist (6,), cov (6, 6), skipped_depth, skipped_flow)``: the posterior and this
            update's counts of RoIs skipped for a bad depth and for a bad flow or pixel.

        Raises:
            numpy.linalg.LinAlgError: if a 6x6 matrix is not positive definite.
        """

    def velocity_run(
        self, model: VelocityModel, q_matrix: np.ndarray, twist: np.ndarray, cov: np.ndarray,
        reference: np.ndarray, dts: np.ndarray, bounds: np.ndarray, rois: RoiRows,
    ) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``n`` steps of :meth:`velocity_predict` then :meth:`velocity_update` in one call
        (only where :attr:`runs`).

        Args:
            model: the filter's constants. q_matrix: (6, 6) process-noise density.
            twist (6,), cov (6, 6), reference (6,): the state before the first step.
            dts: (n,) seconds. bounds: (n+1,) non-decreasing row offsets; step ``k`` updates
                with rows ``bounds[k]:bounds[k+1]`` of ``rois`` (none: predict only).
            rois: the rows of all the steps (``mask`` ``None``).

        Returns:
            ``(done, twists (n, 6), covs (n, 6, 6), references (n, 6), skipped (n, 2))``: the
            states after each of the first ``done`` steps; ``done < n`` when the update of step
            ``done`` met a 6x6 matrix that is not positive definite (nothing of it is kept).
        """
        raise NotImplementedError(f"the {self.name} backend runs single steps only")

    @abstractmethod
    def pivot_noise(self, q_density: np.ndarray, pivot: np.ndarray) -> np.ndarray:
        """The process-noise density ``A diag(q) Aᵀ`` about a pivot (see
        :meth:`VelocityKF.set_pivot`): ``q_density`` (6,), ``pivot`` (3,) m -> (6, 6)."""

    # ------------------------------------------------------------------ pose filters
    @abstractmethod
    def pose_predict(
        self, t: np.ndarray, q: np.ndarray, cov: np.ndarray, twist: np.ndarray, dt: float,
        q_matrix: np.ndarray, bias: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The closed-form unscented predict of :meth:`PoseUKF.predict_state`, on one track's
        arrays with their batch dimension.

        Args:
            t: (1, 3) m. q: (1, 4) wxyz. cov: (1, n, n). twist: (1, 6) ``[v_o, ω]``.
            dt: seconds. q_matrix: (n, n) process-noise density.
            bias: (1, 3) the velocity bias (m/s per m/s) of a filter with one (n = 9), else
                ``None`` (n = 6).

        Returns:
            New float64 arrays ``(t (1, 3), q (1, 4), cov (1, n, n))``.
        """

    def pose_predict_run(
        self, t: np.ndarray, q: np.ndarray, cov: np.ndarray, twists: np.ndarray,
        dts: np.ndarray, q_matrix: np.ndarray, bias: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`pose_predict` for ``m`` steps in one call (only where :attr:`runs`):
        ``twists`` (m, 6), ``dts`` (m,) s; returns the states after each step, ``t``
        (m, 1, 3), ``q`` (m, 1, 4), ``cov`` (m, 1, n, n)."""
        raise NotImplementedError(f"the {self.name} backend runs single steps only")

    @abstractmethod
    def pose_update(
        self, t: tuple[float, ...], q: tuple[float, ...], extra: np.ndarray, cov: np.ndarray,
        initialized: bool, rejected_run: int, t_meas: tuple[float, ...],
        q_meas: tuple[float, ...], R: np.ndarray, valid: bool, gate: float, reinit_after: int,
    ) -> PoseUpdate:
        """The gated closed-form pose update of :meth:`PoseUKF.update_pose_state`.

        Args:
            t: 3 floats, m. q: 4 floats, wxyz. extra: (k,) the state beyond the pose.
            cov: (n, n), n = 6 + k. initialized: whether the track has had a pose.
            rejected_run: poses rejected in a row so far. t_meas, q_meas: the measured pose
                (q_meas of either sign, not necessarily normalised). R: (6, 6) its tangent
                covariance (m², rad²). valid: False for a missing pose. gate: the χ² gate of
                ``νᵀ S⁻¹ ν``. reinit_after: rejections in a row after which the next rejected
                pose is taken.

        Raises:
            numpy.linalg.LinAlgError: if ``S`` is not positive definite.
        """
