"""Motion sources by name (evtrack.tracking.motion): the built-in methods, a user's own motion
source registered and tracked with, and the registry's errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tracker_helpers import make_tracker

from evtrack.errors import ConfigError
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.motion import (
    METHODS,
    MotionSource,
    method_names,
    motion_source_class,
    register_motion_source,
)
from evtrack.tracking.motion.events import EventMotion, VelocityOnlyMotion


def test_the_built_in_methods_are_motion_sources() -> None:
    assert METHODS == ("full", "velocity", "pose", "frame-flow", "ge")
    for name in METHODS:
        assert issubclass(motion_source_class(name), MotionSource)
    assert motion_source_class("full") is EventMotion
    assert VelocityOnlyMotion.poses_only_initialise and not EventMotion.poses_only_initialise
    with pytest.raises(KeyError, match="unknown tracking method 'nope'; known: full, velocity"):
        motion_source_class("nope")
    with pytest.raises(ConfigError, match="method: must be one of"):
        TrackerConfig(method="nope")


class _TrueTwist(MotionSource):
    """A motion source of the tests: the ground truth's twist at each step."""

    truth = None  # set per test: a GroundTruth

    def __init__(self, context) -> None:
        super().__init__(context)
        self.steps = 0

    def step(self, k, dt, pose, poly, usable):
        self.steps += 1
        t_us = self.services.now() + self.config.velocity_step_us // 2
        return torch.as_tensor(self.truth.twist_at(t_us), dtype=torch.float64).reshape(1, 6)


def test_a_registered_motion_source_tracks(fast_sequence) -> None:
    """A user's motion source (the true twist) under its own method name: the tracker uses it
    for every step, and tracks better than the pose-only baseline between the poses."""
    register_motion_source("true-twist", _TrueTwist)
    try:
        assert "true-twist" in method_names()
        _TrueTwist.truth = fast_sequence.ground_truth
        tracker, _ = make_tracker(fast_sequence, method="true-twist")
        assert isinstance(tracker.motion, _TrueTwist)
        traj = tracker.track(fast_sequence)
        assert tracker.motion.steps == tracker.stats.steps > 0
        pose_only, _ = make_tracker(fast_sequence, method="pose")
        base = pose_only.track(fast_sequence)
        gt = fast_sequence.ground_truth

        def error(trajectory) -> float:
            ok = trajectory.tracked.numpy()
            poses = trajectory.poses.numpy()[ok]
            truth = np.stack([gt.pose_at(int(t)).numpy() for t in trajectory.t_us.numpy()[ok]])
            return float(np.sqrt(np.mean(np.sum((poses[:, :3, 3] - truth[:, :3, 3]) ** 2, 1))))

        assert error(traj) < error(base)
    finally:
        from evtrack.tracking import methods

        methods._registered.pop("true-twist", None)


def test_registering_checks_the_name_and_the_class() -> None:
    with pytest.raises(ValueError, match="built in"):
        register_motion_source("full", _TrueTwist)
    with pytest.raises(TypeError, match="MotionSource subclass"):
        register_motion_source("mine", object)

    @register_motion_source("decorated")
    class Decorated(MotionSource):
        pass

    try:
        assert motion_source_class("decorated") is Decorated
    finally:
        from evtrack.tracking import methods

        methods._registered.pop("decorated", None)
