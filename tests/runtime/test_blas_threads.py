"""evtrack.runtime.blas_threads: numpy's BLAS limited inside, restored after, re-entrant per
thread."""

from __future__ import annotations

import threading

import numpy as np
import pytest

threadpoolctl = pytest.importorskip("threadpoolctl")

from evtrack.runtime.blas_threads import BlasThreads  # noqa: E402


def _blas_threads() -> list[int]:
    return [p["num_threads"] for p in threadpoolctl.threadpool_info()
            if p["user_api"] == "blas"]


@pytest.fixture()
def two_blas_threads():
    """numpy's BLAS set to 2 threads for the test (skips without a BLAS threadpoolctl sees)."""
    np.ones((2, 2)) @ np.ones((2, 2))  # BLAS loaded
    if not _blas_threads():
        pytest.skip("threadpoolctl finds no BLAS library in this process")
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        if set(_blas_threads()) != {2}:
            pytest.skip("this BLAS cannot run 2 threads")
        yield


def test_limit_inside_and_restored_after(two_blas_threads):
    limit = BlasThreads(1)
    with limit:
        assert set(_blas_threads()) == {1}
        with limit:  # nested: still limited, and the inner exit does not restore
            assert set(_blas_threads()) == {1}
        assert set(_blas_threads()) == {1}
    assert set(_blas_threads()) == {2}


def test_restored_after_an_error(two_blas_threads):
    with pytest.raises(RuntimeError, match="boom"), BlasThreads(1):
        raise RuntimeError("boom")
    assert set(_blas_threads()) == {2}
    with BlasThreads(1):  # usable again
        assert set(_blas_threads()) == {1}


def test_zero_leaves_the_setting_and_negative_is_refused(two_blas_threads):
    with BlasThreads(0):
        assert set(_blas_threads()) == {2}
    with pytest.raises(ValueError, match="threads"):
        BlasThreads(-1)


def test_depth_is_per_thread(two_blas_threads):
    """Another thread entering and leaving the same limiter does not end this thread's use."""
    limit = BlasThreads(1)
    seen = []
    with limit:
        def other():
            with limit:
                seen.append(set(_blas_threads()))

        worker = threading.Thread(target=other)
        worker.start()
        worker.join()
        # the library setting is process-wide: the other thread's exit restored it; this
        # thread's own exit still balances its enter without error
        assert seen == [{1}]
    assert limit._local.depth == 0


def test_tracker_config_field():
    from evtrack.errors import ConfigError
    from evtrack.tracking.config import TrackerConfig

    assert TrackerConfig().blas_threads == 1
    assert TrackerConfig.from_dict({"blas_threads": 0}).blas_threads == 0
    with pytest.raises(ConfigError, match="blas_threads"):
        TrackerConfig.from_dict({"blas_threads": -1})
