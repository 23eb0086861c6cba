"""The ``ge`` baseline's motion source: the 1-DoF generative event model
(:mod:`evtrack.tracking.baselines.ge_model`) in place of the flow."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from evtrack.errors import ConfigError
from evtrack.events import Events
from evtrack.tracking.baselines.ge_model import GEVelocity
from evtrack.tracking.motion.base import MotionContext, MotionSource
from evtrack.tracking.silhouette import SilhouettePolygon
from evtrack.tracking.stats import StageTimer

__all__ = ["GEMotion"]


class GEMotion(MotionSource):
    """One Kalman row per event against the last RGB frame's log-intensity gradient
    (``method: ge``); needs the RGB frames in the event camera's image."""

    uses_events = True
    uses_rgb = True

    def __init__(self, context: MotionContext) -> None:
        super().__init__(context)
        if not context.aligned:
            raise ConfigError("method 'ge' needs the RGB frames in the event camera's image "
                              "(same camera, identity T_event_rgb)")
        cfg = self.config
        self.ge = GEVelocity(context.camera, cfg.ge, cfg.velocity_kf, device=self.device)
        self._events: Events | None = None
        self._cuts: list[int] | None = None

    def reset(self) -> None:
        self.ge.reset()

    def lost(self) -> None:
        self.ge.reset()

    def twist(self) -> np.ndarray:
        return np.array(self.ge.twist.tolist()[0], np.float64)

    def begin_group(self, ev: Events, t0: int, t_end: int, pose: np.ndarray | None,
                    search_budget: int) -> None:
        step = self.config.velocity_step_us
        n_steps = (t_end - t0) // step
        self._events = ev
        self._cuts = torch.searchsorted(ev.t, t0 + step * torch.arange(
            1, n_steps + 1, dtype=torch.int64)).tolist() if len(ev) else None

    def step(self, k: int, dt: float, pose: np.ndarray | None,
             poly: SilhouettePolygon | None, usable: bool) -> Tensor:
        ev, cuts = self._events, self._cuts
        lo = cuts[k - 1] if (cuts and k) else 0
        ev_k = ev[lo:cuts[k]] if cuts else ev
        depth, t_now = self.services.depth, self.services.now()
        with StageTimer(self.stats.time_s, "velocity"):
            twist = self.ge.step(
                dt, ev_k, pose if (poly is not None and usable) else None,
                lambda uv: depth.lookup(uv, poly, pose, t_now, patch=False))
            self.stats.velocity_updates += int(self.ge.last_rows > 0)
        return twist

    def on_rgb(self, t_us: int, read: Callable[[], np.ndarray]) -> np.ndarray:
        image = read()
        services = self.services
        self.ge.set_frame(t_us, image, services.pose(t_us) if services.initialized() else None)
        return image
