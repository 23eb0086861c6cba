"""Every registered backend (:func:`evtrack.filters.backends.backend_names`; a new one is
picked up here) runs the filters' steps as the torch specification does: to 1e-12 step by
step (in the covariance's metric for the velocity filter), the skip and rejection counters
exactly; a backend with runs gives its single steps' results bit for bit."""

from __future__ import annotations

import pytest
import torch
from filter_helpers import (
    CAM,
    F64,
    TOL,
    VELOCITY_CASES,
    BiasedPoseUKF,
    close,
    close_gaussian,
    flows,
    gaussian_error,
    play,
    pose_script,
    run_rows,
)

from evtrack.camera import PinholeCamera
from evtrack.filters import PoseTwistUKF, PoseUKF, VelocityKF, VelocityKFConfig
from evtrack.filters.backends import TORCH, backend_names, get_backend, single_track_backends


@pytest.fixture(params=backend_names())
def backend(request: pytest.FixtureRequest) -> str:
    """Each registered backend's name (skipped where it cannot run here)."""
    name = request.param
    chosen = get_backend(name)
    if name != TORCH and (chosen is None or chosen.name != name):
        pytest.skip(f"the {name} backend cannot run here")
    return name


@pytest.fixture(params=[b.name for b in single_track_backends() if b.runs])
def runs_backend(request: pytest.FixtureRequest) -> str:
    """Each registered backend with runs of many steps per call (skipped where it cannot run
    here)."""
    chosen = get_backend(request.param)
    if chosen is None or chosen.name != request.param:
        pytest.skip(f"the {request.param} backend cannot run here")
    return request.param


def _expected(backend: str, **counts: int) -> dict[str, int]:
    """The backend calls a script makes: none on the torch backend."""
    return {} if backend == TORCH else {f"{backend}.{k}": v for k, v in counts.items() if v}


# ---------------------------------------------------------------------------- VelocityKF
@pytest.mark.parametrize(
    ("cfg", "kind", "strict"), [c[1:] for c in VELOCITY_CASES], ids=[c[0] for c in VELOCITY_CASES]
)
def test_velocity_steps_equal_torch(
    cfg: VelocityKFConfig, kind: str, strict: bool, calls: dict, backend: str
) -> None:
    g = torch.Generator().manual_seed(0)
    kf, ref = VelocityKF(CAM, 1, cfg, backend=backend), VelocityKF(CAM, 1, cfg, fast_path=False)
    nudged = VelocityKF(CAM, 1, cfg, fast_path=False)  # the torch path, flows 1 ulp larger
    errors, sensitivity = [], []
    for i in range(12):
        for f in (kf, nudged):  # each step from the same state
            f.load_state_dict(ref.state_dict())
        uv, depth, flow, normal = flows(g, 60 + 17 * i, kind)
        mask = torch.rand(depth.shape, generator=g) < 0.9 if i % 3 == 1 else None
        flags = None if i % 4 == 2 else normal
        dt = 1e-3 if i % 2 else torch.tensor([2e-3], dtype=F64)
        for f in (kf, ref):
            out = f(dt, uv, depth, flow, flags, mask)
            assert out is f.twist and f.reference is f.twist
        nudged(dt, uv, depth, flow * (1 + 2.0**-52), flags, mask)
        errors.append(gaussian_error(kf, ref))
        sensitivity.append(gaussian_error(nudged, ref))
        assert torch.equal(kf.cov, kf.cov.transpose(-1, -2))
        assert torch.equal(kf.skipped_depth, ref.skipped_depth)
        assert torch.equal(kf.skipped_flow, ref.skipped_flow)
    tol = TOL if strict else max(TOL, 4 * max(sensitivity))
    assert max(errors) <= tol, (
        f"errors {max(errors):.1e}, torch's own 1-ulp move {max(sensitivity):.1e}"
    )
    assert calls == _expected(backend, velocity_predict=12, velocity_update=12)
    assert int(kf.skipped_depth[0]) > 0 or "+bad" not in kind


def test_velocity_inputs_of_other_dtypes_and_no_valid_rois(calls: dict, backend: str) -> None:
    g = torch.Generator().manual_seed(1)
    uv, depth, flow, normal = flows(g, 40, "mixed")
    kf, ref = VelocityKF(CAM, 1, backend=backend), VelocityKF(CAM, 1, fast_path=False)
    for f in (kf, ref):  # float32 inputs are converted as the torch path does
        f(1e-3, uv.float(), depth.float(), flow.float(), normal)
        f(1e-3, uv, torch.full_like(depth, float("nan")), flow, normal)  # nothing usable
    close_gaussian(kf, ref, "float32 inputs, then no usable RoI")
    assert kf.skipped_depth.tolist() == ref.skipped_depth.tolist() == [40]
    assert calls == _expected(backend, velocity_predict=2, velocity_update=2)


def test_velocity_distorted_camera(backend: str) -> None:
    cam = PinholeCamera(500.0, 480.0, 330.0, 250.0, 640, 480, dist=[-0.2, 0.05, 1e-3, -1e-3])
    g = torch.Generator().manual_seed(2)
    uv, depth, flow, normal = flows(g, 50, "mixed")
    kf, ref = VelocityKF(cam, 1, backend=backend), VelocityKF(cam, 1, fast_path=False)
    for f in (kf, ref):
        f(1e-3, 0.8 * (uv - 300) + 300, depth, flow, normal)
    close_gaussian(kf, ref, "distorted camera")


@pytest.mark.parametrize("call", ["update", "forward"])
def test_velocity_covariance_not_positive_definite_falls_back_to_torch(
    calls: dict, backend: str, call: str
) -> None:
    """A prior that is not positive definite: the backend's update raises inside, the torch
    update runs from the same (predicted) state and gives its NaNs, as the torch path."""
    g = torch.Generator().manual_seed(3)
    uv, depth, flow, normal = flows(g, 30, "mixed")
    bad = -100 * torch.eye(6, dtype=F64)[None]  # stays indefinite through a 1 ms predict
    kf, ref = VelocityKF(CAM, 1, backend=backend), VelocityKF(CAM, 1, fast_path=False)
    for f in (kf, ref):
        f.reset(cov=bad)
        if call == "update":
            f.update(uv, depth, flow, normal)
        else:
            f(1e-3, uv, depth, flow, normal)
    # tried once, then torch
    assert calls == _expected(backend, velocity_update=1, velocity_predict=call == "forward")
    torch.testing.assert_close(kf.cov, ref.cov, equal_nan=True, rtol=0, atol=0)
    torch.testing.assert_close(kf.twist, ref.twist, equal_nan=True, rtol=0, atol=0)


def test_pivot_noise_equals_torch(backend: str) -> None:
    kf, ref = VelocityKF(CAM, backend=backend), VelocityKF(CAM, fast_path=False)
    g = torch.Generator().manual_seed(1)
    for _ in range(20):
        p = torch.randn(3, generator=g, dtype=torch.float64)
        kf.set_pivot(p)
        ref.set_pivot(p)
        assert torch.equal(kf.q_matrix, kf.q_matrix.T)
        torch.testing.assert_close(kf.q_matrix, ref.q_matrix, rtol=1e-14, atol=1e-12)


# ---------------------------------------------------------------------------- pose filters
@pytest.mark.parametrize("cls", [PoseUKF, PoseTwistUKF, BiasedPoseUKF],
                         ids=["PoseUKF", "PoseTwistUKF", "PoseUKF-velocity-bias"])
def test_pose_steps_equal_torch(cls: type, calls: dict, backend: str) -> None:
    g = torch.Generator().manual_seed(5)
    steps = pose_script(g)
    filt, ref = cls(1, backend=backend), cls(1, fast_path=False)
    names = ("t", "q", "cov") + {PoseTwistUKF: ("twist",), BiasedPoseUKF: ("bias",)}.get(cls, ())
    counters = ("initialized", "rejected_run", "rejected", "reinitialised")
    # Each step from the same state: play the script on the reference, and replay every step
    # on the backend's filter from the reference's state before it.
    for k, step in enumerate(steps):
        filt.load_state_dict(ref.state_dict())
        used = []
        for f in (filt, ref):
            play(f, [step], used.append)
        for name in names:
            close(getattr(filt, name), getattr(ref, name), f"step {k} {name}")
        for name in counters:
            assert torch.equal(getattr(filt, name), getattr(ref, name)), f"step {k} {name}"
        if used:
            assert torch.equal(used[0], used[1]), f"step {k} used"
    assert int(ref.reinitialised[0]) == 1 and int(ref.rejected[0]) >= 6
    n_updates = sum(s[0] == "update" for s in steps)
    twist_driven = len(steps) - n_updates if issubclass(cls, PoseUKF) else 0
    if cls is BiasedPoseUKF:  # the updates moved the bias, and the predicts used it
        assert float(ref.bias.abs().max()) > 1e-3
    assert calls == _expected(backend, pose_update=n_updates, pose_predict=twist_driven)


# ---------------------------------------------------------------------------- runs
@pytest.mark.parametrize(
    "cfg", [c[1] for c in VELOCITY_CASES], ids=[c[0] for c in VELOCITY_CASES]
)
@pytest.mark.parametrize("flags", [True, False], ids=["normal flags", "assumed"])
def test_forward_run_equals_forward_calls_bit_for_bit(
    cfg: VelocityKFConfig, flags: bool, runs_backend: str
) -> None:
    """``forward_run`` equals ``forward`` per step (``predict`` for a step without rows):
    every step's twist, the final twist, covariance, reference and skip counters, exactly;
    with a pivot's process noise and uneven steps."""
    g = torch.Generator().manual_seed(11)
    sizes = [16, 0, 1, 30, 3, 0, 0, 12, 9, 25]
    dts = [1e-3, 1e-3, 2.5e-4, 1e-3, 3e-3, 1e-3, 1e-6, 1e-3, 7e-4, 1e-3]
    uv, depth, flow, normal = run_rows(g, sizes)
    bounds = [0, *torch.tensor(sizes).cumsum(0).tolist()]
    run, ref = (VelocityKF(CAM, 1, cfg, backend=runs_backend) for _ in range(2))
    for kf in (run, ref):
        kf.set_pivot(torch.tensor([0.05, -0.02, 0.7], dtype=F64))
        kf(1e-3, *(x[None, :8] for x in (uv, depth, flow)), normal[None, :8])  # a history
    twists = run.forward_run(dts, bounds, uv, depth, flow, normal if flags else None)
    assert twists is not None and twists.shape == (len(dts), 1, 6)
    for k, dt in enumerate(dts):
        lo, hi = bounds[k], bounds[k + 1]
        if hi == lo:
            want = ref.predict(dt)
        else:
            want = ref(dt, uv[None, lo:hi], depth[None, lo:hi], flow[None, lo:hi],
                       normal[None, lo:hi] if flags else None)
        assert torch.equal(twists[k], want), k
    for name in ("twist", "cov", "reference", "skipped_depth", "skipped_flow"):
        assert torch.equal(getattr(run, name), getattr(ref, name)), name
    assert int(run.skipped_depth) > 0 and int(run.skipped_flow) > 0  # the bad RoIs counted


def test_forward_run_stops_before_a_step_it_cannot_do(runs_backend: str) -> None:
    """An update whose prior is not positive definite: the run stops before it, holding the
    state after the steps before; ``forward`` on that step then goes through torch."""
    g = torch.Generator().manual_seed(12)
    uv, depth, flow, normal = run_rows(g, [0, 0, 6])
    kf, ref = (VelocityKF(CAM, 1, backend=runs_backend) for _ in range(2))
    for f in (kf, ref):
        f.reset(cov=-1e6 * torch.eye(6, dtype=F64)[None])
    twists = kf.forward_run([1e-3, 1e-3, 1e-3], [0, 0, 0, 6], uv, depth, flow, normal)
    assert twists is not None and twists.shape == (2, 1, 6)
    ref.predict(1e-3)
    ref.predict(1e-3)
    assert torch.equal(kf.cov, ref.cov) and torch.equal(kf.twist, ref.twist)


@pytest.mark.parametrize("cls", [PoseUKF, BiasedPoseUKF], ids=["PoseUKF", "velocity-bias"])
def test_predict_run_equals_predict_calls_bit_for_bit(cls: type, runs_backend: str) -> None:
    g = torch.Generator().manual_seed(13)
    run, ref = cls(1, backend=runs_backend), cls(1, backend=runs_backend)
    for f in (run, ref):
        f.update(torch.tensor([[0.1, -0.05, 0.6]], dtype=F64),
                 torch.tensor([[0.9, 0.1, -0.2, 0.3]], dtype=F64))
        f.update(f.t + 0.01, f.q)  # a fused pose: a bias moves
    twists = [3 * torch.randn(1, 6, generator=g, dtype=F64) for _ in range(15)]
    dts = [1e-3 * (1 + k % 4) for k in range(15)]
    states = run.predict_run(twists, dts)
    assert states is not None
    for k, (twist, dt) in enumerate(zip(twists, dts, strict=True)):
        ref.predict(twist, dt)
        for got, want in zip(states, (ref.t, ref.q, ref.cov), strict=True):
            assert torch.equal(got[k], want), k
    for name in ("t", "q", "cov"):
        assert torch.equal(getattr(run, name), getattr(ref, name)), name
