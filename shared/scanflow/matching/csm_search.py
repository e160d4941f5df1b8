"""The correlative search itself: the (x, y, theta) window discretised, every candidate scored
on a max-pool stack, exhaustively or by branch and bound, and Olson's covariance of the optimum.

Candidates are the guess plus whole grid cells of translation and whole angular steps; a
candidate's score is the sum of the quantised map probabilities under its transformed points
(seed 2, part 4; Olson 2009; Cartographer's fast correlative matcher for the bound). Both
searches use the same integer scores and the same total order (higher score, then nearer the
guess in translation, then in angle, then by index), so branch and bound returns exactly the
exhaustive optimum. The covariance is Olson's: the spread of the near-optimal candidates
weighted by exp(score difference), plus the discretisation floor. `csm` (the matcher) and
`global` (the whole-map search) both run on it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from scanflow.geometry import Pose2D
from scanflow.maps.grid import GridSpec
from scanflow.maps.maxpool import SCORE_SCALE, MaxPoolStack
from scanflow.matching.inputs import MatchInputError

# Bounds on one search, checked before anything is allocated (`check_search_size`); a larger
# search is refused with MatchInputError naming the options. Measured for scale: the default
# window (+-1 m, +-30 deg, 5 cm) is ~0.35-1.8 M candidates; the whole-map search of aces
# (59 x 58 m at 10 cm, every heading) ~1.0e9, in 0.5 s.
# Translations: +-MAX_HALF_CELLS cells a side (+-102 m at 5 cm): the max-pool stack is padded by
# about that much on every side and holds log2(it) levels (~400 MB of int16 at this cap).
MAX_HALF_CELLS = 2048
# Angles: at most 2**16 per search (a full turn in 0.1 mrad steps); branch and bound seeds up
# to 16 nodes per angle.
MAX_ANGLES = 2**16
# Angles x source points: the (angles, points) int64 cell tables, 1 GiB at this cap.
MAX_TABLE_ENTRIES = 2**26
# Angles x translations: the work of the exhaustive search, and of branch and bound when
# nothing prunes (~17 times the whole-map search of aces).
MAX_CANDIDATES = 2**34
# Distinct optima one search may return (`candidates`): each is a further search that checks
# every earlier one's suppression box.
MAX_TOP_CANDIDATES = 100
MAX_SEARCH_LENGTH_M = 1000.0  # a search's cell, likelihood width and rivals' distance
# Entries of the float temporaries `build_candidates` holds at once (16 MB each).
ROTATION_BLOCK_ENTRIES = 2**21
# Source points up to this many times the reach count towards the angular step (see
# `default_angular_step_rad`); measured on real next-scan pairs: at most 4.7.
REACH_FACTOR = 8.0


@dataclass(frozen=True)
class Candidates:
    """The discretised search problem: per-angle base cells of the points, window half-sizes."""

    stack: MaxPoolStack
    rows: NDArray[np.int64]  # (A, N) cell rows of the points rotated by each angle at zero offset
    cols: NDArray[np.int64]
    angles_rad: NDArray[np.float64]  # (A,) absolute headings
    half_cells: int
    half_steps: int


def build_candidates(
    source: NDArray[np.float64],
    stack: MaxPoolStack,
    guess: Pose2D,
    linear_m: float,
    angular_rad: float,
    angular_step_rad: float,
) -> Candidates:
    """Rotate the source by every angle of the window at once and find each point's cell."""
    res = stack.spec.resolution_m
    half_cells, half_steps = window_steps(res, linear_m, angular_rad, angular_step_rad)
    steps = np.arange(-half_steps, half_steps + 1, dtype=np.float64)
    angles = guess.theta + steps * angular_step_rad
    rows = np.empty((len(angles), len(source)), dtype=np.int64)
    cols = np.empty_like(rows)
    # A block of angles at a time: the float temporaries stay small (same values as all at once).
    block = max(1, ROTATION_BLOCK_ENTRIES // max(len(source), 1))
    for a0 in range(0, len(angles), block):
        part = angles[a0 : a0 + block]
        c, s = np.cos(part)[:, None], np.sin(part)[:, None]
        x = c * source[:, 0] - s * source[:, 1] + guess.x
        y = s * source[:, 0] + c * source[:, 1] + guess.y
        cols[a0 : a0 + block] = np.floor((x - stack.spec.origin_x_m) / res)
        rows[a0 : a0 + block] = np.floor((y - stack.spec.origin_y_m) / res)
    return Candidates(stack, rows, cols, angles, half_cells, half_steps)


def window_steps(
    resolution_m: float, linear_m: float, angular_rad: float, angular_step_rad: float
) -> tuple[int, int]:
    """(half_cells, half_steps) of a window: whole cells and whole angular steps each side; the
    angular window is at most half a turn each side (a full turn in all)."""
    half_cells = math.floor(linear_m / resolution_m + 1e-9)
    half_steps = math.floor(min(angular_rad, math.pi) / angular_step_rad + 1e-9)
    return half_cells, half_steps


def check_search_size(
    half_cells: int, half_steps: int, n_points: int, linear: str, angular: str
) -> None:
    """MatchInputError, naming the options (`linear`, `angular`: their names for the caller),
    when a search exceeds MAX_HALF_CELLS, MAX_ANGLES, MAX_TABLE_ENTRIES or MAX_CANDIDATES."""
    angles = 2 * half_steps + 1
    translations = (2 * half_cells + 1) ** 2
    limits = (
        ("translation half-width", half_cells, MAX_HALF_CELLS, f"{linear}: +-{half_cells} cells"),
        ("angle count", angles, MAX_ANGLES, f"{angular}: {angles} angles"),
        ("angles x source points", angles * n_points, MAX_TABLE_ENTRIES,
         f"{angular}: {angles} angles x {n_points} points"),
        ("candidate count", angles * translations, MAX_CANDIDATES,
         f"{linear}, {angular}: {angles} angles x {translations} translations"),
    )
    for name, count, cap, what in limits:
        if count > cap:
            raise MatchInputError(
                f"search too large: {name} {count} exceeds {cap} ({what}); narrow the window "
                f"or coarsen the resolution"
            )


@njit(cache=True)
def _score(levels, h, rows_k, cols_k, dy, dx, pad):  # type: ignore[no-untyped-def]
    """Sum of level-h pooled scores under the points shifted by (dy, dx) cells; off-grid is 0."""
    n_rows, n_cols = levels.shape[1], levels.shape[2]
    total = 0
    for i in range(rows_k.shape[0]):
        r = min(max(rows_k[i] + dy + pad, 0), n_rows - 1)
        c = min(max(cols_k[i] + dx + pad, 0), n_cols - 1)
        total += levels[h, r, c]
    return total


@njit(cache=True)
def _before(k, ix, iy, best_k, best_ix, best_iy, half_steps):  # type: ignore[no-untyped-def]
    """Tie-break among equal scores: nearer the guess in translation, then in angle, then index."""
    a = (ix * ix + iy * iy, (k - half_steps) ** 2, k, ix, iy)
    b = (
        best_ix * best_ix + best_iy * best_iy,
        (best_k - half_steps) ** 2,
        best_k,
        best_ix,
        best_iy,
    )
    for j in range(5):
        if a[j] != b[j]:
            return a[j] < b[j]
    return False


@njit(cache=True)
def _suppressed(k, ix0, ix1, iy0, iy1, picks, n_picks, r_cells, r_steps):  # type: ignore[no-untyped-def]
    """True if the offsets ix0..ix1 x iy0..iy1 at angle k all lie inside one earlier pick's box
    (+-r_cells offsets, +-r_steps angles): non-maximum suppression for the top-K search."""
    for p in range(n_picks):
        if (
            abs(k - picks[p, 0]) <= r_steps
            and picks[p, 1] - r_cells <= ix0
            and ix1 <= picks[p, 1] + r_cells
            and picks[p, 2] - r_cells <= iy0
            and iy1 <= picks[p, 2] + r_cells
        ):
            return True
    return False


@njit(cache=True, nogil=True)  # seconds on a wide window: other threads run on
def _exhaustive(  # type: ignore[no-untyped-def]
    levels, rows, cols, pad, w, half_steps, picks, n_picks, r_cells, r_steps, floor
):
    # Typed zeros, not the literal 0: _score and _before compile once per layout.
    finest = zero = np.int64(0)
    best = (floor - 1, zero, zero, zero)
    for k in range(rows.shape[0]):
        for iy in range(-w, w + 1):
            for ix in range(-w, w + 1):
                if _suppressed(k, ix, ix, iy, iy, picks, n_picks, r_cells, r_steps):
                    continue
                score = _score(levels, finest, rows[k], cols[k], iy, ix, pad)
                if score > best[0] or (
                    score == best[0] and _before(k, ix, iy, best[1], best[2], best[3], half_steps)
                ):
                    best = (score, k, ix, iy)
    return best


@njit(cache=True)
def _min_square(lo, hi):  # type: ignore[no-untyped-def]
    return 0 if lo <= 0 <= hi else min(lo * lo, hi * hi)


@njit(cache=True, nogil=True)  # seconds on a wide window: other threads run on
def _branch_and_bound(  # type: ignore[no-untyped-def]
    levels, rows, cols, pad, w, top, half_steps, picks, n_picks, r_cells, r_steps, floor
):
    n_angles = rows.shape[0]
    step = 2**top
    starts = np.arange(-w, w + 1, step)
    n_init = n_angles * starts.size * starts.size
    # Node columns: bound, k, ix0, iy0, h; a node covers offsets ix0..ix0+2**h-1 (and iy).
    init = np.empty((n_init, 5), dtype=np.int64)
    n = 0
    for k in range(n_angles):
        for iy0 in starts:
            for ix0 in starts:
                init[n] = (_score(levels, top, rows[k], cols[k], iy0, ix0, pad), k, ix0, iy0, top)
                n += 1
    nodes = np.empty((n_init + 4 * (top + 1), 5), dtype=np.int64)
    nodes[:n_init] = init[np.argsort(init[:, 0], kind="mergesort")]
    size = n_init
    # Scores below `floor` are not wanted: starting the best there prunes them from the start.
    zero = np.int64(0)  # typed, not the literal 0: _before compiles once
    best = (floor - 1, zero, zero, zero)
    children = np.empty((4, 5), dtype=np.int64)
    while size > 0:
        size -= 1
        bound, k, ix0, iy0, h = nodes[size]
        if bound < best[0]:
            continue
        ix1, iy1 = min(ix0 + 2**h - 1, w), min(iy0 + 2**h - 1, w)
        if _suppressed(k, ix0, ix1, iy0, iy1, picks, n_picks, r_cells, r_steps):
            continue
        if bound == best[0] and best[0] >= 0:
            lower = _min_square(ix0, ix1) + _min_square(iy0, iy1)
            if lower > best[2] * best[2] + best[3] * best[3]:
                continue
        if h == 0:
            if bound > best[0] or _before(k, ix0, iy0, best[1], best[2], best[3], half_steps):
                best = (bound, k, ix0, iy0)
            continue
        half = 2 ** (h - 1)
        m = 0
        for dy in (0, half):
            for dx in (0, half):
                if ix0 + dx <= w and iy0 + dy <= w:
                    b = _score(levels, h - 1, rows[k], cols[k], iy0 + dy, ix0 + dx, pad)
                    # Insertion sort, ascending bound: the best child is pushed last, popped first.
                    j = m
                    while j > 0 and children[j - 1, 0] > b:
                        children[j] = children[j - 1]
                        j -= 1
                    children[j] = (b, k, ix0 + dx, iy0 + dy, h - 1)
                    m += 1
        for j in range(m):
            if children[j, 0] >= best[0]:
                nodes[size] = children[j]
                size += 1
    return best


def stack_depth(half_cells: int) -> int:
    """Top level of the search: blocks about half the window wide.

    Blocks spanning the whole window (Cartographer's choice) bound every angle by nearly the
    full score; half-window blocks cost four times the initial nodes but prune far more
    (measured on the real logs: median 0.9 ms vs 2.2 ms at +-1 m, 5 cm).
    """
    return max(math.floor(math.log2(max(2 * half_cells + 1, 2) / 2)), 0)


def search_top(
    cand: Candidates,
    exhaustive: bool,
    count: int,
    suppress_cells: int,
    suppress_steps: int,
    min_ratio: float = 0.0,
) -> list[tuple[int, int, int, int]]:
    """(k, ix, iy, score) of up to `count` distinct optima, best first (greedy non-maximum
    suppression): each is the best candidate outside the boxes of +-suppress_cells offsets and
    +-suppress_steps angles around the earlier ones, scoring > 0 and >= min_ratio x the first
    (which also prunes the later searches). The first is returned even if it scores 0."""
    if count < 1 or suppress_cells < 0 or suppress_steps < 0 or not 0.0 <= min_ratio <= 1.0:
        raise ValueError(
            f"count must be >= 1, suppression >= 0 and min_ratio in [0, 1], got count={count}, "
            f"suppress_cells={suppress_cells}, suppress_steps={suppress_steps}, "
            f"min_ratio={min_ratio}"
        )
    st = cand.stack
    w = cand.half_cells
    top = min(st.depth, stack_depth(w))
    picks = np.zeros((count, 3), dtype=np.int64)
    found: list[tuple[int, int, int, int]] = []
    floor = 0
    for n in range(count):
        if exhaustive:
            score, k, ix, iy = _exhaustive(
                st.levels, cand.rows, cand.cols, st.pad_cells, w, cand.half_steps,
                picks, n, suppress_cells, suppress_steps, floor,
            )
        else:
            score, k, ix, iy = _branch_and_bound(
                st.levels, cand.rows, cand.cols, st.pad_cells, w, top, cand.half_steps,
                picks, n, suppress_cells, suppress_steps, floor,
            )
        if n > 0 and score < floor:
            break
        if n == 0:
            floor = max(1, math.ceil(min_ratio * score))
        picks[n] = (k, ix, iy)
        found.append((int(k), int(ix), int(iy), int(score)))
    return found


def search(cand: Candidates, exhaustive: bool) -> tuple[int, int, int, int]:
    """(k, ix, iy, score) of the best candidate: every one scored, or branch and bound."""
    return search_top(cand, exhaustive, 1, 0, 0)[0]


@njit(cache=True)
def _neighbourhood(levels, rows, cols, pad, k, ix, iy, radius):  # type: ignore[no-untyped-def]
    """(dx, dy, dk, score) rows for the full-resolution candidates within `radius` of the best."""
    k_lo, k_hi = max(k - radius, 0), min(k + radius, rows.shape[0] - 1)
    out = np.empty(((k_hi - k_lo + 1) * (2 * radius + 1) ** 2, 4), dtype=np.int64)
    n, finest = 0, np.int64(0)  # not the literal 0: _score compiles once per layout
    for kk in range(k_lo, k_hi + 1):
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                out[n] = (
                    dx,
                    dy,
                    kk - k,
                    _score(levels, finest, rows[kk], cols[kk], iy + dy, ix + dx, pad),
                )
                n += 1
    return out


def olson_covariance(
    cand: Candidates, k: int, ix: int, iy: int, angular_step_rad: float, radius: int = 3
) -> NDArray[np.float64]:
    """Weighted covariance of the candidates near the optimum, weights exp(score difference).

    A score counts probability mass (one unit per point fully on an obstacle), treated as a
    log-likelihood; the discretisation variance (step^2 / 12 per axis) is the floor.
    """
    st = cand.stack
    near = _neighbourhood(st.levels, cand.rows, cand.cols, st.pad_cells, k, ix, iy, radius)
    weights = np.exp((near[:, 3] - near[:, 3].max()) / SCORE_SCALE)
    res = st.spec.resolution_m
    samples = near[:, :3] * np.array([res, res, angular_step_rad])
    mean = weights @ samples / weights.sum()
    centred = samples - mean
    cov = (centred * weights[:, None]).T @ centred / weights.sum()
    return cov + np.diag([res**2 / 12, res**2 / 12, angular_step_rad**2 / 12])


def default_angular_step_rad(
    source: NDArray[np.float64], resolution_m: float, reach_m: float = math.inf
) -> float:
    """Cartographer's step: the angle that moves the farthest point by about one cell, counting
    points up to REACH_FACTOR x `reach_m` from the source's origin.

    Only points within `reach_m` can ever land on the grid (see `reach_m`): farther ones score
    0 under every candidate. Real scans do have such points (returns past everything the target
    saw: up to 4.7 x the reach on the next-scan pairs of intel, aces and freiburg-079), so the
    step stays Cartographer's for them; only a point farther still, a glitch, is not allowed
    to shrink the step: one return at 20 km made it ~2.5 urad and the search take 17-21 s, and
    a source ~1e6 m off asked for 75 GiB of angles. The angle count is thereby bounded by the
    target's extent.
    """
    far_m = min(float(np.max(np.hypot(source[:, 0], source[:, 1]))), REACH_FACTOR * reach_m)
    far_m = max(far_m, resolution_m)
    # The chord of one cell at far_m; acos(1 - res^2 / 2 far^2) is the same angle but rounds
    # to 0 (a division by zero downstream) once far_m exceeds ~1e7 x resolution_m.
    return 2.0 * math.asin(resolution_m / (2.0 * far_m))


def reach_m(spec: GridSpec, centre: Pose2D, half_m: float) -> float:
    """The largest distance from a candidate's translation (within +-half_m of `centre` in x
    and y) to any point of the grid `spec` covers: a source point farther than that from the
    source's origin lands off the grid, and scores 0, under every candidate."""
    x0, x1 = spec.origin_x_m, spec.origin_x_m + spec.width_m
    y0, y1 = spec.origin_y_m, spec.origin_y_m + spec.height_m
    dx = max(x1 - (centre.x - half_m), (centre.x + half_m) - x0)
    dy = max(y1 - (centre.y - half_m), (centre.y + half_m) - y0)
    return math.hypot(dx, dy)
