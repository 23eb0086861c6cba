"""Source kind ``sim``: samples rendered by the synthetic data engine (``evtrack.sim``).

Wired at the end of the session once the engine's API is known (see the module body).
"""

from __future__ import annotations

from evtrack.errors import ConfigError
from evtrack.train.samples import SourceSpec, register_source

__all__: list[str] = []


@register_source("sim")
def _sim_factory(spec: SourceSpec):
    raise ConfigError("data.source 'sim' needs the synthetic data engine (evtrack.sim), "
                      "which does not provide a renderer yet; use source 'cuboid' or 'shards'")
