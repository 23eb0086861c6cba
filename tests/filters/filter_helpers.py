"""Inputs and comparisons shared by the backend tests: RoI flows with bad RoIs, a script of
pose predicts and updates touching every branch, errors in a covariance's metric."""

from __future__ import annotations

import math

import torch

from evtrack.camera import PinholeCamera
from evtrack.filters import (
    PoseTwistUKF,
    PoseUKF,
    PoseUKFConfig,
    VelocityKF,
    VelocityKFConfig,
    interaction_matrix,
)

F64 = torch.float64
CAM = PinholeCamera(500.0, 480.0, 330.0, 250.0, 640, 480)
TOL = 1e-12

# (name, config, flows, strict): strict cases must agree to TOL; in the others the Laplacian
# weights are steep enough (|r − M|/b up to ~100) that the torch path itself moves by ~1e-12
# when its flows change by one ulp, and a backend must stay within 4x that movement.
VELOCITY_CASES = [
    ("default", VelocityKFConfig(), "mixed+bad", True),
    ("all normal", VelocityKFConfig(), "normal", True),
    ("all full", VelocityKFConfig(), "full+bad", True),
    ("no normal-flow constraint", VelocityKFConfig(normal_flow=False), "mixed+bad", True),
    ("no weighting", VelocityKFConfig(weighting=False), "mixed+bad", True),
    (
        "predicted reference, 3 passes",
        VelocityKFConfig(weighting_reference="predicted", weighting_iterations=3),
        "mixed",
        False,
    ),
    ("fixed scale", VelocityKFConfig(laplace_scale=20.0), "mixed+bad", False),
    ("normal rows' own noise", VelocityKFConfig(normal_flow_std=15.0), "mixed+bad", True),
]


def close(got: torch.Tensor, want: torch.Tensor, what: str) -> None:
    """Max-abs error relative to the largest entry, at most :data:`TOL`."""
    assert got.shape == want.shape and got.dtype == want.dtype, what
    scale = want.abs().max().clamp_min(1e-300)
    err = float((got - want).abs().max() / scale)
    assert err <= TOL, f"{what}: relative error {err:.1e}"


def gaussian_error(kf: VelocityKF, ref: VelocityKF) -> float:
    """How far ``kf``'s twist and covariance are from ``ref``'s, in the metric of the
    reference covariance ``P = L Lᵀ``: the larger of ``|L⁻¹ δV| / |L⁻¹ V|`` and
    ``max |L⁻¹ δP L⁻ᵀ|`` (a plain relative error of ``P = Λ⁻¹`` would multiply every
    difference of the information by the condition number, 1e2-1e4 here)."""
    L = torch.linalg.cholesky(ref.cov[0])
    dV = torch.linalg.solve_triangular(L, (kf.twist - ref.twist)[0, :, None], upper=False)
    V = torch.linalg.solve_triangular(L, ref.twist[0, :, None], upper=False)
    half = torch.linalg.solve_triangular(L, kf.cov[0] - ref.cov[0], upper=False)
    dP = torch.linalg.solve_triangular(L, half.T, upper=False)
    return max(float(dV.norm() / V.norm().clamp_min(1e-300)), float(dP.abs().max()))


def close_gaussian(kf: VelocityKF, ref: VelocityKF, what: str, tol: float = TOL) -> None:
    assert kf.twist.dtype == ref.twist.dtype and kf.cov.shape == ref.cov.shape, what
    err = gaussian_error(kf, ref)
    assert err <= tol, f"{what}: error {err:.1e} > {tol:.0e}"


def flows(g: torch.Generator, N: int, kind: str) -> tuple[torch.Tensor, ...]:
    """RoIs seeing a rigid motion plus noise and outliers; ``kind`` picks the normal flags and
    sprinkles bad RoIs (missing/zero/negative/inf depth, NaN flow, inf pixel, zero flows)."""
    uv = torch.rand(1, N, 2, generator=g, dtype=F64) * torch.tensor([640.0, 480.0], dtype=F64)
    depth = 0.4 + 0.8 * torch.rand(1, N, generator=g, dtype=F64)
    twist = torch.randn(1, 6, generator=g, dtype=F64)
    flow = (interaction_matrix(uv, depth, CAM) @ twist[:, None, :, None]).squeeze(-1)
    flow = flow + 5 * torch.randn(1, N, 2, generator=g, dtype=F64)
    flow[0, : N // 5] = 300 * torch.randn(N // 5, 2, generator=g, dtype=F64)
    normal = {
        "mixed": torch.rand(1, N, generator=g) < 0.5,
        "normal": torch.ones(1, N, dtype=torch.bool),
        "full": torch.zeros(1, N, dtype=torch.bool),
    }[kind.split("+")[0]]
    if "+bad" in kind:
        depth[0, 1], depth[0, 2], depth[0, 3], depth[0, 4] = math.nan, 0.0, -1.0, math.inf
        flow[0, 5, 0] = math.nan
        uv[0, 6, 1] = math.inf
        flow[0, 7] = 0.0  # a zero flow: skipped if normal-only, image axes if full
        flow[0, 8] = 0.0
        normal[0, 7], normal[0, 8] = True, False
    return uv, depth, flow, normal


def run_rows(g: torch.Generator, sizes: list[int]) -> tuple[torch.Tensor, ...]:
    """The rows of steps of ``sizes`` RoIs each, one after the other (bad RoIs included)."""
    parts = [flows(g, max(n, 10), "mixed+bad") for n in sizes]
    return tuple(torch.cat([p[i][0, :n] for p, n in zip(parts, sizes, strict=True)])
                 for i in range(4))


def pose_script(g: torch.Generator) -> list:
    """A script of predicts and updates touching every branch: first pose, fusion, an outlier
    run ending in a re-initialisation, missing and non-finite poses, either quaternion sign,
    default / (6,6) / (1,6,6) covariances, rest, tiny and large rotations."""
    steps: list = []
    for i in range(40):
        twist = torch.randn(1, 6, generator=g, dtype=F64) * (3.0 if i % 5 else 0.0)
        if i == 7:
            twist[0, 3:] = 1e-25  # below the exp's small-angle switch
        if i == 9:
            twist[0, 3:] = torch.tensor([300.0, -200.0, 100.0])  # ~0.4 rad per ms
        steps.append(("predict", twist, 1e-3 if i % 3 else torch.tensor([5e-3], dtype=F64)))
        if i % 2:
            continue
        noise = 0.01 * torch.randn(1, 7, generator=g, dtype=F64)
        outlier = 5.0 if 16 <= i <= 26 else 0.0  # 6 rejections in a row: re-initialise
        cov = [None, 2e-4 * torch.eye(6, dtype=F64), 3e-4 * torch.eye(6, dtype=F64)[None]][i % 3]
        valid = None if i % 7 else torch.tensor([i % 14 == 0])
        sign = -1.0 if i % 4 == 0 else 1.0
        t_off = noise[:, :3] + outlier
        if i == 30:
            t_off = t_off * math.nan
        steps.append(("update", t_off, noise[:, 3:], sign, cov, valid))
    return steps


def play(filt: PoseUKF | PoseTwistUKF, steps: list, check) -> None:  # noqa: ANN001
    """Run the steps of :func:`pose_script` on ``filt``; ``check`` gets each update's result."""
    for step in steps:
        if step[0] == "predict":
            if isinstance(filt, PoseUKF):
                filt.predict(step[1], step[2])
            else:
                filt.predict(step[2])
        else:
            _, t_off, q_off, sign, cov, valid = step
            q = sign * (filt.q + q_off)
            check(filt.update(filt.t + t_off, q, cov, valid))


class BiasedPoseUKF(PoseUKF):
    """A PoseUKF with a velocity bias in its state (``bias``, a 9x9 covariance)."""

    def __init__(self, batch_size: int = 1, fast_path: bool = True, backend: str = "auto"
                 ) -> None:
        cfg = PoseUKFConfig(velocity_bias=True, init_std_velocity_bias=0.3)
        super().__init__(batch_size, cfg, fast_path=fast_path, backend=backend)
