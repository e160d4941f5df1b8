"""FrontendStart and load_prior_map: the prior map the settings name, read once, and bad maps
named."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
from numpy.typing import NDArray
from scanflow.config import FrontendSettings
from scanflow.frontend.prior import FrontendStart, PriorMapError, load_prior_map
from scanflow.geometry import Pose2D
from scanflow.maps.export import save_map
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams

Scanner = Callable[[Pose2D], NDArray[np.float64]]
PriorGrid = Callable[[Scanner], OccupancyGrid]


def test_frontend_start_reads_the_prior_map_once_and_hands_out_copies(
    tmp_path, settings: FrontendSettings, scan_at: Scanner, prior_grid: PriorGrid
) -> None:
    grid = prior_grid(scan_at)
    path = save_map(grid, tmp_path / "office.npz")
    given = settings.model_copy(update={"prior_map": str(path), "initial_pose": [1.0, 2.0, 90.0]})
    start = FrontendStart(given)
    path.unlink()  # read at start-up: later robots do not need the file
    first, second = start.grid(), start.grid()
    assert start.pose == Pose2D(1.0, 2.0, math.pi / 2)
    np.testing.assert_array_equal(first.log_odds, grid.log_odds)
    assert first is not second and not np.shares_memory(first.log_odds, second.log_odds)
    none = FrontendStart(settings)
    assert none.pose is None and none.grid() is None
    yaml = save_map(grid, tmp_path / "office.yaml")  # the map_server form loads too
    assert load_prior_map(settings.model_copy(update={"prior_map": str(yaml)})) is not None


@pytest.mark.parametrize(
    ("content", "named"),
    [(None, "no file"), (b"not a map", "prior_map"), ("empty", "no occupied cell")],
)
def test_a_bad_prior_map_is_named(tmp_path, settings: FrontendSettings, content, named) -> None:
    path = tmp_path / "bad.npz"
    if content == "empty":
        save_map(OccupancyGrid(OccupancyParams()), path)
    elif content is not None:
        path.write_bytes(content)
    with pytest.raises(PriorMapError, match=named):
        load_prior_map(settings.model_copy(update={"prior_map": str(path)}))


def test_a_prior_map_with_cells_but_none_occupied_is_refused(
    tmp_path, settings: FrontendSettings
) -> None:
    """A map_server map all free (or all unknown) has cells but nothing to localise against:
    refused at start-up as the message says, not left to fail when a robot first appears
    (localise only) or to be silently replaced by a fresh map."""
    from PIL import Image

    for name, shade in (("free", 254), ("unknown", 205)):
        Image.fromarray(np.full((20, 30), shade, np.uint8), mode="L").save(tmp_path / f"{name}.pgm")
        yaml = tmp_path / f"{name}.yaml"
        yaml.write_text(f"image: {name}.pgm\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\n")
        with pytest.raises(PriorMapError, match="no occupied cell"):
            load_prior_map(settings.model_copy(update={"prior_map": str(yaml)}))


def test_localise_only_without_a_prior_map_is_refused_at_start(settings: FrontendSettings) -> None:
    """update_map off and no map: refused when the start is read, not by the tracker at each
    robot's first scan (a traceback in `scanflow run`, every robot refused in a matcher)."""
    with pytest.raises(PriorMapError, match=r"update_map=false .* prior_map is unset"):
        FrontendStart(settings.model_copy(update={"update_map": False}))
