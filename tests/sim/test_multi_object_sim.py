"""Several objects in one simulation: labels, layouts, per-object ground truth, the format."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml

from evtrack import Sequence
from evtrack.errors import ConfigError
from evtrack.sequence import SequenceMeta
from evtrack.sim.config import EventConfig, FrameConfig, SimConfig, TrajectoryConfig
from evtrack.sim.engine import sequence_trajectories, sequence_trajectory, simulate
from evtrack.sim.groundtruth import point_flow
from evtrack.sim.layout import depth_bands, grid_cells, object_trajectories
from evtrack.sim.objects import make_box, make_can
from evtrack.sim.renderer import Renderer


def _config(layout: str = "apart", **changes) -> SimConfig:
    base = SimConfig(duration=0.08, seed=5,
                     trajectory=TrajectoryConfig(preset="faster", layout=layout),
                     frames=FrameConfig.noiseless(), events=EventConfig(threshold_mismatch=0.03))
    base = dataclasses.replace(base, camera=base.camera.resized(160, 120))
    return dataclasses.replace(base, **changes)


@pytest.fixture(scope="module")
def objects():
    can = make_can(seed=0)
    box = dataclasses.replace(make_box(size=(0.08, 0.1, 0.05), seed=1), name="box")
    return [can, box]


@pytest.fixture(scope="module")
def two_objects(tmp_path_factory, objects):
    out = tmp_path_factory.mktemp("multi") / "two"
    cfg = _config()
    stats = simulate(objects, cfg, out)
    assert stats.num_events > 1000
    return out, cfg


def _pose(t) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = t
    return T


def test_the_renderer_labels_each_object_and_the_nearer_hides_the_farther(objects) -> None:
    cam = _config().camera.camera()
    with Renderer(cam) as r:
        r.set_objects(objects)
        raw = r.render_raw([_pose([0.0, 0.0, 0.5]), _pose([0.02, 0.0, 0.8])]).copy()
        labels = r.labels()
        assert set(np.unique(labels)) == {0, 1, 2}
        assert np.array_equal(labels > 0, raw[..., 3] > 0)
        # each object alone: the can (nearer) keeps all its pixels, the box loses those behind
        r.set_objects([objects[0]])
        r.render_raw(_pose([0.0, 0.0, 0.5]))
        can_alone = r.labels() == 1
        r.set_objects([objects[1]])
        r.render_raw(_pose([0.02, 0.0, 0.8]))
        box_alone = r.labels() == 1
    assert np.array_equal(labels == 1, can_alone)
    assert np.array_equal(labels == 2, box_alone & ~can_alone)
    assert (box_alone & can_alone).sum() > 50  # the test has an overlap to resolve


def test_the_renderer_wants_one_pose_per_object(objects) -> None:
    with Renderer(_config().camera.camera()) as r:
        r.set_objects(objects)
        with pytest.raises(ValueError, match="1 pose.*2 object"):
            r.render_raw(_pose([0.0, 0.0, 0.5]))
        with pytest.raises(ConfigError, match="at least one mesh"):
            r.set_objects([])


def test_depth_bands_keep_neighbours_apart() -> None:
    radii = [0.1, 0.05, 0.08]
    bands = depth_bands((0.4, 1.2), radii)
    assert bands[0][0] == pytest.approx(0.4) and bands[-1][1] == pytest.approx(1.2)
    for k in range(2):
        assert bands[k + 1][0] - bands[k][1] == pytest.approx(radii[k] + radii[k + 1])
    assert len({round(b[1] - b[0], 12) for b in bands}) == 1
    with pytest.raises(ConfigError, match="z_range.*too short.*apart"):
        depth_bands((0.4, 0.6), radii)


def test_grid_cells_cover_the_image_in_reading_order() -> None:
    cam = _config().camera.camera()
    cells = grid_cells(cam, 4)
    assert cells[0] == (0.0, 79.0, 0.0, 59.0) and cells[3] == (80.0, 159.0, 60.0, 119.0)
    assert len(grid_cells(cam, 3)) == 3 and grid_cells(cam, 2)[1][0] == 80.0


@pytest.mark.parametrize("layout", ["crossing", "apart"])
def test_layouts_keep_the_objects_apart(layout) -> None:
    cfg = _config(layout, duration=1.0)
    cam = cfg.camera.camera()
    radii = [0.06, 0.05, 0.04]
    if layout == "apart":
        cfg = dataclasses.replace(cfg, trajectory=dataclasses.replace(
            cfg.trajectory, z_range=(0.4, 2.0)))
    trajs = object_trajectories(1.0, cam, radii, cfg.trajectory, [1, 2, 3])
    t = np.linspace(0.0, 1.0, 201)
    centres = np.stack([tr.pose(t)[:, :3, 3] for tr in trajs])  # (K, T, 3)
    if layout == "crossing":
        for a in range(3):
            for b in range(a + 1, 3):
                gap = np.linalg.norm(centres[a] - centres[b], axis=1)
                assert (gap >= radii[a] + radii[b] - 1e-9).all()
        return
    for k, cell in enumerate(grid_cells(cam, 3)):
        p = centres[k]
        u = cam.fx * p[:, 0] / p[:, 2] + cam.cx
        v = cam.fy * p[:, 1] / p[:, 2] + cam.cy
        ru = cam.fx * radii[k] / p[:, 2]
        rv = cam.fy * radii[k] / p[:, 2]
        assert (u - ru >= cell[0] - 1e-6).all() and (u + ru <= cell[1] + 1e-6).all()
        assert (v - rv >= cell[2] - 1e-6).all() and (v + rv <= cell[3] + 1e-6).all()


def test_an_object_that_cannot_fit_its_cell_is_refused() -> None:
    cfg = _config("apart")
    with pytest.raises(ConfigError, match="object 0.*fits in its image cell.*crossing"):
        object_trajectories(1.0, cfg.camera.camera(), [0.5, 0.05], cfg.trajectory, [1, 2])


def test_object_zero_of_one_object_keeps_the_single_object_trajectory(objects) -> None:
    cfg = _config()
    one = sequence_trajectories(cfg, objects[:1])[0]
    ref = sequence_trajectory(cfg, objects[0])
    assert np.array_equal(one.pose(np.linspace(0, 0.08, 9)), ref.pose(np.linspace(0, 0.08, 9)))


def test_a_two_object_sequence_has_per_object_files_and_ground_truth(two_objects,
                                                                     objects) -> None:
    out, cfg = two_objects
    seq = Sequence.load(out)
    assert [o.name for o in seq.objects] == ["can", "box"]
    assert seq.meta.object_name == "can" and seq.object_mesh_file(0) == seq.mesh_file
    assert seq.object_mesh_file(1) == out / "objects" / "1" / "object.glb"
    trajs = sequence_trajectories(cfg, objects)
    for k in range(2):
        gt = seq.object_ground_truth(k)
        t = gt.pose_t_us.numpy()
        assert np.allclose(gt.poses.numpy(), trajs[k].pose(t * 1e-6))
        assert np.allclose(gt.twists.numpy(), trajs[k].twist(t * 1e-6))
    meta = yaml.safe_load((out / "meta.yaml").read_text())
    assert [o["name"] for o in meta["extra"]["objects"]] == ["can", "box"]


def test_each_event_is_labelled_with_its_object_and_flows_with_it(two_objects,
                                                                   objects) -> None:
    out, cfg = two_objects
    seq = Sequence.load(out)
    gt = seq.ground_truth
    owner = gt.event_object.numpy()
    assert len(owner) == len(seq.events)
    assert set(np.unique(owner)) <= {-1, 0, 1}
    assert (owner == 0).sum() > 200 and (owner == 1).sum() > 200
    flow = gt.event_flow.numpy()
    assert np.array_equal(np.isnan(flow[:, 0]), owner == -1)
    # the flow of an event is its own object's: recompute it from that object's twist
    ev = seq.events
    trajs = sequence_trajectories(cfg, objects)
    cam = cfg.camera.camera()
    checked = 0
    with Renderer(cam) as r:
        r.set_objects(objects)
        for k in range(2):
            for i in np.flatnonzero(owner == k)[::50][:20]:
                t = int(ev.t[i])
                depth = np.abs(r.render_raw([tr.pose(t * 1e-6) for tr in trajs])[..., 3])
                labels = r.labels()
                x, y = int(ev.x[i]), int(ev.y[i])
                if labels[y, x] != k + 1:  # on an edge: the render at the event's time differs
                    continue
                ref = point_flow(np.array([[x, y]], float), np.array([depth[y, x]]),
                                 trajs[k].twist(t * 1e-6), cam)[0]
                assert np.allclose(flow[i], ref, rtol=0.05, atol=2.0)
                checked += 1
    assert checked >= 20


def test_a_saved_copy_keeps_every_object(two_objects, tmp_path) -> None:
    out, _ = two_objects
    seq = Sequence.load(out)
    seq.save(tmp_path / "copy")
    copy = Sequence.load(tmp_path / "copy")
    assert [o.name for o in copy.objects] == ["can", "box"]
    assert copy.object_mesh_file(1).is_file()
    assert np.array_equal(copy.object_ground_truth(1).poses, seq.object_ground_truth(1).poses)
    assert np.array_equal(copy.ground_truth.event_object, seq.ground_truth.event_object)


def test_objects_need_unique_names(objects, tmp_path) -> None:
    with pytest.raises(ValueError, match="unique"):
        simulate([objects[0], objects[0]], _config(), tmp_path / "x")
    with pytest.raises(ValueError, match="1 trajectories for 2 objects"):
        simulate(objects, _config(), tmp_path / "y",
                 trajectory=[sequence_trajectory(_config(), objects[0])])
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


@pytest.mark.parametrize("objects_field, message", [
    ("not a list", "field 'objects' must be a list"),
    ([{"name": "a"}, {"name": "a"}], "unique"),
    ([{"name": "a", "colour": 1}], r"objects\[0\] has unknown field"),
    ([{"name": ""}], r"objects\[0\].name must be a non-empty string"),
    ([{"name": "a", "mesh": 3}], r"objects\[0\].mesh must be a file path"),
    ([{"name": "b"}], r"objects\[0\] \('b'\) must be the sequence's object"),
])
def test_bad_objects_in_meta_are_named(objects_field, message) -> None:
    data = SequenceMeta(_config().camera.camera(), object_name="a").to_dict()
    data["objects"] = objects_field
    with pytest.raises(ConfigError, match=message):
        SequenceMeta.from_dict(data, "seq/meta.yaml")


def test_two_renderers_in_one_thread_each_draw_their_own(objects) -> None:
    """Each call makes its renderer's GL context current: interleaved renderers (one per
    tracked object's appearance alignment) give what each gives alone."""
    cam = _config().camera.camera()
    pose = _pose([0.0, 0.0, 0.5])
    with Renderer(cam) as first:
        first.set_object(objects[0])
        alone = first.render_raw(pose).copy()
        with Renderer(cam) as second:
            second.set_object(objects[1])
            other = second.render_raw(pose).copy()
            again = first.render_raw(pose).copy()
            assert np.array_equal(again, alone)
            assert np.array_equal(second.render_raw(pose), other)
            assert not np.array_equal(alone, other)
        assert np.array_equal(first.render_raw(pose), alone)
