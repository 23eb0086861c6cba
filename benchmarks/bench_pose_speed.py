"""Latency of the pose networks: torch eager vs onnxruntime, side by side in one process.

For each model: parameters, FLOPs (torch.utils.flop_counter; 1 multiply-add = 2 FLOPs) at
640x480 and 320x240, and the median and minimum latency of one frame (batch 1) on the CPU with
a fixed number of threads (default 2), for torch eager and for onnxruntime on the same
exported graph. Torch and onnxruntime calls alternate, so both see the same machine load; on
a shared machine the minimum is the best estimate of the unloaded latency. Also the decoding +
PnP cost on ideal maps of one object, and the same on a GPU when one is available (torch CUDA;
onnxruntime CUDA when its provider is there). Weights are random: latency does not depend on
their values.

The pose search over corner identities (``DecodeConfig.search_below``; 8 pooled points):
its batched P3P (``evtrack.models.p3p``) against the reference it replaced, one
``cv2.solveP3P`` per problem, alternating; both must find the same best pose.

Last, the whole estimator on a simulated 640x480 frame of the demo object with its shipped
weights (``estimator(rgb)``: preprocessing, network, decoding, PnP), in one pass and with the
second pass on a crop around the detection (``DecodeConfig.crop_refine``, the default), torch
eager and onnxruntime alternating as above; torch also without folding the batch norms
(``TorchPoseEstimator(fold_batchnorm=False)``) against the default; and the crop pass alone
around a prior pose, as the tracker runs it while it holds the track
(``estimate_near``, ``TrackerConfig.pose_prior``; the prior: the true pose moved 1 cm and
5 deg).

Target (issue 6): onnxruntime CPU <= 40 ms per 640x480 frame.

    python benchmarks/bench_pose_speed.py [--models dope_lite_small dope_lite_base]
        [--threads 2] [--repeats 30] [--no-estimator]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

# first, before torch loads: evtrack sets OpenMP's wait policy (see evtrack.runtime.openmp_wait)
import evtrack  # noqa: F401  # isort: skip
import cv2
import numpy as np
import torch

from evtrack.models import (
    Cuboid,
    WeightsRecord,
    count_flops,
    count_parameters,
    create,
    decode_poses,
    export_onnx,
)
from evtrack.runtime.openmp_wait import wait_policy

SIZES = ((480, 640), (240, 320))
TARGET_MS = 40.0
DEFAULT_MODELS = ("dope_lite_small", "dope_lite_base", "dope_lite_large")


def timeit(fn, repeats: int, warmup: int = 3) -> tuple[float, float]:
    """Median and minimum of ``fn()`` in milliseconds."""
    return timeit_pair(fn, None, repeats, warmup)[0]


def timeit_pair(fa, fb, repeats: int, warmup: int = 3):
    """Time ``fa`` and ``fb`` alternately (so both see the same machine load).

    Returns:
        ``((median_a, min_a), (median_b, min_b))`` in milliseconds (``None`` for a missing fb).
    """
    fns = [f for f in (fa, fb) if f is not None]
    for _ in range(warmup):
        for f in fns:
            f()
    times: list[list[float]] = [[] for _ in fns]
    for _ in range(repeats):
        for f, out in zip(fns, times, strict=True):
            t = time.perf_counter()
            f()
            out.append((time.perf_counter() - t) * 1e3)
    stats = [(statistics.median(t), min(t)) for t in times]
    return stats[0], (stats[1] if len(stats) > 1 else None)


def ort_session(path: Path, provider: str, threads: int):
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    return ort.InferenceSession(str(path), opts, providers=[provider])


_IDEAL_POSE = np.eye(4)
_IDEAL_POSE[:3, :3] = np.array([[0.36, 0.48, -0.8], [-0.8, 0.6, 0.0], [0.48, 0.64, 0.6]])
_IDEAL_POSE[:3, 3] = (0.02, -0.01, 0.6)


def ideal_maps(h: int, w: int) -> tuple[np.ndarray, np.ndarray, Cuboid, np.ndarray]:
    """Belief/affinity maps of one box at a known pose (what a good network outputs)."""
    cub = Cuboid((0.1, 0.16, 0.07))
    K = np.array([[520.0, 0, (w - 1) / 2], [0, 520.0, (h - 1) / 2], [0, 0, 1]])
    uv = cub.project(_IDEAL_POSE, K)
    gy, gx = np.mgrid[0:h // 8, 0:w // 8]
    px, py = gx * 8 + 3.5, gy * 8 + 3.5
    belief = np.stack([np.exp(-((px - u) ** 2 + (py - v) ** 2) / 128.0) for u, v in uv])
    affinity = np.zeros((16, h // 8, w // 8))
    for k in range(8):
        d = (uv[8] - uv[k]) / np.linalg.norm(uv[8] - uv[k])
        disc = np.hypot(px - uv[k, 0], py - uv[k, 1]) < 12
        affinity[2 * k][disc], affinity[2 * k + 1][disc] = d
    return belief.astype(np.float32), affinity.astype(np.float32), cub, K


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=list(DEFAULT_MODELS))
    parser.add_argument("--threads", type=int, default=2, help="CPU threads (torch and ORT)")
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--no-estimator", action="store_true",
                        help="skip the end-to-end estimator timing (it simulates one frame)")
    args = parser.parse_args()

    import onnxruntime as ort

    torch.set_num_threads(args.threads)
    cuda = torch.cuda.is_available()
    ort_cuda = "CUDAExecutionProvider" in ort.get_available_providers()
    print(f"torch {torch.__version__}, onnxruntime {ort.__version__}, CPU threads "
          f"{args.threads}, repeats {args.repeats}, CUDA: {cuda} (onnxruntime CUDA: {ort_cuda}), "
          f"OMP_WAIT_POLICY {wait_policy()}")
    print()
    header = (f"{'model':<16} {'params':>8} {'GFLOPs':>7} {'input':>8} {'device':>6} "
              f"{'torch eager ms':>20} {'onnxruntime ms':>20} {'speed-up':>8}  target")
    print("latencies: median (min) over the repeats, batch 1")
    print(header)
    print("-" * len(header))
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.models:
            torch.manual_seed(0)
            net = create(name).eval()
            params = count_parameters(net)
            record = WeightsRecord(arch=name, object_name="bench", cuboid=Cuboid((0.1,) * 3))
            path = export_onnx(net, Path(tmp) / f"{name}.onnx", record=record)
            sess = ort_session(path, "CPUExecutionProvider", args.threads)
            for h, w in SIZES:
                gflops = count_flops(net, h, w) / 1e9
                x = rng.standard_normal((1, 3, h, w)).astype(np.float32)
                xt = torch.from_numpy(x)
                with torch.inference_mode():
                    (t_med, t_min), (o_med, o_min) = timeit_pair(
                        lambda: net(xt),  # noqa: B023
                        lambda: sess.run(None, {"image": x}),  # noqa: B023
                        args.repeats)
                ok = "" if (h, w) != SIZES[0] else ("met" if o_med <= TARGET_MS else "MISSED")
                print(f"{name:<16} {params / 1e6:>7.2f}M {gflops:>7.2f} {w:>4}x{h:<3} "
                      f"{'cpu':>6} {t_med:>11.1f} ({t_min:>6.1f}) {o_med:>11.1f} ({o_min:>6.1f}) "
                      f"{t_med / o_med:>7.1f}x  {ok}")
                if cuda:
                    gnet = net.to("cuda")
                    xg = xt.to("cuda")

                    def run_gpu():
                        with torch.inference_mode():
                            gnet(xg)  # noqa: B023
                        torch.cuda.synchronize()

                    g_med, g_min = timeit(run_gpu, args.repeats)
                    og = "-"
                    if ort_cuda:
                        gs = ort_session(path, "CUDAExecutionProvider", args.threads)
                        og_med, og_min = timeit(lambda: gs.run(None, {"image": x}),  # noqa: B023
                                                args.repeats)
                        og = f"{og_med:>11.1f} ({og_min:>6.1f})"
                    print(f"{name:<16} {'':>8} {'':>7} {w:>4}x{h:<3} {'cuda':>6} "
                          f"{g_med:>11.1f} ({g_min:>6.1f}) {og:>20}")
                    net = gnet.to("cpu")
    print()
    for h, w in SIZES:
        belief, affinity, cub, K = ideal_maps(h, w)
        med, low = timeit(lambda: decode_poses(belief, affinity, cub, K),  # noqa: B023
                          args.repeats)
        print(f"decode + PnP (one instance, ideal maps) at {w}x{h}: {med:.2f} ms "
              f"(min {low:.2f})")
    print()
    time_search(args.repeats)
    if not args.no_estimator:
        print()
        time_estimators(args.threads, args.repeats)


def time_search(repeats: int) -> None:
    """The pose search on maps of one box whose corner maps all fire on every corner."""
    from evtrack.models.pose_search import search_pose

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "models"))
    from pose_search_reference import opencv_search

    belief, _, cub, K = ideal_maps(480, 640)
    uv = cub.project(_IDEAL_POSE, K)
    confused = np.maximum(belief, 0.4 * belief[:8].max(axis=0, keepdims=True).repeat(9, 0))
    confused[8] = belief[8]
    points = np.c_[uv[:8], np.ones(8)]

    def to_grid(p):
        return (p - 3.5) / 8

    def batched():
        return search_pose(points, uv[8], confused, cub, K, None, to_grid)

    def reference():
        return opencv_search(points, uv[8], confused, cub, K, to_grid)

    (b_med, b_min), (r_med, r_min) = timeit_pair(batched, reference, max(5, repeats // 3))
    found, (R, t, _, n_ref) = batched(), reference()
    same = (np.abs(cv2.Rodrigues(found.rvec)[0] - R).max() < 1e-6
            and np.abs(found.tvec.reshape(3) - t).max() < 1e-6)
    print(f"pose search, 8 points (one thread of numpy): batched P3P {b_med:.1f} ms (min "
          f"{b_min:.1f}, {found.hypotheses} poses) | cv2.solveP3P per problem {r_med:.1f} ms "
          f"(min {r_min:.1f}, {n_ref} poses) | same best pose: {'yes' if same else 'NO'}")


def time_estimators(threads: int, repeats: int) -> None:
    """The shipped demo weights end to end on one simulated 640x480 frame: one pass against
    the default second pass on a crop, torch eager and onnxruntime alternating."""
    from evtrack import Sequence
    from evtrack.cli import main as evtrack_main
    from evtrack.demo import DEMO_OBJECT
    from evtrack.eval.pose_setup import find_object_weights
    from evtrack.models import DecodeConfig, OnnxPoseEstimator, TorchPoseEstimator, load_model

    weights = find_object_weights(DEMO_OBJECT)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "seq"
        if evtrack_main(["simulate", "--object", DEMO_OBJECT, "--speed", "regular", "--seed",
                         "1000", "--duration", "0.1", "--out", str(folder), "--quiet"]) != 0:
            raise SystemExit("simulating the demo object failed")
        seq = Sequence.load(folder)
        image, cam = seq.rgb(3), seq.meta.rgb_camera
        net, _ = load_model(weights)
        onnx = export_onnx(net, Path(tmp) / "pose.onnx")
        print(f"estimator end to end, {DEMO_OBJECT} ({weights.name}), one {cam.width}x"
              f"{cam.height} frame: median (min) ms")
        print(f"{'passes':<34} {'torch eager ms':>20} {'onnxruntime ms':>20}  detections")
        passes = (("one pass", 0.0), ("+ crop pass (default)", DecodeConfig().crop_refine))
        for label, crop in passes:
            decode = DecodeConfig(crop_refine=crop)
            est_t = TorchPoseEstimator(net, cam, decode=decode)
            est_o = OnnxPoseEstimator(onnx, cam, threads=threads,
                                      providers=["CPUExecutionProvider"], decode=decode)
            (t_med, t_min), (o_med, o_min) = timeit_pair(
                lambda: est_t(image), lambda: est_o(image), repeats)  # noqa: B023
            found = len(est_o(image))
            print(f"{label:<34} {t_med:>11.1f} ({t_min:>6.1f}) {o_med:>11.1f} ({o_min:>6.1f})  "
                  f"{found}")
        est_t = TorchPoseEstimator(net, cam)
        plain = TorchPoseEstimator(net, cam, fold_batchnorm=False)
        (f_med, f_min), (p_med, p_min) = timeit_pair(lambda: est_t(image), lambda: plain(image),
                                                     repeats)
        print(f"torch, two passes: batch norms folded (default) {f_med:.1f} ms (min {f_min:.1f})"
              f" | not folded {p_med:.1f} ms (min {p_min:.1f})")
        truth = seq.ground_truth.pose_at(int(seq.rgb_times_us[3])).numpy()
        prior = seq.meta.T_event_rgb.inverse().numpy() @ truth  # event -> RGB camera
        prior[:3, 3] += (0.007, -0.007, 0.0)  # 1 cm off
        prior[:3, :3] = cv2.Rodrigues(np.radians([0.0, 0.0, 5.0]))[0] @ prior[:3, :3]
        est_o = OnnxPoseEstimator(onnx, cam, threads=threads, providers=["CPUExecutionProvider"])
        (t_med, t_min), (o_med, o_min) = timeit_pair(
            lambda: est_t.estimate_near(image, prior), lambda: est_o.estimate_near(image, prior),
            repeats)
        print(f"{'crop pass at a prior (tracking)':<34} {t_med:>11.1f} ({t_min:>6.1f}) "
              f"{o_med:>11.1f} ({o_min:>6.1f})  {len(est_o.estimate_near(image, prior))}")


if __name__ == "__main__":
    main()
