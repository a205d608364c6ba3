"""Ground control points as survey teams hand them over: OpenDroneMap's ``gcp_list.txt``.

The format (OpenDroneMap; WebODM's GCP editor writes it, NodeODM takes it with every task): the first
line is the points' coordinate system (a PROJ string, ``EPSG:nnnn`` or ``WGS84``); every other line
is one observation, ``x y z px py image [name] [extra ...]`` separated by tabs or spaces, where
``x y z`` is the point (easting, northing and height; longitude, latitude and height for WGS84) and
``px py`` its pixel in ``image`` with pixel centres at integers (OpenSfM's convention). Lines
starting with ``#`` and blank lines are skipped. Without a name column, observations with the same
coordinates are one point, as OpenDroneMap groups them.

Real files have flaws, so reading one never fails on a single bad line: every problem is reported
with its line or point and the rest goes on. Only a file that cannot be used at all (no coordinate
system pyproj knows, fewer than 3 usable points) is refused, with the reason.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import pyproj
from pyproj.exceptions import CRSError

MIN_POINTS = 3  # a similarity (7 unknowns) needs three points


class GcpError(ValueError):
    """The GCP file cannot be used at all; the message says why."""


@dataclass(frozen=True)
class Observation:
    image: str
    pixel: tuple[float, float]  # pixel centres at integers
    line: int  # 1-based line of the file


@dataclass
class ControlPoint:
    name: str
    xyz: np.ndarray  # (3,) metres in GcpFile.frame: easting, northing, height
    observations: list[Observation] = field(default_factory=list)


@dataclass
class GcpFile:
    """``crs``: the file's coordinate system; ``frame``: the metric one the points are in (the same
    when the file's is projected in metres, else the UTM zone of the points); ``points``: the
    points with at least two usable observations; ``problems``: one line per problem found."""

    crs: pyproj.CRS
    frame: pyproj.CRS
    points: dict[str, ControlPoint]
    problems: list[str]
    unusable: dict[str, str]  # point name -> why it cannot be used

    def summary(self) -> dict[str, object]:
        return {
            "crs": self.crs.to_string(),
            "frame": self.frame.to_string(),
            "points": sorted(self.points),
            "unusable": dict(sorted(self.unusable.items())),
            "problems": list(self.problems),
        }


def parse_crs(text: str) -> pyproj.CRS:
    spec = text.strip()
    if spec.upper() == "WGS84":
        spec = "EPSG:4326"
    try:
        crs = pyproj.CRS.from_user_input(spec)
    except CRSError as e:
        raise GcpError(f"line 1: unknown coordinate system {text.strip()!r} ({e})") from None
    if not (crs.is_projected or crs.is_geographic):
        # a geocentric (Earth-centred XYZ) or engineering system: its x and y are neither
        # longitude/latitude nor map metres, and reading them as either places points anywhere
        raise GcpError(
            f"line 1: {crs.name} is not a map projection or longitude/latitude: give the points in a"
            " projected system (e.g. their UTM zone's EPSG code) or in WGS84"
        )
    return crs


def metric_frame(crs: pyproj.CRS, lon_lat: tuple[float, float] | None) -> pyproj.CRS:
    """The file's own system where it is projected (metres or feet), else the UTM zone holding the
    points: a similarity is fitted in a Cartesian frame, and degrees are not one."""
    if crs.is_projected:
        return crs
    if lon_lat is None:
        raise GcpError(f"line 1: {crs.name} is not projected and the file has no point to place a UTM zone")
    lon, lat = lon_lat
    zone = math.floor((lon + 180.0) / 6.0) % 60 + 1
    return pyproj.CRS.from_epsg((32600 if lat >= 0 else 32700) + zone)


def read_gcp_file(text: str, image_sizes: Mapping[str, tuple[int, int]]) -> GcpFile:
    """Parse and check ``text`` against the project's images (name -> (width, height))."""
    lines = text.splitlines()
    header = next((i for i, s in enumerate(lines) if s.strip() and not s.lstrip().startswith("#")), None)
    if header is None:
        raise GcpError("the GCP file is empty: its first line must name the coordinate system")
    crs = parse_crs(lines[header])
    problems: list[str] = []
    raw: list[tuple[str, np.ndarray, Observation]] = []
    for i, line in enumerate(lines[header + 1 :], start=header + 2):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        fields = s.split()
        try:
            x, y, z, px, py = (float(v) for v in fields[:5])
            image = fields[5]
        except (ValueError, IndexError):
            problems.append(f"line {i}: expected 'x y z px py image [name]', got {s[:80]!r}")
            continue
        if not all(map(math.isfinite, (x, y, z, px, py))):
            problems.append(f"line {i}: a coordinate is not a finite number")
            continue
        name = fields[6] if len(fields) > 6 else f"{x:.3f},{y:.3f},{z:.3f}"
        if not crs.is_projected and not (-180.0 <= x <= 180.0 and -90.0 <= y <= 90.0):
            problems.append(f"line {i}: {name}: ({x:g}, {y:g}) is not a longitude and latitude")
            continue
        size = image_sizes.get(image)
        if size is None:
            problems.append(f"line {i}: {name}: image {image!r} is not in the project")
            continue
        w, h = size
        if not (-0.5 <= px <= w - 0.5 and -0.5 <= py <= h - 0.5):
            problems.append(f"line {i}: {name}: pixel ({px:g}, {py:g}) is outside {image} ({w}x{h})")
            continue
        raw.append((name, np.array([x, y, z], np.float64), Observation(image, (px, py), i)))

    lon_lat = None
    if raw and not crs.is_projected:
        lon_lat = (float(raw[0][1][0]), float(raw[0][1][1]))
    frame = metric_frame(crs, lon_lat)
    to_frame = pyproj.Transformer.from_crs(crs, frame, always_xy=True)
    scale = float(frame.axis_info[0].unit_conversion_factor) if frame.axis_info else 1.0

    points: dict[str, ControlPoint] = {}
    for name, xyz, obs in raw:
        if crs.is_projected:
            metric = xyz * scale
        else:
            e, n = to_frame.transform(xyz[0], xyz[1])
            metric = np.array([e, n, xyz[2]], np.float64)
        p = points.get(name)
        if p is None:
            points[name] = ControlPoint(name, metric, [obs])
            continue
        if np.linalg.norm(p.xyz - metric) > 1e-6:
            problems.append(
                f"line {obs.line}: {name}: its coordinates differ from its first line's; kept the first"
            )
            continue
        if any(o.image == obs.image for o in p.observations):
            problems.append(f"line {obs.line}: {name}: a second observation in {obs.image}; kept the first")
            continue
        p.observations.append(obs)

    unusable: dict[str, str] = {}
    for name, p in list(points.items()):
        if len(p.observations) < 2:
            why = f"seen in one photo only (line {p.observations[0].line}): a point needs two to be placed"
            unusable[name] = why
            problems.append(f"{name}: {why}")
            del points[name]
    if len(points) < MIN_POINTS:
        found = f"{len(points)} usable point{'s' if len(points) != 1 else ''}"
        detail = "; ".join(problems[:5])
        raise GcpError(
            f"the GCP file leaves {found}, and georeferencing needs {MIN_POINTS}"
            + (f" ({detail})" if detail else "")
        )
    return GcpFile(crs, frame, points, problems, unusable)
