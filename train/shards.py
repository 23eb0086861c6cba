"""Caching samples to disk: HDF5 shards written atomically, read back as a source.

Layout of a shard folder::

    index.json            # written last: format, version, object, cuboid, image size,
                          #   fingerprint, source description, shards [{file, count}]
    shard_00000.h5        # images (S,H,W,3) uint8 chunked per image, K (S,3,3) float64,
    shard_00001.h5        #   poses (S,I,4,4) float64 and keypoints (S,I,9,2) float32 padded
    ...                   #   with NaN to I instances, num_instances (S,) int32

Every shard and the index are written to a temporary name and renamed, so a folder is either
complete (it has ``index.json``) or ignored and rewritten. Reading opens each shard lazily in
every process (DataLoader workers included) and reads one sample at a time.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from evtrack.errors import ConfigError, EvtrackError
from evtrack.models.cuboid import NUM_KEYPOINTS, Cuboid
from evtrack.train.samples import PoseSample, SampleSource, SourceSpec, register_source
from evtrack.utils import atomic_path, atomic_write_text

__all__ = ["ShardError", "ShardSource", "write_shards", "fingerprint", "INDEX_NAME"]

INDEX_NAME = "index.json"
FORMAT = "evtrack.pose_shards"
FORMAT_VERSION = 1


class ShardError(EvtrackError, OSError):
    """A shard folder or file that is missing, incomplete or corrupt."""

    def __init__(self, path: object, problem: str) -> None:
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


def fingerprint(description: dict[str, Any]) -> str:
    """A stable hex digest of a JSON-able description of what a cache holds."""
    blob = json.dumps(description, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def _write_shard(path: Path, samples: list[PoseSample]) -> None:
    s = len(samples)
    h, w = samples[0].image.shape[:2]
    inst = max(1, max(x.num_instances for x in samples))
    poses = np.full((s, inst, 4, 4), np.nan)
    kps = np.full((s, inst, NUM_KEYPOINTS, 2), np.nan, np.float32)
    for i, x in enumerate(samples):
        poses[i, : x.num_instances] = x.poses
        kps[i, : x.num_instances] = x.keypoints
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.create_dataset("images", data=np.stack([x.image for x in samples]),
                         chunks=(1, h, w, 3))
        f.create_dataset("K", data=np.stack([x.K for x in samples]).astype(np.float64))
        f.create_dataset("poses", data=poses)
        f.create_dataset("keypoints", data=kps)
        f.create_dataset("num_instances",
                         data=np.array([x.num_instances for x in samples], np.int32))


def _render_shard(source: SampleSource, path: Path, start: int, stop: int
                  ) -> tuple[int, tuple[int, int]]:
    """Render samples ``[start, stop)`` of ``source`` into the shard ``path``.

    Returns:
        ``(count, (H, W))`` of the shard's samples.

    Raises:
        ValueError: the samples' images differ in size.
    """
    batch = [source[i].check(f"sample {i}") for i in range(start, stop)]
    size = batch[0].image.shape[:2]
    for i, x in enumerate(batch):
        if x.image.shape[:2] != size:
            raise ValueError(f"sample {start + i}: image size {x.image.shape[:2]} differs "
                             f"from {size}; shards need one size")
    _write_shard(path, batch)
    return len(batch), tuple(size)


def _check_size(results: list[tuple[int, tuple[int, int]]], start: int) -> None:
    """Raise unless the last shard's image size equals the first's (``start``: its first
    sample)."""
    if results[-1][1] != results[0][1]:
        raise ValueError(f"sample {start}: image size {results[-1][1]} differs from "
                         f"{results[0][1]}; shards need one size")


def write_shards(
    source: SampleSource,
    folder: str | Path,
    *,
    samples_per_shard: int = 256,
    fingerprint_value: str = "",
    progress: Callable[[int, int], None] | None = None,
    workers: int = 0,
) -> Path:
    """Render every sample of ``source`` into HDF5 shards in ``folder``.

    An existing complete folder (with an index) is an error, so a cache is never overwritten
    by accident; an incomplete one (a crashed run) is overwritten.

    Args:
        source: any sample source; all its images must have one size. Samples must depend on
            their index only (as every registered source does), so that any split of the
            work gives the same shards.
        folder: destination folder (created).
        samples_per_shard: samples per shard file.
        fingerprint_value: stored in the index to recognise the cache later.
        progress: called with ``(done, total)`` after each shard, in shard order.
        workers: render the shards in this many processes (``spawn``ed, so each makes its
            own OpenGL context); ``0`` renders in this process. The shards are the same
            either way.

    Returns:
        ``folder``.
    """
    folder = Path(folder)
    if (folder / INDEX_NAME).exists():
        raise ShardError(folder, f"already holds a complete shard set ({INDEX_NAME}); "
                                 "remove it or choose another folder")
    if samples_per_shard < 1:
        raise ConfigError(f"samples_per_shard must be >= 1, got {samples_per_shard}")
    if workers < 0:
        raise ConfigError(f"workers must be >= 0, got {workers}")
    folder.mkdir(parents=True, exist_ok=True)
    n = len(source)
    ranges = [(start, min(n, start + samples_per_shard))
              for start in range(0, n, samples_per_shard)]
    names = [f"shard_{k:05d}.h5" for k in range(len(ranges))]
    results: list[tuple[int, tuple[int, int]]] = []
    if workers == 0 or len(ranges) < 2:
        done = 0
        for name, (start, stop) in zip(names, ranges, strict=True):
            results.append(_render_shard(source, folder / name, start, stop))
            _check_size(results, start)
            done += stop - start
            if progress is not None:
                progress(done, n)
    else:
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(min(workers, len(ranges)), mp_context=context) as pool:
            futures = [pool.submit(_render_shard, source, folder / name, start, stop)
                       for name, (start, stop) in zip(names, ranges, strict=True)]
            done = 0
            try:
                for future, (start, stop) in zip(futures, ranges, strict=True):
                    results.append(future.result())
                    _check_size(results, start)
                    done += stop - start
                    if progress is not None:
                        progress(done, n)
            except BaseException:
                pool.shutdown(cancel_futures=True)  # do not render the rest first
                raise
    size = results[0][1] if results else None
    index = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "object_name": source.object_name,
        "cuboid": source.cuboid.to_dict(),
        "image_size": list(size) if size else None,
        "num_samples": n,
        "fingerprint": fingerprint_value,
        "description": source.description,
        "shards": [{"file": name, "count": count}
                   for name, (count, _) in zip(names, results, strict=True)],
    }
    atomic_write_text(folder / INDEX_NAME, json.dumps(index, indent=1))
    return folder


class ShardSource:
    """Samples read back from a shard folder written by :func:`write_shards`.

    Args:
        folder: the shard folder.
        limit: use only the first ``limit`` samples (default: all).

    Raises:
        ShardError: no index, wrong format, or missing shard files.
    """

    def __init__(self, folder: str | Path, limit: int | None = None) -> None:
        self.folder = Path(folder)
        index_path = self.folder / INDEX_NAME
        if not index_path.is_file():
            raise ShardError(self.folder, f"no {INDEX_NAME}: not a shard folder, or its "
                                          "writing did not finish")
        try:
            index = json.loads(index_path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ShardError(index_path, f"unreadable index: {exc}") from exc
        if index.get("format") != FORMAT or index.get("format_version") != FORMAT_VERSION:
            raise ShardError(index_path, f"not a version-{FORMAT_VERSION} {FORMAT} index")
        self.index = index
        self.object_name = str(index["object_name"])
        self.cuboid = Cuboid.from_dict(index["cuboid"], f"{index_path}: cuboid")
        self.fingerprint = str(index.get("fingerprint", ""))
        self._files = [self.folder / s["file"] for s in index["shards"]]
        counts = np.array([int(s["count"]) for s in index["shards"]], np.int64)
        missing = [str(p.name) for p in self._files if not p.is_file()]
        if missing:
            raise ShardError(self.folder, f"shard file(s) missing: {missing[:5]}")
        total = int(counts.sum())
        if limit is not None and limit > total:
            raise ShardError(self.folder, f"holds {total} samples, {limit} were asked for")
        self._n = total if limit is None else int(limit)
        self._starts = np.concatenate([[0], np.cumsum(counts)])
        self.description = f"{self._n} cached samples from {self.folder} " \
                           f"({index.get('description', '')})"
        self._handles: dict[int, h5py.File] = {}
        self._meta: dict[int, dict[str, np.ndarray]] = {}
        self._pid = -1

    def __len__(self) -> int:
        return self._n

    def _file(self, shard: int) -> h5py.File:
        if self._pid != os.getpid():  # fresh handles in each (forked) process
            self._handles, self._meta, self._pid = {}, {}, os.getpid()
        if shard not in self._handles:
            path = self._files[shard]
            try:
                self._handles[shard] = h5py.File(path, "r")
            except OSError as exc:
                raise ShardError(path, f"cannot open shard: {exc}") from exc
        return self._handles[shard]

    def __getitem__(self, index: int) -> PoseSample:
        if not 0 <= index < self._n:
            raise IndexError(f"sample {index} out of range 0..{self._n - 1}")
        shard = int(np.searchsorted(self._starts, index, side="right") - 1)
        j = index - int(self._starts[shard])
        try:
            meta = self._shard_meta(shard)
            n = int(meta["num_instances"][j])
            sample = PoseSample(
                image=np.asarray(self._file(shard)["images"][j]),
                K=meta["K"][j].copy(),
                poses=meta["poses"][j, :n].copy(),
                keypoints=meta["keypoints"][j, :n].copy(),
            )
        except (KeyError, OSError, ValueError) as exc:
            raise ShardError(self._files[shard], f"corrupt shard (sample {j}): {exc}") from exc
        return sample.check(f"{self._files[shard]} sample {j}")

    def _shard_meta(self, shard: int) -> dict[str, np.ndarray]:
        """A shard's small arrays (``K``, ``poses``, ``keypoints``, ``num_instances``), read
        whole on first use and kept: one HDF5 read per sample (the image) instead of five,
        which took a third of a training item's CPU time."""
        meta = self._meta.get(shard) if self._pid == os.getpid() else None
        if meta is None:
            f = self._file(shard)  # resets the per-process caches after a fork
            meta = {
                "K": np.asarray(f["K"][()], np.float64),
                "poses": np.asarray(f["poses"][()], np.float64),
                "keypoints": np.asarray(f["keypoints"][()], np.float32),
                "num_instances": np.asarray(f["num_instances"][()], np.int64),
            }
            self._meta[shard] = meta
        return meta

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_handles"], state["_meta"], state["_pid"] = {}, {}, -1  # h5py handles do not pickle
        return state


@register_source("shards")
def _shard_factory(spec: SourceSpec) -> ShardSource:
    unknown = sorted(set(spec.options) - {"folder"})
    if unknown or "folder" not in spec.options:
        raise ConfigError(f"{spec.options_key}: the shards source takes exactly 'folder', got "
                          f"{sorted(spec.options)}")
    source = ShardSource(spec.options["folder"], limit=spec.num_samples)
    if source.object_name != spec.object_name:
        raise ConfigError(f"{spec.options_key}.folder holds samples of {source.object_name!r}, "
                          f"the config trains {spec.object_name!r}")
    return source
