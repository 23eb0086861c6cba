"""Errors of the simulator (subclasses of :class:`evtrack.errors.EvtrackError`)."""

from __future__ import annotations

from evtrack.errors import EvtrackError

__all__ = ["MeshFileError", "RendererUnavailableError", "GL_SYSTEM_PACKAGES"]

#: Debian/Ubuntu packages that provide headless OpenGL through EGL (Mesa llvmpipe on CPU).
GL_SYSTEM_PACKAGES = ("libegl1", "libgl1", "libgl1-mesa-dri", "libgbm1")


class MeshFileError(EvtrackError, OSError):
    """A mesh file that is missing, unreadable, empty or implausibly sized."""

    def __init__(self, path: object, problem: str) -> None:
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self) -> tuple:
        # rebuilt from its arguments (the default would pass the message as ``path``), so
        # that the error crosses process boundaries (evaluate --jobs)
        return type(self), (self.path, self.problem)


class RendererUnavailableError(EvtrackError, RuntimeError):
    """No headless OpenGL context could be created."""
