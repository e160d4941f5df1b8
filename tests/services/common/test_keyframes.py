"""Keyframes to and from a KeyframesMessage: each scan's points, stamp, mount and pose kept in
order, through a payload too."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scanflow.backend import ScanNode
from scanflow.geometry import Pose2D
from scanflow.wire import KeyframesMessage, MessageError

from services.common.keyframes import keyframes_message, scan_nodes

finite = st.floats(-1e3, 1e3, allow_nan=False)
poses = st.builds(Pose2D, finite, finite, st.floats(-3, 3))
IDENTITY = Pose2D()


def points(max_rows: int) -> st.SearchStrategy[np.ndarray]:
    return st.integers(0, max_rows).flatmap(
        lambda n: hnp.arrays(np.float64, (n, 2), elements=finite)
    )


nodes = st.builds(ScanNode, finite, points(6), points(3), poses)


def _node(stamp_s: float, hits: int, misses: int, mount: Pose2D = IDENTITY) -> ScanNode:
    """A keyframe whose hit rows are all `stamp_s` and no-return rows all `-stamp_s`."""
    return ScanNode(stamp_s, np.full((hits, 2), stamp_s), np.full((misses, 2), -stamp_s), mount)


def assert_same_nodes(got: list[ScanNode], want: list[ScanNode]) -> None:
    assert len(got) == len(want)
    for a, b in zip(got, want, strict=True):
        assert a.stamp_s == b.stamp_s and type(a.stamp_s) is float
        assert a.mount == b.mount
        np.testing.assert_array_equal(a.points, b.points.reshape(-1, 2))
        np.testing.assert_array_equal(a.no_return, b.no_return.reshape(-1, 2))


def test_a_message_lays_the_keyframes_out_in_order() -> None:
    mount = Pose2D(0.2, 0.0, 0.1)
    message = keyframes_message(
        "r", [3, 8], [_node(1.0, 2, 1, mount), _node(2.0, 1, 0)], [[1, 2, 3], [4, 5, 6]]
    )
    assert message.robot_id == "r"
    assert message.seqs.tolist() == [3, 8] and message.seqs.dtype == np.int64
    assert message.stamps_s.tolist() == [1.0, 2.0]
    assert message.poses.tolist() == [[1, 2, 3], [4, 5, 6]]
    assert message.mounts.tolist() == [mount.to_array().tolist(), [0.0, 0.0, 0.0]]
    assert message.hit_counts.tolist() == [2, 1] and message.miss_counts.tolist() == [1, 0]
    assert message.hits.tolist() == [[1.0, 1.0], [1.0, 1.0], [2.0, 2.0]]
    assert message.misses.tolist() == [[-1.0, -1.0]]


def test_no_keyframes_make_an_empty_message_and_back() -> None:
    message = keyframes_message("r", [], [], [])  # as the map server passes no poses
    assert len(message.seqs) == 0 and message.hits.shape == message.misses.shape == (0, 2)
    assert message.poses.shape == message.mounts.shape == (0, 3)
    assert scan_nodes(message) == []
    assert scan_nodes(KeyframesMessage.decode(message.encode())) == []


def test_poses_may_be_a_list_of_rows_or_one_array() -> None:
    """The map server passes a list of (3,) arrays, the matcher one (N, 3) array."""
    kept = [_node(1.0, 1, 1), _node(2.0, 1, 1)]
    rows = [np.array([1.0, 2.0, 3.0]), np.array([4.0, 5.0, 6.0])]
    for poses in (rows, np.stack(rows)):
        message = keyframes_message("r", [1, 2], kept, poses)
        assert message.poses.tolist() == [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]


@settings(max_examples=40, deadline=None)
@given(kept=st.lists(nodes, max_size=5), data=st.data())
def test_scan_nodes_gives_back_the_keyframes_a_message_was_made_of(kept, data) -> None:
    seqs = sorted(data.draw(st.sets(st.integers(0, 10**6), min_size=len(kept), max_size=len(kept))))
    drawn = data.draw(hnp.arrays(np.float64, (len(kept), 3), elements=finite))
    message = keyframes_message("robot", seqs, kept, drawn)
    assert_same_nodes(scan_nodes(message), kept)
    decoded = KeyframesMessage.decode(message.encode())
    assert_same_nodes(scan_nodes(decoded), kept)
    assert decoded.seqs.tolist() == seqs
    np.testing.assert_array_equal(decoded.poses, drawn)


@pytest.mark.parametrize(
    ("seqs", "poses", "pattern"),
    [
        ([1], np.zeros((2, 3)), "stamps_s must have shape"),  # one seq for two keyframes
        ([1, 2], np.zeros((1, 3)), "poses must have shape"),
        ([2, 1], np.zeros((2, 3)), "seqs must be >= 0 and strictly increasing"),
    ],
)
def test_keyframes_that_do_not_line_up_are_refused(seqs, poses, pattern) -> None:
    with pytest.raises(MessageError, match=pattern):
        keyframes_message("r", seqs, [_node(1.0, 1, 0), _node(2.0, 0, 1)], poses)
