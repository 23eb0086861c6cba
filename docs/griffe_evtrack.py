"""Griffe extension for the API reference (``mkdocs.yml``), not a page of the site.

- ``pyproject.toml`` maps the folders ``models/``, ``filters/`` and ``train/`` into the package
  as ``evtrack.models``, ``evtrack.filters`` and ``evtrack.train``. Griffe reads the sources
  statically and finds ``evtrack`` alone in ``evtrack/``; :class:`MappedPackages` loads the
  three folders and attaches them to ``evtrack`` under their import names.
- The docstrings cross-reference with Sphinx roles (``:class:`~evtrack.Tracker```), which
  Markdown would show as written: the extension renders each as inline code of its name
  (``Tracker``), in the rendered text only.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

MAPPED = ("models", "filters", "train")

# :role:`target`, :role:`~a.b.target` (shown as its last part), :role:`title <target>`
_ROLE = re.compile(r":(?:py:)?(?:class|meth|func|mod|attr|data|exc|obj|const|ref):`([^`]+)`")


def _role_text(match: re.Match[str]) -> str:
    text = match.group(1).strip()
    titled = re.fullmatch(r"(.+?)\s*<[^<>]+>", text)
    if titled:
        return f"`{titled.group(1)}`"
    if text.startswith("~"):
        text = text[1:].rsplit(".", 1)[-1]
    return f"`{text}`"


def plain_roles(text: str) -> str:
    """``text`` with each Sphinx cross-reference role written as inline code."""
    return _ROLE.sub(_role_text, text)


class MappedPackages(griffe.Extension):
    """Attach the mapped sub-packages to ``evtrack`` and render Sphinx roles as code."""

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader,
                   **kwargs: Any) -> None:
        if pkg.name != "evtrack":
            return
        for name in MAPPED:
            if name not in pkg.members:
                pkg.set_member(name, loader.load(name))

    def on_object(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if not obj.is_alias and obj.docstring is not None:
            obj.docstring.value = plain_roles(obj.docstring.value)
