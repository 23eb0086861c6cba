"""compile_steps routes the stateful methods through torch.compile'd pure steps.

The dynamo tracing is checked here with the "eager" backend (no C++ build); the inductor
build itself is exercised, and compared with eager, by benchmarks/bench_filters.py.
"""

from __future__ import annotations

import torch

from evtrack.camera import PinholeCamera
from evtrack.filters import PoseUKF, VelocityKF

CAM = PinholeCamera(500.0, 480.0, 330.0, 250.0, 640, 480)


def test_compiled_steps_give_the_eager_results() -> None:
    g = torch.Generator().manual_seed(0)
    uv = torch.rand(2, 30, 2, generator=g, dtype=torch.float64) * 400 + 100
    depth = torch.rand(2, 30, generator=g, dtype=torch.float64) + 0.5
    flow = torch.randn(2, 30, 2, generator=g, dtype=torch.float64) * 100
    normal = torch.rand(2, 30, generator=g) < 0.5
    eager, compiled = VelocityKF(CAM, 2), VelocityKF(CAM, 2).compile_steps(backend="eager")
    assert compiled.step_function("update_state") is not compiled.update_state
    for kf in (eager, compiled):
        kf(1e-3, uv, depth, flow, normal)
    torch.testing.assert_close(compiled.twist, eager.twist, rtol=0, atol=0)
    torch.testing.assert_close(compiled.cov, eager.cov, rtol=0, atol=0)

    pose, pose_c = PoseUKF(2), PoseUKF(2).compile_steps(backend="eager")
    for ukf in (pose, pose_c):
        ukf.update(torch.zeros(2, 3, dtype=torch.float64), torch.tensor([[1.0, 0, 0, 0]] * 2))
        ukf.predict(eager.twist, 1e-3)
        ukf.update(ukf.t + 0.01, ukf.q)
    assert torch.equal(pose.t, pose_c.t) and torch.equal(pose.cov, pose_c.cov)
    pose_c.compile_steps(enabled=False)
    assert pose_c.step_function("step") == pose_c.step
