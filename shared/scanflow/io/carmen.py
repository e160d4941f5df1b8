"""CARMEN log reader (`.log`, `.clf`, gzip or plain): laser records and wheel odometry, streamed.

Records understood (all others, e.g. PARAM, SYNC, NEFF, TRUEPOS, `#` comments, are skipped
and counted in `CarmenReader.skipped`):

- `FLASER`/`RLASER n r_1..r_n x y theta odom_x odom_y odom_theta ipc_ts host logger_ts`
  (front/rear laser). The old format has no explicit angles; the layout is inferred from the
  beam count n over a 180 deg field of view starting at -90 deg, counter-clockwise:
  odd n (181, 361) -> step = 180 / (n - 1) deg, first beam -90 deg, last beam +90 deg;
  even n (180, 360) -> step = 180 / n deg, first beam -90 deg, last beam 90 deg - step
  (the field of view covered by beam centres is 180 deg minus one step).
  `x y theta` is the stored (in corrected logs: SLAM-corrected) pose of the laser, exposed as
  `CarmenLaser.pose`; `odom_x odom_y odom_theta` is exposed as `CarmenLaser.odom_pose`.
- `ROBOTLASER1 type start_angle fov resolution max_range accuracy remission_mode n r_1..r_n
  m rem_1..rem_m laser_x laser_y laser_theta robot_x robot_y robot_theta tv rv forward_safety
  side_safety turn_axis ipc_ts host logger_ts`: explicit angles (rad); `pose` is the laser pose,
  `odom_pose` the robot pose; remissions become intensities when there is one per beam.
- `RAWLASER1` (same as ROBOTLASER1 up to the remissions, then the timestamps): no pose, so
  `pose` and `odom_pose` are None.
- `ODOM x y theta tv rv accel ipc_ts host logger_ts` -> `Odometry` with velocity (tv, 0, rv).

Mount (`LaserScan.mount`, the laser's pose on the robot; laser_pose = robot_pose * mount):
- ROBOTLASER1: per record, `laser_pose` relative to `robot_pose` (beyond `MAX_MOUNT_OFFSET_M`
  the line is malformed);
- FLASER / RLASER / RAWLASER1: identity. The `robot_frontlaser_offset` / `robot_rearlaser_*`
  PARAM lines are not applied: corrected logs store one pose for both laser and robot (the data
  README), and on freiburg-079 (PARAM offset -0.04 m) the corrected poses fit the wheel
  odometry no better with that offset than without. Declare a mount when it is known
  (`dataclasses.replace(scan, mount=...)`, or `SCANFLOW_INGEST_MOUNT` for the services).

Every record may also end with a single timestamp instead of `ipc_ts host logger_ts` (older
loggers). Times: the logger timestamp is used as `stamp_s`; timestamps in real logs can be zero
or out of order, so the order of lines, kept by this reader, is the order of events. Old-format
lasers carry no sweep timing, so `scan_duration_s` is 0 there.

"No return" rule: a beam is invalid at or above `range_max_m`. With `max_range_m=None` (the
default) `range_max_m = min(50 m, detected sentinel, the record's own max range if it has one)`.
50 m is what the logs' PARAM lines give as the laser's maximum range and lies below the
81.8-81.9 m and 50-51.3 m sentinels seen in real logs; PARAM lines themselves are not trusted
because their names and values disagree between CARMEN versions. A sentinel below 50 m
(e.g. 32.8 m, a SICK in millimetre mode) is detected from the first `SENTINEL_PRESCAN_RECORDS`
laser records: the largest reading is a sentinel when the readings within 5 cm of it are many
(>= 10) and at least three times as many as those in the metre below (real far returns thin
out; a sentinel piles up). Pass `max_range_m` to impose a value and skip the detection.

Malformed lines never produce a scan: with `strict=True` they raise `CarmenFormatError` naming
file and line; otherwise they are skipped, recorded in `CarmenReader.errors` and passed to
`on_error` if given.
"""

from __future__ import annotations

import contextlib
import gzip
import io
import math
import zlib
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import IDENTITY, Pose2D
from scanflow.scan import LaserScan, Odometry, ScanError

DEFAULT_MAX_RANGE_M = 50.0
SENTINEL_PRESCAN_RECORDS = 1000
SENTINEL_BAND_M = 0.05
SENTINEL_MIN_COUNT = 10
SENTINEL_PEAK_RATIO = 3.0
MAX_RECORDED_ERRORS = 1000
MAX_READINGS = 100_000
MAX_MOUNT_OFFSET_M = 5.0  # a laser farther than this from the robot's origin is a broken record

OLD_LASER_TYPES = ("FLASER", "RLASER")
NEW_LASER_TYPES = ("ROBOTLASER1", "RAWLASER1")
LASER_TYPES = OLD_LASER_TYPES + NEW_LASER_TYPES
FRAME_IDS = {
    "FLASER": "front_laser",
    "RLASER": "rear_laser",
    "ROBOTLASER1": "laser",
    "RAWLASER1": "laser",
}
GZIP_MAGIC = b"\x1f\x8b"


class CarmenFormatError(ValueError):
    """A malformed CARMEN line (raised only with `strict=True`); names the file and line."""


@dataclass(frozen=True)
class CarmenLineError:
    """One malformed line that was skipped."""

    path: str
    line_no: int
    reason: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line_no}: {self.reason}"


@dataclass(frozen=True)
class CarmenLaser:
    """A laser record: the scan, the stored laser pose and the stored odometry pose.

    Both poses are as the record stores them (None for RAWLASER1, which carries no pose); the
    laser's pose on the robot is `scan.mount` (module docstring).
    """

    scan: LaserScan
    pose: Pose2D | None
    odom_pose: Pose2D | None
    line_no: int
    record_type: str = "FLASER"


@dataclass(frozen=True)
class CarmenOdom:
    """An ODOM record."""

    odom: Odometry
    line_no: int


class _LineError(Exception):
    """Internal: why one line could not be parsed."""


def open_text(path: str | Path) -> IO[str]:
    """Open a text log, decompressing it when it starts with the gzip magic bytes."""
    with open(path, "rb") as f:
        magic = f.read(2)
    # The caller owns the returned stream (it is used as a context manager).
    raw = gzip.open(path, "rb") if magic == GZIP_MAGIC else open(path, "rb")  # noqa: SIM115
    return io.TextIOWrapper(raw, encoding="latin-1", newline=None)


def old_laser_layout(n: int) -> tuple[float, float]:
    """(angle_min_rad, angle_increment_rad) of an old-format laser record with n beams."""
    if n < 2:
        raise ValueError(f"beam count must be >= 2, got {n}")
    step_deg = 180.0 / (n - 1) if n % 2 else 180.0 / n
    return -math.pi / 2, math.radians(step_deg)


def _float(token: str, field: str) -> float:
    try:
        value = float(token)
    except ValueError:
        raise _LineError(f"{field} is not a number: {token!r}") from None
    if not math.isfinite(value):
        raise _LineError(f"{field} must be finite, got {token!r}")
    return value


def _count(token: str, field: str) -> int:
    try:
        value = int(token)
    except ValueError:
        raise _LineError(f"{field} is not an integer: {token!r}") from None
    if not 0 <= value <= MAX_READINGS:
        raise _LineError(f"{field} must be in [0, {MAX_READINGS}], got {value}")
    return value


def _floats(tokens: list[str], field: str) -> NDArray[np.float64]:
    try:
        return np.asarray(tokens, dtype=np.float64)
    except ValueError:
        bad = next(t for t in tokens if not _is_number(t))
        raise _LineError(f"{field} holds a non-number: {bad!r}") from None


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _pose(tokens: list[str], field: str) -> Pose2D:
    x, y, th = (_float(t, f"{field}.{n}") for t, n in zip(tokens, ("x", "y", "theta"), strict=True))
    return Pose2D(x, y, th)


def _stamp(tail: list[str]) -> float:
    """Logger timestamp from the trailing `ipc_ts host logger_ts` (or a lone timestamp)."""
    if len(tail) == 3:
        _float(tail[0], "ipc_timestamp")
        return _float(tail[2], "logger_timestamp")
    if len(tail) == 1:
        return _float(tail[0], "timestamp")
    raise _LineError(f"expected 'ipc_ts host logger_ts' or one timestamp, got {len(tail)} tokens")


def _ranges(parts: list[str], start: int, field: str = "n") -> tuple[int, NDArray[np.float64]]:
    """Read a count at `start` and that many numbers after it."""
    if start >= len(parts):
        raise _LineError(f"line ends before the {field} field")
    n = _count(parts[start], field)
    values = parts[start + 1 : start + 1 + n]
    if len(values) != n:
        raise _LineError(f"{field}={n} but only {len(values)} values follow")
    return n, _floats(values, "ranges" if field == "n" else "remissions")


@dataclass(frozen=True)
class _Laser:
    """Fields of a laser line before the range limit is applied."""

    ranges_m: NDArray[np.float64]
    angle_min_rad: float
    angle_increment_rad: float
    record_max_range_m: float
    intensities: NDArray[np.float64] | None
    pose: Pose2D | None
    odom_pose: Pose2D | None
    stamp_s: float
    mount: Pose2D = IDENTITY


def _mount(laser_pose: Pose2D, robot_pose: Pose2D) -> Pose2D:
    """The laser's pose on the robot from a record's laser and robot poses (same frame)."""
    mount = laser_pose.relative_to(robot_pose)
    if mount.translation_norm() > MAX_MOUNT_OFFSET_M:
        raise _LineError(
            f"laser_pose is {mount.translation_norm():.3g} m from robot_pose, more than "
            f"{MAX_MOUNT_OFFSET_M} m: not a laser mount"
        )
    return mount


def _parse_old_laser(parts: list[str]) -> _Laser:
    n, ranges = _ranges(parts, 1)
    if n < 2:
        raise _LineError(f"n must be >= 2 beams, got {n}")
    rest = parts[2 + n :]
    if len(rest) not in (7, 9):
        raise _LineError(f"expected {n + 11} tokens for n={n}, got {len(parts)}")
    angle_min, step = old_laser_layout(n)
    return _Laser(
        ranges, angle_min, step, math.inf, None,
        _pose(rest[0:3], "pose"), _pose(rest[3:6], "odom_pose"), _stamp(rest[6:]),
    )  # fmt: skip


def _parse_new_laser(parts: list[str]) -> _Laser:
    kind = parts[0]
    if len(parts) < 9:
        raise _LineError(f"{kind} needs at least 9 tokens, got {len(parts)}")
    start = _float(parts[2], "start_angle")
    for index, field in (
        (1, "laser_type"),
        (3, "field_of_view"),
        (6, "accuracy"),
        (7, "remission_mode"),
    ):
        _float(parts[index], field)
    step = _float(parts[4], "angular_resolution")
    if step <= 0:
        raise _LineError(f"angular_resolution must be > 0, got {step}")
    max_range = _float(parts[5], "maximum_range")
    n, ranges = _ranges(parts, 8)
    m, remissions = _ranges(parts, 9 + n, "num_remissions")
    if m not in (0, n):
        raise _LineError(f"num_remissions must be 0 or n={n}, got {m}")
    rest = parts[10 + n + m :]
    pose = odom_pose = None
    mount = IDENTITY
    if kind == "ROBOTLASER1":
        if len(rest) not in (12, 14):
            raise _LineError(f"expected {n + m + 24} tokens for n={n}, got {len(parts)}")
        pose, odom_pose = _pose(rest[0:3], "laser_pose"), _pose(rest[3:6], "robot_pose")
        mount = _mount(pose, odom_pose)
        for token, field in zip(
            rest[6:11], ("tv", "rv", "forward_safety", "side_safety", "turn"), strict=True
        ):
            _float(token, field)
        rest = rest[11:]
    return _Laser(
        ranges, start, step, max_range if max_range > 0 else math.inf,
        remissions if m else None, pose, odom_pose, _stamp(rest), mount,
    )  # fmt: skip


def _parse_odom(parts: list[str], robot_id: str, seq: int) -> Odometry:
    if len(parts) not in (8, 10):
        raise _LineError(f"ODOM expects 10 tokens, got {len(parts)}")
    tv, rv = _float(parts[4], "tv"), _float(parts[5], "rv")
    _float(parts[6], "accel")
    return Odometry(_stamp(parts[7:]), _pose(parts[1:4], "pose"), (tv, 0.0, rv), robot_id, seq)


class _DamagedError(Exception):
    """Internal: the file cannot be read past line `line_no` (truncated or corrupt gzip)."""

    def __init__(self, line_no: int, reason: str) -> None:
        super().__init__(reason)
        self.line_no = line_no


def _numbered_lines(f: IO[str]) -> Iterator[tuple[int, str]]:
    """(line number, line) of a text log; `_DamagedError` where the compressed stream breaks off
    (the lines before it are good and were given)."""
    line_no = 0
    try:
        for line_no, line in enumerate(f, start=1):
            yield line_no, line
    except (EOFError, zlib.error, gzip.BadGzipFile) as exc:
        raise _DamagedError(line_no + 1, f"the file cannot be read past here: {exc}") from None


def detect_sentinel_m(
    path: str | Path, max_records: int = SENTINEL_PRESCAN_RECORDS
) -> float | None:
    """The "no return" value of a log, if its readings pile up at their maximum (module doc)."""
    chunks: list[NDArray[np.float64]] = []
    with open_text(path) as f, contextlib.suppress(_DamagedError):  # the reader reports it
        for _, line in _numbered_lines(f):
            parts = line.split()
            if not parts or parts[0] not in LASER_TYPES:
                continue
            try:
                parse = _parse_old_laser if parts[0] in OLD_LASER_TYPES else _parse_new_laser
                chunks.append(parse(parts).ranges_m)
            except (_LineError, ValueError):
                continue
            if len(chunks) >= max_records:
                break
    if not chunks:
        return None
    r = np.concatenate(chunks)
    r = r[np.isfinite(r) & (r > 0)]
    if r.size == 0:
        return None
    top = float(r.max())
    peak = r >= top - SENTINEL_BAND_M
    shoulder = (r >= top - SENTINEL_BAND_M - 1.0) & ~peak
    n_peak = int(np.count_nonzero(peak))
    if n_peak >= SENTINEL_MIN_COUNT and n_peak >= SENTINEL_PEAK_RATIO * np.count_nonzero(shoulder):
        return float(r[peak].min())
    return None


class CarmenReader:
    """Iterates the records of one CARMEN log in file order; keeps errors and skip counts."""

    def __init__(
        self,
        path: str | Path,
        *,
        robot_id: str = "robot",
        strict: bool = False,
        max_range_m: float | None = None,
        on_error: Callable[[str, int, str], None] | None = None,
    ) -> None:
        self.path = Path(path)
        self.robot_id = robot_id
        self.strict = strict
        self.on_error = on_error
        if max_range_m is not None and not max_range_m > 0:
            raise ValueError(f"max_range_m must be > 0, got {max_range_m}")
        self.max_range_m = max_range_m
        self.errors: list[CarmenLineError] = []
        self.error_count = 0
        self.skipped: Counter[str] = Counter()
        self.sentinel_m: float | None = None

    def _range_limit_m(self) -> float:
        if self.max_range_m is not None:
            return self.max_range_m
        self.sentinel_m = detect_sentinel_m(self.path)
        return min(DEFAULT_MAX_RANGE_M, self.sentinel_m or math.inf)

    def __iter__(self) -> Iterator[CarmenLaser | CarmenOdom]:
        limit_m = self._range_limit_m()
        with open_text(self.path) as f:
            try:
                yield from self._records(_numbered_lines(f), limit_m)
            except _DamagedError as damage:  # what came before stands; nothing after can be read
                self._report(damage.line_no, str(damage))

    def _records(
        self, lines: Iterator[tuple[int, str]], limit_m: float
    ) -> Iterator[CarmenLaser | CarmenOdom]:
        n_laser = n_odom = 0
        for line_no, line in lines:
            parts = line.split()
            kind = parts[0] if parts else ""
            try:
                if kind in LASER_TYPES:
                    yield self._laser(kind, parts, line_no, n_laser, limit_m)
                    n_laser += 1
                elif kind == "ODOM":
                    odom = _parse_odom(parts, self.robot_id, n_odom)
                    yield CarmenOdom(odom, line_no)
                    n_odom += 1
                else:
                    self.skipped[kind if kind and not kind.startswith("#") else "#"] += 1
            except (_LineError, ScanError) as exc:
                self._report(line_no, f"{kind}: {exc}")

    def _laser(
        self, kind: str, parts: list[str], line_no: int, seq: int, limit_m: float
    ) -> CarmenLaser:
        parsed = (_parse_old_laser if kind in OLD_LASER_TYPES else _parse_new_laser)(parts)
        # Parsed as float64 (the sentinel prescan reads them so); a scan holds float32.
        intensities = None if parsed.intensities is None else parsed.intensities.astype(np.float32)
        scan = LaserScan(
            ranges_m=parsed.ranges_m.astype(np.float32),
            angle_min_rad=parsed.angle_min_rad,
            angle_increment_rad=parsed.angle_increment_rad,
            range_max_m=min(limit_m, parsed.record_max_range_m),
            stamp_s=parsed.stamp_s,
            robot_id=self.robot_id,
            frame_id=FRAME_IDS[kind],
            intensities=intensities,
            seq=seq,
            mount=parsed.mount,
        )
        return CarmenLaser(scan, parsed.pose, parsed.odom_pose, line_no, kind)

    def _report(self, line_no: int, reason: str) -> None:
        if self.strict:
            raise CarmenFormatError(f"{self.path}:{line_no}: {reason}")
        self.error_count += 1
        if len(self.errors) < MAX_RECORDED_ERRORS:
            self.errors.append(CarmenLineError(str(self.path), line_no, reason))
        if self.on_error is not None:
            self.on_error(str(self.path), line_no, reason)


def read_carmen(
    path: str | Path,
    *,
    robot_id: str = "robot",
    strict: bool = False,
    max_range_m: float | None = None,
    on_error: Callable[[str, int, str], None] | None = None,
) -> Iterator[CarmenLaser | CarmenOdom]:
    """Stream the laser and odometry records of a CARMEN log in file order (see module doc)."""
    return iter(
        CarmenReader(
            path, robot_id=robot_id, strict=strict, max_range_m=max_range_m, on_error=on_error
        )
    )


@dataclass(frozen=True)
class Keyframe:
    """A laser scan with its ground-truth pose and a continuous wheel-odometry pose."""

    scan: LaserScan
    true_pose: Pose2D
    odom_pose: Pose2D


def load_keyframes(
    path: str | Path,
    robot_id: str = "robot",
    *,
    max_range_m: float | None = None,
    on_error: Callable[[str, int, str], None] | None = None,
) -> list[Keyframe]:
    """Front-laser records with the robot's poses, plus odometry chained from the raw increments.

    Both poses are the robot's (the frame every module works in), not the laser's: `true_pose`
    is the record's stored laser pose moved back through the mount, `pose * inverse(mount)`.
    Corrected logs re-anchor the ODOM stream at every laser record, so the raw motion from
    record i to i+1 is `inverse(odom_pose_i) * (last ODOM before record i+1)` (the record's
    stored odom pose is the anchor; in corrected logs it equals the corrected pose, in raw logs
    it is the odometry at the record). These are wheel, so robot, motions; chaining them from
    the first keyframe's `true_pose` gives the trajectory. When no ODOM lies between two
    records, the increment is the difference of their stored odom poses. Rear lasers and
    RAWLASER1 (no pose) are left out. Lines that cannot be read are skipped, each passed to
    `on_error` (path, line number, reason) when given.
    """
    frames: list[Keyframe] = []
    prev_anchor: Pose2D | None = None
    last_odom: Pose2D | None = None
    records = read_carmen(path, robot_id=robot_id, max_range_m=max_range_m, on_error=on_error)
    for rec in records:
        if isinstance(rec, CarmenOdom):
            last_odom = rec.odom.pose
            continue
        if rec.pose is None or rec.odom_pose is None or rec.record_type == "RLASER":
            continue
        true_pose = rec.pose * rec.scan.mount.inverse()
        if prev_anchor is None:
            odom = true_pose
        else:
            end = last_odom if last_odom is not None else rec.odom_pose
            odom = frames[-1].odom_pose * end.relative_to(prev_anchor)
        frames.append(Keyframe(rec.scan, true_pose, odom))
        prev_anchor, last_odom = rec.odom_pose, None
    return frames
