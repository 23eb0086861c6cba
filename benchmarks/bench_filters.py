"""Per-step latency of the filters on CPU, side by side with filterpy, in one run.

    python benchmarks/bench_filters.py [--threads 1] [--repeats 7] [--quick] [--no-compile]

Targets (issue 5): VelocityKF update with 400 RoI flows <= 150 µs at B = 1; PoseUKF
predict + update <= 200 µs at B = 1 and <= 5 µs per track at B = 1024.

The main table puts the paths side by side for each case and batch size:

* ``torch step``: the eager pure step function (``update_state``; ``step`` = predict + gated
  update), without the stateful bookkeeping and input checks (the path before the fast path);
* ``torch call``: the stateful call users run (``kf.update(...)``; ``ukf(twist, dt, t, q)``)
  with ``fast_path=False``;
* ``fast call``: the same stateful call on the default single-track backend (``"numba"``,
  :mod:`evtrack.filters.fast_compiled`: the NumPy backend with its velocity update and pose
  predict compiled), what a tracker runs at B = 1; it applies to B = 1 only (at B > 1 the
  call is the torch call);
* ``fast NumPy``: the fast call on the NumPy backend (``backend="numpy"``,
  :mod:`evtrack.filters.fast_path`), the form before the compiled kernel;
* ``compiled step``: the pure step after ``compile_steps()`` (torch.compile, inductor),
  checked against eager first;
* ``filterpy``: filterpy's KalmanFilter / UnscentedKalmanFilter on the same models; it has no
  batch dimension, so B tracks cost B times its B = 1 step.

Targets are judged on the path a user runs: the fast call at B = 1, the torch call per track
at B = 1024. Each cell is the median over ``--repeats`` runs of the mean call time in µs of
this process's CPU time (what a dedicated core would see; wall time in a second table). On a
shared machine absolute times drift with the load, so the table also gives each path's time
relative to filterpy's, measured in the same run. The fast call is checked against the torch
call (1e-12) before it is timed. A third VelocityKF row has the 16 RoIs of a tracker's step
(no target, no filterpy). Further rows: other filters and onnxruntime.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple


def _threads_argument(argv: list[str]) -> str:
    """The ``--threads`` value on the command line (default 1), read before NumPy loads."""
    for i, arg in enumerate(argv):
        if arg == "--threads" and i + 1 < len(argv):
            return argv[i + 1]
        if arg.startswith("--threads="):
            return arg.split("=", 1)[1]
    return "1"


# NumPy's OpenBLAS (filterpy, the fast path) runs with as many threads as torch: its pool must
# be sized before NumPy loads, and idle pool threads spinning would count as this process's CPU.
os.environ.setdefault("OPENBLAS_NUM_THREADS", _threads_argument(sys.argv))

import numpy as np  # noqa: E402
import torch  # noqa: E402
from filterpy.kalman import (  # noqa: E402
    KalmanFilter,
    MerweScaledSigmaPoints,
    UnscentedKalmanFilter,
)
from scipy.spatial.transform import Rotation  # noqa: E402

from evtrack.camera import PinholeCamera  # noqa: E402
from evtrack.filters import (  # noqa: E402
    PoseTwistUKF,
    PoseUKF,
    PoseUKFConfig,
    VelocityKF,
    interaction_matrix,
)
from evtrack.filters.onnx_export import export_step, step_inputs  # noqa: E402

ROIS = 400
TRACKER_ROIS = 16  # RoI flows per velocity step of the tracker on a `faster` YCB sequence
CAM = PinholeCamera(500.0, 480.0, 330.0, 250.0, 640, 480)


def _time(fn: Callable[[], object], repeats: int, budget_s: float = 0.25) -> Timing:
    """Median over ``repeats`` of the mean call time in µs, wall-clock and CPU (this process).

    On a shared machine the wall time includes the time other processes hold the core; the CPU
    time is what the call costs when the core is its own.
    """
    for _ in range(3):
        fn()
    t0 = time.perf_counter()
    fn()
    once = max(time.perf_counter() - t0, 1e-7)
    n = max(3, min(2000, int(budget_s / once)))
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        for _ in range(n):
            fn()
        cpu.append((time.process_time() - c0) / n * 1e6)
        wall.append((time.perf_counter() - w0) / n * 1e6)
    return Timing(statistics.median(wall), statistics.median(cpu))


class Timing(NamedTuple):
    wall: float  # µs
    cpu: float  # µs

    def __mul__(self, k: float) -> Timing:
        return Timing(self.wall * k, self.cpu * k)


# ---------------------------------------------------------------------------- VelocityKF
def _velocity_inputs(B: int, seed: int = 0, rois: int = ROIS) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    uv = torch.rand(B, rois, 2, generator=g, dtype=torch.float64) * torch.tensor([640.0, 480.0])
    depth = 0.4 + 0.8 * torch.rand(B, rois, generator=g, dtype=torch.float64)
    twist = torch.randn(B, 6, generator=g, dtype=torch.float64)
    flow = (interaction_matrix(uv, depth, CAM) @ twist[:, None, :, None]).squeeze(-1)
    flow = flow + 5 * torch.randn(B, rois, 2, generator=g, dtype=torch.float64)
    normal = torch.rand(B, rois, generator=g) < 0.5
    mask = torch.ones(B, rois, dtype=torch.bool)
    return twist, uv, depth, flow, normal, mask


def bench_velocity(B: int, repeats: int, compiled: bool = False, rois: int = ROIS) -> Timing:
    kf = VelocityKF(CAM, B)
    twist, uv, depth, flow, normal, mask = _velocity_inputs(B, rois=rois)
    args = (twist, kf.cov.clone(), twist, uv, depth, flow, normal, mask)
    fn = _compiled(kf, "update_state", args) if compiled else kf.update_state
    return _time(lambda: fn(*args), repeats)


def bench_velocity_call(B: int, repeats: int, fast: bool, rois: int = ROIS,
                        numpy_update: bool = False) -> Timing:
    """The stateful ``kf.update`` (fast path on or off), after checking both give the same;
    ``numpy_update``: on the NumPy backend instead of the default (compiled) one."""
    twist, uv, depth, flow, normal, _ = _velocity_inputs(B, rois=rois)
    kf = VelocityKF(CAM, B, fast_path=fast, backend="numpy" if numpy_update else "auto")
    if fast:
        ref = VelocityKF(CAM, B, fast_path=False)
        for f in (kf, ref):
            f.reset(twist=twist)
            f.update(uv, depth, flow, normal)
        _same(kf.twist, ref.twist, "VelocityKF twist")
        _same(kf.cov, ref.cov, "VelocityKF cov")
    return _time(lambda: kf.update(uv, depth, flow, normal), repeats)


def bench_pose_call(B: int, repeats: int, fast: bool) -> Timing:
    """The stateful ``ukf(twist, dt, t_meas, q_meas)``: predict over 1 ms, then a gated pose
    update (fast path on or off); the measurement stays near the state, so every pose is
    fused (checked), as in tracking."""
    t, q, twist = _pose_inputs(B)
    twist = 0.01 * twist
    t_m, q_m = t + 1e-3, q

    def make(fast_path: bool) -> PoseUKF:
        ukf = PoseUKF(B, fast_path=fast_path)
        ukf.reset(t=t, q=q)
        return ukf

    ukf = make(fast)
    if fast:
        ref = make(False)
        for f in (ukf, ref):
            for _ in range(3):
                f(twist, 1e-3, t_m, q_m)
        for name in ("t", "q", "cov"):
            _same(getattr(ukf, name), getattr(ref, name), f"PoseUKF {name}")
    timing = _time(lambda: ukf(twist, 1e-3, t_m, q_m), repeats)
    if int(ukf.rejected.sum()):
        raise RuntimeError("bench_pose_call: poses were rejected; the timing is not of fusing")
    return timing


def _same(got: torch.Tensor, want: torch.Tensor, what: str) -> None:
    err = float((got - want).abs().max() / want.abs().max().clamp_min(1e-300))
    if not err <= 1e-12:
        raise RuntimeError(f"fast path: {what} differs from the torch path by {err:.1e}")


def _compiled(filt: VelocityKF | PoseUKF, name: str, args: tuple) -> Callable[..., object]:
    """The compiled pure function, after checking it reproduces the eager one."""
    fn = filt.compile_steps().step_function(name)
    for got, want in zip(fn(*args), getattr(filt, name)(*args), strict=True):
        if not torch.allclose(got.double(), want.double(), rtol=1e-9, atol=1e-12):
            raise RuntimeError(f"compiled {type(filt).__name__}.{name} differs from eager")
    return fn


def bench_velocity_filterpy(repeats: int) -> Timing:
    twist, uv, depth, flow, _, _ = _velocity_inputs(1)
    H = interaction_matrix(uv[0], depth[0], CAM).reshape(-1, 6).numpy()
    z = flow[0].reshape(-1).numpy()
    kf = KalmanFilter(dim_x=6, dim_z=2 * ROIS)
    kf.R = 50.0**2 * np.eye(2 * ROIS)
    kf.H = H
    P0 = np.diag([1.0] * 3 + [9.0] * 3)

    def step() -> None:
        kf.x, kf.P = np.zeros(6), P0.copy()
        kf.update(z)

    return _time(step, repeats)


# ---------------------------------------------------------------------------- PoseUKF
def _pose_inputs(B: int, seed: int = 1) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    t = torch.randn(B, 3, generator=g, dtype=torch.float64)
    q = torch.randn(B, 4, generator=g, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    twist = torch.randn(B, 6, generator=g, dtype=torch.float64)
    return t, q, twist


def bench_pose(B: int, repeats: int, sigma_points: bool = False, compiled: bool = False) -> Timing:
    ukf = PoseUKF(B, PoseUKFConfig(sigma_points=sigma_points))
    t, q, twist = _pose_inputs(B)
    ukf.reset(t=t, q=q)
    dt = torch.full((B,), 1e-3, dtype=torch.float64)
    R = ukf.meas_cov.expand(B, 6, 6)
    valid = torch.ones(B, dtype=torch.bool)
    t_m, q_m = t + 0.01, q
    args = (ukf.t, ukf.q, ukf.cov, ukf.initialized, ukf.rejected_run, twist, dt, t_m, q_m, R, valid)
    fn = _compiled(ukf, "step", args) if compiled else ukf.step
    return _time(lambda: fn(*args), repeats)


def bench_pose_twist(B: int, repeats: int) -> Timing:
    cv = PoseTwistUKF(B)
    t, q, twist = _pose_inputs(B)
    cv.reset(t=t, q=q, twist=twist)
    dt = torch.full((B,), 1e-3, dtype=torch.float64)
    R = cv.meas_cov.expand(B, 6, 6)
    valid = torch.ones(B, dtype=torch.bool)
    state = (cv.t, cv.q, cv.twist, cv.cov, cv.initialized, cv.rejected_run)
    return _time(lambda: cv.step(*state, dt, t + 0.01, q, R, valid), repeats)


def bench_pose_filterpy(repeats: int) -> Timing:
    """filterpy's UKF on the Euclidean stand-in [t, rotation vector] with the same motion."""

    def fx(x: np.ndarray, dt: float, twist: np.ndarray) -> np.ndarray:
        rho, phi = twist[:3] * dt, twist[3:] * dt
        th = np.linalg.norm(phi)
        a = (1 - np.cos(th)) / th**2 if th > 1e-6 else 0.5
        b = (th - np.sin(th)) / th**3 if th > 1e-6 else 1 / 6
        c = np.cross(phi, rho)
        p = rho + a * c + b * np.cross(phi, c)
        Rd = Rotation.from_rotvec(phi)
        return np.concatenate([Rd.apply(x[:3]) + p, (Rd * Rotation.from_rotvec(x[3:])).as_rotvec()])

    ukf = UnscentedKalmanFilter(
        dim_x=6,
        dim_z=6,
        dt=1e-3,
        hx=lambda x: x,
        fx=fx,
        points=MerweScaledSigmaPoints(6, alpha=1.0, beta=2.0, kappa=0.0),
    )
    ukf.Q = np.eye(6) * 1e-6
    ukf.R = np.eye(6) * 1e-4
    twist = np.array([0.1, -0.2, 0.05, 0.5, 1.0, -0.3])
    z = np.array([0.1, 0.0, 1.0, 0.01, 0.0, 0.0])

    def step() -> None:
        ukf.x, ukf.P = np.array([0.1, 0.0, 1.0, 0.0, 0.0, 0.0]), np.eye(6) * 1e-3
        ukf.predict(twist=twist)
        ukf.update(z)

    return _time(step, repeats)


# ---------------------------------------------------------------------------- onnxruntime
def bench_onnx(filt: VelocityKF | PoseUKF, B: int, repeats: int, folder: Path) -> Timing:
    import onnxruntime as ort

    path = export_step(filt, folder / f"{type(filt).__name__}.onnx")
    options = ort.SessionOptions()
    options.intra_op_num_threads = torch.get_num_threads()
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    inputs = step_inputs(filt, batch=B, rois=ROIS)
    feed = {i.name: x.numpy() for i, x in zip(session.get_inputs(), inputs, strict=True)}
    return _time(lambda: session.run(None, feed), repeats)


# ---------------------------------------------------------------------------- table
PATHS = ("torch step", "torch call", "fast call", "fast NumPy", "compiled step", "filterpy")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--threads", type=int, default=1, help="torch, onnxruntime and NumPy BLAS threads"
    )
    parser.add_argument("--repeats", type=int, default=7, help="timed runs per cell (median)")
    parser.add_argument("--quick", action="store_true", help="3 repeats")
    parser.add_argument(
        "--no-compile",
        action="store_true",
        help="skip the torch.compile cells (each compiles for ~20-60 s first)",
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    warnings.filterwarnings("ignore")
    rep = 3 if args.quick else args.repeats
    big = 1024
    compile_ = not args.no_compile
    load_before = os.getloadavg()[0]

    fp_kf, fp_ukf = bench_velocity_filterpy(rep), bench_pose_filterpy(rep)
    # (case, B, {path: Timing}, target µs, judged path, per "step" or "track")
    Row = tuple[str, int, dict[str, Timing], float | None, str, str]
    rows: list[Row] = []
    for B, rois in ((1, ROIS), (big, ROIS), (1, TRACKER_ROIS)):
        cells = {
            "torch step": bench_velocity(B, rep, rois=rois),
            "torch call": bench_velocity_call(B, rep, fast=False, rois=rois),
        }
        if rois == ROIS:
            cells["filterpy"] = fp_kf * B
        if B == 1:
            cells["fast call"] = bench_velocity_call(B, rep, fast=True, rois=rois)
            cells["fast NumPy"] = bench_velocity_call(B, rep, fast=True, rois=rois,
                                                      numpy_update=True)
        if compile_ and B == 1:  # (at B = 1024 the eager step is arithmetic-bound already)
            cells["compiled step"] = bench_velocity(B, rep, compiled=True, rois=rois)
        judged = ("fast call", 150.0, "step") if B == 1 else ("torch call", None, "")
        if rois != ROIS:
            judged = ("fast call", None, "")
        rows.append((f"VelocityKF update, {rois} RoIs", B, cells, judged[1], judged[0],
                     judged[2]))
    for B in (1, big):
        cells = {
            "torch step": bench_pose(B, rep),
            "torch call": bench_pose_call(B, rep, fast=False),
            "filterpy": fp_ukf * B,
        }
        if B == 1:
            cells["fast call"] = bench_pose_call(B, rep, fast=True)
        if compile_:
            cells["compiled step"] = bench_pose(B, rep, compiled=True)
        judged = ("fast call", 200.0, "step") if B == 1 else ("torch call", 5.0, "track")
        rows.append(("PoseUKF predict+update", B, cells, judged[1], judged[0], judged[2]))

    others: list[tuple[str, int, Timing]] = [
        ("PoseUKF sigma points, torch step", 1, bench_pose(1, rep, True)),
        ("PoseUKF sigma points, torch step", big, bench_pose(big, rep, True)),
        ("PoseTwistUKF predict+update, torch step", 1, bench_pose_twist(1, rep)),
        ("PoseTwistUKF predict+update, torch step", big, bench_pose_twist(big, rep)),
    ]
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        others += [
            ("VelocityKF step, onnxruntime", 1, bench_onnx(VelocityKF(CAM, 1), 1, rep, folder)),
            ("PoseUKF step, onnxruntime", 1, bench_onnx(PoseUKF(1), 1, rep, folder)),
            ("PoseUKF step, onnxruntime", big, bench_onnx(PoseUKF(1), big, rep, folder)),
        ]

    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), float64, CPU "
        f"({os.cpu_count()} cores); median of {rep} runs; load average "
        f"{load_before:.1f} -> {os.getloadavg()[0]:.1f}"
    )
    failed = _table(rows, "cpu", "µs per step, CPU time of this process (targets judged here)")
    _table(rows, "wall", "µs per step, wall time")
    _ratios(rows)
    print("\nother paths (cpu µs per step)")
    for case, B, t in others:
        print(f"  {case:<40} {B:>5} {t.cpu:>12,.1f} {t.cpu / B:>10.2f}/track")
    print(
        "filterpy: KalmanFilter.update with the 800-row flow model; UnscentedKalmanFilter on the "
        "Euclidean stand-in [t, rotvec]; no batch dimension, so B tracks cost B x its B=1 step."
    )
    return 1 if failed else 0


def _table(rows: list, field: str, title: str) -> bool:
    """Print one side-by-side table of ``field`` ("cpu" or "wall"); True if a target failed."""
    print(f"\n{title}")
    head = f"{'case':<28} {'B':>5} " + " ".join(f"{p:>13}" for p in PATHS)
    head += f" {'target':>16} {'result':>6}"
    print(head)
    print("-" * len(head))
    failed = False
    for case, B, cells, target, judged, kind in rows:
        values = []
        for path in PATHS:
            t = cells.get(path)
            values.append("-" if t is None else f"{getattr(t, field):,.1f}")
        target_s, result = "-", ""
        if target is not None and field == "cpu":
            value = cells[judged].cpu if kind == "step" else cells[judged].cpu / B
            failed |= value > target
            target_s = f"<={target:g}/{kind} {judged.split()[0]}"
            result = "pass" if value <= target else "FAIL"
        print(
            f"{case:<28} {B:>5} "
            + " ".join(f"{v:>13}" for v in values)
            + f" {target_s:>16} {result:>6}"
        )
    return failed


def _ratios(rows: list) -> None:
    """Each path's CPU time over filterpy's in the same run (load-independent-ish)."""
    print("\nrelative to filterpy in this run (cpu time / filterpy's; < 1 is faster)")
    for case, B, cells, *_ in rows:
        if "filterpy" not in cells:
            continue
        ref = cells["filterpy"].cpu
        parts = [f"{p} {cells[p].cpu / ref:.3f}" for p in PATHS[:-1] if p in cells]
        print(f"  {case:<28} {B:>5}  " + ", ".join(parts))


if __name__ == "__main__":
    sys.exit(main())
