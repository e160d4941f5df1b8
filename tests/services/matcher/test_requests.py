"""The matcher's answer to a match request that is not valid."""

from __future__ import annotations

import numpy as np
import pytest
from scanflow.wire import MatchRequest

from services.matcher.requests import answer


@pytest.mark.parametrize(
    ("options", "named"),
    [
        ({"no_such_option": 1}, "unknown option 'no_such_option' for method 'plicp'"),
        ({"max_iterations": "many"}, "option max_iterations of method 'plicp' must be"),
        ({"max_step_m": 0.0}, "option max_step_m must be > 0"),
    ],
)
def test_a_match_request_with_a_bad_option_is_answered_with_its_name(options, named) -> None:
    """Not every request comes through the gateway: the matcher's answer names the option."""
    points = np.random.default_rng(0).uniform(-3, 3, (40, 2))
    reply = answer(MatchRequest("plicp", points, points, options=options), lambda _r: None)
    assert reply.error.startswith("MatchInputError: ") and named in reply.error
