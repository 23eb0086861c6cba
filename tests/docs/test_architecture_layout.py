"""docs/architecture.md's package layout lists every module of the package, and no other."""

from __future__ import annotations

import os
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGE_FOLDERS = ("evtrack", "filters", "models", "train")


def _modules() -> set[str]:
    found = set()
    for top in PACKAGE_FOLDERS:
        for dirpath, dirnames, filenames in os.walk(ROOT / top):
            dirnames[:] = [d for d in dirnames if d != "__pycache__"
                           and not os.path.islink(os.path.join(dirpath, d))]
            rel = Path(dirpath).relative_to(ROOT).as_posix()
            found |= {f"{rel}/{name}" for name in filenames if name.endswith(".py")}
    return found


def _listed() -> set[str]:
    text = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    layout = text[text.index("## Package layout"):]
    layout = layout[:layout.index("\n## ", 1)]
    listed, folder = set(), None
    for line in layout.splitlines():
        heading = re.fullmatch(r"\*\*`(.+)/`\*\*", line.strip())
        if heading:
            folder = heading.group(1)
        row = re.match(r"\| `([^`]+\.py)` \| (.+) \|$", line)
        if row:
            assert folder is not None and row.group(2).strip(), line
            listed.add(f"{folder}/{row.group(1)}")
    return listed


def test_every_module_is_listed_once_with_what_it_holds() -> None:
    modules, listed = _modules(), _listed()
    assert not modules - listed, f"not in docs/architecture.md: {sorted(modules - listed)}"
    assert not listed - modules, f"listed but gone: {sorted(listed - modules)}"
