"""Griffe extension for the API reference: evtrack's mapped sub-packages.

``pyproject.toml`` maps the folders ``models/``, ``filters/`` and ``train/`` into the package
as ``evtrack.models``, ``evtrack.filters`` and ``evtrack.train``. Griffe reads the sources
statically and finds ``evtrack`` alone in ``evtrack/``; this extension loads the three folders
and attaches them to ``evtrack`` under their import names.
"""

from __future__ import annotations

from typing import Any

import griffe

MAPPED = ("models", "filters", "train")


class MappedPackages(griffe.Extension):
    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs: Any) -> None:
        if pkg.name != "evtrack":
            return
        for name in MAPPED:
            if name not in pkg.members:
                pkg.set_member(name, loader.load(name))
