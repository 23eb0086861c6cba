"""The choice of the backend that runs a filter's call: the registry, the preference, and the
single-track backends taken exactly where they apply (their results: test_backend_parity.py)."""

from __future__ import annotations

import pytest
import torch
from filter_helpers import CAM, F64, flows, run_rows

from evtrack.filters import PoseTwistUKF, PoseUKF, PoseUKFConfig, VelocityKF, backends
from evtrack.filters.backends import (
    AUTO,
    TORCH,
    backend_names,
    check_backend_name,
    get_backend,
    set_default_backend,
    single_track_backends,
)
from evtrack.filters.fast_compiled import available as numba_available
from evtrack.filters.lie import quat_exp

SINGLE = [b.name for b in single_track_backends()]


@pytest.fixture(params=SINGLE)
def single(request: pytest.FixtureRequest) -> str:
    """Each registered single-track backend (skipped where it cannot run here)."""
    chosen = get_backend(request.param)
    if chosen is None or chosen.name != request.param:
        pytest.skip(f"the {request.param} backend cannot run here")
    return request.param


# ---------------------------------------------------------------------------- registry
def test_registry_names_and_auto() -> None:
    assert backend_names()[0] == TORCH and {"numba", "numpy"} <= set(backend_names())
    assert get_backend(TORCH) is None
    assert get_backend("numpy").name == "numpy"
    assert get_backend(AUTO).name == ("numba" if numba_available() else "numpy")
    with pytest.raises(ValueError, match="unknown filter backend"):
        check_backend_name("cupy")
    with pytest.raises(ValueError, match="unknown filter backend"):
        VelocityKF(CAM, 1, backend="cupy")


def test_a_backend_missing_here_falls_back_to_the_next(monkeypatch: pytest.MonkeyPatch) -> None:
    numba = get_backend("numba")
    monkeypatch.setattr(type(numba), "available", lambda self: False)
    assert get_backend("numba").name == "numpy"
    assert get_backend(AUTO).name == "numpy"


def test_default_backend_is_what_auto_stands_for(calls: dict) -> None:
    g = torch.Generator().manual_seed(4)
    uv, depth, flow, normal = flows(g, 20, "mixed")
    try:
        set_default_backend("numpy")
        assert backends.default_backend() == "numpy"
        VelocityKF(CAM, 1)(1e-3, uv, depth, flow, normal)
        VelocityKF(CAM, 1, backend="numba" if numba_available() else "numpy").update(
            uv, depth, flow, normal)
        set_default_backend(TORCH)
        VelocityKF(CAM, 1)(1e-3, uv, depth, flow, normal)
        with pytest.raises(ValueError, match="unknown filter backend"):
            set_default_backend("cupy")
    finally:
        set_default_backend(AUTO)
    named = "numba" if numba_available() else "numpy"
    want = {"numpy.velocity_predict": 1, "numpy.velocity_update": 1}
    want[f"{named}.velocity_update"] = want.get(f"{named}.velocity_update", 0) + 1
    assert calls == want


def test_fast_path_attribute_is_the_torch_preference() -> None:
    kf = VelocityKF(CAM, 1, backend="numpy")
    assert kf.fast_path and kf.backend == "numpy"
    kf.fast_path = True  # keeps the named backend
    assert kf.backend == "numpy"
    kf.fast_path = False
    assert kf.backend == TORCH and not kf.fast_path
    kf.fast_path = True
    assert kf.backend == AUTO
    assert PoseUKF(1, fast_path=False, backend="numpy").backend == TORCH


# ---------------------------------------------------------------------------- VelocityKF
def test_velocity_backend_only_where_it_applies(calls: dict) -> None:
    g = torch.Generator().manual_seed(4)
    uv, depth, flow, normal = flows(g, 20, "mixed")
    VelocityKF(CAM, 2)(
        1e-3,
        uv.expand(2, -1, -1),
        depth.expand(2, -1),
        flow.expand(2, -1, -1),
        normal.expand(2, -1),
    )
    VelocityKF(CAM, 1).to(torch.float32)(1e-3, uv, depth, flow, normal)
    VelocityKF(CAM, 1, fast_path=False)(1e-3, uv, depth, flow, normal)
    VelocityKF(CAM, 1, backend=TORCH)(1e-3, uv, depth, flow, normal)
    VelocityKF(CAM, 1).compile_steps(backend="eager")(1e-3, uv, depth, flow, normal)
    assert calls == {}
    wants_grad = uv.clone().requires_grad_(True)
    VelocityKF(CAM, 1, backend="numpy").update(wants_grad, depth, flow, normal)
    assert calls == {}
    with torch.no_grad():  # no gradients wanted: a single-track backend again
        VelocityKF(CAM, 1, backend="numpy").update(wants_grad, depth, flow, normal)
    assert calls == {"numpy.velocity_update": 1}


def test_velocity_single_track_checks_inputs(single: str) -> None:
    kf = VelocityKF(CAM, 1, backend=single)
    uv, depth, flow = torch.zeros(1, 4, 2), torch.ones(1, 4), torch.ones(1, 4, 2)
    with pytest.raises(ValueError, match="depth must be"):
        kf.update(uv, torch.ones(2, 4), flow)
    with pytest.raises(ValueError, match="flow must be"):
        kf.update(uv, depth, torch.zeros(1, 5, 2))
    with pytest.raises(ValueError, match="normal_only must be"):
        kf.update(uv, depth, flow, torch.ones(1, 4))
    with pytest.raises(ValueError, match="dt must be"):
        kf.predict(torch.ones(3))


def test_forward_run_declines_without_runs_and_checks_inputs() -> None:
    g = torch.Generator().manual_seed(13)
    uv, depth, flow, normal = run_rows(g, [5, 5])
    args = ([1e-3, 1e-3], [0, 5, 10], uv, depth, flow, normal)
    declining = [VelocityKF(CAM, 2), VelocityKF(CAM, 1).to(torch.float32),
                 VelocityKF(CAM, 1, fast_path=False)]
    declining += [VelocityKF(CAM, 1, backend=b.name) for b in single_track_backends()
                  if not b.runs]
    for kf in declining:
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


# ---------------------------------------------------------------------------- pose filters
def test_pose_backend_only_where_it_applies(calls: dict, single: str) -> None:
    twist = torch.zeros(1, 6, dtype=F64)
    PoseUKF(2, backend=single).predict(twist.expand(2, 6), 1e-3)
    PoseUKF(1, PoseUKFConfig(sigma_points=True), backend=single).predict(twist, 1e-3)
    PoseUKF(1, backend=single).to(torch.float32).predict(twist.float(), 1e-3)
    PoseUKF(1, fast_path=False).predict(twist, 1e-3)
    PoseUKF(1, backend=single).predict(twist.clone().requires_grad_(True), 1e-3)
    assert calls == {}
    PoseUKF(1, backend=single).predict(twist, 1e-3)
    PoseUKF(1, backend=single).predict([[0.0] * 6], 1e-3)  # converted, then one track
    PoseTwistUKF(1, backend=single).predict(1e-3)  # sigma points: torch
    assert calls == {f"{single}.pose_predict": 2}
    states = PoseUKF(1, backend=single).predict_run([twist], [1e-3])
    assert (states is not None) == get_backend(single).runs  # runs only where it has them


def test_pose_single_track_checks_inputs(single: str) -> None:
    ukf = PoseUKF(1, backend=single)
    with pytest.raises(ValueError, match="twist must have shape"):
        ukf.predict(torch.zeros(2, 6), 0.01)
    with pytest.raises(ValueError, match="dt must be"):
        ukf.predict(torch.zeros(1, 6), torch.ones(2))
    with pytest.raises(ValueError, match="q_meas must have shape"):
        ukf.update(torch.zeros(1, 3), torch.zeros(1, 3))
    with pytest.raises(ValueError, match="cov_meas must have shape"):
        ukf.update(torch.zeros(1, 3), torch.ones(1, 4), torch.eye(5))


def test_pose_state_stays_unit_and_symmetric_on_a_single_track_backend(single: str) -> None:
    g = torch.Generator().manual_seed(6)
    ukf = PoseUKF(1, backend=single)
    ukf.reset(t=torch.zeros(1, 3, dtype=F64), q=quat_exp(torch.ones(1, 3, dtype=F64)))
    for i in range(2000):
        ukf.predict(5 * torch.randn(1, 6, generator=g, dtype=F64), 1e-3)
        if i % 200 == 0:
            ukf.update(ukf.t + 0.01, ukf.q)
    assert abs(float(ukf.q.norm()) - 1) < 1e-12
    assert torch.equal(ukf.cov, ukf.cov.transpose(-1, -2))
    assert torch.linalg.eigvalsh(ukf.cov).min() > 0
