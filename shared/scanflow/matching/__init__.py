"""Scan matchers behind one interface: `match(source, target, initial_guess, method=...)`.

One module per method; importing this package registers all of them.
"""

from scanflow.matching import (  # noqa: F401  (importing registers the methods)
    csm,
    global_search,
    gn,
    gn_plicp,
    hybrid,
    icp,
    lm,
    ndt,
    plicp,
    svd,
)
from scanflow.matching.api import (
    DEFAULT_METHOD,
    MatchInputError,
    MatchResult,
    MatchStatus,
    available_methods,
    match,
)

__all__ = [
    "DEFAULT_METHOD",
    "MatchInputError",
    "MatchResult",
    "MatchStatus",
    "available_methods",
    "match",
]
