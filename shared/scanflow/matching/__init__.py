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
    forward_options,
    match,
)

# These two pass their **options on; what they take is what those functions take.
# (Better as `register_method(..., forwards_to=[...])` in their own modules.)
forward_options("csm_exhaustive", csm.match_csm)
forward_options(global_search.GLOBAL_METHOD, global_search.localise_globally)

__all__ = [
    "DEFAULT_METHOD",
    "MatchInputError",
    "MatchResult",
    "MatchStatus",
    "available_methods",
    "match",
]
