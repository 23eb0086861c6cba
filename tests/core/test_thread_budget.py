"""CPU thread budgets: each job gets at most its share of the cores."""

from __future__ import annotations

import pytest

from evtrack import utils
from evtrack.utils import threads_per_job, usable_cpu_count


def test_usable_cpu_count_is_positive_and_bounded_by_the_machine() -> None:
    import os

    assert 1 <= usable_cpu_count() <= max(1, os.cpu_count() or 1)


@pytest.mark.parametrize(("requested", "jobs", "cores", "expected"), [
    (2, 1, 2, 2),    # what was asked, when it fits
    (2, 1, 1, 1),    # never more than the cores
    (2, 2, 2, 1),    # two jobs on two cores: one each
    (4, 2, 16, 4),   # plenty of cores: what was asked
    (0, 2, 16, 8),   # 0: the whole share
    (3, 4, 2, 1),    # more jobs than cores: still one thread
])
def test_threads_per_job(requested, jobs, cores, expected) -> None:
    assert threads_per_job(requested, jobs, cores) == expected


def test_threads_per_job_defaults_to_the_usable_cores(monkeypatch) -> None:
    monkeypatch.setattr(utils, "usable_cpu_count", lambda: 6)
    assert threads_per_job(0, 2) == 3
    assert threads_per_job(8) == 6


@pytest.mark.parametrize(("requested", "jobs"), [(-1, 1), (2, 0)])
def test_threads_per_job_refuses_nonsense(requested, jobs) -> None:
    with pytest.raises(ValueError, match="requested >= 0 and jobs >= 1"):
        threads_per_job(requested, jobs, 2)
