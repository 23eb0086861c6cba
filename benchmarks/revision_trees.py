"""A git revision's evtrack package, exported as an importable folder, for a benchmark that runs
an older revision beside the working tree (``benchmarks/bench_tracker.py --baseline REV``)."""

from __future__ import annotations

import shutil
import subprocess
import tarfile
from pathlib import Path

__all__ = ["PACKAGE_DIRS", "export_package", "resolve_revision", "tree_commit"]

#: The folders of a revision that make the installed package, and where each goes in it.
PACKAGE_DIRS = {"evtrack": "evtrack", "models": "evtrack/models", "filters": "evtrack/filters",
                "train": "evtrack/train"}
#: Written into an export (kept with ``--export-dir``): the commit it holds.
MARKER = ".bench-tracker-commit"


def _git(args: list[str], cwd: Path) -> str:
    out = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"git {' '.join(args)}: {out.stderr.strip()}")
    return out.stdout.strip()


def tree_commit(folder: Path) -> str:
    """``folder``'s checkout: its commit, and a note when the package's folders have
    uncommitted changes (what runs is the working tree)."""
    try:
        top = Path(_git(["rev-parse", "--show-toplevel"], folder))
        head = _git(["rev-parse", "--short", "HEAD"], top)
        dirty = _git(["status", "--porcelain", "--", *PACKAGE_DIRS], top)
    except (RuntimeError, OSError):
        return f"{folder} (not a git checkout)"
    return f"{head}" + (" + uncommitted changes" if dirty else "") + f" ({top})"


def resolve_revision(rev: str, repo: Path) -> str:
    """The full commit id of ``rev`` in ``repo``."""
    return _git(["rev-parse", "--verify", "--quiet", f"{rev}^{{commit}}"], repo)


def export_package(commit: str, repo: Path, dest: Path) -> Path:
    """Assemble an importable copy of the package of ``commit`` under ``dest``: ``dest/evtrack``
    with the revision's ``models``, ``filters``, ``train`` inside it, as installed. Returns
    ``dest`` (the folder to put on ``PYTHONPATH``). A ``dest`` that already holds ``commit``
    (written by this function) is reused, with the compiled-kernel caches in it."""
    marker = dest / MARKER
    if marker.is_file() and marker.read_text().strip() == commit:
        return dest
    if dest.exists() and any(dest.iterdir()):
        raise RuntimeError(f"{dest} is not empty and holds no export of {commit[:12]}; give an "
                           "empty or new folder")
    repo = Path(_git(["rev-parse", "--show-toplevel"], repo))  # paths are from the top
    present = _git(["ls-tree", "--name-only", commit], repo).splitlines()
    parts = [p for p in PACKAGE_DIRS if p in present]
    if "evtrack" not in parts:
        raise RuntimeError(f"revision {commit[:12]} has no evtrack/ folder")
    dest.mkdir(parents=True, exist_ok=True)
    src = dest / ".src"
    src.mkdir()
    archive = src / "tree.tar"
    _git(["archive", "--format=tar", "-o", str(archive), commit, "--", *parts], repo)
    with tarfile.open(archive) as tar:
        tar.extractall(src, filter="data")
    for part in parts:
        shutil.move(str(src / part), str(dest / PACKAGE_DIRS[part]))
    shutil.rmtree(src)
    marker.write_text(commit + "\n")
    return dest
