"""End to end at a small resolution: the sequence folder, blur, depth, flow, determinism."""

from __future__ import annotations

import dataclasses
import filecmp
from pathlib import Path

import numpy as np
import pytest
import torch
from sim_raycast import raycast

from evtrack import Sequence
from evtrack.sim.config import EventConfig, FrameConfig, SimConfig, TrajectoryConfig
from evtrack.sim.engine import (
    MESH_FILE,
    render_times_us,
    sequence_scene,
    sequence_trajectory,
    simulate,
)
from evtrack.sim.frames import exposure_windows, linear_to_srgb
from evtrack.sim.objects import load_mesh, make_can
from evtrack.sim.renderer import Renderer
from evtrack.sim.trajectory import static_trajectory


def _config(**changes) -> SimConfig:
    base = SimConfig(duration=0.06, seed=3, trajectory=TrajectoryConfig(preset="faster"),
                     frames=FrameConfig.noiseless(),
                     events=EventConfig(threshold_mismatch=0.03))
    base = dataclasses.replace(base, camera=base.camera.resized(128, 96))
    return dataclasses.replace(base, **changes)


@pytest.fixture(scope="module")
def can():
    return make_can(seed=0)


@pytest.fixture(scope="module")
def sequence(tmp_path_factory, can) -> tuple[Path, SimConfig]:
    out = tmp_path_factory.mktemp("sim") / "can"
    cfg = _config()
    stats = simulate(can, cfg, out)
    assert stats.num_events > 1000 and stats.num_rgb == 3
    return out, cfg


def test_sequence_folder(sequence, can) -> None:
    out, cfg = sequence
    seq = Sequence.load(out)
    assert seq.meta.source == "simulation" and seq.meta.object_name == "can"
    assert seq.meta.event_camera == cfg.camera.camera() == seq.meta.rgb_camera
    assert seq.meta.rates["render_hz"] == 500.0
    ev = seq.events
    assert ev.validate().ok and ev.sensor_size == (128, 96)
    gt = seq.ground_truth
    times = render_times_us(cfg.duration, 500.0)
    assert torch.equal(gt.pose_t_us, torch.from_numpy(times))
    traj = sequence_trajectory(cfg, can)
    np.testing.assert_allclose(gt.poses.numpy(), traj.pose(times * 1e-6), atol=1e-12)
    np.testing.assert_allclose(gt.twists.numpy(), traj.twist(times * 1e-6), atol=1e-12)
    assert gt.event_flow.shape == (len(ev), 2)
    assert torch.isfinite(gt.event_flow).all()  # no noise: every event is on the object
    mesh = load_mesh(out / MESH_FILE, recenter=False)
    np.testing.assert_allclose(mesh.vertices, can.vertices, atol=1e-7)
    assert seq.num_rgb == seq.num_depth == 3


def test_event_flow_matches_finite_differences_of_the_surface_point(sequence, can) -> None:
    """At an event, the flow is d/dt of the projection of the surface point seen there."""
    out, cfg = sequence
    seq = Sequence.load(out)
    cam = seq.meta.event_camera
    traj = sequence_trajectory(cfg, can)
    ev, flow = seq.events, seq.ground_truth.event_flow.numpy()
    pick = np.random.default_rng(0).choice(len(ev), 300, replace=False)
    tm = can.to_trimesh()
    errs, h = [], 1e-6
    for i in pick:
        t = int(ev.t[i]) * 1e-6
        uv = np.array([[float(ev.x[i]), float(ev.y[i])]])
        depth, X, _ = raycast(tm, traj.pose(t), cam, uv)
        if not np.isfinite(depth[0]):
            continue  # silhouette pixel: the ray misses the surface at the event's time

        def proj(s, X=X):
            T = traj.pose(s)
            return cam.project(torch.from_numpy(X @ T[:3, :3].T + T[:3, 3])).numpy()[0]

        fd = (proj(t + h) - proj(t - h)) / (2 * h)
        errs.append(np.linalg.norm(flow[i] - fd) / max(np.linalg.norm(fd), 1.0))
    errs = np.array(errs)
    assert len(errs) > 200
    assert np.median(errs) < 0.005
    assert np.percentile(errs, 90) < 0.05


def test_blurred_frame_equals_mean_of_rendered_subframes(sequence, can) -> None:
    out, cfg = sequence
    seq = Sequence.load(out)
    cam = cfg.camera.camera()
    traj = sequence_trajectory(cfg, can)
    times = render_times_us(cfg.duration, 500.0)
    windows = exposure_windows(times, 60.0, 1.0, int(cfg.duration * 1e6))
    with Renderer(cam) as r:
        sequence_scene(cfg).apply(r)
        r.set_object(can)
        for w in windows:
            subs = [r.render(traj.pose(times[k] * 1e-6)).rgb for k in range(w.first, w.last + 1)]
            expected = linear_to_srgb(np.mean(subs, axis=0))
            assert int(seq.rgb_times_us[w.index]) == w.t_us
            diff = np.abs(seq.rgb(w.index).astype(int) - expected.astype(int))
            assert diff.max() <= 1
            # and it is blurred: differs from the single render at its middle
            mid = linear_to_srgb(subs[len(subs) // 2])
            assert np.abs(mid.astype(int) - expected.astype(int)).max() > 20
            # depth: the render nearest the frame's time, in mm
            k = w.first + int(np.argmin(np.abs(times[w.first:w.last + 1] - w.t_us)))
            assert int(seq.depth_times_us[w.index]) == times[k]
            rendered = r.render(traj.pose(times[k] * 1e-6)).depth
            np.testing.assert_allclose(seq.depth(w.index), rendered, atol=5e-4)


def test_static_scene_emits_no_events(tmp_path, can) -> None:
    T = np.eye(4)
    T[:3, 3] = [0.02, -0.01, 0.5]
    cfg = _config(duration=0.03)
    stats = simulate(can, cfg, tmp_path / "static", trajectory=static_trajectory(T, 1.0))
    assert stats.num_events == 0
    seq = Sequence.load(tmp_path / "static")
    assert len(seq.events) == 0 and seq.ground_truth.event_flow.shape == (0, 2)
    assert np.abs(seq.ground_truth.twists.numpy()).max() == 0


def _files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


def test_same_seed_same_bytes(tmp_path, can) -> None:
    cfg = _config(duration=0.04, frames=FrameConfig(),
                  events=EventConfig(shot_noise_hz=5.0, leak_noise_hz=1.0))
    a, b, c = (tmp_path / k / "seq" for k in "abc")  # same folder name: same meta.yaml
    simulate(can, cfg, a)
    simulate(can, cfg, b)
    simulate(can, dataclasses.replace(cfg, seed=4), c)
    files = _files(a)
    assert files == _files(b) and "events.h5" in files and len(files) > 8
    match, mismatch, errors = filecmp.cmpfiles(a, b, files, shallow=False)
    assert mismatch == [] and errors == []
    for name in ("events.h5", "groundtruth.h5", "rgb/000000.png", "depth/000000.png"):
        assert not filecmp.cmp(a / name, c / name, shallow=False), name


def test_adaptive_rendering_adds_renders(tmp_path, can) -> None:
    cfg = _config(duration=0.03)
    cfg = dataclasses.replace(cfg, render=dataclasses.replace(
        cfg.render, adaptive=True, max_log_change=0.2, max_subdivisions=2))
    stats = simulate(can, cfg, tmp_path / "adaptive")
    assert stats.subdivided_intervals > 0 and stats.num_renders > stats.num_base_renders
    gt = Sequence.load(tmp_path / "adaptive").ground_truth
    assert len(gt.pose_t_us) == stats.num_renders
    assert bool((gt.pose_t_us[1:] > gt.pose_t_us[:-1]).all())


def test_refuses_to_overwrite(tmp_path, can) -> None:
    (tmp_path / "x").mkdir()
    with pytest.raises(FileExistsError):
        simulate(can, _config(duration=0.02), tmp_path / "x")
