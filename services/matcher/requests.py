"""Answer MatchRequests with the library's `match`: scan-to-scan, or scan-to-map here."""

from __future__ import annotations

from collections.abc import Callable

from scanflow.matching import match
from scanflow.matching.api import MapTarget, Target
from scanflow.scan import LaserScan
from scanflow.wire import MapRef, MatchRequest, MatchResponse


def answer(request: MatchRequest, map_of: Callable[[str], MapTarget | None]) -> MatchResponse:
    """Run the requested method; a missing map or bad input becomes an error response."""
    target: LaserScan | Target | None
    if isinstance(request.target, MapRef):
        target = map_of(request.target.robot_id)
        if target is None:
            return MatchResponse.from_error(
                f"no map for robot {request.target.robot_id!r} on this matcher", request.method
            )
    else:
        target = request.target
    try:
        result = match(
            request.source,
            target,
            request.initial_guess,
            method=request.method,
            **request.options,
        )
    except (ValueError, TypeError) as exc:
        return MatchResponse.from_error(f"{type(exc).__name__}: {exc}", request.method)
    return MatchResponse.from_result(result)
