"""Readers of the field's datasets, and their import into evtrack sequence folders.

Each module reads one dataset's layout (BOP scenes and models, YCB-Ev, the Event Camera
Dataset) and, where it makes sequences, exposes ``register_import(subparsers)``: the
``evtrack import NAME`` subcommand (:mod:`evtrack.cli.import_data` finds it).
"""

from __future__ import annotations

import importlib
import pkgutil
from types import ModuleType

__all__ = ["importer_modules"]


def importer_modules() -> list[ModuleType]:
    """The modules of this package that define an ``evtrack import`` subcommand, by name."""
    modules = []
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{__name__}.{info.name}")
        if hasattr(module, "register_import"):
            modules.append(module)
    return modules
