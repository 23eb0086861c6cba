"""The objects of a sequence with several: ``meta.yaml``'s ``objects`` list.

Each entry names an object, its mesh and its ground-truth file, relative to the sequence folder
or absolute; the first is the sequence's own object (``object``, ``groundtruth.h5``). See
:attr:`evtrack.Sequence.objects`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from evtrack.errors import ConfigError

__all__ = ["SequenceObject", "parse_objects"]


@dataclass
class SequenceObject:
    """One of several objects of a sequence (``meta.yaml``'s ``objects`` list).

    Attributes:
        name: the object's name (unique in the sequence).
        mesh_path: its mesh, relative to the sequence folder or absolute; ``None`` if unknown.
        ground_truth_path: its ground-truth file (:class:`~evtrack.sequence.GroundTruth`),
            relative or absolute; ``None`` if it has none.
    """

    name: str
    mesh_path: str | None = None
    ground_truth_path: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "mesh": self.mesh_path, "ground_truth": self.ground_truth_path}


def parse_objects(data: Any, source: str) -> list[SequenceObject]:
    """``meta.yaml``'s ``objects`` list; errors name the entry and the field."""
    if data is None:
        return []
    if not isinstance(data, list):
        raise ConfigError(f"{source}: field 'objects' must be a list of mappings with 'name', "
                          "'mesh' and 'ground_truth'")
    out = []
    for k, entry in enumerate(data):
        if not isinstance(entry, Mapping):
            raise ConfigError(f"{source}: objects[{k}] must be a mapping")
        unknown = sorted(set(entry) - {"name", "mesh", "ground_truth"})
        if unknown:
            raise ConfigError(f"{source}: objects[{k}] has unknown field(s) {unknown}")
        name = entry.get("name")
        if not isinstance(name, str) or not name:
            raise ConfigError(f"{source}: objects[{k}].name must be a non-empty string")
        paths = {}
        for key in ("mesh", "ground_truth"):
            value = entry.get(key)
            if value is not None and not isinstance(value, str):
                raise ConfigError(f"{source}: objects[{k}].{key} must be a file path, got "
                                  f"{value!r}")
            paths[key] = value
        out.append(SequenceObject(name, paths["mesh"], paths["ground_truth"]))
    return out
