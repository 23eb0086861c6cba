"""HDF5 shard caching: round trip, atomicity, corrupt and incomplete folders."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from evtrack.errors import ConfigError
from evtrack.models import Cuboid
from evtrack.train import (
    CuboidSourceOptions,
    ShardError,
    ShardSource,
    SourceSpec,
    SyntheticCuboidSource,
    build_source,
    write_shards,
)

CUBOID = Cuboid((0.1, 0.16, 0.07))


@pytest.fixture(scope="module")
def source():
    return SyntheticCuboidSource(CUBOID, 7, (48, 64), object_name="box",
                                 options=CuboidSourceOptions(max_instances=3))


@pytest.fixture(scope="module")
def folder(source, tmp_path_factory):
    out = tmp_path_factory.mktemp("shards") / "set"
    done = []
    write_shards(source, out, samples_per_shard=3, fingerprint_value="abc",
                 progress=lambda d, n: done.append((d, n)))
    assert done == [(3, 7), (6, 7), (7, 7)]
    return out


def test_roundtrip(source, folder):
    cached = ShardSource(folder)
    assert len(cached) == 7 and cached.object_name == "box" and cached.cuboid == CUBOID
    assert cached.fingerprint == "abc"
    assert sorted(p.name for p in folder.iterdir()) == [
        "index.json", "shard_00000.h5", "shard_00001.h5", "shard_00002.h5"]
    for i in range(7):
        a, b = source[i], cached[i]
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.K, b.K)
        np.testing.assert_array_equal(a.poses, b.poses)
        np.testing.assert_array_equal(a.keypoints, b.keypoints)
    assert len(ShardSource(folder, limit=4)) == 4
    with pytest.raises(ShardError, match="holds 7 samples, 9 were asked"):
        ShardSource(folder, limit=9)
    with pytest.raises(IndexError):
        cached[7]


def test_rendering_in_worker_processes_gives_the_same_shards(source, folder, tmp_path):
    out = tmp_path / "parallel"
    done = []
    write_shards(source, out, samples_per_shard=3, fingerprint_value="abc", workers=2,
                 progress=lambda d, n: done.append((d, n)))
    assert done[-1] == (7, 7) and len(done) == 3
    assert (out / "index.json").read_text() == (folder / "index.json").read_text()
    serial, parallel = ShardSource(folder), ShardSource(out)
    for i in range(7):
        np.testing.assert_array_equal(parallel[i].image, serial[i].image)
        np.testing.assert_array_equal(parallel[i].poses, serial[i].poses)
        np.testing.assert_array_equal(parallel[i].keypoints, serial[i].keypoints)
    with pytest.raises(ConfigError, match="workers must be >= 0"):
        write_shards(source, tmp_path / "bad", workers=-1)


class _BrokenAtFive:
    """A source whose sample 5 fails (module level, so spawned workers can unpickle it)."""

    def __init__(self, inner):
        self.inner = inner
        self.object_name, self.cuboid, self.description = inner.object_name, inner.cuboid, "x"

    def __len__(self):
        return len(self.inner)

    def __getitem__(self, i):
        if i == 5:
            raise RuntimeError("broken sample 5")
        return self.inner[i]


@pytest.mark.parametrize("workers", [0, 2])
def test_a_failing_sample_leaves_no_index(source, tmp_path, workers):
    out = tmp_path / "broken"
    with pytest.raises(RuntimeError, match="broken sample 5"):
        write_shards(_BrokenAtFive(source), out, samples_per_shard=3, workers=workers)
    assert not (out / "index.json").exists()


def test_source_pickles_for_worker_processes(folder):
    cached = ShardSource(folder)
    cached[0]  # opens a file handle
    clone = pickle.loads(pickle.dumps(cached))
    np.testing.assert_array_equal(clone[5].image, cached[5].image)


def test_samples_do_not_share_the_cached_shard_arrays(folder):
    cached = ShardSource(folder)
    first = cached[4]
    kept = first.keypoints.copy(), first.K.copy(), first.poses.copy()
    first.keypoints[:] = -1.0  # a caller (an augmentation) writing into its sample
    first.K[:] = 0.0
    first.poses[:] = 0.0
    again = cached[4]
    np.testing.assert_array_equal(again.keypoints, kept[0])
    np.testing.assert_array_equal(again.K, kept[1])
    np.testing.assert_array_equal(again.poses, kept[2])


def test_complete_folders_are_not_overwritten(source, folder):
    with pytest.raises(ShardError, match="already holds a complete shard set"):
        write_shards(source, folder)


def test_incomplete_folder_is_refused_then_rewritten(source, tmp_path):
    out = tmp_path / "partial"
    out.mkdir()
    (out / "shard_00000.h5").write_bytes(b"half-written")
    with pytest.raises(ShardError, match="no index.json"):
        ShardSource(out)
    write_shards(source, out, samples_per_shard=4)
    assert len(ShardSource(out)) == 7
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporaries left


def test_corrupt_and_missing_shards_are_clear_errors(source, tmp_path):
    out = tmp_path / "c"
    write_shards(source, out, samples_per_shard=4)
    (out / "shard_00001.h5").write_bytes(b"garbage")
    cached = ShardSource(out)
    cached[0]
    with pytest.raises(ShardError, match="shard_00001.h5: cannot open shard"):
        cached[5]
    (out / "shard_00001.h5").unlink()
    with pytest.raises(ShardError, match="missing"):
        ShardSource(out)
    (out / "index.json").write_text("{not json")
    with pytest.raises(ShardError, match="unreadable index"):
        ShardSource(out)


def test_shards_source_kind(folder):
    spec = SourceSpec({"folder": str(folder)}, "box", CUBOID, None, 5, (48, 64), 0)
    assert len(build_source("shards", spec)) == 5
    with pytest.raises(ConfigError, match="holds samples of 'box'"):
        build_source("shards", SourceSpec({"folder": str(folder)}, "mug", CUBOID, None, 5,
                                          (48, 64), 0))
    with pytest.raises(ConfigError, match="exactly 'folder'"):
        build_source("shards", SourceSpec({}, "box", CUBOID, None, 5, (48, 64), 0))
    with pytest.raises(ConfigError, match="unknown kind 'nope'"):
        build_source("nope", spec)
