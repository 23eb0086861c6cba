"""The output of :class:`~evtrack.flow.TripletFlow`: RoI flows and optional per-event flows."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from evtrack.utils import atomic_path

__all__ = ["FlowResult"]

_ROI_FIELDS = ("xy", "t", "flow", "support", "cost", "normal", "normal_dir", "full_flow",
               "n_events", "roi", "window")


@dataclass
class FlowResult:
    """RoI flows of consecutive time windows (R rows, sorted by window then RoI).

    Attributes:
        xy: (R, 2) float32 RoI centres in px.
        t: (R,) int64 window centres in µs.
        flow: (R, 2) float32 flow in px/s (the normal flow where ``normal``).
        support: (R,) int64 events of the RoI window with at least one candidate.
        cost: (R,) float32 mean registration cost ``min_c |F - F_ic|`` over the events used
            (px/s).
        normal: (R,) bool, True when the candidates span one direction only (aperture): then
            ``flow`` is the normal flow along ``normal_dir``.
        normal_dir: (R, 2) float32 unit normal where ``normal``, NaN elsewhere.
        full_flow: (R, 2) float32 the registered candidate itself (equals ``flow`` unless
            ``normal``).
        n_events: (R,) int64 all events of the RoI window.
        roi: (R,) int64 RoI index (row-major over the RoI grid).
        window: (R,) int64 window index (window ``w`` covers ``[w, w+1) * window_us``).
        event_start: stream index of the first event of ``event_flow``.
        event_flow: (E, 2) float32 per-event flow in px/s, or None: for each event, its
            candidate nearest to its RoI's registered flow; NaN for events without
            candidates or whose RoI window was not reported.
    """

    xy: Tensor
    t: Tensor
    flow: Tensor
    support: Tensor
    cost: Tensor
    normal: Tensor
    normal_dir: Tensor
    full_flow: Tensor
    n_events: Tensor
    roi: Tensor
    window: Tensor
    event_start: int = 0
    event_flow: Tensor | None = None

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def __repr__(self) -> str:
        n = len(self)
        parts = [f"{n} RoI flows"]
        if n:
            t0, t1 = int(self.t.min()), int(self.t.max())
            speed = torch.linalg.vector_norm(self.flow.float(), dim=1)
            parts += [f"t {t0}..{t1} µs", f"median speed {float(speed.median()):.0f} px/s",
                      f"{int(self.normal.sum())} normal-only"]
        if self.event_flow is not None:
            parts.append(f"per-event flows of {self.event_flow.shape[0]} events from "
                         f"#{self.event_start}")
        return f"FlowResult({', '.join(parts)}, device={self.t.device})"

    @classmethod
    def empty(cls, device: str | torch.device = "cpu", event_start: int = 0,
              with_events: bool = False) -> FlowResult:
        f2 = torch.zeros(0, 2, dtype=torch.float32, device=device)
        i1 = torch.zeros(0, dtype=torch.int64, device=device)
        return cls(xy=f2, t=i1, flow=f2, support=i1, cost=torch.zeros(0, device=device),
                   normal=torch.zeros(0, dtype=torch.bool, device=device), normal_dir=f2,
                   full_flow=f2, n_events=i1, roi=i1, window=i1, event_start=event_start,
                   event_flow=f2.clone() if with_events else None)

    @staticmethod
    def cat(parts: list[FlowResult]) -> FlowResult:
        """Join consecutive results of one stream (per-event flows are contiguous)."""
        if not parts:
            return FlowResult.empty()
        ev = [p.event_flow for p in parts]
        has = [e is not None for e in ev]
        if any(has) and not all(has):
            raise ValueError("cannot join results with and without per-event flows")
        # parts without rows add nothing (a streaming update has several): one part with rows
        # is the result itself, with the first part's event start
        full = [p for p in parts if len(p) or (p.event_flow is not None and len(p.event_flow))]
        if len(full) <= 1:
            return dataclasses.replace(full[0] if full else parts[0],
                                       event_start=parts[0].event_start)
        kw = {name: torch.cat([getattr(p, name) for p in full]) for name in _ROI_FIELDS}
        return FlowResult(**kw, event_start=parts[0].event_start,
                          event_flow=torch.cat([p.event_flow for p in full]) if all(has)
                          else None)

    def to(self, device: str | torch.device) -> FlowResult:
        kw = {f.name: getattr(self, f.name) for f in fields(self)}
        for name in _ROI_FIELDS:
            kw[name] = kw[name].to(device)
        if self.event_flow is not None:
            kw["event_flow"] = self.event_flow.to(device)
        return FlowResult(**kw)

    def numpy(self) -> dict[str, np.ndarray]:
        """The RoI fields (and ``event_flow`` when present) as numpy arrays."""
        out = {name: getattr(self, name).cpu().numpy() for name in _ROI_FIELDS}
        if self.event_flow is not None:
            out["event_flow"] = self.event_flow.cpu().numpy()
        return out

    def save(self, path: str | Path) -> None:
        """Write to ``.csv`` (RoI rows), ``.h5``/``.hdf5`` or ``.npz`` (atomically).

        CSV columns: ``t_us, window, roi, x, y, flow_x, flow_y, support, n_events, cost,
        normal, normal_x, normal_y, full_flow_x, full_flow_y``. HDF5/NPZ hold every field as a
        dataset/array (``event_flow`` and ``event_start`` too when present).
        """
        path = Path(path)
        suffix = path.suffix.lower()
        arrays = self.numpy()
        with atomic_path(path) as tmp:
            if suffix == ".csv":
                self._write_csv(tmp, arrays)
            elif suffix in (".h5", ".hdf5"):
                import h5py

                with h5py.File(tmp, "w") as f:
                    for name, arr in arrays.items():
                        f.create_dataset(name, data=arr)
                    f.attrs["event_start"] = self.event_start
                    f.attrs["units"] = "xy px, t µs, flow px/s"
            elif suffix == ".npz":
                with open(tmp, "wb") as fh:
                    np.savez(fh, event_start=np.int64(self.event_start), **arrays)
            else:
                raise ValueError(f"{path}: unknown flow output format '{suffix}' "
                                 "(use .csv, .h5, .hdf5 or .npz)")

    @staticmethod
    def _write_csv(path: Path, a: dict[str, np.ndarray]) -> None:
        header = ("t_us,window,roi,x,y,flow_x,flow_y,support,n_events,cost,normal,"
                  "normal_x,normal_y,full_flow_x,full_flow_y")
        lines = [header]
        for r in range(a["t"].shape[0]):
            lines.append(",".join([
                str(int(a["t"][r])), str(int(a["window"][r])), str(int(a["roi"][r])),
                f"{a['xy'][r, 0]:.1f}", f"{a['xy'][r, 1]:.1f}",
                f"{a['flow'][r, 0]:.6g}", f"{a['flow'][r, 1]:.6g}",
                str(int(a["support"][r])), str(int(a["n_events"][r])),
                f"{a['cost'][r]:.6g}", str(int(a["normal"][r])),
                f"{a['normal_dir'][r, 0]:.6g}", f"{a['normal_dir'][r, 1]:.6g}",
                f"{a['full_flow'][r, 0]:.6g}", f"{a['full_flow'][r, 1]:.6g}"]))
        path.write_text("\n".join(lines) + "\n", encoding="utf-8")
