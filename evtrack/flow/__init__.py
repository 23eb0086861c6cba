"""Event optical flow by triplet matching with RoI registration (method paper, Sec. III-A).

Public API::

    from evtrack.flow import TripletFlow, FlowConfig
    flow = TripletFlow(roi_size=32, window_us=2000)     # or TripletFlow(FlowConfig(...))
    res = flow(events)            # res.xy (R,2) px, res.t (R,) µs, res.flow (R,2) px/s, ...
    part = flow.update(batch)     # streaming; flow.flush() at the end; flow.reset()

``FlowConfig.backend`` and the device choose the kernels (tensors, numba on CPU, Triton on
CUDA): :func:`evtrack.flow.backends.resolve`.
"""

from evtrack.flow.candidates import Candidates, CandidateSearch
from evtrack.flow.config import FlowConfig, dt_bounds_us, search_offsets
from evtrack.flow.registration import Registration, register_groups
from evtrack.flow.result import FlowResult
from evtrack.flow.sampling import sampled_search
from evtrack.flow.triplet import TripletFlow

__all__ = [
    "Candidates",
    "CandidateSearch",
    "FlowConfig",
    "FlowResult",
    "Registration",
    "TripletFlow",
    "dt_bounds_us",
    "register_groups",
    "sampled_search",
    "search_offsets",
]
