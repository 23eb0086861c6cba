"""Fixtures of the evaluation tests: one tiny simulated benchmark shared by the session."""

from __future__ import annotations

import pytest
from eval_helpers import TINY_TRACKER_YAML, make_tiny_benchmark


@pytest.fixture(scope="session")
def tiny_benchmark(tmp_path_factory):
    """Folder with two tiny sequences (box regular, box faster), see eval_helpers."""
    return make_tiny_benchmark(tmp_path_factory.mktemp("eval") / "bench")


@pytest.fixture(scope="session")
def tiny_tracker_yaml(tmp_path_factory):
    path = tmp_path_factory.mktemp("eval_cfg") / "tracker.yaml"
    path.write_text(TINY_TRACKER_YAML)
    return path
