"""Fixtures of the training tests."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def gl():
    """Skips the test where no headless OpenGL context can be made (the renders need one)."""
    pytest.importorskip("moderngl")
    from evtrack.sim.errors import RendererUnavailableError
    from evtrack.sim.renderer import create_gl_context

    try:
        create_gl_context().release()
    except RendererUnavailableError as exc:
        pytest.skip(f"no headless OpenGL: {exc}")
