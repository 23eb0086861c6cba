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
    "terminate_as_interrupt", "output_folder",
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
                        what: str = "--out", inputs: dict[str, str | Path | None] | None = None
                        ) -> Path | None:
    """Make the folder ``out`` ready for a command's outputs ``names`` (files or folders):
    refuse, before any work, when an earlier run's outputs are there and ``overwrite`` is
    off; delete them when it is on. Other files in ``out`` are never touched, and neither is
    any of ``inputs`` (option -> path): one that lies at or under an output's place is an
    error, with or without ``overwrite``. Temporary files an interrupted write left beside an
    output (``.NAME.tmp*``) go with the outputs.

    Returns:
        The first folder made here (``out`` or an ancestor), or ``None`` when ``out`` existed:
        a failed run removes it again if empty (see :func:`remove_outputs`).

    Raises:
        ConfigError: ``out`` is a file or a broken link, its place is not writable, an input
            lies among the outputs, or ``out`` holds earlier outputs and ``overwrite`` is off
            (naming them and ``--overwrite``).
    """
    from evtrack.errors import ConfigError

    out = Path(out)
    if out.is_symlink() and not out.exists():
        raise ConfigError(f"{what} {out}: a broken symbolic link; remove it or choose another "
                          f"{what}")
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{what} {out}: exists and is not a folder")
    if out.is_dir():
        if not os.access(out, os.W_OK | os.X_OK):
            raise ConfigError(f"{what} {out}: the folder is not writable")
    else:
        check_writable(out, what)
    for option, path in (inputs or {}).items():
        if path is None:
            continue
        inside = Path(path).resolve()
        for name in names:
            place = (out / name).resolve()
            if inside == place or place in inside.parents:
                raise ConfigError(f"{option} {path} lies in {out / name}, which this command "
                                  f"writes; choose another {what}")
    earlier = _existing_outputs(out, names)
    if earlier and not overwrite:
        listed = ", ".join(p.name + ("/" if p.is_dir() and not p.is_symlink() else "")
                           for p in earlier)
        raise ConfigError(f"{what} {out} holds the outputs of an earlier run ({listed}); pass "
                          f"--overwrite to replace them, or choose another {what}")
    first_made = next((a for a in reversed([out, *out.parents]) if not a.exists()), None)
    out.mkdir(parents=True, exist_ok=True)
    remove_outputs(out, names)
    return first_made


def _existing_outputs(out: Path, names: tuple[str, ...]) -> list[Path]:
    """The outputs ``names`` present in ``out`` (links too, even broken ones)."""
    if not out.is_dir():
        return []
    return [out / n for n in names if (out / n).exists() or (out / n).is_symlink()]


def remove_outputs(out: str | Path, names: tuple[str, ...], made: Path | None = None) -> None:
    """Delete the outputs ``names`` in the folder ``out`` (files, folders or links; a link is
    removed, never followed; other files stay) and the temporary files an interrupted write
    left beside them (``.NAME.tmp*``); then the folders from ``out`` up to ``made`` (the
    first folder a run made, see :func:`claim_output_folder`) that are empty: what a failed
    run leaves."""
    import shutil

    out = Path(out)
    if out.is_dir():
        for path in _existing_outputs(out, names):
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            else:
                path.unlink()
        for name in names:
            for tmp in out.glob(f".{name}.tmp*"):
                if tmp.is_file() or tmp.is_symlink():
                    tmp.unlink()
    chain = [out, *out.parents]
    if made is None or Path(made) not in chain:
        return
    for folder in chain[:chain.index(Path(made)) + 1]:
        if not folder.is_dir() or any(folder.iterdir()):
            break
        folder.rmdir()


@contextlib.contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """Within the block, a SIGTERM (the signal of ``kill``, ``timeout`` and job schedulers)
    raises :class:`KeyboardInterrupt` in the main thread, as Ctrl-C does, so that the clean-up
    of a long command runs instead of the process dying with half-written outputs. Outside the
    main thread, or where the platform has no SIGTERM handler, nothing changes."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread() or not hasattr(signal,
                                                                                "SIGTERM"):
        yield
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt(f"signal {signum}")

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def output_folder(out: str | Path, names: tuple[str, ...], overwrite: bool,
                  what: str = "--out", inputs: dict[str, str | Path | None] | None = None
                  ) -> Iterator[Path]:
    """A long command's work into the folder ``out``: :func:`claim_output_folder` before the
    block (its checks and errors), SIGTERM as Ctrl-C inside it (:func:`terminate_as_interrupt`),
    and on any failure or interruption :func:`remove_outputs`, so that nothing half-written is
    left behind. Yields ``out`` as a ``Path``."""
    out = Path(out)
    made = claim_output_folder(out, names, overwrite, what, inputs)
    try:
        with terminate_as_interrupt():
            yield out
    except BaseException:
        remove_outputs(out, names, made)
        raise


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
