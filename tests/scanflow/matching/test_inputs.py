"""What match refuses: option specs read from signatures, their type and finiteness checks, and
the range checks, each refusal a MatchInputError naming the option."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any, Optional

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.matching.inputs import (
    MAX_ITERATIONS,
    MatchInputError,
    OptionSpec,
    check_named,
    function_options,
    require_at_least,
    require_at_most,
    require_in,
    require_iterations,
    require_non_negative,
    require_positive,
)

NUMBER = OptionSpec("step_m", (float,))
COUNT = OptionSpec("levels", (int,))


def _method(
    source: np.ndarray,
    target: np.ndarray,
    *,
    step_m: float = 0.5,
    levels: int = 3,
    exhaustive: bool = False,
    gate_m: float | None = None,
    old_style: Optional[int] = None,  # noqa: UP045 (the typing.Union spelling is read too)
    name: str = "x",
    weights: np.ndarray | None = None,
    untyped=1.5,
    no_default: float,
) -> None:
    """A method's signature: keyword options of every kind."""


def _open_ended(source: np.ndarray, *, step_m: float = 0.5, **options: Any) -> None:
    """A method that passes further options on."""


def test_match_input_error_is_a_value_error() -> None:
    assert issubclass(MatchInputError, ValueError)


def test_options_are_read_from_a_methods_keyword_parameters_with_defaults() -> None:
    specs, open_ended = function_options(_method)
    assert not open_ended
    assert {name: spec.kinds for name, spec in specs.items()} == {
        "step_m": (float,),
        "levels": (int,),
        "exhaustive": (bool,),
        "gate_m": (float, type(None)),
        "old_style": (int, type(None)),
        "name": (str,),
        "weights": None,  # an array: the method checks it itself
        "untyped": (float,),  # no annotation: its default's type
    }
    assert all(name == spec.name for name, spec in specs.items())
    assert function_options(_open_ended)[1]


def test_options_of_a_decorated_method_are_its_wrapped_functions() -> None:
    def decorate(fn: Callable[..., None]) -> Callable[..., None]:
        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> None:
            return fn(*args, **kwargs)

        return wrapper

    specs, open_ended = function_options(decorate(_open_ended))
    assert set(specs) == {"step_m"} and specs["step_m"].kinds == (float,) and open_ended


def test_an_annotation_that_does_not_evaluate_falls_back_to_the_defaults_type() -> None:
    def method(source: np.ndarray, *, step_m: NoSuch = 0.5, gate: NoSuch = None) -> None:  # noqa: F821
        """Annotations naming a type that is not defined anywhere."""

    specs, _ = function_options(method)
    assert specs["step_m"].kinds == (float,) and specs["gate"].kinds is None


@pytest.mark.parametrize(
    ("spec", "value", "expected"),
    [
        (NUMBER, 0.25, 0.25),
        (NUMBER, 2, 2.0),  # an int for a float is made a float
        (NUMBER, np.float32(0.5), 0.5),
        (NUMBER, np.int64(3), 3.0),
        (COUNT, np.int64(3), 3),
        (OptionSpec("flag", (bool,)), np.bool_(True), True),
        (OptionSpec("name", (str,)), "plicp", "plicp"),
        (OptionSpec("gate_m", (float, type(None))), None, None),
    ],
)
def test_option_values_come_out_as_plain_python_scalars(
    spec: OptionSpec, value: object, expected: object
) -> None:
    got = spec.check("m", value)
    assert got == expected and type(got) is type(expected)


@settings(max_examples=50, deadline=None)
@given(value=st.floats(allow_nan=False, allow_infinity=False) | st.integers(-(2**60), 2**60))
def test_any_finite_number_is_taken_for_a_float_option_unchanged(value: float) -> None:
    got = NUMBER.check("m", value)
    assert type(got) is float and got == float(value)


@pytest.mark.parametrize(
    ("spec", "value", "expected"),
    [
        (COUNT, 2.0, "an integer"),
        (COUNT, True, "an integer"),  # a bool is no integer here
        (NUMBER, np.bool_(False), "a number"),
        (NUMBER, "0.5", "a number"),
        (NUMBER, None, "a number"),
        (NUMBER, [0.5], "a number"),
        (OptionSpec("flag", (bool,)), 1, "true or false"),
        (OptionSpec("either", (int, float)), "1", "an integer or a number"),
    ],
)
def test_a_value_of_the_wrong_type_is_refused_naming_the_option_and_the_types(
    spec: OptionSpec, value: object, expected: str
) -> None:
    with pytest.raises(MatchInputError, match=rf"^option {spec.name} of method 'm' must be "
                                              rf"{expected}, got {type(value).__name__} "):
        spec.check("m", value)


@pytest.mark.parametrize("spec", [NUMBER, COUNT, OptionSpec("anything", None)])
@pytest.mark.parametrize("value", [math.nan, -math.inf, np.float64(np.inf), 10**400])
def test_a_non_finite_number_is_refused_whatever_the_options_type(
    spec: OptionSpec, value: float
) -> None:
    with pytest.raises(MatchInputError, match=rf"^option {spec.name} of method 'm' must be finite"):
        spec.check("m", value)


def test_an_option_of_no_checked_type_is_passed_on_as_it_is() -> None:
    weights = np.ones(3)
    assert OptionSpec("weights", None).check("m", weights) is weights


def test_named_options_are_checked_and_converted() -> None:
    specs, _ = function_options(_method)
    checked = check_named("m", specs, {"step_m": 1, "levels": np.int64(2), "gate_m": None})
    assert checked == {"step_m": 1.0, "levels": 2, "gate_m": None}
    assert [type(v) for v in checked.values()] == [float, int, type(None)]
    assert check_named("m", specs, {}) == {}


def test_an_unknown_option_is_refused_listing_the_methods_options() -> None:
    specs = {"b": OptionSpec("b", (float,)), "a": OptionSpec("a", (int,))}
    with pytest.raises(MatchInputError, match=r"^unknown option 'c' for method 'm'; its options: "
                                              r"a, b$"):
        check_named("m", specs, {"a": 1, "c": 2.0})
    with pytest.raises(MatchInputError, match=r"its options: none$"):
        check_named("m", {}, {"c": 2.0})


def test_an_open_method_takes_any_name_but_only_finite_numbers() -> None:
    assert check_named("m", None, {"anything": "goes", "n": 3}) == {"anything": "goes", "n": 3}
    with pytest.raises(MatchInputError, match=r"option n of method 'm' must be finite"):
        check_named("m", None, {"anything": "goes", "n": math.inf})


def test_require_names_the_first_bad_option_and_skips_unset_ones() -> None:
    require_positive(a=1.0, b=None)
    for bad in (0.0, -1.0, math.nan, "x"):
        with pytest.raises(MatchInputError, match=r"option b must be > 0"):
            require_positive(a=1.0, b=bad)


_VALUES = st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from(
    [0.0, -0.0, 1.0, -1.0, 2.0, 3.0, 5.0, 7.0, 1000.0, 1001.0, math.inf, -math.inf, math.nan])


@settings(max_examples=100, deadline=None)
@given(value=_VALUES)
def test_each_range_check_refuses_exactly_the_values_outside_its_range(value: float) -> None:
    """Every require_* against its documented predicate; a refusal names the option and the
    range it missed, an accepted value raises nothing."""
    checks: list[tuple[str, Callable[[], None], bool, str]] = [
        ("v", lambda: require_positive(v=value), value > 0 and math.isfinite(value),
         r"> 0|finite"),
        ("v", lambda: require_non_negative(v=value), value >= 0 and math.isfinite(value),
         r">= 0|finite"),
        ("v", lambda: require_at_least(2, v=value), value >= 2, r">= 2"),
        ("v", lambda: require_at_most(5.0, v=value), value <= 5, r"<= 5"),
        ("v", lambda: require_in(1.0, 7.0, v=value), 1 <= value <= 7, r"in \[1, 7\]"),
        ("max_iterations", lambda: require_iterations(value), 1 <= value <= MAX_ITERATIONS,
         rf">= 1|<= {MAX_ITERATIONS}"),
    ]
    for name, check, ok, message in checks:
        if ok:
            check()
        else:
            with pytest.raises(MatchInputError, match=rf"^option {name} must be ({message})"):
                check()


def test_range_checks_skip_unset_options_and_name_the_first_bad_one() -> None:
    require_at_least(1, a=None, b=1)
    require_in(0.0, 1.0, a=None, b=0.0, c=1.0)
    with pytest.raises(MatchInputError, match=r"^option b must be <= 0.5, got 0.8$"):
        require_at_most(0.5, a=0.5, b=0.8, c=0.9)
    with pytest.raises(MatchInputError, match=r"^option b must be finite, got inf$"):
        require_positive(a=1.0, b=math.inf, c=None)


def test_range_checks_refuse_values_that_do_not_compare() -> None:
    for check in (lambda v: require_at_least(1, a=v), lambda v: require_in(0, 1, a=v)):
        for value in ("1", [0.5], np.ones(2)):
            with pytest.raises(MatchInputError, match=r"^option a must be"):
                check(value)
