"""Options of `match()`: every method's names, types and finiteness checked in one place (api),
ranges by each method; all refused with MatchInputError naming the option."""

import math
import re

import numpy as np
import pytest
from scanflow.geometry import Pose2D
from scanflow.matching import MatchInputError, available_methods, match
from scanflow.matching.api import method_options
from scanflow.matching.inputs import MAX_ITERATIONS
from scanflow.matching.plicp import match_plicp

METHODS = available_methods()


def _points() -> np.ndarray:
    t = np.linspace(0, 4, 50, endpoint=False)
    z = np.zeros_like(t)
    return np.vstack([np.c_[t, z], np.c_[z + 4, t], np.c_[4 - t, z + 4], np.c_[z, 4 - t]])


def _number_option(method: str) -> str:
    """An option of `method` that takes a number (svd's only option is its weights array)."""
    if method == "svd":
        return "weights"
    specs = method_options(method)
    assert specs is not None, f"{method} does not say which options it takes"
    return next(n for n, s in specs.items() if s.kinds is not None and float in s.kinds)


@pytest.mark.parametrize("method", METHODS)
def test_every_method_lists_its_options(method: str) -> None:
    assert method_options(method), f"{method}: no options known, so none are checked"


@pytest.mark.parametrize("method", METHODS)
def test_unknown_option_names_it_and_the_methods_options(method: str) -> None:
    with pytest.raises(MatchInputError, match=r"unknown option 'no_such_option'.*its options: \w"):
        match(_points(), _points(), method=method, no_such_option=1.0)


@pytest.mark.parametrize("method", METHODS)
def test_wrong_typed_option_is_named(method: str) -> None:
    name = _number_option(method)
    with pytest.raises(MatchInputError, match=rf"\b{name}\b"):
        match(_points(), _points(), method=method, **{name: "abc"})


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, 10**400])
@pytest.mark.parametrize("method", METHODS)
def test_non_finite_option_is_named(method: str, value: float) -> None:
    name = _number_option(method)
    with pytest.raises(MatchInputError, match=rf"option {name} .*finite"):
        match(_points(), _points(), method=method, **{name: value})


@pytest.mark.parametrize(
    ("method", "options", "name"),
    [
        ("plicp", {"max_iterations": 2.0}, "max_iterations"),  # an int option: no float
        ("plicp", {"max_iterations": True}, "max_iterations"),  # nor a bool
        ("plicp", {"max_step_m": None}, "max_step_m"),
        ("plicp", {"normal_neighbours": "8"}, "normal_neighbours"),
        ("gn", {"levels": 1.5}, "levels"),
        ("csm", {"exhaustive": 1}, "exhaustive"),  # a bool option: no int
        ("csm", {"refine": 3}, "refine"),
        ("icp", {"max_free_space_share": "0.5"}, "max_free_space_share"),  # the fit check's
        ("gn+plicp", {"max_iterations": "30"}, "max_iterations"),  # passed on to gn
        ("csm+plicp", {"cauchy_min_m": [0.01]}, "cauchy_min_m"),  # passed on to plicp
        ("global", {"candidates": 2.0}, "candidates"),
    ],
)
def test_types_that_do_not_fit_the_parameter_are_named(
    method: str, options: dict, name: str
) -> None:
    expected = rf"option {name} of method {re.escape(repr(method))} must be"
    with pytest.raises(MatchInputError, match=expected):
        match(_points(), _points(), method=method, **options)


def test_an_int_for_a_float_and_numpy_scalars_are_taken(room, caster) -> None:
    truth = Pose2D(0.1, -0.05, 0.03)
    source, target = caster(room, truth), caster(room, Pose2D())
    r = match(source, target, Pose2D(), method="plicp", max_step_m=1,
              max_iterations=np.int64(60), tolerance_m=np.float32(1e-3))
    assert r.ok and r.pose.relative_to(truth).translation_norm() < 0.01


@pytest.mark.parametrize(
    ("method", "options", "message"),
    [
        ("plicp", {"max_step_m": 0}, r"max_step_m must be > 0"),
        ("plicp", {"max_step_rad": 0}, r"max_step_rad must be > 0"),
        ("plicp", {"cauchy_min_m": math.nan}, r"cauchy_min_m .*finite"),
        ("plicp", {"cauchy_min_m": 0}, r"cauchy_min_m must be > 0"),
        ("plicp", {"normal_neighbours": 1}, r"normal_neighbours must be in \[2, 64\]"),
        # Unbounded, these overflowed or allocated without end deep inside (a fuzzing audit).
        ("plicp", {"normal_neighbours": 2**70}, r"normal_neighbours must be in \[2, 64\]"),
        ("ndt", {"cell_size_m": 1e-300}, r"cell_size_m must be in \[0.01, 10\]"),
        ("ndt", {"cell_size_m": 30.0}, r"cell_size_m must be in \[0.01, 10\]"),
        ("gn+plicp", {"gate_m": 1000.0}, r"gate_m must be <= 5"),
        ("csm", {"suppress_m": 1e300}, r"suppress_m must be <= 1000"),
        ("csm", {"resolution_m": 1e300}, r"resolution_m must be <= 1000"),
        ("csm", {"angular_resolution_rad": 1e300}, r"angular_resolution_rad must be <= 6.28"),
        ("csm", {"suppress_rad": 1e300}, r"suppress_rad must be <= 6.28"),
        ("plicp", {"normal_fit_radius_m": 0.8}, r"normal_fit_radius_m must be <= 0.5"),
        ("plicp", {"min_inlier_fraction": 1.5}, r"min_inlier_fraction must be in \[0, 1\]"),
        ("icp", {"keep_fraction": 0}, r"keep_fraction must be > 0"),
        ("icp", {"surface_step_m": 0}, r"surface_step_m must be > 0"),
        ("ndt", {"levels": 0}, r"levels must be in \[1, 16\]"),
        ("ndt", {"levels": -1}, r"levels must be in \[1, 16\]"),
        ("ndt", {"levels": 10**7}, r"levels must be in \[1, 16\]"),
        ("ndt", {"cell_size_m": 0}, r"cell_size_m must be > 0"),
        ("gn", {"resolution_m": 0}, r"resolution_m must be > 0"),
        ("gn", {"sigma_m": -1}, r"sigma_m must be > 0"),
        ("lm", {"levels": 0}, r"levels must be in \[1, 16\]"),
        ("lm", {"tau": 0}, r"tau must be > 0"),
        ("gn+plicp", {"min_gate_m": 0.5}, r"min_gate_m must be <= 0.2"),
        ("gn+plicp", {"levels": 0}, r"levels must be in \[1, 16\]"),  # gn's, passed on
        ("csm+plicp", {"hypotheses": 0}, r"hypotheses must be >= 1"),
        ("csm+plicp", {"linear_m": -1}, r"linear_m must be >= 0"),
        ("csm+plicp", {"max_step_m": 0}, r"max_step_m must be > 0"),  # plicp's, passed on
        ("gn", {"max_free_space_share": 1.5}, r"max_free_space_share must be in \[0, 1\]"),
        ("icp", {"free_space_margin_m": -0.2}, r"free_space_margin_m must be >= 0"),
    ],
)
def test_out_of_range_options_are_named_with_their_range(
    room, caster, method: str, options: dict, message: str
) -> None:
    """On real scans, where these values used to crash deep inside (ZeroDivisionError,
    UnboundLocalError, numba's LinAlgError, numpy's 'array is too big') or match anyway."""
    source, target = caster(room, Pose2D(0.1, 0.0, 0.02)), caster(room, Pose2D())
    with pytest.raises(MatchInputError, match=message):
        match(source, target, Pose2D(), method=method, **options)


@pytest.mark.parametrize("method", ["icp", "plicp", "gn", "lm", "ndt", "gn+plicp", "csm+plicp"])
@pytest.mark.parametrize("max_iterations", [0, -1])
def test_no_iterations_is_an_input_error_not_a_status(
    room, caster, method: str, max_iterations: int
) -> None:
    source, target = caster(room, Pose2D(0.1, 0.0, 0.02)), caster(room, Pose2D())
    with pytest.raises(MatchInputError, match=r"max_iterations must be >= 1"):
        match(source, target, Pose2D(), method=method, max_iterations=max_iterations)


@pytest.mark.parametrize("method", ["icp", "plicp", "gn", "lm", "ndt", "gn+plicp", "csm+plicp"])
def test_iterations_are_bounded(room, caster, method: str) -> None:
    """600,000 icp iterations held a matcher service for 22 s."""
    source, target = caster(room, Pose2D(0.1, 0.0, 0.02)), caster(room, Pose2D())
    with pytest.raises(MatchInputError, match=r"max_iterations must be <= 1000"):
        match(source, target, Pose2D(), method=method, max_iterations=MAX_ITERATIONS + 1)
    match(source, target, Pose2D(), method=method, max_iterations=MAX_ITERATIONS)


def test_a_method_called_directly_checks_its_ranges_too(room, caster) -> None:
    scan = caster(room, Pose2D())
    with pytest.raises(MatchInputError, match="max_step_m must be > 0"):
        match_plicp(scan, scan, Pose2D(), max_step_m=0.0)
