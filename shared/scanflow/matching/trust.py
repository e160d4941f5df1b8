"""The check every local method's converged result passes before it may say OK.

A local method converges to the optimum of the basin it starts in, and its own score cannot
tell a wrong basin from the right one. Against a scan target the free-space test
(free_space.py) can: a result OK by the method's own checks becomes POOR_FIT when more than
`max_free_space_share` of the tested source points lie in space the target scan saw as free.

Limits, from the sensor model rather than from any log:
- margin 0.2 m: the range difference of two scans of the same surface has a standard deviation
  of sqrt(2) x the range noise (1-3 cm for the planar lidars of the logs and the simulator), so
  0.2 m is > 4 sigma of it, and it also covers the surface offset of a pose within 10 cm;
- share 0.1: at a right pose only what moved between the scans conflicts (zero on every
  simulated static pair); a person 0.5 m wide at 2.5 m covers ~11 deg, 6 % of a 180-deg scan, so
  0.1 allows one close passer-by. Simulated wrong basins (rooms and loop worlds, guesses off
  by up to 1 m / 30 deg) conflict by a median 0.17, 73 % of them above 0.1
  (BENCHMARKS.md, `## Scan matching`, the `poor_fit` update).
A map target is not tested and its results stand as they are: its points do not hold its free
space, and the free cells of an occupancy map built along drifting poses, tried and dropped,
contradict right poses too often (same update, "Front end").
"""

from __future__ import annotations

import functools
import inspect
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import Pose2D
from scanflow.matching.api import MatchResult, MatchStatus, MethodFn
from scanflow.matching.free_space import free_space_test
from scanflow.matching.inputs import require_in, require_non_negative

FREE_SPACE_MARGIN_M = 0.2
MAX_FREE_SPACE_SHARE = 0.1
# Fewer tested points give a share too noisy to judge at 10 % (one point would be >= 10 %).
MIN_TESTED = 20


def assess_fit(
    result: MatchResult,
    source: NDArray[np.float64],
    target: object,
    margin_m: float = FREE_SPACE_MARGIN_M,
    max_share: float = MAX_FREE_SPACE_SHARE,
) -> MatchResult:
    """`result` with status POOR_FIT when it is OK but contradicts the target scan's free space
    (not tested at all with `max_share` >= 1, which no share can exceed)."""
    if not result.ok or not isinstance(target, np.ndarray) or max_share >= 1.0:
        return result
    test = free_space_test(result.pose.transform_points(source), target, margin_m)
    extra = {**result.extra, "free_space_share": test.share, "free_space_tested": test.tested}
    if test.tested < MIN_TESTED or test.share <= max_share:
        return replace(result, extra=extra)
    message = (
        f"{test.share:.0%} of {test.tested} tested source points lie over {margin_m} m in front "
        f"of the target's surfaces, in space it saw as free (max_free_space_share {max_share})"
    )
    return replace(result, status=MatchStatus.POOR_FIT, message=message, extra=extra)


def fit_checked(fn: MethodFn) -> MethodFn:
    """Wrap a local method so its OK results pass `assess_fit`; the options
    `free_space_margin_m` and `max_free_space_share` set its limits."""

    @functools.wraps(fn)
    def run(
        source: NDArray[np.float64], target: object, guess: Pose2D, **options: Any
    ) -> MatchResult:
        margin_m = options.pop("free_space_margin_m", FREE_SPACE_MARGIN_M)
        max_share = options.pop("max_free_space_share", MAX_FREE_SPACE_SHARE)
        require_non_negative(free_space_margin_m=margin_m)
        require_in(0.0, 1.0, max_free_space_share=max_share)
        return assess_fit(fn(source, target, guess, **options), source, target, margin_m, max_share)

    # The method's own options and these two, as `match` checks them and help() shows them.
    # (inspect.signature reads a function's __signature__, which typeshed does not declare.)
    signature = inspect.signature(fn)
    run.__signature__ = signature.replace(  # type: ignore[attr-defined]
        parameters=[
            *signature.parameters.values(),
            *(
                inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=default,
                                  annotation=float)
                for name, default in (
                    ("free_space_margin_m", FREE_SPACE_MARGIN_M),
                    ("max_free_space_share", MAX_FREE_SPACE_SHARE),
                )
            ),
        ]
    )
    return run
