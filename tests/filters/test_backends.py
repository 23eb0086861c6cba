"""The single-track fast path (NumPy) equals the torch steps to 1e-12, step by step, and is
taken exactly when it applies."""

from __future__ import annotations

import math

import pytest
import torch

import evtrack.filters.fast_path as fp
from evtrack.camera import PinholeCamera
from evtrack.filters import (
    PoseTwistUKF,
    PoseUKF,
    PoseUKFConfig,
    VelocityKF,
    VelocityKFConfig,
    interaction_matrix,
)
from evtrack.filters.lie import quat_exp

F64 = torch.float64
CAM = PinholeCamera(500.0, 480.0, 330.0, 250.0, 640, 480)
TOL = 1e-12


def _close(got: torch.Tensor, want: torch.Tensor, what: str) -> None:
    """Max-abs error relative to the largest entry."""
    assert got.shape == want.shape and got.dtype == want.dtype, what
    scale = want.abs().max().clamp_min(1e-300)
    err = float((got - want).abs().max() / scale)
    assert err <= TOL, f"{what}: relative error {err:.1e}"


def _gaussian_error(kf: VelocityKF, ref: VelocityKF) -> float:
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


def _close_gaussian(kf: VelocityKF, ref: VelocityKF, what: str, tol: float = TOL) -> None:
    assert kf.twist.dtype == ref.twist.dtype and kf.cov.shape == ref.cov.shape, what
    err = _gaussian_error(kf, ref)
    assert err <= tol, f"{what}: error {err:.1e} > {tol:.0e}"


@pytest.fixture
def calls(monkeypatch: pytest.MonkeyPatch) -> dict[str, int]:
    """Counts the fast-path kernels that run."""
    counts: dict[str, int] = {}
    for name in ("velocity_predict", "velocity_update", "pose_predict", "pose_update"):
        original = getattr(fp, name)

        def counted(*args: object, _f=original, _n=name) -> object:  # noqa: ANN001
            counts[_n] = counts.get(_n, 0) + 1
            return _f(*args)

        monkeypatch.setattr(fp, name, counted)
    original_compiled = fp._compiled.pose_predict

    def counted_compiled(*args: object) -> object:
        counts["compiled_pose_predict"] = counts.get("compiled_pose_predict", 0) + 1
        return original_compiled(*args)

    monkeypatch.setattr(fp._compiled, "pose_predict", counted_compiled)
    return counts


# ---------------------------------------------------------------------------- VelocityKF
@pytest.fixture(params=["compiled", "numpy"])
def update_form(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Runs a test with the compiled (numba) kernels of the fast path (the velocity update,
    the pose predict) and with their NumPy forms."""
    if request.param == "compiled" and not fp._compiled.available():
        pytest.skip("numba is not installed")
    monkeypatch.setattr(fp, "COMPILED", request.param == "compiled")
    return request.param


def _flows(g: torch.Generator, N: int, kind: str) -> tuple[torch.Tensor, ...]:
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


# (name, config, flows, strict): strict cases must agree to TOL; in the others the Laplacian
# weights are steep enough (|r − M|/b up to ~100) that the torch path itself moves by ~1e-12
# when its flows change by one ulp, and the fast path must stay within 4x that movement.
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


@pytest.mark.parametrize(
    ("cfg", "kind", "strict"), [c[1:] for c in VELOCITY_CASES], ids=[c[0] for c in VELOCITY_CASES]
)
def test_velocity_steps_equal_torch(
    cfg: VelocityKFConfig, kind: str, strict: bool, calls: dict, update_form: str
) -> None:
    g = torch.Generator().manual_seed(0)
    fast, ref = VelocityKF(CAM, 1, cfg), VelocityKF(CAM, 1, cfg, fast_path=False)
    nudged = VelocityKF(CAM, 1, cfg, fast_path=False)  # the torch path, flows 1 ulp larger
    errors, sensitivity = [], []
    for i in range(12):
        for kf in (fast, nudged):  # each step from the same state
            kf.load_state_dict(ref.state_dict())
        uv, depth, flow, normal = _flows(g, 60 + 17 * i, kind)
        mask = torch.rand(depth.shape, generator=g) < 0.9 if i % 3 == 1 else None
        flags = None if i % 4 == 2 else normal
        dt = 1e-3 if i % 2 else torch.tensor([2e-3], dtype=F64)
        for kf in (fast, ref):
            out = kf(dt, uv, depth, flow, flags, mask)
            assert out is kf.twist and kf.reference is kf.twist
        nudged(dt, uv, depth, flow * (1 + 2.0**-52), flags, mask)
        errors.append(_gaussian_error(fast, ref))
        sensitivity.append(_gaussian_error(nudged, ref))
        assert torch.equal(fast.cov, fast.cov.transpose(-1, -2))
        assert torch.equal(fast.skipped_depth, ref.skipped_depth)
        assert torch.equal(fast.skipped_flow, ref.skipped_flow)
    tol = TOL if strict else max(TOL, 4 * max(sensitivity))
    assert max(errors) <= tol, (
        f"errors {max(errors):.1e}, torch's own 1-ulp move {max(sensitivity):.1e}"
    )
    assert calls == {"velocity_predict": 12, "velocity_update": 12}
    assert int(fast.skipped_depth[0]) > 0 or "+bad" not in kind


def test_velocity_inputs_of_other_dtypes_and_no_valid_rois(calls: dict, update_form: str) -> None:
    g = torch.Generator().manual_seed(1)
    uv, depth, flow, normal = _flows(g, 40, "mixed")
    fast, ref = VelocityKF(CAM, 1), VelocityKF(CAM, 1, fast_path=False)
    for kf in (fast, ref):  # float32 inputs are converted as the torch path does
        kf(1e-3, uv.float(), depth.float(), flow.float(), normal)
        kf(1e-3, uv, torch.full_like(depth, math.nan), flow, normal)  # nothing usable
    _close_gaussian(fast, ref, "float32 inputs, then no usable RoI")
    assert fast.skipped_depth.tolist() == ref.skipped_depth.tolist() == [40]
    assert calls["velocity_update"] == 2


def test_velocity_distorted_camera(update_form: str) -> None:
    cam = PinholeCamera(500.0, 480.0, 330.0, 250.0, 640, 480, dist=[-0.2, 0.05, 1e-3, -1e-3])
    g = torch.Generator().manual_seed(2)
    uv, depth, flow, normal = _flows(g, 50, "mixed")
    fast, ref = VelocityKF(cam, 1), VelocityKF(cam, 1, fast_path=False)
    for kf in (fast, ref):
        kf(1e-3, 0.8 * (uv - 300) + 300, depth, flow, normal)
    _close_gaussian(fast, ref, "distorted camera")


@pytest.mark.parametrize("call", ["update", "forward"])
def test_velocity_covariance_not_positive_definite_falls_back_to_torch(
    calls: dict, update_form: str, call: str
) -> None:
    """A prior that is not positive definite: the fast update raises inside, the torch
    update runs from the same (predicted) state and gives its NaNs, as the torch path."""
    g = torch.Generator().manual_seed(3)
    uv, depth, flow, normal = _flows(g, 30, "mixed")
    bad = -100 * torch.eye(6, dtype=F64)[None]  # stays indefinite through a 1 ms predict
    fast, ref = VelocityKF(CAM, 1), VelocityKF(CAM, 1, fast_path=False)
    for kf in (fast, ref):
        kf.reset(cov=bad)
        if call == "update":
            kf.update(uv, depth, flow, normal)
        else:
            kf(1e-3, uv, depth, flow, normal)
    assert calls["velocity_update"] == 1  # tried once, then torch
    assert calls.get("velocity_predict", 0) == (call == "forward")
    torch.testing.assert_close(fast.cov, ref.cov, equal_nan=True, rtol=0, atol=0)
    torch.testing.assert_close(fast.twist, ref.twist, equal_nan=True, rtol=0, atol=0)


def test_velocity_fast_path_only_where_it_applies(calls: dict) -> None:
    g = torch.Generator().manual_seed(4)
    uv, depth, flow, normal = _flows(g, 20, "mixed")
    VelocityKF(CAM, 2)(
        1e-3,
        uv.expand(2, -1, -1),
        depth.expand(2, -1),
        flow.expand(2, -1, -1),
        normal.expand(2, -1),
    )
    VelocityKF(CAM, 1).to(torch.float32)(1e-3, uv, depth, flow, normal)
    VelocityKF(CAM, 1, fast_path=False)(1e-3, uv, depth, flow, normal)
    VelocityKF(CAM, 1).compile_steps(backend="eager")(1e-3, uv, depth, flow, normal)
    assert calls == {}
    wants_grad = uv.clone().requires_grad_(True)
    VelocityKF(CAM, 1).update(wants_grad, depth, flow, normal)
    assert calls == {}
    with torch.no_grad():  # no gradients wanted: fast again
        VelocityKF(CAM, 1).update(wants_grad, depth, flow, normal)
    assert calls == {"velocity_update": 1}


def test_velocity_fast_path_checks_inputs() -> None:
    kf = VelocityKF(CAM, 1)
    uv, depth, flow = torch.zeros(1, 4, 2), torch.ones(1, 4), torch.ones(1, 4, 2)
    with pytest.raises(ValueError, match="depth must be"):
        kf.update(uv, torch.ones(2, 4), flow)
    with pytest.raises(ValueError, match="flow must be"):
        kf.update(uv, depth, torch.zeros(1, 5, 2))
    with pytest.raises(ValueError, match="normal_only must be"):
        kf.update(uv, depth, flow, torch.ones(1, 4))
    with pytest.raises(ValueError, match="dt must be"):
        kf.predict(torch.ones(3))


# ---------------------------------------------------------------------------- PoseUKF
def _pose_run(g: torch.Generator) -> list:
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


def _play(filt: PoseUKF | PoseTwistUKF, steps: list, check) -> None:  # noqa: ANN001
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


class _BiasedPoseUKF(PoseUKF):
    """A PoseUKF with a velocity bias in its state (``bias``, a 9x9 covariance)."""

    def __init__(self, batch_size: int = 1, fast_path: bool = True) -> None:
        cfg = PoseUKFConfig(velocity_bias=True, init_std_velocity_bias=0.3)
        super().__init__(batch_size, cfg, fast_path=fast_path)


@pytest.mark.parametrize("cls", [PoseUKF, PoseTwistUKF, _BiasedPoseUKF],
                         ids=["PoseUKF", "PoseTwistUKF", "PoseUKF-velocity-bias"])
def test_pose_steps_equal_torch(cls: type, calls: dict, update_form: str) -> None:
    g = torch.Generator().manual_seed(5)
    steps = _pose_run(g)
    fast, ref = cls(1, fast_path=True), cls(1, fast_path=False)
    names = ("t", "q", "cov") + {PoseTwistUKF: ("twist",), _BiasedPoseUKF: ("bias",)}.get(cls, ())
    counters = ("initialized", "rejected_run", "rejected", "reinitialised")
    # Each step from the same state: play the script on the reference, and replay every step
    # on the fast filter from the reference's state before it.
    for k, step in enumerate(steps):
        fast.load_state_dict(ref.state_dict())
        used = []
        for filt in (fast, ref):
            _play(filt, [step], used.append)
        for name in names:
            _close(getattr(fast, name), getattr(ref, name), f"step {k} {name}")
        for name in counters:
            assert torch.equal(getattr(fast, name), getattr(ref, name)), f"step {k} {name}"
        if used:
            assert torch.equal(used[0], used[1]), f"step {k} used"
    assert int(ref.reinitialised[0]) == 1 and int(ref.rejected[0]) >= 6
    n_updates = sum(s[0] == "update" for s in steps)
    n_predicts = len(steps) - n_updates
    assert calls.get("pose_update") == n_updates
    twist_driven = n_predicts if issubclass(cls, PoseUKF) else 0
    if cls is _BiasedPoseUKF:  # the updates moved the bias, and the predicts used it
        assert float(ref.bias.abs().max()) > 1e-3
    compiled = update_form == "compiled"
    assert calls.get("compiled_pose_predict", 0) == (twist_driven if compiled else 0)
    assert calls.get("pose_predict", 0) == (0 if compiled else twist_driven)


def test_pose_fast_path_only_where_it_applies(calls: dict, update_form: str) -> None:
    twist = torch.zeros(1, 6, dtype=F64)
    PoseUKF(2).predict(twist.expand(2, 6), 1e-3)
    PoseUKF(1, PoseUKFConfig(sigma_points=True)).predict(twist, 1e-3)
    PoseUKF(1).to(torch.float32).predict(twist.float(), 1e-3)
    PoseUKF(1, fast_path=False).predict(twist, 1e-3)
    PoseUKF(1).predict(twist.clone().requires_grad_(True), 1e-3)
    assert calls == {}
    PoseUKF(1).predict(twist, 1e-3)
    PoseTwistUKF(1).predict(1e-3)  # sigma points: torch
    assert calls == {"compiled_pose_predict" if update_form == "compiled" else "pose_predict": 1}


def test_pose_fast_path_checks_inputs() -> None:
    ukf = PoseUKF(1)
    with pytest.raises(ValueError, match="twist must have shape"):
        ukf.predict(torch.zeros(2, 6), 0.01)
    with pytest.raises(ValueError, match="dt must be"):
        ukf.predict(torch.zeros(1, 6), torch.ones(2))
    with pytest.raises(ValueError, match="q_meas must have shape"):
        ukf.update(torch.zeros(1, 3), torch.zeros(1, 3))
    with pytest.raises(ValueError, match="cov_meas must have shape"):
        ukf.update(torch.zeros(1, 3), torch.ones(1, 4), torch.eye(5))


def test_pose_state_stays_unit_and_symmetric_on_the_fast_path() -> None:
    g = torch.Generator().manual_seed(6)
    ukf = PoseUKF(1)
    ukf.reset(t=torch.zeros(1, 3, dtype=F64), q=quat_exp(torch.ones(1, 3, dtype=F64)))
    for i in range(2000):
        ukf.predict(5 * torch.randn(1, 6, generator=g, dtype=F64), 1e-3)
        if i % 200 == 0:
            ukf.update(ukf.t + 0.01, ukf.q)
    assert abs(float(ukf.q.norm()) - 1) < 1e-12
    assert torch.equal(ukf.cov, ukf.cov.transpose(-1, -2))
    assert torch.linalg.eigvalsh(ukf.cov).min() > 0


# ---------------------------------------------------------------------------- forward_run
def _run_rows(g: torch.Generator, sizes: list[int]) -> tuple[torch.Tensor, ...]:
    """The rows of steps of ``sizes`` RoIs each, one after the other (bad RoIs included)."""
    parts = [_flows(g, max(n, 10), "mixed+bad") for n in sizes]
    uv, depth, flow, normal = (torch.cat([p[i][0, :n] for p, n in zip(parts, sizes, strict=True)])
                               for i in range(4))
    return uv, depth, flow, normal


@pytest.mark.parametrize(
    "cfg", [c[1] for c in VELOCITY_CASES], ids=[c[0] for c in VELOCITY_CASES]
)
@pytest.mark.parametrize("flags", [True, False], ids=["normal flags", "assumed"])
def test_forward_run_equals_forward_calls_bit_for_bit(cfg: VelocityKFConfig, flags: bool) -> None:
    """``forward_run`` equals ``forward`` per step (``predict`` for a step without rows):
    every step's twist, the final twist, covariance, reference and skip counters, exactly;
    with a pivot's process noise and uneven steps."""
    if not fp._compiled.available():
        pytest.skip("numba is not installed")
    g = torch.Generator().manual_seed(11)
    sizes = [16, 0, 1, 30, 3, 0, 0, 12, 9, 25]
    dts = [1e-3, 1e-3, 2.5e-4, 1e-3, 3e-3, 1e-3, 1e-6, 1e-3, 7e-4, 1e-3]
    uv, depth, flow, normal = _run_rows(g, sizes)
    bounds = [0, *torch.tensor(sizes).cumsum(0).tolist()]
    run, ref = VelocityKF(CAM, 1, cfg), VelocityKF(CAM, 1, cfg)
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


def test_forward_run_stops_before_a_step_it_cannot_do() -> None:
    """An update whose prior is not positive definite: the run stops before it, holding the
    state after the steps before; ``forward`` on that step then goes through torch."""
    if not fp._compiled.available():
        pytest.skip("numba is not installed")
    g = torch.Generator().manual_seed(12)
    uv, depth, flow, normal = _run_rows(g, [0, 0, 6])
    kf, ref = VelocityKF(CAM, 1), VelocityKF(CAM, 1)
    for f in (kf, ref):
        f.reset(cov=-1e6 * torch.eye(6, dtype=F64)[None])
    twists = kf.forward_run([1e-3, 1e-3, 1e-3], [0, 0, 0, 6], uv, depth, flow, normal)
    assert twists is not None and twists.shape == (2, 1, 6)
    ref.predict(1e-3)
    ref.predict(1e-3)
    assert torch.equal(kf.cov, ref.cov) and torch.equal(kf.twist, ref.twist)


def test_forward_run_declines_where_forward_is_not_compiled_and_checks_inputs() -> None:
    g = torch.Generator().manual_seed(13)
    uv, depth, flow, normal = _run_rows(g, [5, 5])
    args = ([1e-3, 1e-3], [0, 5, 10], uv, depth, flow, normal)
    for kf in (VelocityKF(CAM, 2), VelocityKF(CAM, 1).to(torch.float32),
               VelocityKF(CAM, 1, fast_path=False),
               VelocityKF(PinholeCamera(500.0, 480.0, 330.0, 250.0, 640, 480,
                                        dist=[0.1, 0.0, 0.0, 0.0, 0.0]), 1)):
        before = kf.twist.clone(), kf.cov.clone()
        assert kf.forward_run(*args) is None
        assert torch.equal(kf.twist, before[0]) and torch.equal(kf.cov, before[1])
    kf = VelocityKF(CAM, 1)
    with pytest.raises(ValueError, match="need 3 row bounds"):
        kf.forward_run([1e-3, 1e-3], [0, 10], uv, depth, flow)
    with pytest.raises(ValueError, match="must rise"):
        kf.forward_run([1e-3, 1e-3], [0, 6, 5], uv, depth, flow)
    with pytest.raises(ValueError, match="must rise"):
        kf.forward_run([1e-3, 1e-3], [0, 5, 11], uv, depth, flow)
    with pytest.raises(ValueError, match=r"uv \(N,2\)"):
        kf.forward_run([1e-3], [0, 5], uv[None], depth, flow)
