"""Save and load occupancy maps: PNG for people, PGM + YAML for ROS map_server/nav2, and a
lossless native .npz. Every write is atomic (temporary file, then os.replace), so a reader never
sees half a map.

map_server conventions: image row 0 is the top (largest y) row; `origin` is the world pose of
the lower-left pixel; with `negate: 0` a pixel's occupancy is (255 - value) / 255, trinary mode
calls it occupied above `occupied_thresh`, free below `free_thresh`, unknown otherwise. We write
what nav2's map_saver writes from the map's ROS occupancy (`RosGrid`: -1 unknown, 0..100 percent,
as the map server sends a region): 254 free at or below rint(100 free_thresh), else 0 occupied at
or above rint(100 occupied_thresh), else 205 unknown. One rule on those percentages, so a whole
map and a region of it draw each cell alike.
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from collections.abc import Mapping
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import IO

import numpy as np
from numpy.typing import ArrayLike, NDArray
from PIL import Image

from scanflow.maps.grid import CellBox, GridSpec
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams

OCCUPIED_PIXEL = 0
FREE_PIXEL = 254
UNKNOWN_PIXEL = 205
OCCUPIED_THRESH = 0.65
FREE_THRESH = 0.196
NPZ_FORMAT = "scanflow-occupancy"
NPZ_VERSION = 2  # v2 added the per-cell hit sums; v1 files load with cell-centre fallback
NPZ_READABLE_VERSIONS = (1, 2)


def _write_atomic(path: Path, data: bytes) -> Path:
    """Write bytes to a temporary file beside `path`, then rename it over `path`."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


@dataclass(frozen=True, slots=True)
class RosGrid:
    """A map as ROS carries it (nav_msgs/OccupancyGrid): `data` -1 unknown, 0..100 percent
    occupied, rows growing with y, placed by `spec`. What every map file is drawn from."""

    data: NDArray[np.int8]
    spec: GridSpec

    @staticmethod
    def of(grid: OccupancyGrid | RosGrid) -> RosGrid:
        """The ROS occupancy of a grid (`to_int8` over its extent), or `grid` itself."""
        return grid if isinstance(grid, RosGrid) else RosGrid(grid.to_int8(), grid.spec)


def trinary_image(
    grid: OccupancyGrid | RosGrid,
    occupied_thresh: float = OCCUPIED_THRESH,
    free_thresh: float = FREE_THRESH,
) -> NDArray[np.uint8]:
    """Grey image of the map, top row = largest y: 0 occupied, 254 free, 205 unknown, by
    nav2 map_saver's trinary rule on the ROS percentages (module docstring)."""
    if not 0.0 < free_thresh < occupied_thresh < 1.0:
        raise ValueError(
            f"need 0 < free_thresh < occupied_thresh < 1, got {free_thresh}, {occupied_thresh}"
        )
    data = RosGrid.of(grid).data
    if data.size == 0:
        raise ValueError("grid is empty: nothing to draw")
    known = (data >= 0) & (data <= 100)
    image = np.full(data.shape, UNKNOWN_PIXEL, dtype=np.uint8)
    image[known & (data >= round(100.0 * occupied_thresh))] = OCCUPIED_PIXEL
    image[known & (data <= round(100.0 * free_thresh))] = FREE_PIXEL  # map_saver tests it first
    return np.ascontiguousarray(image[::-1])


def png_bytes(grid: OccupancyGrid | RosGrid) -> bytes:
    """A PNG for people: free white, occupied black, unknown grey, y up."""
    buffer = io.BytesIO()
    Image.fromarray(trinary_image(grid), mode="L").save(buffer, format="PNG")
    return buffer.getvalue()


def save_png(grid: OccupancyGrid, path: Path | str) -> Path:
    """Write `png_bytes` of the map to `path`."""
    return _write_atomic(Path(path), png_bytes(grid))


def pgm_bytes(image: NDArray[np.uint8]) -> bytes:
    """A binary (P5) 8-bit PGM of a grey image."""
    rows, cols = image.shape
    header = f"P5\n# CREATOR: scanflow\n{cols} {rows}\n255\n".encode("ascii")
    return header + np.ascontiguousarray(image, dtype=np.uint8).tobytes()


def map_server_files(
    grid: OccupancyGrid | RosGrid,
    name: str,
    occupied_thresh: float = OCCUPIED_THRESH,
    free_thresh: float = FREE_THRESH,
) -> tuple[bytes, bytes]:
    """The map_server pair of one map, in memory: `<name>.yaml` (naming `<name>.pgm` as its
    image) and that trinary PGM."""
    ros = RosGrid.of(grid)
    spec = ros.spec
    pgm = pgm_bytes(trinary_image(ros, occupied_thresh, free_thresh))
    text = (
        f"image: {name}.pgm\n"
        "mode: trinary\n"
        f"resolution: {spec.resolution_m!r}\n"
        f"origin: [{spec.origin_x_m!r}, {spec.origin_y_m!r}, 0.0]\n"
        "negate: 0\n"
        f"occupied_thresh: {occupied_thresh!r}\n"
        f"free_thresh: {free_thresh!r}\n"
    )
    return text.encode("utf-8"), pgm


def save_map_server(
    grid: OccupancyGrid,
    yaml_path: Path | str,
    occupied_thresh: float = OCCUPIED_THRESH,
    free_thresh: float = FREE_THRESH,
) -> Path:
    """Write `<name>.yaml` and `<name>.pgm` beside it, loadable by map_server/nav2 (trinary)."""
    yaml_path = Path(yaml_path)
    text, pgm = map_server_files(grid, yaml_path.stem, occupied_thresh, free_thresh)
    _write_atomic(yaml_path.with_suffix(".pgm"), pgm)
    return _write_atomic(yaml_path, text)


def map_server_zip(grid: OccupancyGrid | RosGrid, name: str = "map") -> bytes:
    """`<name>.yaml` and `<name>.pgm` in one zip: a pair that cannot come from two revisions of
    a growing map, as two downloads can. Stamped 1980-01-01, so one map gives the same bytes."""
    text, pgm = map_server_files(grid, name)
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for suffix, data in ((".yaml", text), (".pgm", pgm)):
            entry = zipfile.ZipInfo(f"{name}{suffix}", date_time=(1980, 1, 1, 0, 0, 0))
            entry.compress_type = zipfile.ZIP_DEFLATED
            entry.external_attr = 0o644 << 16  # rw-r--r-- when unzipped
            archive.writestr(entry, data)
    return buffer.getvalue()


MAP_FILE_FORMATS = ("png", "pgm", "yaml", "zip")


def map_file_bytes(grid: OccupancyGrid | RosGrid, fmt: str, name: str) -> bytes:
    """One map file, in memory: png, or map_server's pgm or yaml (naming `<name>.pgm`), or the
    two in one zip; ValueError for any other format. A grid and its `RosGrid.of` (a region as
    the map server sends it) give the same bytes."""
    if fmt == "png":
        return png_bytes(grid)
    if fmt == "zip":
        return map_server_zip(grid, name)
    if fmt in ("yaml", "pgm"):
        text, pgm = map_server_files(grid, name)
        return text if fmt == "yaml" else pgm
    raise ValueError(f"format must be one of {MAP_FILE_FORMATS}, got {fmt!r}")


def _parse_flat_yaml(text: str, source: Path) -> dict[str, str]:
    """The `key: value` lines of a map_server YAML file (flat, comments allowed)."""
    fields: dict[str, str] = {}
    for line_no, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line or line == "---":
            continue
        key, sep, value = line.partition(":")
        if not sep:
            raise ValueError(f"{source}:{line_no}: expected 'key: value', got {raw!r}")
        fields[key.strip()] = value.strip().strip("'\"")
    return fields


def _yaml_float(
    fields: dict[str, str], key: str, source: Path, default: float | None = None
) -> float:
    """Field `key` as a number (`default` when it is absent and one is given)."""
    if key not in fields and default is not None:
        return default
    try:
        return float(fields[key])
    except KeyError:
        raise ValueError(f"{source}: missing field {key!r}") from None
    except ValueError:
        raise ValueError(f"{source}: field {key!r} is not a number: {fields[key]!r}") from None


YAML_TRUE = ("1", "true", "yes", "on", "y")
YAML_FALSE = ("0", "false", "no", "off", "n")


def _yaml_flag(fields: dict[str, str], key: str, source: Path) -> bool:
    """Field `key` as map_server reads a flag (0/1 or a YAML boolean, false when absent): any
    other word is refused, never taken for true (`negate: FALSE` used to invert the map)."""
    value = fields.get(key, "0").lower()
    if value not in YAML_TRUE + YAML_FALSE:
        raise ValueError(
            f"{source}: field {key!r} must be 0, 1, true or false, got {fields[key]!r}"
        )
    return value in YAML_TRUE


def _occupancy_from_pixels(
    shade: NDArray[np.float64],
    opacity: NDArray[np.float64] | None,
    mode: str,
    negate: bool,
    occupied_thresh: float,
    free_thresh: float,
) -> NDArray[np.int8]:
    """map_server's pixel -> ROS occupancy (-1, 0..100) for trinary and scale modes. With an
    alpha channel, trinary averages the opacity in as a fourth channel and scale calls every
    pixel that is not opaque unknown, as map_server and nav2 do (scale maps mark unknown so)."""
    if opacity is not None and mode == "trinary":
        shade = (3.0 * shade + opacity) / 4.0
    occ = shade / 255.0 if negate else (255.0 - shade) / 255.0
    if mode == "trinary":
        middle = np.full(shade.shape, -1.0)
    else:
        middle = np.rint(99.0 * (occ - free_thresh) / (occupied_thresh - free_thresh))
    data = np.where(occ > occupied_thresh, 100.0, np.where(occ < free_thresh, 0.0, middle))
    if opacity is not None and mode == "scale":
        data[opacity < 255.0] = -1.0
    return data.astype(np.int8)


def _shade_of(image_path: Path) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """The image's grey level per pixel on map_server's 0..255 scale, and its opacity (0..255)
    when it has an alpha channel or a transparent colour (None otherwise): colour channels
    averaged as map_server does, 16-bit images (PGM with maxval > 255, PNG) scaled down from
    0..65535 rather than clipped at 255 (Pillow reads both as 0..65535)."""
    try:
        with Image.open(image_path) as img:
            mode = img.mode
            if mode == "I" or mode.startswith("I;16"):
                pixels = np.asarray(img, dtype=np.float64)
                if pixels.size and (pixels.min() < 0.0 or pixels.max() > 65535.0):
                    raise ValueError(
                        f"{image_path}: mode {mode} pixels outside 0..65535 "
                        f"({pixels.min():.0f}..{pixels.max():.0f}): not a 16-bit grey map"
                    )
                transparent = img.info.get("transparency")  # a 16-bit PNG's tRNS grey level
                opacity = None if transparent is None else 255.0 * (pixels != transparent)
                return pixels * (255.0 / 65535.0), opacity
            if "A" in mode or "transparency" in img.info:
                rgba = np.asarray(img.convert("RGBA"), dtype=np.float64)
                return rgba[..., :3].mean(axis=2), rgba[..., 3]
            if mode == "L":
                return np.asarray(img, dtype=np.float64), None
            if mode == "F":
                raise ValueError(f"{image_path}: floating-point image (mode F): not a map image")
            return np.asarray(img.convert("RGB"), dtype=np.float64).mean(axis=2), None
    except Image.DecompressionBombError as exc:  # a size no map has: a corrupt header
        raise ValueError(f"{image_path}: {exc}") from exc
    except FileNotFoundError:
        raise
    except (OSError, SyntaxError, ValueError) as exc:  # cut short, empty, not an image at all
        if str(exc).startswith(f"{image_path}:"):  # said above
            raise
        raise ValueError(
            f"{image_path}: not a readable image ({type(exc).__name__}: {exc})"
        ) from exc


def load_map_server(yaml_path: Path | str, params: OccupancyParams | None = None) -> OccupancyGrid:
    """Read a map_server YAML and its image (PGM, PNG, ...) into an OccupancyGrid."""
    yaml_path = Path(yaml_path)
    text = yaml_path.read_text(encoding="utf-8-sig")  # a byte order mark is no part of a key
    fields = _parse_flat_yaml(text, yaml_path)
    if "image" not in fields:
        raise ValueError(f"{yaml_path}: missing field 'image'")
    resolution_m = _yaml_float(fields, "resolution", yaml_path)
    occupied_thresh = _yaml_float(fields, "occupied_thresh", yaml_path, OCCUPIED_THRESH)
    free_thresh = _yaml_float(fields, "free_thresh", yaml_path, FREE_THRESH)
    if not 0.0 <= free_thresh < occupied_thresh <= 1.0:  # scale mode divides by their gap
        raise ValueError(
            f"{yaml_path}: fields 'free_thresh' and 'occupied_thresh' must satisfy 0 <= free < "
            f"occupied <= 1, got {free_thresh} and {occupied_thresh}"
        )
    mode = fields.get("mode", "trinary")
    if mode not in ("trinary", "scale"):
        raise ValueError(f"{yaml_path}: field 'mode' must be trinary or scale, got {mode!r}")
    origin_text = fields.get("origin", "")
    try:
        origin = [float(v) for v in origin_text.strip("[]").split(",") if v.strip()]
    except ValueError:
        origin = []
    if len(origin) != 3 or origin[2] != 0.0:
        raise ValueError(f"{yaml_path}: field 'origin' must be [x, y, 0.0], got {origin_text!r}")
    shade, opacity = _shade_of(yaml_path.parent / fields["image"])
    negate = _yaml_flag(fields, "negate", yaml_path)
    data = _occupancy_from_pixels(shade, opacity, mode, negate, occupied_thresh, free_thresh)
    data = data[::-1]  # image row 0 is the top of the map, grid row 0 its bottom
    try:  # a resolution or origin the grid refuses (not positive, not finite): name the file
        grid_params = replace(params or OccupancyParams(), resolution_m=resolution_m)
        return OccupancyGrid.from_int8(data, origin[0], origin[1], grid_params)
    except ValueError as exc:
        raise ValueError(f"{yaml_path}: {exc}") from exc


def npz_arrays(grid: OccupancyGrid) -> dict[str, NDArray]:
    """The native format's arrays: log-odds, observed mask, hit sums and a JSON `meta` with the
    lattice placement, params and revision. Callers may add arrays of their own beside them
    (a map server snapshot adds the trajectory) and the result still loads as a map."""
    box = grid.extent or CellBox(0, 0, 0, 0)
    meta = {
        "format": NPZ_FORMAT,
        "version": NPZ_VERSION,
        "anchor_x_m": grid.anchor_x_m,
        "anchor_y_m": grid.anchor_y_m,
        "box": [box.row0, box.col0, box.row1, box.col1],
        "params": asdict(grid.params),
        "revision": grid.revision,
    }
    return {
        "log_odds": grid.log_odds,
        "observed": grid.observed,
        "hit_sums": grid.hit_sums,
        "meta": np.array(json.dumps(meta)),
    }


def npz_bytes(arrays: Mapping[str, ArrayLike], compressed: bool = True) -> bytes:
    """`arrays` as the bytes of one .npz, zlib-compressed unless `compressed` is False (scan
    points, which hardly compress, are written faster plain)."""
    buffer = io.BytesIO()
    # allow_pickle given (its default) so that no array can be taken for it: a name clash fails.
    (np.savez_compressed if compressed else np.savez)(buffer, allow_pickle=True, **arrays)
    return buffer.getvalue()


def write_npz(
    path: Path | str, arrays: Mapping[str, ArrayLike], compressed: bool = True
) -> Path:
    """`arrays` as one .npz (`npz_bytes`) that replaces `path` atomically."""
    return _write_atomic(Path(path), npz_bytes(arrays, compressed))


def save_npz(grid: OccupancyGrid, path: Path | str) -> Path:
    """Lossless native format (`npz_arrays`), written atomically."""
    return write_npz(path, npz_arrays(grid))


def grid_from_npz(data: Mapping[str, NDArray], source: Path | str) -> OccupancyGrid:
    """The map in an opened native .npz (`np.load`), exactly as it was saved (a v1 file has
    no hit sums: its matching fields use cell centres); `source` names it in errors."""
    meta = json.loads(str(data["meta"]))
    if meta.get("format") != NPZ_FORMAT or meta.get("version") not in NPZ_READABLE_VERSIONS:
        raise ValueError(
            f"{source}: not a {NPZ_FORMAT} file of version {NPZ_READABLE_VERSIONS} "
            f"(format {meta.get('format')!r}, version {meta.get('version')!r})"
        )
    return OccupancyGrid.from_arrays(
        data["log_odds"],
        data["observed"],
        CellBox(*meta["box"]),
        meta["anchor_x_m"],
        meta["anchor_y_m"],
        OccupancyParams(**meta["params"]),
        meta["revision"],
        data.get("hit_sums"),
    )


def grid_from_npz_bytes(data: bytes, source: str) -> OccupancyGrid:
    """The map in the bytes of a native .npz (a map sent over the bus); ValueError naming
    `source` when they are not one."""
    return _read_npz(io.BytesIO(data), source)


def load_npz(path: Path | str) -> OccupancyGrid:
    """Read a map written by `save_npz` (or any file of `npz_arrays` plus other arrays);
    ValueError naming `path` when it is no readable one (truncated, corrupt, foreign)."""
    return _read_npz(path, str(path))


def _read_npz(file: Path | str | IO[bytes], source: str) -> OccupancyGrid:
    """The map in a native .npz; a file that cannot be read as one is a ValueError naming
    `source`, whatever failed (zip, zlib, npy or a missing key), a missing file an OSError."""
    try:
        with np.load(file, allow_pickle=False) as arrays:
            return grid_from_npz(arrays, source)
    except OSError:
        raise
    except Exception as exc:
        if str(exc).startswith(f"{source}:"):
            raise
        raise ValueError(f"{source}: not a readable .npz ({type(exc).__name__}: {exc})") from exc


def save_map(grid: OccupancyGrid, path: Path | str) -> Path:
    """Save by suffix: .npz native, .yaml/.yml map_server (+ .pgm), .png picture."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npz":
        return save_npz(grid, path)
    if suffix in (".yaml", ".yml"):
        return save_map_server(grid, path)
    if suffix == ".png":
        return save_png(grid, path)
    raise ValueError(f"map path suffix must be .npz, .yaml, .yml or .png, got {suffix!r}")


def load_map(path: Path | str, params: OccupancyParams | None = None) -> OccupancyGrid:
    """Load by suffix: .npz native (exact) or .yaml/.yml map_server (with `params`' model)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npz":
        return load_npz(path)
    if suffix in (".yaml", ".yml"):
        return load_map_server(path, params)
    raise ValueError(f"map path suffix must be .npz, .yaml or .yml, got {suffix!r}")
