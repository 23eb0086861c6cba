"""Shared fixtures: the ../shared data folder, device and dtype options."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

SHARED = Path(__file__).resolve().parents[1].parent / "shared"


def pytest_configure(config: pytest.Config) -> None:
    # One intra-op thread: the suite's tensors are small, and on a shared 2-core machine two
    # OpenMP threads made some steps 10-100x slower. Benchmarks set their own thread counts.
    torch.set_num_threads(1)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--device", default="cpu", help="torch device for device-aware tests")


@pytest.fixture(scope="session")
def device(request: pytest.FixtureRequest) -> torch.device:
    dev = torch.device(request.config.getoption("--device"))
    if dev.type == "cuda" and not torch.cuda.is_available():
        pytest.skip("--device cuda given but CUDA is not available")
    return dev


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """The ../shared folder beside the checkout; tests that need it skip when it is absent."""
    if not SHARED.is_dir():
        pytest.skip(f"../shared is absent (looked for {SHARED}); these tests need its data files")
    return SHARED


@pytest.fixture(scope="session")
def formats_dir(shared_dir: Path) -> Path:
    path = shared_dir / "data" / "formats"
    if not path.is_dir():
        pytest.skip(f"{path} is absent: the real camera files for reader tests are missing")
    return path


@pytest.fixture(scope="session")
def ycb_dir(shared_dir: Path) -> Path:
    path = shared_dir / "data" / "ycb"
    if not path.is_dir():
        pytest.skip(f"{path} is absent: the YCB meshes are missing")
    return path


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
