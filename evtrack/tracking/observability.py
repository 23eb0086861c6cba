"""Which of the object's rotations its pose corrections observed.

A depth alignment cannot see a can turning about its axis, and an appearance alignment of a
texture-less object cannot either: the fit's Gauss-Newton information has (nearly) no weight
along such a direction, whatever pose the fit returns. :class:`RotationObservability` adds up,
per correction source (``"depth"``, ``"appearance"``), the rotational information of every
fused alignment, expressed in the **object's** frame (so that the can's axis stays one
direction while the can moves), and :meth:`RotationObservability.unobserved` names the object
axes that no source observed.

Per alignment, the rotational information is the fit's information with the translation
marginalised out (the Schur complement ``I_θθ − I_θt I_tt⁺ I_tθ``, rad⁻²), which does not depend
on the point the fit's motion is about; divided by the fit's residual variance; carried from
the camera's frame to the object's, ``Rᵀ I R`` (``R``: the aligned object-to-camera rotation).
A direction ``a`` (unit, object frame) counts as unobserved by a source when one of its
alignments, on average, pins the rotation about ``a`` no better than ``max_std_deg``: the
standard deviation ``1 / sqrt(aᵀ Ī a)`` of the source's mean information ``Ī`` (its sum over
its alignment count) is at least that; and as unobserved by the tracker when that holds for
every source that fused an alignment. The mean, not the sum: the alignments' errors are not
independent (the mesh is the same in every one), so many alignments do not pin what one
cannot.

The standard deviation is the fit's own claim (``rmse² · information⁻¹``), so the report names
the directions the geometry or texture does not constrain, not every direction a fit gets
wrong. On the simulator (640x480, one depth frame, the pose turned 5° about the object axis
and aligned again): a procedural cylinder claimed ±4.8° about its axis and was left 4.9° off
(a direction it did not observe); the YCB tomato soup can, a near-cylinder whose mesh is not
quite symmetric, claimed ±0.3-0.5° and was left 0.2-3.8° off (median 0.9°); the mustard bottle
claimed ±0.1-0.2° and was left 0.1-0.8°.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["RotationObservability", "UnobservedRotation", "rotational_information"]


def rotational_information(information: np.ndarray) -> np.ndarray:
    """(3, 3) information of the rotation ``δθ`` of a fit's (6, 6) normal matrix over
    ``[δt, δθ]`` (or ``[δv, δω]`` about any point), the translation marginalised out:
    ``I_θθ − I_θt I_tt⁺ I_tθ`` (a pseudo-inverse, so that a translation the fit did not see
    does not raise an error)."""
    info = 0.5 * (np.asarray(information, np.float64) + np.asarray(information, np.float64).T)
    if info.shape != (6, 6) or not np.isfinite(info).all():
        raise ValueError(f"rotational_information: need a finite (6, 6) matrix, got shape "
                         f"{info.shape}")
    tt, tr, rr = info[:3, :3], info[:3, 3:], info[3:, 3:]
    marginal = rr - tr.T @ np.linalg.pinv(tt, rcond=1e-12, hermitian=True) @ tr
    return 0.5 * (marginal + marginal.T)


@dataclass(frozen=True)
class UnobservedRotation:
    """An object axis about which the pose corrections did not observe the rotation.

    Attributes:
        axis: (3,) unit axis in the object's frame (its sign is arbitrary; the largest
            component is made positive).
        std_deg: per source, one alignment's standard deviation about the axis (degrees).
    """

    axis: np.ndarray
    std_deg: dict[str, float]

    def describe(self) -> str:
        """One line: the axis and each source's standard deviation about it, e.g. ``"about
        the object's axis (+0.00, +1.00, +0.00): depth ±4.8°"``."""
        axis = ", ".join(f"{v:+.2f}".replace("-0.00", "+0.00") for v in self.axis)
        std = ", ".join(f"{k} ±{v:.2g}°" for k, v in sorted(self.std_deg.items()))
        return f"about the object's axis ({axis}): {std}"


@dataclass
class RotationObservability:
    """Summed rotational information of the fused alignments, per source, object frame
    (see the module docstring).

    Attributes:
        information: per source, (3, 3) summed information (rad⁻²) in the object's frame.
        alignments: per source, alignments added.

    Example:
        >>> obs = RotationObservability()
        >>> info = np.diag([1e4, 1e4, 1e4, 1e5, 1e5, 10.0])  # the fit barely saw a turn about z
        >>> obs.add("depth", info, variance=1.0, rotation=np.eye(3))
        >>> for unobserved in obs.unobserved(max_std_deg=2.0):
        ...     print(unobserved.describe())
        about the object's axis (+0.00, +0.00, +1.00): depth ±18°
    """

    information: dict[str, np.ndarray] = field(default_factory=dict)
    alignments: dict[str, int] = field(default_factory=dict)

    def add(self, source: str, information: np.ndarray, variance: float,
            rotation: np.ndarray) -> None:
        """Add one fused alignment.

        Args:
            source: the correction's name (``"depth"``, ``"appearance"``).
            information: (6, 6) the fit's normal matrix per unit residual variance, over a
                camera-frame motion ``[δt, δθ]`` (or ``[δv, δω]`` about any point).
            variance: the fit's residual variance (its unit over the information's gives
                rad⁻²); floored at 1e-12.
            rotation: (3, 3) the aligned object-to-camera rotation, in the fit's camera.
        """
        if not math.isfinite(variance):
            raise ValueError(f"RotationObservability.add({source!r}): non-finite residual "
                             f"variance {variance}")
        R = np.asarray(rotation, np.float64).reshape(3, 3)
        info = R.T @ rotational_information(information) @ R / max(float(variance), 1e-12)
        if not np.isfinite(info).all():
            raise ValueError(f"RotationObservability.add({source!r}): non-finite information "
                             "or rotation")
        self.information[source] = self.information.get(source, np.zeros((3, 3))) + info
        self.alignments[source] = self.alignments.get(source, 0) + 1

    def std_deg(self, source: str, axis: np.ndarray) -> float:
        """One alignment's standard deviation (degrees) of ``source`` about ``axis`` (object
        frame): ``1 / sqrt(aᵀ Ī a)`` of its mean information; infinite where it has none."""
        mean = self.information[source] / self.alignments[source]
        a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
        info = float(a @ mean @ a)
        return math.degrees(1.0 / math.sqrt(info)) if info > 0 else math.inf

    def unobserved(self, max_std_deg: float = 2.0) -> list[UnobservedRotation]:
        """The object axes no source observed: each source's eigen-directions about which one
        alignment's standard deviation is at least ``max_std_deg``, kept when every other
        source's is too; of two within 25° of each other, the first. Empty when no alignment
        was added (nothing was measured, so nothing can be said)."""
        if not max_std_deg > 0:
            raise ValueError(f"max_std_deg must be > 0, got {max_std_deg}")
        found: list[UnobservedRotation] = []
        for source in sorted(self.information):
            _, V = np.linalg.eigh(self.information[source])
            for axis in V.T:
                std = {s: self.std_deg(s, axis) for s in self.information}
                if min(std.values()) < max_std_deg:
                    continue
                if any(abs(float(axis @ u.axis)) > math.cos(math.radians(25)) for u in found):
                    continue
                axis = axis * np.sign(axis[np.argmax(np.abs(axis))])
                found.append(UnobservedRotation(axis + 0.0, std))
        return found

    def to_dict(self, max_std_deg: float = 2.0) -> dict[str, object]:
        """The counts and the unobserved axes, for JSON."""
        return {"alignments": dict(self.alignments),
                "unobserved": [{"axis": [round(float(v), 4) for v in u.axis],
                                "std_deg": {k: float(f"{v:.3g}") for k, v in u.std_deg.items()}}
                               for u in self.unobserved(max_std_deg)]}
