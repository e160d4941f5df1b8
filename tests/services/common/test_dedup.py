"""SeenSamples: a sample whose timestamp came on its key already is a copy."""

from __future__ import annotations

import pytest

from services.common.dedup import SeenSamples


def test_a_timestamp_seen_on_its_key_is_a_copy_and_none_is_never_judged() -> None:
    seen = SeenSamples()
    assert seen.first("r/scan", 1) and seen.first("r/scan", 2)
    assert not seen.first("r/scan", 1) and not seen.first("r/scan", 2)
    assert seen.first("q/scan", 1)  # another key's sample
    assert seen.first("r/scan", None) and seen.first("r/scan", None)


def test_only_the_last_samples_of_a_key_and_the_last_keys_are_remembered() -> None:
    seen = SeenSamples(per_key=3, max_keys=2)
    for t in range(4):
        assert seen.first("a", t)
    assert seen.first("a", 0)  # pushed out by 1, 2, 3
    assert not seen.first("a", 3)
    seen.first("b", 0)
    seen.first("c", 0)  # "a" was used least recently: forgotten
    assert seen.first("a", 3) and not seen.first("c", 0)


def test_bounds_must_be_positive() -> None:
    with pytest.raises(ValueError, match="per_key and max_keys"):
        SeenSamples(per_key=0)


def test_a_retired_robots_keys_are_forgotten_and_the_others_kept() -> None:
    seen = SeenSamples()
    for key in ("scan:sf/r/scan/raw", "odom:sf/r/odom", "scan:sf/r2/scan/raw"):
        seen.first(key, 1)
    assert seen.forget(lambda key: key.partition(":")[2].startswith("sf/r/")) == 2
    assert seen.first("scan:sf/r/scan/raw", 1)  # new again: a copy of it is not known
    assert not seen.first("scan:sf/r2/scan/raw", 1)
