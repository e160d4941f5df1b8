"""Service health figures a service answers on its stats queryable."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from scanflow.wire.base import Message, check_count, check_finite, check_text
from scanflow.wire.errors import MessageError
from scanflow.wire.schema import NUMBER, TEXT, Schema, mapping


@dataclass(frozen=True, eq=False)
class ServiceStatsMessage(Message):
    """Monotonic `counters` (e.g. messages_in, decode_errors) and point-in-time `gauges`.

    Gauges may be +-inf (e.g. an unbounded queue limit) but never NaN.
    """

    TYPE = "service_stats"
    WIRE: ClassVar[Schema] = {
        "service": TEXT,
        "instance": TEXT,
        "stamp_s": NUMBER,
        "counters": mapping((int,), "an integer"),
        "gauges": mapping((int, float), "a number"),
    }
    service: str
    instance: str
    stamp_s: float
    counters: dict[str, int] = field(default_factory=dict)
    gauges: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_text("service", self.service)
        check_text("instance", self.instance)
        object.__setattr__(self, "stamp_s", check_finite("stamp_s", self.stamp_s))
        counters = {
            _key("counters", k): check_count(f"counters[{k!r}]", v)
            for k, v in self.counters.items()
        }
        gauges = {_key("gauges", k): _gauge(k, v) for k, v in self.gauges.items()}
        object.__setattr__(self, "counters", counters)
        object.__setattr__(self, "gauges", gauges)


def _key(name: str, key: Any) -> str:
    if not isinstance(key, str):
        raise MessageError(f"{name} key {key!r} must be a string")
    return key


def _gauge(key: str, value: Any) -> float:
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Real):
        raise MessageError(f"gauges[{key!r}] must be a number, got {value!r}")
    if math.isnan(value):
        raise MessageError(f"gauges[{key!r}] must not be NaN")
    return float(value)
