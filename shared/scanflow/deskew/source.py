"""What deskewing needs from a source of poses over time, and how the first usable one is chosen."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

PoseArrays = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]
# The pose sources there are, by the name a deskew result reports (`DeskewResult.source_used`).
SourceName = Literal["odometry", "constant_velocity"]


class DeskewError(ValueError):
    """Deskewing input that cannot be used; the message names the field and the value."""


def finite_times(times_s: ArrayLike) -> NDArray[np.float64]:
    """`times_s` as a flat float64 array; DeskewError naming a time that is not finite (a NaN
    time would give a NaN pose, not an error)."""
    t = np.ascontiguousarray(times_s, dtype=np.float64).reshape(-1)
    if not np.isfinite(t).all():
        raise DeskewError(f"times_s must be finite, got {t[~np.isfinite(t)][0]}")
    return t


class PoseSource(Protocol):
    """Robot poses at arbitrary times, or a reason why some times cannot be covered."""

    name: SourceName

    def coverage_gap(self, start_s: float, end_s: float) -> str | None:
        """None when poses over [start_s, end_s] are available, else why not (for the result)."""
        ...

    def poses_at(self, times_s: NDArray[np.float64]) -> PoseArrays:
        """Poses (x, y, theta) at sorted times; raises DeskewError when not covered."""
        ...

    def relative_poses(self, times_s: NDArray[np.float64], reference_s: float) -> PoseArrays:
        """Poses at sorted times expressed in the frame of the pose at `reference_s`."""
        ...


def choose_source(
    sources: PoseSource | Sequence[PoseSource] | None, start_s: float, end_s: float
) -> tuple[PoseSource | None, str]:
    """The first source that covers [start_s, end_s], and the reasons the earlier ones did not."""
    if sources is None:
        return None, "no pose source given"
    candidates = sources if isinstance(sources, list | tuple) else (sources,)
    reasons: list[str] = []
    for source in candidates:
        gap = source.coverage_gap(start_s, end_s)
        if gap is None:
            return source, "; ".join(reasons)
        reasons.append(f"{source.name}: {gap}")
    return None, "; ".join(reasons) if reasons else "no pose source given"
