"""Map files: exact native round trip, map_server PGM/YAML as ROS reads it, PNG for people."""

import io
import json
import math
import zipfile
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from PIL import Image
from scanflow.geometry import Pose2D
from scanflow.maps.export import (
    FREE_PIXEL,
    MAP_FILE_FORMATS,
    OCCUPIED_PIXEL,
    UNKNOWN_PIXEL,
    RosGrid,
    grid_from_npz_bytes,
    load_map,
    map_file_bytes,
    map_server_zip,
    npz_arrays,
    npz_bytes,
    save_map,
    save_map_server,
    save_npz,
    trinary_image,
)
from scanflow.maps.grid import CellBox
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams


def l_shaped_room_scans(grid: OccupancyGrid, scans: int = 6) -> None:
    """A few scans of an L-shaped set of walls, so maps have free, occupied and unknown cells."""
    rng = np.random.default_rng(3)
    a = np.linspace(-math.pi, math.pi, 240, endpoint=False)
    d = np.column_stack((np.cos(a), np.sin(a)))
    for i in range(scans):
        center = np.array([0.2 * i - 0.7, 0.1 * i + 0.33])
        with np.errstate(divide="ignore"):
            t = np.min([2.5, 3.5] / np.abs(d), axis=1)
        grid.insert_scan(center + d * t[:, None] + rng.normal(0, 0.005, (240, 2)), center)


def classes(grid: OccupancyGrid) -> np.ndarray:
    """0 free, 1 occupied, 2 unknown per cell, as nav2's map_saver draws the grid's ROS
    occupancy with the default thresholds: free <= rint(19.6) %, else occupied >= 65 %."""
    data = grid.to_int8()
    return np.where(data < 0, 2, np.where(data <= 20, 0, np.where(data >= 65, 1, 2)))


def map_saver_pixels(data: np.ndarray, occupied_thresh: float = 0.65,
                     free_thresh: float = 0.196) -> np.ndarray:
    """nav2 map_saver's trinary image of ROS occupancy (nav2_map_server map_io.cpp), cell by
    cell, top row first: unknown outside 0..100, free at or below rint(100 free_thresh), else
    occupied at or above rint(100 occupied_thresh), else unknown."""
    free, occupied = round(100.0 * free_thresh), round(100.0 * occupied_thresh)  # std::rint
    out = np.empty(data.shape, np.uint8)
    for (row, col), value in np.ndenumerate(data[::-1]):
        if value < 0 or value > 100:
            out[row, col] = UNKNOWN_PIXEL
        elif value <= free:
            out[row, col] = FREE_PIXEL
        elif value >= occupied:
            out[row, col] = OCCUPIED_PIXEL
        else:
            out[row, col] = UNKNOWN_PIXEL
    return out


def grid_of(probability: np.ndarray) -> OccupancyGrid:
    """A grid whose cells hold these occupancy probabilities (NaN: never observed)."""
    p = np.asarray(probability, dtype=np.float64)
    seen = np.isfinite(p)
    q = np.where(seen, p, 0.5)
    return OccupancyGrid.from_arrays(
        np.log(q / (1.0 - q)), seen, CellBox(0, 0, *p.shape), 0.01, -0.02, revision=7
    )


# Cells just either side of the thresholds: 65 % and 20 % are map_saver's occupied and free.
AT_THE_THRESHOLDS = np.array([
    [0.653, 0.647, 0.643, 0.9, np.nan],
    [0.196, 0.2, 0.203, 0.207, 0.19],
])


def parse_pgm(data: bytes) -> tuple[int, int, int, np.ndarray]:
    """A tiny independent P5 parser: magic, comments, width, height, maxval, raw bytes."""
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < 4:
        while data[pos : pos + 1].isspace():
            pos += 1
        if data[pos : pos + 1] == b"#":
            pos = data.index(b"\n", pos) + 1
            continue
        end = pos
        while not data[end : end + 1].isspace():
            end += 1
        tokens.append(data[pos:end])
        pos = end
    assert tokens[0] == b"P5"
    width, height, maxval = (int(t) for t in tokens[1:])
    pixels = np.frombuffer(data[pos + 1 :], dtype=np.uint8)
    assert pixels.size == width * height
    return width, height, maxval, pixels.reshape(height, width)


@pytest.fixture
def grid() -> OccupancyGrid:
    g = OccupancyGrid(OccupancyParams(resolution_m=0.05, p_hit=0.8), anchor_x_m=0.01)
    l_shaped_room_scans(g)
    return g


def test_npz_round_trip_is_exact(tmp_path: Path, grid: OccupancyGrid):
    path = save_map(grid, tmp_path / "map.npz")
    loaded = load_map(path)
    assert loaded.params == grid.params
    assert loaded.extent == grid.extent and loaded.spec == grid.spec
    assert (loaded.anchor_x_m, loaded.anchor_y_m) == (grid.anchor_x_m, grid.anchor_y_m)
    assert loaded.revision == grid.revision
    np.testing.assert_array_equal(loaded.log_odds, grid.log_odds)
    np.testing.assert_array_equal(loaded.observed, grid.observed)
    assert grid.hit_sums[2].sum() > 0
    np.testing.assert_array_equal(loaded.hit_sums, grid.hit_sums)
    # The loaded map keeps growing on the same lattice as the original.
    for g in (grid, loaded):
        g.insert_scan([[9.0, 9.0]], (0.0, 0.0))
    np.testing.assert_array_equal(loaded.log_odds, grid.log_odds)


def test_version_1_npz_without_hit_sums_loads_with_cell_centres(
    tmp_path: Path, grid: OccupancyGrid
):
    path = tmp_path / "v1.npz"
    box = grid.extent
    meta = {
        "format": "scanflow-occupancy",
        "version": 1,
        "anchor_x_m": grid.anchor_x_m,
        "anchor_y_m": grid.anchor_y_m,
        "box": [box.row0, box.col0, box.row1, box.col1],
        "params": asdict(grid.params),
        "revision": grid.revision,
    }
    np.savez_compressed(
        path, log_odds=grid.log_odds, observed=grid.observed, meta=np.array(json.dumps(meta))
    )
    loaded = load_map(path)
    np.testing.assert_array_equal(loaded.log_odds, grid.log_odds)
    assert not loaded.hit_sums.any()
    # No hits recorded: the field peaks on the occupied cells' centres (those whose
    # interpolation square lies inside the map).
    world = MatchingMap(loaded)
    value, _ = world.likelihood_field().sample(world.occupied_points())
    assert np.count_nonzero(value) > 0.5 * len(value)
    np.testing.assert_allclose(value[value > 0], 1.0)


def test_npz_of_an_empty_grid(tmp_path: Path):
    loaded = load_map(save_npz(OccupancyGrid(), tmp_path / "empty.npz"))
    assert loaded.is_empty


def test_npz_rejects_foreign_files(tmp_path: Path):
    path = tmp_path / "other.npz"
    np.savez(path, meta=np.array('{"format": "other", "version": 1}'))
    with pytest.raises(ValueError, match="not a scanflow-occupancy"):
        load_map(path)


@pytest.mark.parametrize("damage", ["empty", "half", "short", "flipped"])
def test_a_damaged_npz_file_is_a_value_error_naming_it(tmp_path: Path, grid: OccupancyGrid,
                                                       damage: str):
    """A map file cut short or corrupted on disk (a prior map, a snapshot): one ValueError
    naming the file, which the services catch, not a zipfile or zlib error from inside numpy."""
    path = save_npz(grid, tmp_path / "map.npz")
    data = path.read_bytes()
    middle = len(data) // 2
    path.write_bytes({
        "empty": b"", "half": data[:middle], "short": data[:-10],
        "flipped": data[:middle] + bytes(b ^ 0xFF for b in data[middle:middle + 64])
        + data[middle + 64:],
    }[damage])
    with pytest.raises(ValueError, match=f"^{path}: "):
        load_map(path)


def test_npz_bytes_round_trip_and_unreadable_bytes_name_their_source(grid: OccupancyGrid):
    """A map sent over the bus: exact, or a ValueError naming where the bytes came from."""
    loaded = grid_from_npz_bytes(npz_bytes(npz_arrays(grid)), "the matcher's map")
    np.testing.assert_array_equal(loaded.log_odds, grid.log_odds)
    np.testing.assert_array_equal(loaded.hit_sums, grid.hit_sums)
    assert loaded.extent == grid.extent and loaded.revision == grid.revision
    foreign = npz_bytes({"meta": np.array('{"format": "other", "version": 1}')})
    for data, reason in (
        (b"", "EOFError"), (b"PK\x03\x04 cut short", "BadZipFile"), (b"junk", "pickled"),
        (npz_bytes({"log_odds": np.zeros(2)}), "KeyError"), (foreign, "not a scanflow-occupancy"),
    ):
        with pytest.raises(ValueError, match=f"^the matcher's map: .*{reason}"):
            grid_from_npz_bytes(data, "the matcher's map")


@pytest.mark.parametrize(("field", "value", "reason"), [
    ("box", [-61.0, -81.0, 61.0, 81.0], "box must hold integers"),
    ("box", [0, 0, 2**62, 2**62], "box must hold integers within"),
    ("revision", "x", "revision must be an integer"),
    ("revision", -1, "revision must be an integer"),
    ("anchor_x_m", 1e300, "anchor must be finite and within"),
])
def test_a_map_whose_meta_is_malformed_is_refused_naming_it(
    grid: OccupancyGrid, field: str, value: object, reason: str
):
    """Bytes from the bus (a resume answer, a whole map) whose meta has the wrong types loaded,
    then failed deep inside a compiled kernel at the first insert (a fuzzing audit)."""
    arrays = npz_arrays(grid)
    meta = json.loads(str(arrays["meta"]))
    meta[field] = value
    arrays["meta"] = np.array(json.dumps(meta))
    with pytest.raises(ValueError, match=f"^the matcher's map: .*{reason}"):
        grid_from_npz_bytes(npz_bytes(arrays), "the matcher's map")


def test_map_server_files_are_what_ros_expects(tmp_path: Path, grid: OccupancyGrid):
    yaml_path = save_map_server(grid, tmp_path / "office.yaml")
    text = yaml_path.read_text()
    spec = grid.spec
    assert "image: office.pgm\n" in text
    assert "mode: trinary\n" in text
    assert f"resolution: {spec.resolution_m!r}\n" in text
    assert f"origin: [{spec.origin_x_m!r}, {spec.origin_y_m!r}, 0.0]\n" in text
    assert "negate: 0\n" in text
    assert "occupied_thresh: 0.65\n" in text and "free_thresh: 0.196\n" in text
    width, height, maxval, pixels = parse_pgm((tmp_path / "office.pgm").read_bytes())
    assert (width, height, maxval) == (spec.cols, spec.rows, 255)
    # map_server (negate 0, trinary): occupancy = (255 - pixel) / 255 against the thresholds;
    # row 0 of the image is the top (largest y) row of the map.
    occ = (255.0 - pixels[::-1]) / 255.0
    ros_classes = np.where(occ > 0.65, 1, np.where(occ < 0.196, 0, 2))
    np.testing.assert_array_equal(ros_classes, classes(grid))


def test_map_server_round_trip_keeps_free_occupied_unknown(tmp_path: Path, grid: OccupancyGrid):
    loaded = load_map(save_map(grid, tmp_path / "m.yaml"))
    assert loaded.spec.shape == grid.spec.shape
    assert loaded.spec.origin_x_m == pytest.approx(grid.spec.origin_x_m, abs=1e-12)
    assert loaded.spec.origin_y_m == pytest.approx(grid.spec.origin_y_m, abs=1e-12)
    want = classes(grid)
    assert {0, 1, 2} <= set(np.unique(want))
    np.testing.assert_array_equal(classes(loaded), want)


def test_a_map_server_zip_holds_the_pair_that_reads_back(tmp_path: Path, grid: OccupancyGrid):
    """One download for map_server / nav2: `<name>.yaml` naming `<name>.pgm`, the same files
    save_map_server writes, which read back to the same map."""
    data = map_server_zip(grid, "office")
    assert map_server_zip(grid, "office") == data  # no clock in it
    archive = zipfile.ZipFile(io.BytesIO(data))
    assert sorted(archive.namelist()) == ["office.pgm", "office.yaml"]
    archive.extractall(tmp_path / "zip")
    save_map_server(grid, tmp_path / "office.yaml")
    for name in ("office.yaml", "office.pgm"):
        assert (tmp_path / "zip" / name).read_bytes() == (tmp_path / name).read_bytes()
    loaded = load_map(tmp_path / "zip" / "office.yaml")
    assert loaded.spec.shape == grid.spec.shape
    np.testing.assert_array_equal(classes(loaded), classes(grid))


def test_reads_a_hand_written_map_server_map(tmp_path: Path):
    """A map as other tools write it: comments, quotes, PNG image, scale mode, negate."""
    image = np.array([[0, 255, 128], [255, 255, 0]], dtype=np.uint8)  # top row first
    Image.fromarray(image, mode="L").save(tmp_path / "hand.png")
    (tmp_path / "hand.yaml").write_text(
        "# saved by hand\n"
        "image: 'hand.png'\n"
        "resolution: 0.1\n"
        "origin: [-1.5, 2.0, 0.0]  # lower-left pixel\n"
        "negate: 1\n"
        "occupied_thresh: 0.65\n"
        "free_thresh: 0.25\n"
        "mode: scale\n"
    )
    grid = load_map(tmp_path / "hand.yaml")
    assert grid.resolution_m == 0.1
    assert (grid.spec.origin_x_m, grid.spec.origin_y_m) == (-1.5, 2.0)
    # negate: occupancy = value / 255; bottom row of the map is the last image row.
    data = grid.to_int8()
    assert data[0, 0] == data[0, 1] == data[1, 1] == 97  # 100 clamped at log_odds_max 3.5
    assert data[0, 2] == data[1, 0] == 12  # 0 clamped at log_odds_min -2.0
    expected = round(99 * (128 / 255 - 0.25) / (0.65 - 0.25))
    assert abs(data[1, 2] - expected) <= 1


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("resolution: 0.05\norigin: [0, 0, 0]\n", "image"),
        ("image: a.pgm\norigin: [0, 0, 0]\n", "resolution"),
        ("image: a.pgm\nresolution: 0.05\norigin: [0, 0, 0.5]\n", "origin"),
        ("image: a.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nmode: raw\n", "mode"),
    ],
)
def test_bad_map_server_yaml_names_the_field(tmp_path: Path, text: str, field: str):
    (tmp_path / "bad.yaml").write_text(text)
    with pytest.raises(ValueError, match=field):
        load_map(tmp_path / "bad.yaml")


@pytest.mark.parametrize(
    ("resolution", "origin", "reason"),
    [("-0.05", "[0, 0, 0]", r"resolution_m must be in \[0.001, 100\] m"),
     ("nan", "[0, 0, 0]", r"resolution_m must be in \[0.001, 100\] m"),
     # 1e300 loaded, then overflowed a search; 1e-6 asked for TiB at the first insert
     ("1e300", "[0, 0, 0]", r"resolution_m must be in \[0.001, 100\] m"),
     ("1e-6", "[0, 0, 0]", r"resolution_m must be in \[0.001, 100\] m"),
     ("0.05", "[nan, 0, 0]", "must be finite"), ("0.05", "[0, inf, 0]", "must be finite")],
)
def test_a_resolution_or_origin_the_grid_refuses_names_the_file(
    tmp_path: Path, resolution: str, origin: str, reason: str
):
    Image.fromarray(np.full((3, 4), FREE_PIXEL, np.uint8)).save(tmp_path / "a.pgm")
    (tmp_path / "bad.yaml").write_text(f"image: a.pgm\nresolution: {resolution}\n"
                                       f"origin: {origin}\n")
    with pytest.raises(ValueError, match=f"^{tmp_path / 'bad.yaml'}: .*{reason}"):
        load_map(tmp_path / "bad.yaml")


def test_png_for_people(tmp_path: Path, grid: OccupancyGrid):
    path = save_map(grid, tmp_path / "map.png")
    with Image.open(path) as img:
        pixels = np.asarray(img)
    assert pixels.shape == grid.spec.shape
    np.testing.assert_array_equal(pixels, trinary_image(grid))
    assert set(np.unique(pixels)) == {OCCUPIED_PIXEL, FREE_PIXEL, UNKNOWN_PIXEL}
    np.testing.assert_array_equal(pixels[::-1] == OCCUPIED_PIXEL, grid.to_int8() >= 65)


def test_cells_at_the_thresholds_are_drawn_as_map_saver_draws_their_percentages():
    """0.647 is 65 %: occupied, as map_saver draws it from the map's ROS occupancy (and as a
    region of it, sent as those percentages, is drawn); compared on the probability it was
    unknown. Likewise 0.2 and 0.203 are 20 %: free."""
    grid = grid_of(AT_THE_THRESHOLDS)
    np.testing.assert_array_equal(grid.to_int8(), [[65, 65, 64, 90, -1], [20, 20, 20, 21, 19]])
    image = trinary_image(grid)
    np.testing.assert_array_equal(image, map_saver_pixels(grid.to_int8()))
    o, f, u = OCCUPIED_PIXEL, FREE_PIXEL, UNKNOWN_PIXEL
    np.testing.assert_array_equal(image[::-1], [[o, o, u, o, u], [f, f, f, u, f]])


def test_a_grid_and_its_ros_occupancy_give_the_same_files():
    grid = grid_of(AT_THE_THRESHOLDS)
    ros = RosGrid.of(grid)
    assert ros.spec == grid.spec and RosGrid.of(ros) is ros
    for fmt in MAP_FILE_FORMATS:
        assert map_file_bytes(ros, fmt, "m") == map_file_bytes(grid, fmt, "m"), fmt
    with pytest.raises(ValueError, match="empty"):
        trinary_image(RosGrid.of(OccupancyGrid()))


probabilities = hnp.arrays(
    np.float64, st.tuples(st.integers(1, 6), st.integers(1, 6)),
    elements=st.one_of(st.floats(0.12, 0.97), st.just(np.nan)),
)


@settings(max_examples=60, deadline=None)
@given(p=probabilities, window=st.tuples(*[st.integers(0, 5)] * 4),
       thresholds=st.sampled_from([(0.65, 0.196), (0.65, 0.25), (0.55, 0.305), (0.9, 0.1)]))
def test_a_window_of_the_ros_occupancy_draws_as_the_whole_map_does(p, window, thresholds):
    """Any grid, whole or any window of its percentages: map_saver's pixels, cell for cell."""
    grid = grid_of(p)
    data = grid.to_int8()
    image = trinary_image(grid, *thresholds)
    np.testing.assert_array_equal(image, map_saver_pixels(data, *thresholds))
    rows, cols = data.shape
    r0, c0 = min(window[0], rows - 1), min(window[1], cols - 1)
    r1, c1 = r0 + 1 + window[2] % (rows - r0), c0 + 1 + window[3] % (cols - c0)
    spec = CellBox(r0, c0, r1, c1).spec(grid.spec.origin_x_m, grid.spec.origin_y_m,
                                        grid.resolution_m)
    part = trinary_image(RosGrid(data[r0:r1, c0:c1], spec), *thresholds)
    np.testing.assert_array_equal(part[::-1], image[::-1][r0:r1, c0:c1])


def test_writes_are_atomic_and_leave_no_temporaries(tmp_path: Path, grid: OccupancyGrid):
    for name in ("a.npz", "a.yaml", "a.png"):
        save_map(grid, tmp_path / name)
        save_map(grid, tmp_path / name)  # overwrite in place
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz", "a.pgm", "a.png", "a.yaml"]


def test_unknown_suffix_and_empty_map_are_refused(tmp_path: Path):
    with pytest.raises(ValueError, match="suffix"):
        load_map(tmp_path / "map.bmp")
    with pytest.raises(ValueError, match="empty"):
        save_map(OccupancyGrid(), tmp_path / "map.png")


def test_a_loaded_map_can_be_matched_against(tmp_path: Path, grid: OccupancyGrid):
    """Localisation on a prior map: the field of a loaded map attracts a shifted wall point."""
    for name in ("prior.npz", "prior.yaml"):
        world = MatchingMap(load_map(save_map(grid, tmp_path / name)))
        assert not world.is_empty
        field = world.likelihood_field()
        wall = world.occupied_points()
        value, grad = field.sample(Pose2D(0.03, 0.0, 0.0).transform_points(wall))
        assert value.mean() > 0.5
        assert grad[:, 0].mean() < 0  # pulls the points back towards -x


def test_localisation_on_a_prior_map_loaded_from_disk(tmp_path: Path):
    """Map the simulator's rooms, save, load, and match a new scan against the loaded map."""
    from scanflow.matching import match
    from scanflow.sim import cast_rays, get_world

    walls = get_world("rooms").segments

    def scan(pose: Pose2D) -> np.ndarray:
        angles = pose.theta + np.linspace(-math.pi, math.pi, 360, endpoint=False)
        ranges = cast_rays(np.tile([pose.x, pose.y], (360, 1)), angles, walls, 12.0)
        ok = np.isfinite(ranges)
        rel = angles[ok] - pose.theta
        return np.column_stack((ranges[ok] * np.cos(rel), ranges[ok] * np.sin(rel)))

    grid = OccupancyGrid()
    for x, y in get_world("rooms").waypoints:
        pose = Pose2D(x, y, 0.3)
        grid.insert_scan(pose.transform_points(scan(pose)), (x, y))
    truth = Pose2D(7.0, 2.2, 0.4)
    for name in ("prior.npz", "prior.yaml"):
        world = MatchingMap(load_map(save_map(grid, tmp_path / name)))
        result = match(scan(truth), world, Pose2D(7.12, 2.1, 0.45), method="gn")
        assert result.ok, result.message
        # A field built on 5 cm cell centres can be biased by up to half a cell.
        assert math.hypot(result.pose.x - truth.x, result.pose.y - truth.y) < 0.04
        assert abs(result.pose.theta - truth.theta) < math.radians(1.0)


@pytest.mark.parametrize(
    ("line", "field"),
    [
        ("occupied_thresh: high\n", "occupied_thresh"),
        ("free_thresh: low\n", "free_thresh"),
        ("origin: [a, 0.0, 0.0]\n", "origin"),
    ],
)
def test_a_map_server_field_that_is_not_a_number_is_named(tmp_path: Path, line: str, field: str):
    """Not float's bare "could not convert string to float": the file and the field."""
    Image.fromarray(np.full((2, 3), 254, np.uint8), mode="L").save(tmp_path / "a.pgm")
    text = "image: a.pgm\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\n"
    if line.startswith("origin"):
        text = text.replace("origin: [0.0, 0.0, 0.0]\n", "")
    (tmp_path / "bad.yaml").write_text(text + line)
    with pytest.raises(ValueError, match=f"bad.yaml: field '{field}'"):
        load_map(tmp_path / "bad.yaml")


def test_an_image_whose_header_claims_billions_of_pixels_is_a_value_error_naming_it(
    tmp_path: Path,
):
    """A corrupt PGM header (20000 x 20000): PIL refuses it with its DecompressionBombError,
    which is no OSError or ValueError and got past every caller's handler (a prior map stopped
    the service with a traceback)."""
    (tmp_path / "big.pgm").write_bytes(b"P5\n20000 20000\n255\n" + bytes(64))
    (tmp_path / "big.yaml").write_text("image: big.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n")
    with pytest.raises(ValueError, match=r"big\.pgm"):
        load_map(tmp_path / "big.yaml")


@pytest.mark.parametrize(
    "thresholds", ["free_thresh: 0.65\noccupied_thresh: 0.65\n", "free_thresh: 0.7\n",
                   "occupied_thresh: 1.5\n", "free_thresh: -0.1\n"],
)
def test_map_server_thresholds_out_of_order_are_named(tmp_path: Path, thresholds: str):
    """free < occupied within [0, 1]: equal ones made scale mode divide by zero, swapped ones
    let a shade count as both occupied and free."""
    Image.fromarray(np.full((2, 3), 254, np.uint8), mode="L").save(tmp_path / "a.pgm")
    text = "image: a.pgm\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\nmode: scale\n"
    (tmp_path / "bad.yaml").write_text(text + thresholds)
    with pytest.raises(ValueError, match=r"bad\.yaml: fields 'free_thresh' and 'occupied_thresh'"):
        load_map(tmp_path / "bad.yaml")


@pytest.mark.parametrize("image_format", ["pgm", "png"])
def test_a_16_bit_map_image_reads_as_its_8_bit_twin(tmp_path: Path, image_format: str):
    """A 16-bit map image (a PGM with maxval 65535, a 16-bit PNG): its grey levels are on
    0..65535, which used to be clipped at 255 (every shade read as white: free). Scaled down,
    it gives the cells its 8-bit twin gives."""
    shades8 = np.array([[0, 254, 205], [128, 40, 230]], dtype=np.uint8)
    wide = shades8.astype(np.uint16) * 257  # the same shade on 0..65535
    Image.fromarray(shades8, mode="L").save(tmp_path / "eight.pgm")
    if image_format == "pgm":
        header = b"P5\n3 2\n65535\n"
        (tmp_path / f"wide.{image_format}").write_bytes(header + wide.astype(">u2").tobytes())
    else:
        Image.fromarray(wide).save(tmp_path / "wide.png")
    origin = "resolution: 0.05\norigin: [0.0, 0.0, 0.0]\nmode: scale\n"
    (tmp_path / "eight.yaml").write_text("image: eight.pgm\n" + origin)
    (tmp_path / "wide.yaml").write_text(f"image: wide.{image_format}\n" + origin)
    expected = load_map(tmp_path / "eight.yaml").to_int8()
    assert np.array_equal(load_map(tmp_path / "wide.yaml").to_int8(), expected)
    assert len(np.unique(expected)) >= 3  # occupied, free and a shade between


def test_a_floating_point_image_is_a_value_error_naming_it(tmp_path: Path):
    Image.fromarray(np.zeros((2, 3), np.float32), mode="F").save(tmp_path / "f.tiff")
    (tmp_path / "f.yaml").write_text("image: f.tiff\nresolution: 0.05\norigin: [0, 0, 0]\n")
    with pytest.raises(ValueError, match=r"f\.tiff: floating-point image"):
        load_map(tmp_path / "f.yaml")


@pytest.mark.parametrize("cut", [0, 11, 30])
def test_an_image_cut_short_or_empty_is_a_value_error_naming_it(tmp_path: Path, cut: int):
    """Pillow's OSError or UnidentifiedImageError came out bare (a fuzzing audit)."""
    Image.fromarray(np.full((40, 50), FREE_PIXEL, np.uint8)).save(tmp_path / "whole.pgm")
    (tmp_path / "cut.pgm").write_bytes((tmp_path / "whole.pgm").read_bytes()[:cut])
    (tmp_path / "cut.yaml").write_text("image: cut.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n")
    with pytest.raises(ValueError, match=r"cut\.pgm: not a readable image"):
        load_map(tmp_path / "cut.yaml")
    (tmp_path / "gone.yaml").write_text("image: gone.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n")
    with pytest.raises(FileNotFoundError):  # a missing file stays what it is
        load_map(tmp_path / "gone.yaml")


@pytest.mark.parametrize(
    ("negate", "inverted"),
    [("0", False), ("false", False), ("FALSE", False), ("no", False), ("off", False),
     ("1", True), ("true", True), ("True", True), ("yes", True), ("ON", True)],
)
def test_negate_is_read_as_map_server_reads_a_flag(tmp_path: Path, negate: str, inverted: bool):
    """Every YAML spelling of false keeps the map as drawn: `negate: FALSE` or `no` used to
    invert it (anything but 0, false and False was taken for true)."""
    image = np.array([[0, 254, 205], [254, 0, 254]], dtype=np.uint8)  # top row first
    Image.fromarray(image, mode="L").save(tmp_path / "a.pgm")
    (tmp_path / "a.yaml").write_text(
        f"image: a.pgm\nresolution: 0.5\norigin: [-1.0, -2.0, 0.0]\nnegate: {negate}\n"
    )
    occupied = load_map(tmp_path / "a.yaml").occupied_mask()[::-1]
    np.testing.assert_array_equal(occupied, (image != 0) if inverted else (image == 0))


@pytest.mark.parametrize("negate", ["2", "0.0", "maybe"])
def test_a_negate_that_is_no_flag_is_named(tmp_path: Path, negate: str):
    Image.fromarray(np.full((2, 3), 254, np.uint8), mode="L").save(tmp_path / "a.pgm")
    (tmp_path / "bad.yaml").write_text(
        f"image: a.pgm\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\nnegate: {negate}\n"
    )
    with pytest.raises(ValueError, match=r"bad\.yaml: field 'negate' must be 0, 1, true or false"):
        load_map(tmp_path / "bad.yaml")


@pytest.mark.parametrize("image_mode", ["RGBA", "LA", "P", "I;16"])
def test_transparent_pixels_of_a_scale_map_are_unknown(tmp_path: Path, image_mode: str):
    """nav2's map_saver in scale mode marks unknown cells by transparency (grey 128, alpha 0):
    the alpha channel used to be dropped, so they read as half-occupied observed cells, and as
    walls where occupied_thresh is below 0.5."""
    grey = np.array([[0, 128, 255], [127, 128, 0]], dtype=np.uint8)  # top row first
    opaque = np.array([[True, False, True], [True, False, True]])
    rgba = np.dstack([grey, grey, grey, np.where(opaque, 255, 0).astype(np.uint8)])
    image = Image.fromarray(rgba, mode="RGBA")
    options = {}
    if image_mode == "LA":
        image = image.convert("LA")
    elif image_mode == "P":  # a palette with a transparent entry (PNG tRNS)
        image = image.quantize(colors=8)
    elif image_mode == "I;16":  # 16-bit grey with a transparent grey level (PNG tRNS)
        image, options = Image.fromarray(grey.astype(np.uint16) * 257), {"transparency": 128 * 257}
    image.save(tmp_path / "scale.png", **options)
    (tmp_path / "scale.yaml").write_text(
        "image: scale.png\nmode: scale\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\n"
        "negate: 0\noccupied_thresh: 0.45\nfree_thresh: 0.25\n"
    )
    grid = load_map(tmp_path / "scale.yaml")
    np.testing.assert_array_equal(grid.observed[::-1], opaque)
    np.testing.assert_array_equal(grid.occupied_mask()[::-1], opaque & (255 - grey > 0.45 * 255))


def test_a_trinary_map_with_alpha_reads_as_map_server_reads_it(tmp_path: Path):
    """Trinary mode averages the opacity in with the colour channels (map_server and nav2
    alike), so an opaque unknown grey (205) lightens to free; negate applies after."""
    grey = np.array([[0, 254, 205], [205, 0, 254]], dtype=np.uint8)
    alpha = np.array([[255, 255, 255], [0, 0, 255]], dtype=np.uint8)
    Image.fromarray(np.dstack([grey, grey, grey, alpha]), mode="RGBA").save(tmp_path / "t.png")
    for negate in (0, 1):
        (tmp_path / "t.yaml").write_text(
            f"image: t.png\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\nnegate: {negate}\n"
        )
        shade = (3.0 * grey + alpha) / 4.0
        occ = shade / 255.0 if negate else (255.0 - shade) / 255.0
        want = np.where(occ > 0.65, 1, np.where(occ < 0.196, 0, 2))
        np.testing.assert_array_equal(classes(load_map(tmp_path / "t.yaml"))[::-1], want)


def test_a_map_server_yaml_with_a_byte_order_mark_and_crlf_lines_reads(
    tmp_path: Path, grid: OccupancyGrid
):
    """As a Windows editor saves it: the BOM used to stick to the first key ('missing field
    image' for a file that has one)."""
    yaml_path = save_map_server(grid, tmp_path / "win.yaml")
    text = yaml_path.read_text().replace("\n", "\r\n")
    yaml_path.write_bytes(b"\xef\xbb\xbf" + text.encode("utf-8"))
    loaded = load_map(yaml_path)
    assert loaded.spec == grid.spec
    np.testing.assert_array_equal(classes(loaded), classes(grid))
