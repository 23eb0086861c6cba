"""Small shared utilities: atomic file writes, output folders, CPU thread budgets."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

__all__ = [
    "atomic_path", "atomic_write_text", "atomic_write_bytes", "usable_cpu_count",
    "threads_per_job", "check_writable", "claim_output_folder", "remove_outputs",
]


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only on success.

    On an exception the temporary file is removed, so nothing half-written is left behind.
    The temporary name ends with ``suffix`` (default: the target's suffix), for libraries
    that choose a format by extension. The finished file gets the permissions of a file
    created with ``open()`` (``0o666`` less the umask), not the private ``0o600`` of the
    temporary file.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.name}.tmp-", suffix=path.suffix if suffix is None else suffix,
        dir=path.parent,
    )
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if tmp_path.exists():
            os.chmod(tmp_path, 0o666 & ~_current_umask())
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def make_public(folder: str | Path) -> None:
    """Give ``folder`` and the folders below it the mode of one made with ``mkdir`` (``0o777``
    less the umask) instead of a temporary folder's private ``0o700``."""
    folder = Path(folder)
    mode = 0o777 & ~_current_umask()
    for sub in (folder, *(p for p in folder.rglob("*") if p.is_dir())):
        sub.chmod(mode)


def _current_umask() -> int:
    """The process umask (read by setting and restoring it)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temporary file, then rename)."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))


def check_writable(path: str | Path, what: str = "output") -> None:
    """Check before a long job that ``path`` can be written: it is no folder, and its
    nearest existing ancestor is a writable folder (the missing ones are made when writing).
    Nothing is created.

    Raises:
        ConfigError: naming ``what`` and the path.
    """
    from evtrack.errors import ConfigError

    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{what} {path} is a folder: give a file name")
    ancestor = path.parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise ConfigError(f"{what} {path}: {ancestor} is a file, not a folder")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise ConfigError(f"{what} {path}: the folder {ancestor} is not writable")


def claim_output_folder(out: str | Path, names: tuple[str, ...], overwrite: bool,
                        what: str = "--out") -> bool:
    """Make the folder ``out`` ready for a command's outputs ``names`` (files or folders):
    refuse, before any work, when an earlier run's outputs are there and ``overwrite`` is
    off; delete them when it is on. Other files in ``out`` are never touched.

    Returns:
        Whether ``out`` is new (made here): a failed run may then remove it again (see
        :func:`remove_outputs`).

    Raises:
        ConfigError: ``out`` is a file, its place is not writable, or it holds earlier
            outputs and ``overwrite`` is off (naming them and ``--overwrite``).
    """
    from evtrack.errors import ConfigError

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{what} {out}: exists and is not a folder")
    check_writable(out / names[0], what)
    earlier = [out / n for n in names if (out / n).exists()] if out.is_dir() else []
    if earlier and not overwrite:
        listed = ", ".join(p.name + ("/" if p.is_dir() else "") for p in earlier)
        raise ConfigError(f"{what} {out} holds the outputs of an earlier run ({listed}); pass "
                          f"--overwrite to replace them, or choose another {what}")
    made = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    remove_outputs(out, names)
    return made


def remove_outputs(out: str | Path, names: tuple[str, ...], made: bool = False) -> None:
    """Delete the outputs ``names`` in the folder ``out`` (files or folders; other files stay),
    and ``out`` itself when ``made`` by this run and empty then: what a failed run leaves."""
    import shutil

    out = Path(out)
    for path in (out / n for n in names):
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif path.exists() or path.is_symlink():
            path.unlink()
    if made and out.is_dir() and not any(out.iterdir()):
        out.rmdir()


def usable_cpu_count() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # macOS, Windows
        return max(1, os.cpu_count() or 1)


def threads_per_job(requested: int, jobs: int = 1, cores: int | None = None) -> int:
    """Torch threads for each of ``jobs`` concurrent jobs, so that they do not oversubscribe.

    Args:
        requested: threads asked for per job (0: as many as the share allows).
        jobs: jobs running at the same time.
        cores: cores to share (default: :func:`usable_cpu_count`).

    Returns:
        ``min(requested, cores // jobs)``, at least 1 (``cores // jobs`` when ``requested``
        is 0).
    """
    if requested < 0 or jobs < 1:
        raise ValueError(f"need requested >= 0 and jobs >= 1, got {requested} and {jobs}")
    share = max(1, (usable_cpu_count() if cores is None else cores) // jobs)
    return share if requested == 0 else min(requested, share)
