"""The sequence folder: round trip, laziness, atomic writes, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import yaml

from evtrack import ConfigError, EventFileError, Sequence
from evtrack.geometry import integrate_twist
from evtrack.sequence import GroundTruth, SequenceWriter


def test_roundtrip(tmp_path, sequence_factory):
    seq = sequence_factory()
    seq.save(tmp_path / "seq")
    back = Sequence.load(tmp_path / "seq")
    assert back.events == seq.events
    assert back.meta.event_camera == seq.meta.event_camera
    assert back.meta.extra == {"seed": 0, "array": [0, 1, 2]}
    assert torch.equal(back.rgb_times_us, seq.rgb_times_us)
    for i in range(seq.num_rgb):
        assert np.array_equal(back.rgb(i), seq.rgb(i))
        d0, d1 = seq.depth(i), back.depth(i)
        assert np.array_equal(np.isnan(d0), np.isnan(d1))
        assert np.nanmax(np.abs(d0 - d1)) <= 0.0005 + 1e-7  # mm quantisation
    gt0, gt1 = seq.ground_truth, back.ground_truth
    assert torch.equal(gt0.poses, gt1.poses) and torch.equal(gt0.twists, gt1.twists)
    assert torch.equal(gt0.event_flow, gt1.event_flow)
    assert back.mesh_file == tmp_path / "seq" / "box.obj"


def test_float_depth_is_exact(tmp_path, sequence_factory):
    seq = sequence_factory()
    seq.meta.depth_unit = "m_float32"
    seq.save(tmp_path / "seq")
    back = Sequence.load(tmp_path / "seq")
    d0, d1 = seq.depth(1), back.depth(1)
    assert np.array_equal(np.isnan(d0), np.isnan(d1))
    assert np.nanmax(np.abs(d0 - d1)) == 0.0


def test_load_is_lazy(tmp_path, sequence_factory):
    sequence_factory().save(tmp_path / "seq")
    back = Sequence.load(tmp_path / "seq")
    assert back._events is None and not back._gt_loaded
    windows = list(back.iter_events(window_us=10_000))
    assert back._events is None
    assert sum(len(w) for w in windows) == 2000


def test_missing_depth_reads_as_nan(tmp_path, sequence_factory):
    sequence_factory().save(tmp_path / "seq")
    d = Sequence.load(tmp_path / "seq").depth(0)
    assert np.isnan(d[:2, :2]).all() and not np.isnan(d[2:, 2:]).any()


def test_failed_write_leaves_nothing(tmp_path, sequence_factory):
    seq = sequence_factory()
    with pytest.raises(RuntimeError), SequenceWriter(tmp_path / "seq", seq.meta) as w:
        w.add_events(seq.events)
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_existing_folder_needs_overwrite(tmp_path, sequence_factory):
    seq = sequence_factory()
    seq.save(tmp_path / "seq")
    with pytest.raises(FileExistsError):
        seq.save(tmp_path / "seq")
    seq2 = sequence_factory(n_events=10, seed=1)
    seq2.save(tmp_path / "seq", overwrite=True)
    assert len(Sequence.load(tmp_path / "seq").events) == 10
    assert [p.name for p in tmp_path.iterdir()] == ["seq"]


def test_frames_out_of_order_raise(tmp_path, sequence_factory):
    seq = sequence_factory()
    with pytest.raises(ValueError, match="before"), SequenceWriter(tmp_path / "s", seq.meta) as w:
        w.add_rgb(100, seq.rgb(0))
        w.add_rgb(50, seq.rgb(1))


def test_missing_meta_field_names_file_and_field(tmp_path, sequence_factory):
    sequence_factory().save(tmp_path / "seq")
    meta_path = tmp_path / "seq" / "meta.yaml"
    data = yaml.safe_load(meta_path.read_text())
    del data["event_camera"]["fx"]
    meta_path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"meta\.yaml.*event_camera.*'fx'"):
        Sequence.load(tmp_path / "seq")
    del data["event_camera"]
    meta_path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"meta\.yaml.*'event_camera'"):
        Sequence.load(tmp_path / "seq")


def test_unknown_meta_field_and_bad_yaml(tmp_path, sequence_factory):
    sequence_factory().save(tmp_path / "seq")
    meta_path = tmp_path / "seq" / "meta.yaml"
    data = yaml.safe_load(meta_path.read_text())
    data["colour"] = "red"
    meta_path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match="unknown field.*colour"):
        Sequence.load(tmp_path / "seq")
    meta_path.write_text("a: [unclosed")
    with pytest.raises(ConfigError, match="invalid YAML"):
        Sequence.load(tmp_path / "seq")


def test_not_a_sequence_folder(tmp_path):
    with pytest.raises(EventFileError, match="meta.yaml is missing"):
        Sequence.load(tmp_path)
    with pytest.raises(EventFileError, match="no such directory"):
        Sequence.load(tmp_path / "nope")


def test_bad_timestamps_file(tmp_path, sequence_factory):
    sequence_factory().save(tmp_path / "seq")
    (tmp_path / "seq" / "rgb" / "timestamps.txt").write_text("0\nabc\n")
    with pytest.raises(EventFileError, match="line 2"):
        Sequence.load(tmp_path / "seq")
    (tmp_path / "seq" / "rgb" / "timestamps.txt").write_text("10\n5\n")
    with pytest.raises(EventFileError, match="backwards"):
        Sequence.load(tmp_path / "seq")


def test_missing_frame_file(tmp_path, sequence_factory):
    sequence_factory().save(tmp_path / "seq")
    seq = Sequence.load(tmp_path / "seq")
    with pytest.raises(IndexError):
        seq.rgb(3)
    (tmp_path / "seq" / "rgb" / "000001.png").unlink()
    with pytest.raises(EventFileError, match="frame 000001 is missing"):  # at load, not later
        Sequence.load(tmp_path / "seq")
    with pytest.raises(EventFileError, match="000001.png"):  # a file gone after the load
        seq.rgb(1)


def test_frames_without_a_timestamp_are_an_error_not_left_out(tmp_path, sequence_factory):
    sequence_factory().save(tmp_path / "seq")
    stamps = tmp_path / "seq" / "depth" / "timestamps.txt"
    lines = stamps.read_text().splitlines()
    stamps.write_text("\n".join(lines[:-1]) + "\n")
    with pytest.raises(EventFileError, match=f"lists {len(lines) - 1} frames but the folder "
                                             f"has {len(lines)}"):
        Sequence.load(tmp_path / "seq")


def test_ground_truth_interpolation_is_geodesic(sequence_factory):
    seq = sequence_factory()
    gt = seq.ground_truth
    # the stored poses follow a constant twist, so interpolation must reproduce it exactly
    t = torch.tensor([1234, 25_001, 49_999])
    expected = integrate_twist(gt.poses[0].expand(3, 4, 4), gt.twists[:3], t * 1e-6)
    assert torch.allclose(gt.pose_at(t), expected, atol=1e-12)
    assert torch.allclose(gt.pose_at(-5), gt.poses[0])
    assert torch.allclose(gt.pose_at(10**9), gt.poses[-1])
    assert torch.allclose(gt.twist_at(777), gt.twists[0])


def test_ground_truth_checks_shapes():
    with pytest.raises(ValueError, match="poses"):
        GroundTruth(torch.arange(3), torch.zeros(2, 4, 4), torch.arange(2), torch.zeros(2, 6))
    with pytest.raises(ValueError, match="increasing"):
        GroundTruth(torch.tensor([0, 0]), torch.zeros(2, 4, 4), torch.arange(2),
                    torch.zeros(2, 6))


def test_summary(tmp_path, sequence_factory):
    sequence_factory().save(tmp_path / "seq")
    s = Sequence.load(tmp_path / "seq").summary()
    assert s["events"] == 2000 and s["rgb frames"] == 3 and "poses" in s["ground truth"]


def test_extra_files_land_with_the_folder(tmp_path, sequence_factory):
    seq = sequence_factory()
    with SequenceWriter(tmp_path / "seq", seq.meta) as w:
        w.add_events(seq.events)
        w.file_path("object.glb").write_bytes(b"mesh")
        assert not (tmp_path / "seq").exists()
    assert (tmp_path / "seq" / "object.glb").read_bytes() == b"mesh"
    with pytest.raises(ValueError, match="reserved"), SequenceWriter(tmp_path / "s2",
                                                                      seq.meta) as w:
        w.file_path("meta.yaml")
    with pytest.raises(ValueError, match="relative"), SequenceWriter(tmp_path / "s3",
                                                                      seq.meta) as w:
        w.file_path("../escape.txt")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]


def test_meta_fields_of_the_wrong_type_are_named(tmp_path, sequence_factory):
    sequence_factory().save(tmp_path / "seq")
    meta_path = tmp_path / "seq" / "meta.yaml"
    meta = yaml.safe_load(meta_path.read_text())
    for change, says in ((("rates", {"rgb_hz": "fast"}), "'rates.rgb_hz' must be a number"),
                         (("object", {"name": "box", "mesh": 5}), "'object.mesh' must be a file")):
        meta_path.write_text(yaml.safe_dump({**meta, change[0]: change[1]}))
        with pytest.raises(ConfigError, match=says):
            Sequence.load(tmp_path / "seq")


def test_events_of_another_sensor_size_than_meta_yaml_says_are_an_error(tmp_path,
                                                                          sequence_factory):
    sequence_factory().save(tmp_path / "seq")
    meta_path = tmp_path / "seq" / "meta.yaml"
    meta = yaml.safe_load(meta_path.read_text())
    width = meta["event_camera"]["width"]
    meta["event_camera"]["width"] = width + 10
    meta_path.write_text(yaml.safe_dump(meta))
    with pytest.raises(EventFileError, match=f"events.h5.*its sensor is {width}x.*meta.yaml "
                                             f"gives the event camera as {width + 10}x"):
        Sequence.load(tmp_path / "seq")
