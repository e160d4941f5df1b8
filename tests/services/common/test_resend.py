"""Resend selectors and the parsing of a resend query's range."""

from __future__ import annotations

import pytest
import zenoh
from hypothesis import given
from hypothesis import strategies as st

from services.common.resend import resend_range, resend_selector


@given(st.integers(-1, 10**12), st.integers(1, 10**6))
def test_a_resend_selector_reads_back_as_its_range(after: int, span: int) -> None:
    selector = resend_selector("scanflow/r/map/resend", after, after + span)
    _, parameters = selector.split("?")
    assert resend_range(zenoh.Parameters(parameters)) == (after, after + span)


@pytest.mark.parametrize(
    ("parameters", "named"),
    [("through=4", "after"), ("after=x;through=4", "after"), ("after=2", "through"),
     ("after=-2;through=4", "after"), ("after=4;through=4", "through > after")],
)
def test_a_bad_resend_query_is_refused_naming_the_parameter(parameters: str, named: str) -> None:
    with pytest.raises(ValueError, match=named):
        resend_range(zenoh.Parameters(parameters))
