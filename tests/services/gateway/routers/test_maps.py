"""GET /robots/{robot}/map and map.{png,pgm,yaml,zip}: metadata, the whole map, a region."""

from __future__ import annotations

import io
import zipfile

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from PIL import Image
from scanflow import keys
from scanflow.maps.grid import CellBox, GridSpec
from scanflow.maps.occupancy import OccupancyGrid
from scanflow.wire import MapImageMessage, MapMetaMessage, MapRegionMessage

from services.gateway.routers.maps import export_region
from services.mapserver import replies
from services.mapserver.robot import RobotMap

from ..conftest import off_the_loop

META = MapMetaMessage.from_spec("r1", GridSpec(-1.0, -2.0, 0.5, 4, 6), revision=3, stamp_s=5.0)


def test_map_meta_and_png(client, peer):
    png = io.BytesIO()
    Image.new("L", (6, 4), 254).save(png, format="PNG")
    peer.answer(keys.map_key("r1", "meta"), lambda q: META.encode())
    peer.answer(keys.map_key("r1", "image"), lambda q: MapImageMessage(
        "r1", 3, q.parameters.get("format"), png.getvalue()).encode())
    meta = client.get("/api/v1/robots/r1/map").json()
    assert (meta["rows"], meta["cols"], meta["width_m"], meta["revision"]) == (4, 6, 3.0, 3)
    r = client.get("/api/v1/robots/r1/map.png")
    assert r.headers["content-type"] == "image/png" and r.content == png.getvalue()
    assert r.headers["x-map-revision"] == "3"
    bundle = client.get("/api/v1/robots/r1/map.zip")
    assert bundle.headers["content-type"] == "application/zip"
    for fmt, got in (("png", r), ("zip", bundle)):  # the name a .yaml's `image:` gives
        assert got.headers["content-disposition"] == f'inline; filename="r1.{fmt}"'


def test_map_region_is_exported_by_the_library(client, peer):
    occupancy = np.full((2, 3), -1, np.int8)
    occupancy[0, 0] = 100
    occupancy[1, :] = 0
    seen = []

    def region(query):
        seen.append(dict(query.parameters))
        return MapRegionMessage(META, 1, 2, occupancy).encode()

    peer.answer(keys.map_key("r1", "region"), region)
    r = client.get("/api/v1/robots/r1/map.pgm", params={"x0": 0, "y0": -1.5, "x1": 1, "y1": -1})
    assert r.status_code == 200 and r.content.startswith(b"P5")
    assert seen[0] == {"x0": "0.0", "y0": "-1.5", "x1": "1.0", "y1": "-1.0"}
    yaml = client.get("/api/v1/robots/r1/map.yaml", params={"x0": 0, "y0": -1.5, "x1": 1, "y1": -1})
    assert "origin: [0.0, -1.5, 0.0]" in yaml.text and "resolution: 0.5" in yaml.text
    png = client.get("/api/v1/robots/r1/map.png", params={"x0": 0, "y0": -1.5, "x1": 1, "y1": -1})
    pixels = np.asarray(Image.open(io.BytesIO(png.content)))
    assert pixels.shape == (2, 3) and pixels[1, 0] == 0 and pixels[0, 2] == 254  # y up
    bundle = client.get("/api/v1/robots/r1/map.zip",
                        params={"x0": 0, "y0": -1.5, "x1": 1, "y1": -1})
    assert bundle.headers["content-type"] == "application/zip"
    archive = zipfile.ZipFile(io.BytesIO(bundle.content))  # named as the whole map's files
    assert archive.read("r1.yaml") == yaml.content and archive.read("r1.pgm") == r.content
    assert "image: r1.pgm" in yaml.text
    assert yaml.headers["content-disposition"] == 'inline; filename="r1.yaml"'


def test_partial_region_and_missing_map(client, peer):
    r = client.get("/api/v1/robots/r1/map.png", params={"x0": 0})
    assert r.status_code == 422 and "x0, y0, x1, y1" in r.json()["detail"]
    peer.answer(keys.map_key("r9", "meta"), lambda q: (_ for _ in ()).throw(
        LookupError("no map for robot 'r9'")))
    r = client.get("/api/v1/robots/r9/map")
    assert r.status_code == 404 and "r9" in r.json()["detail"]


def test_a_regions_export_runs_off_the_event_loop(client, peer, monkeypatch):
    """Writing a large region's PNG is CPU work: on the event loop, every other request (the
    latest pose, a dictionary look-up) waited for it (0.5 s for 2000 x 2000 cells)."""
    calls = off_the_loop(monkeypatch, "services.gateway.routers.maps.export_region")
    peer.answer(keys.map_key("r1", "meta"), lambda q: META.encode())
    region = MapRegionMessage(META, 0, 0, np.zeros((4, 6), np.int8)).encode()
    peer.answer(keys.map_key("r1", "region"), lambda q: region)
    for fmt in ("png", "pgm"):
        r = client.get(f"/api/v1/robots/r1/map.{fmt}?x0=-1&y0=-2&x1=2&y1=0")  # a region
        assert r.status_code == 200, r.text
    assert calls == [True, True]


def pixels(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)))


# 0.653 and 0.647 are 65 %, 0.2 and 0.204 are 20 %: map_saver's occupied and free thresholds.
AT_THE_THRESHOLDS = np.array([[0.653, 0.647, 0.643, np.nan], [0.196, 0.2, 0.204, 0.207],
                              [0.9, 0.15, 0.5, 0.66]])


@settings(max_examples=40, deadline=None)
@example(p=AT_THE_THRESHOLDS, corner=(1, 1))
@given(p=hnp.arrays(np.float64, st.tuples(st.integers(1, 5), st.integers(1, 5)),
                    elements=st.one_of(st.floats(0.12, 0.97), st.just(np.nan))),
       corner=st.tuples(st.integers(0, 4), st.integers(0, 4)))
def test_a_region_draws_each_cell_as_the_whole_map_does(p: np.ndarray, corner: tuple[int, int]):
    """The map server's whole-map export (from its grid) and the gateway's export of a region
    (from the percentages the map server's region reply carries) of one revision: the same
    pixel for every cell. 0.647 was occupied in the first and unknown in the second, 0.2 free
    and unknown."""
    seen = np.isfinite(p)
    q = np.where(seen, p, 0.5)
    grid = OccupancyGrid.from_arrays(np.log(q / (1.0 - q)), seen, CellBox(3, -2, 3 + p.shape[0],
                                     -2 + p.shape[1]), 0.01, -0.02, revision=5)
    robot = RobotMap("r1", lambda: grid)
    whole = replies.region(robot, None)
    for fmt in ("png", "pgm"):
        assert export_region(whole, fmt, "r1") == replies.image(robot, fmt).data, fmt
    assert export_region(whole, "yaml", "r1") == replies.image(robot, "yaml").data
    # A window of it: cells [r0, rows) x [c0, cols), bounded by those cells' centres.
    r0, c0 = min(corner[0], p.shape[0] - 1), min(corner[1], p.shape[1] - 1)
    spec = grid.spec
    x0, y0 = spec.origin_x_m + (c0 + 0.5) * spec.resolution_m, spec.origin_y_m + (r0 + 0.5) * (
        spec.resolution_m)
    x1, y1 = spec.origin_x_m + spec.width_m - 0.01, spec.origin_y_m + spec.height_m - 0.01
    window = replies.region(robot, (x0, y0, x1, y1))
    assert (window.row0, window.col0) == (r0, c0)
    for fmt in ("png", "pgm"):
        part, full = (pixels(d) for d in (export_region(window, fmt, "r1"),
                                          replies.image(robot, fmt).data))
        np.testing.assert_array_equal(part[::-1], full[::-1][r0:, c0:])
