"""Key expressions: every builder yields a valid Zenoh key, ids are checked, robot_of inverts."""

from __future__ import annotations

import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow import keys

ID_ALPHABET = "abcXYZ019_-."
ids = st.text(ID_ALPHABET, min_size=1, max_size=64).filter(lambda s: s.strip("."))
robot_ids = ids.filter(lambda s: s not in keys.RESERVED_ROBOT_IDS)
prefixes = st.lists(ids, min_size=1, max_size=3).map("/".join)
PER_ROBOT = [
    keys.raw_scan,
    keys.odom,
    keys.deskewed_scan,
    keys.pose,
    keys.robot_match,
    keys.trajectory,
    *[lambda r, p, w=w: keys.map_key(r, w, p) for w in ("meta", "image", "region", "changed")],
    lambda r, p: keys.retire(r, "matcher", p),
]


def test_default_layout() -> None:
    assert keys.raw_scan("r1") == "scanflow/r1/scan/raw"
    assert keys.deskewed_scan() == "scanflow/*/scan/deskewed"
    assert keys.map_key("r1", "region") == "scanflow/r1/map/region"
    assert keys.scan_match() == "scanflow/match"
    assert keys.retire("r1", "mapserver") == "scanflow/r1/retire/mapserver"
    assert keys.retire() == "scanflow/*/retire/*"
    assert keys.health() == "scanflow/health/*/*"
    assert keys.stats("matcher", "0", prefix="site/sf") == "site/sf/stats/matcher/0"


def test_per_robot_keys_are_distinct() -> None:
    built = [fn("r1", keys.DEFAULT_PREFIX) for fn in PER_ROBOT]
    assert len(set(built)) == len(built)


@settings(max_examples=100, deadline=None)
@given(robot_ids, prefixes, st.sampled_from(PER_ROBOT))
def test_builders_give_valid_zenoh_keys_and_robot_of_inverts(robot, prefix, build) -> None:
    key = build(robot, prefix)
    zenoh.KeyExpr(key)  # raises on an invalid key expression
    zenoh.KeyExpr(build("*", prefix))
    assert keys.robot_of(key, prefix) == robot
    assert zenoh.KeyExpr(build("*", prefix)).intersects(zenoh.KeyExpr(key))


@settings(max_examples=100, deadline=None)
@given(st.text(max_size=70).filter(
    lambda s: not (keys._ID_RE.match(s) and s.strip(".")) and s != "*"
))
def test_invalid_ids_are_rejected_with_the_value(bad: str) -> None:
    """Anything but an id, or "*" (every robot: the wildcard subscriptions use)."""
    with pytest.raises(keys.KeyExprError, match="robot id"):
        keys.raw_scan(bad)


@pytest.mark.parametrize("bad", ["", "a/b", "a*", "$x", "a b", "x" * 65, "ä", ".", ".."])
def test_bad_ids_in_every_position(bad: str) -> None:
    with pytest.raises(keys.KeyExprError, match="service"):
        keys.health(bad)
    with pytest.raises(keys.KeyExprError, match="instance"):
        keys.stats("svc", bad)
    with pytest.raises(keys.KeyExprError, match="prefix"):
        keys.pose("r", prefix=bad + "/" if bad else "")
    with pytest.raises(keys.KeyExprError, match="map topic"):
        keys.map_key("r", bad)


@pytest.mark.parametrize("robot", sorted(keys.RESERVED_ROBOT_IDS))
def test_reserved_robot_ids_would_collide_with_service_keys(robot: str) -> None:
    with pytest.raises(keys.KeyExprError, match="reserved"):
        keys.raw_scan(robot)
    # Without the reservation this scan key would equal a service key:
    assert f"scanflow/{robot}/scan/raw" in (keys.health("scan", "raw"), keys.stats("scan", "raw"))


@pytest.mark.parametrize(
    "key", ["scanflow/match", "other/r1/pose", "scanflow", "scanflowx/r1/pose", "scanflow/stats/a"]
)
def test_robot_of_rejects_keys_that_are_not_per_robot(key: str) -> None:
    with pytest.raises(keys.KeyExprError):
        keys.robot_of(key)
