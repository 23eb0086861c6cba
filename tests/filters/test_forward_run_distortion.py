"""The velocity filter's compiled runs (:meth:`VelocityKF.forward_run`) with a distorted camera:
the rows are mapped to the ideal pinhole image once for the whole run, and every step's twist,
the final state and the skip counters equal those of :meth:`VelocityKF.forward` step by step
(to 1e-12 relative; the counters exactly). The undistortion's table of pixels gives the values
of the direct computation."""

from __future__ import annotations

import pytest
import torch
from filter_helpers import F64, close, close_gaussian, run_rows

from evtrack.camera import PinholeCamera
from evtrack.filters import VelocityKF, VelocityKFConfig
from evtrack.filters.backends import get_backend, single_track_backends
from evtrack.filters.interaction import UndistortionTable, undistort_flow

CAM_PINHOLE = PinholeCamera(500.0, 480.0, 330.0, 250.0, 640, 480)

# OpenCV's models: radial-tangential (4 and 5 coefficients) and the rational one (8)
DISTORTIONS = {
    "k1k2p1p2": [-0.2, 0.05, 1e-3, -1e-3],
    "k1k2p1p2k3": [-0.3, 0.1, 1e-3, -1e-3, -0.02],
    "rational": [-0.3, 0.1, 1e-3, -1e-3, -0.02, 0.01, 0.002, 0.001],
}


@pytest.fixture(params=[b.name for b in single_track_backends() if b.runs])
def runs_backend(request: pytest.FixtureRequest) -> str:
    chosen = get_backend(request.param)
    if chosen is None or chosen.name != request.param:
        pytest.skip(f"the {request.param} backend cannot run here")
    return request.param


@pytest.mark.parametrize("dist", DISTORTIONS.values(), ids=DISTORTIONS.keys())
@pytest.mark.parametrize("flags", [True, False], ids=["normal flags", "assumed"])
def test_forward_run_equals_forward_calls_with_distortion(dist: list[float], flags: bool,
                                                          runs_backend: str) -> None:
    cam = PinholeCamera(500.0, 480.0, 330.0, 250.0, 640, 480, dist=dist)
    g = torch.Generator().manual_seed(21)
    sizes = [16, 0, 1, 30, 3, 0, 0, 12, 9, 25]
    dts = [1e-3, 1e-3, 2.5e-4, 1e-3, 3e-3, 1e-3, 1e-6, 1e-3, 7e-4, 1e-3]
    uv, depth, flow, normal = run_rows(g, sizes)
    bounds = [0, *torch.tensor(sizes).cumsum(0).tolist()]
    run, ref = (VelocityKF(cam, 1, VelocityKFConfig(), backend=runs_backend) for _ in range(2))
    for kf in (run, ref):
        kf.set_pivot(torch.tensor([0.05, -0.02, 0.7], dtype=F64))
    twists = run.forward_run(dts, bounds, uv, depth, flow, normal if flags else None)
    assert twists is not None and twists.shape == (len(dts), 1, 6)
    for k, dt in enumerate(dts):
        lo, hi = bounds[k], bounds[k + 1]
        if hi == lo:
            want = ref.predict(dt)
        else:
            want = ref(dt, uv[None, lo:hi], depth[None, lo:hi], flow[None, lo:hi],
                       normal[None, lo:hi] if flags else None)
        close(twists[k], want, f"step {k}")
    close_gaussian(run, ref, "final state")
    close(run.reference, ref.reference, "reference")
    for name in ("skipped_depth", "skipped_flow"):
        assert torch.equal(getattr(run, name), getattr(ref, name)), name
    assert int(run.skipped_depth) > 0 and int(run.skipped_flow) > 0


def test_distortion_changes_the_run() -> None:
    """The run does undistort: the same rows through an undistorted camera give another
    twist."""
    g = torch.Generator().manual_seed(22)
    uv, depth, flow, normal = run_rows(g, [20, 20])
    cams = (PinholeCamera(500.0, 480.0, 330.0, 250.0, 640, 480),
            PinholeCamera(500.0, 480.0, 330.0, 250.0, 640, 480, dist=DISTORTIONS["k1k2p1p2"]))
    out = [VelocityKF(cam, 1).forward_run([1e-3, 1e-3], [0, 20, 40], uv, depth, flow, normal)
           for cam in cams]
    if out[0] is None:
        pytest.skip("no backend with runs here (numba missing)")
    assert out[1] is not None and not torch.allclose(out[0], out[1])


def test_undistortion_table_gives_the_direct_values() -> None:
    """:class:`UndistortionTable`: the values of ``undistort_flow`` without it, bit for bit,
    whichever batches first met the pixels; pixels it does not take (float32, non-finite,
    gradients) go the direct way."""
    cam = PinholeCamera(300.0, 290.0, 160.0, 120.0, 320, 240, dist=DISTORTIONS["rational"])
    table = UndistortionTable(cam, max_points=300)
    g = torch.Generator().manual_seed(23)
    grid = torch.stack(torch.meshgrid(torch.arange(6.0, 320.0, 12.0),
                                      torch.arange(6.0, 240.0, 12.0), indexing="ij"), -1)
    grid = grid.reshape(-1, 2).to(F64)  # 540 RoI centres: the table starts afresh once
    for _ in range(20):
        uv = grid[torch.randint(0, len(grid), (1, 40), generator=g)]
        flow = 100 * torch.randn(uv.shape, generator=g, dtype=F64)
        normal = torch.rand(uv.shape[:-1], generator=g) < 0.5
        want = undistort_flow(cam, uv, flow, normal)
        got = undistort_flow(cam, uv, flow, normal, table)
        assert all(torch.equal(a, b) for a, b in zip(got, want, strict=True))
        assert 0 < len(table) <= 300
    bad = grid[:3].clone()[None]
    bad[0, 1, 0] = float("inf")
    for uv in (bad, grid[None, :3].float(), grid[None, :3].clone().requires_grad_(True)):
        assert not UndistortionTable.applies(uv)
    assert UndistortionTable.applies(grid[None, :3])


def test_prepare_pixels_fills_the_table_and_keeps_the_results() -> None:
    cam = PinholeCamera(500.0, 480.0, 330.0, 250.0, 640, 480, dist=DISTORTIONS["k1k2p1p2k3"])
    g = torch.Generator().manual_seed(24)
    uv, depth, flow, normal = run_rows(g, [30])
    uv = torch.round(uv.clamp(0, 600))  # finite pixels
    warm, cold = VelocityKF(cam, 1), VelocityKF(cam, 1)
    warm.prepare_pixels(uv.float())
    assert len(warm._undistortion) == len({tuple(p) for p in uv.tolist()})
    for kf in (warm, cold):
        kf(1e-3, uv[None], depth[None], flow[None], normal[None])
    assert torch.equal(warm.twist, cold.twist) and torch.equal(warm.cov, cold.cov)
    VelocityKF(CAM_PINHOLE, 1).prepare_pixels(uv)  # no distortion: nothing to do
