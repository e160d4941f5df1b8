"""What `match` refuses, and how: `MatchInputError`; a method's options checked against its
keyword parameters (names, scalar types, finiteness: `function_options`, `check_named`); and
the range checks that need a method's meaning, which each method makes itself
(`require_positive` and its kin, `require_iterations`)."""

from __future__ import annotations

import inspect
import math
import numbers
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np


class MatchInputError(ValueError):
    """Inputs that cannot be matched at all (wrong shapes, NaN guess, unknown method, an
    option unknown to the method, of the wrong type, not finite or out of its range)."""


_SCALARS = (bool, int, float, str, type(None))
_KIND_NAMES = {bool: "true or false", int: "an integer", float: "a number", str: "a string",
               type(None): "None"}


@dataclass(frozen=True)
class OptionSpec:
    """One keyword option of a method: the scalar types it takes (None: not checked here,
    e.g. an array, which the method checks itself)."""

    name: str
    kinds: tuple[type, ...] | None

    @property
    def expected(self) -> str:
        """The accepted types in words ("an integer or a number"), for error messages."""
        return " or ".join(_KIND_NAMES[k] for k in self.kinds or ())

    def check(self, method: str, value: Any) -> Any:
        """`value` as a plain bool/int/float/str (numpy scalars unwrapped, an int for a float
        made a float), or MatchInputError naming the option."""
        if isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_)):
            try:
                finite = math.isfinite(value)
            except OverflowError:  # an int too large for a float
                finite = False
            if not finite:
                raise MatchInputError(
                    f"option {self.name} of method {method!r} must be finite, got {value!r}"
                )
        kinds = self.kinds
        if kinds is None:
            return value
        if value is None and type(None) in kinds:
            return None
        if isinstance(value, (bool, np.bool_)):
            if bool in kinds:
                return bool(value)
        elif isinstance(value, numbers.Integral) and int in kinds:
            return int(value)
        elif isinstance(value, numbers.Real) and float in kinds:
            return float(value)
        elif isinstance(value, str) and str in kinds:
            return value
        raise MatchInputError(
            f"option {self.name} of method {method!r} must be {self.expected}, "
            f"got {type(value).__name__} {value!r}"
        )


def _option_kinds(parameter: inspect.Parameter, hints: dict[str, Any]) -> tuple[type, ...] | None:
    """The scalar types a parameter takes: from its annotation, else from its default's type;
    None when it takes anything else too (an array, an object)."""
    annotation = hints.get(parameter.name, parameter.annotation)
    if annotation is inspect.Parameter.empty or isinstance(annotation, str):
        default = parameter.default
        return None if default is None else (type(default),)
    union = isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union
    members = typing.get_args(annotation) if union else (annotation,)
    if not all(m in _SCALARS for m in members):
        return None
    return tuple(members)


def function_options(fn: Callable[..., Any]) -> tuple[dict[str, OptionSpec], bool]:
    """The keyword parameters with defaults of `fn` (through its `__signature__`, else its
    wrapped function's), and whether it also takes `**options`."""
    try:
        hints = typing.get_type_hints(inspect.unwrap(fn))
    except Exception:  # an annotation that does not evaluate: fall back to the defaults' types
        hints = {}
    specs: dict[str, OptionSpec] = {}
    var_keyword = False
    for p in inspect.signature(fn).parameters.values():
        if p.kind is p.VAR_KEYWORD:
            var_keyword = True
        elif p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD) and p.default is not p.empty:
            specs[p.name] = OptionSpec(p.name, _option_kinds(p, hints))
    return specs, var_keyword


def check_named(
    method: str, specs: dict[str, OptionSpec] | None, options: dict[str, Any]
) -> dict[str, Any]:
    """`options` of `method` as the method gets them (see `OptionSpec.check`), or
    MatchInputError naming the first one unknown to `specs` (listing them; None: any name),
    of the wrong type or not finite. Ranges are the method's own (`require_positive` and its
    kin)."""
    checked: dict[str, Any] = {}
    for name, value in options.items():
        if specs is None:
            spec = OptionSpec(name, None)  # any name: only its finiteness is checked
        elif name in specs:
            spec = specs[name]
        else:
            known = ", ".join(sorted(specs)) or "none"
            raise MatchInputError(
                f"unknown option {name!r} for method {method!r}; its options: {known}"
            )
        checked[name] = spec.check(method, value)
    return checked


def _require(test: Callable[[Any], bool], allowed: str, options: dict[str, Any]) -> None:
    for name, value in options.items():
        try:
            ok = value is None or bool(test(value))
        except (TypeError, ValueError):  # not comparable: a caller that bypassed check_options
            ok = False
        if not ok:
            raise MatchInputError(f"option {name} must be {allowed}, got {value!r}")


def require_positive(**options: Any) -> None:
    """MatchInputError naming the first option not finite and > 0 (None: not set, skipped)."""
    _require(lambda v: v > 0, "> 0", options)
    _require(lambda v: not math.isinf(v), "finite", options)


def require_non_negative(**options: Any) -> None:
    """MatchInputError naming the first option not finite and >= 0."""
    _require(lambda v: v >= 0, ">= 0", options)
    _require(lambda v: not math.isinf(v), "finite", options)


def require_at_least(minimum: int, **options: Any) -> None:
    """MatchInputError naming the first option below `minimum`."""
    _require(lambda v: v >= minimum, f">= {minimum}", options)


def require_at_most(maximum: float, **options: Any) -> None:
    """MatchInputError naming the first option above `maximum`."""
    _require(lambda v: v <= maximum, f"<= {maximum:g}", options)


MAX_ITERATIONS = 1000  # no method here gains past a few dozen; a bound keeps a request's cost


def require_iterations(max_iterations: int) -> None:
    """MatchInputError unless 1 <= max_iterations <= MAX_ITERATIONS (600,000 icp iterations
    held a matcher for 22 s)."""
    require_at_least(1, max_iterations=max_iterations)
    require_at_most(MAX_ITERATIONS, max_iterations=max_iterations)


# Cells of a grid laid over a point target's bounding box (a field, NDT's half-cells): 512 MiB
# of float64 at this cap, a 400 m square at 5 cm. One return 10 km off asked numpy for 298 GiB.
MAX_GRID_CELLS = 2**26


def require_grid_cells(rows: float, cols: float, what: str) -> None:
    """MatchInputError when a rows x cols grid over the target (`what`: built with which
    options) exceeds MAX_GRID_CELLS, before anything is allocated."""
    if rows * cols > MAX_GRID_CELLS:
        raise MatchInputError(
            f"target too large for {what}: {rows:.0f} x {cols:.0f} cells (at most "
            f"{MAX_GRID_CELLS}): a point far from the others, or cells too fine"
        )


def require_in(low: float, high: float, **options: Any) -> None:
    """MatchInputError naming the first option outside [low, high]."""
    _require(lambda v: low <= v <= high, f"in [{low:g}, {high:g}]", options)
