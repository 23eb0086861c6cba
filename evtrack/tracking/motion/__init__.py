"""Motion sources: what measures the object's motion between poses, one per tracking method
(``TrackerConfig.method``), found by name in a registry a user can add to.

Example (a motion source of one's own)::

    from evtrack.tracking.motion import MotionSource, register_motion_source

    @register_motion_source("still")
    class Still(MotionSource):
        def step(self, k, dt, pose, poly, usable):
            return torch.zeros(1, 6, dtype=torch.float64)

    tracker = evtrack.Tracker(evtrack.TrackerConfig(method="still"), camera=cam, mesh=mesh)
"""

from evtrack.tracking.methods import (
    METHODS,
    method_names,
    motion_source_class,
    register_motion_source,
)
from evtrack.tracking.motion.base import MotionContext, MotionServices, MotionSource, StepRun

__all__ = [
    "METHODS",
    "MotionContext",
    "MotionServices",
    "MotionSource",
    "StepRun",
    "method_names",
    "motion_source_class",
    "register_motion_source",
]
