"""Pacing and backpressure for ingest: real time (or a multiple), or credit from pose seqs."""

from __future__ import annotations

import threading
import time


class Pacer:
    """Sleeps so that stamps are published `rate` times faster than real time (0: no pacing).

    Stamps that go backwards (unreliable log clocks) are published without waiting.
    """

    def __init__(self, rate: float, stop: threading.Event) -> None:
        if rate < 0:
            raise ValueError(f"rate must be >= 0, got {rate}")
        self.rate = rate
        self._stop = stop
        self._anchor: tuple[float, float] | None = None

    def wait(self, stamp_s: float) -> None:
        """Sleep until `stamp_s` is due (the first stamp anchors the clock); wakes early on stop."""
        if self.rate == 0:
            return
        now = time.monotonic()
        if self._anchor is None:
            self._anchor = (now, stamp_s)
            return
        wall0, stamp0 = self._anchor
        delay_s = wall0 + (stamp_s - stamp0) / self.rate - now
        if delay_s > 0:
            self._stop.wait(delay_s)


class CreditWindow:
    """At most `window` scans of a robot in flight: scan k waits for the pose of scan k - window.

    Poses come back from the matcher on the bus. If no pose arrives for `stall_timeout_s`
    (matcher restarted, scans in flight lost) the window restarts from the current scan so
    the pipeline resumes; each such stall is counted.
    """

    def __init__(self, window: int, stall_timeout_s: float, stop: threading.Event) -> None:
        if window < 0:
            raise ValueError(f"window must be >= 0, got {window}")
        self.window = window
        self.stall_timeout_s = stall_timeout_s
        self.stalls = 0
        self._stop = stop
        self._cond = threading.Condition()
        self._acked: dict[str, int] = {}

    def on_pose(self, robot_id: str, seq: int) -> None:
        """Called from the pose subscriber: scan `seq` of `robot_id` has left the pipeline."""
        with self._cond:
            if seq > self._acked.get(robot_id, -1):
                self._acked[robot_id] = seq
                self._cond.notify_all()

    def reset(self, robot_id: str) -> None:
        """A new replay restarts seqs at 0: forget what was acknowledged."""
        with self._cond:
            self._acked.pop(robot_id, None)

    def acked(self, robot_id: str) -> int:
        """The robot's highest acknowledged pose seq since its last reset; -1 for none."""
        with self._cond:
            return self._acked.get(robot_id, -1)

    def acquire(self, robot_id: str, seq: int) -> bool:
        """Wait until scan `seq` may be published; False if the service is stopping."""
        if self.window == 0:
            return not self._stop.is_set()
        if self._wait_for(robot_id, seq - self.window, self.stall_timeout_s):
            return True
        if self._stop.is_set():
            return False
        with self._cond:
            self.stalls += 1
            self._acked[robot_id] = max(self._acked.get(robot_id, -1), seq - 1)
        return True

    def drain(self, robot_id: str, last_seq: int, timeout_s: float) -> bool:
        """Wait until the pose of `last_seq` is back (True) or `timeout_s` passes (False)."""
        return self._wait_for(robot_id, last_seq, timeout_s)

    def _wait_for(self, robot_id: str, seq: int, timeout_s: float) -> bool:
        """True once `seq` is acknowledged; False when stopping or after `timeout_s` of silence."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._acked.get(robot_id, -1) < seq:
                last = self._acked.get(robot_id, -1)
                remaining = deadline - time.monotonic()
                if self._stop.is_set() or remaining <= 0:
                    return False
                self._cond.wait(min(remaining, 0.1))
                if self._acked.get(robot_id, -1) > last:
                    deadline = time.monotonic() + timeout_s
            return True
