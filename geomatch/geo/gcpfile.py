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
system pyproj knows, fewer than 3 usable points, points that coincide or lie on one line) is refused,
with the reason.

The coordinate system is text a client sends, and PROJ reads files and URLs named in it (``+init=``,
``+nadgrids=``, a WKT's ``PARAMETERFILE``): a server took ``+init=/etc/shadow:x`` and opened the
file, and ``+init=`` on a FIFO or /dev/kmsg blocked a thread holding the GIL for good. So the line
is held to an allow-list before PROJ sees it (``WGS84``, an EPSG or ESRI code, a PROJ string of
plain parameters, WKT without files or extensions), the parsed object is checked again, PROJ's
network access is off, and every PROJ error is a refusal naming line 1.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import pyproj
import pyproj.network
from pyproj.exceptions import CRSError, ProjError

MIN_POINTS = 3  # a similarity (7 unknowns) needs three points

# grids and definitions come from the server's own PROJ data, never from the network (a coordinate
# system is request text: a URL in it would make the server fetch it)
# (pyproj.network re-exports it from its compiled module without __all__)
pyproj.network.set_network_enabled(False)  # type: ignore[attr-defined]

MAX_CRS_CHARS = 8000  # a projected CRS's WKT2 is 1-3 kB
_AUTHORITY = re.compile(r"(?:EPSG|ESRI):\d{1,6}(?:\+\d{1,6})?", re.IGNORECASE)  # EPSG:4326+5773: compound
# one parameter of a PROJ string: +key or +key=value, the value numbers, names and commas only
# (no "/", ":", "@" or "~": nothing that names a file, a URL or PROJ's grid prefixes)
_PROJ_PARAM = re.compile(r"\+?([a-z_][a-z0-9_]*)(?:=([A-Za-z0-9_.,+-]*))?")
# parameters whose value PROJ opens as a file (init files, grids, deformation models, catalogs)
_FILE_PARAMS = frozenset({"init", "nadgrids", "geoidgrids", "grids", "file", "model", "catalog"})
_WKT_START = re.compile(
    r"(PROJCS|GEOGCS|GEOCCS|COMPD_CS|PROJCRS|PROJECTEDCRS|GEOGCRS|GEOGRAPHICCRS|GEODCRS|GEODETICCRS"
    r"|COMPOUNDCRS|BOUNDCRS)\s*[\[(]",
    re.IGNORECASE,
)
# WKT that names a file (a grid of a bound CRS's transformation) or carries a PROJ string
_WKT_FILES = re.compile(r"PARAMETERFILE|PARAMETER_FILE|EXTENSION\s*[\[(]|\+init|grids\s*=", re.IGNORECASE)
# the Earth's semi-major axis is 6378.137 km; a sphere of radius 1 m or another planet's is not a
# survey's frame (PROJ then fails inside a transformation, or places points anywhere)
EARTH_SEMI_MAJOR_M = (6.3e6, 6.4e6)
# coordinates past these in the metric frame are no place on the Earth, and a similarity over them
# loses every digit of the survey (x + 1e300 is 1e300): the same heights the photos' metadata takes
MAX_EASTING_NORTHING_M = 1e8
HEIGHT_RANGE_M = (-11_000.0, 100_000.0)
# a control set must span something: points within this of their centroid are one point, and a set
# whose second extent is under this share of its first lies on a line (the rotation about it is free)
MIN_SPREAD_M = 0.1
MIN_SPREAD_RATIO = 0.01


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


CRS_FORMS = (
    "give WGS84, an EPSG or ESRI code (EPSG:32632), a PROJ string of parameters "
    "(+proj=utm +zone=32 +datum=WGS84) or WKT"
)


def _allowed_crs_text(spec: str) -> str | None:
    """Why ``spec`` may not reach PROJ, None when it may: the allow-list, before any parsing."""
    if len(spec) > MAX_CRS_CHARS:
        return f"a coordinate system of {len(spec)} characters (at most {MAX_CRS_CHARS})"
    if not spec.isprintable():
        return "a coordinate system with control characters"
    if _AUTHORITY.fullmatch(spec):
        return None
    if _WKT_START.match(spec):
        if _WKT_FILES.search(spec):
            return "a WKT coordinate system may not name files or carry extensions (PARAMETERFILE, EXTENSION)"
        return None
    if spec.startswith("+") or spec.lower().startswith("proj="):
        for token in spec.split():
            key = token.lstrip("+").partition("=")[0].lower()
            if key in _FILE_PARAMS or key.endswith(("grids", "_file")):
                return f"the PROJ parameter +{key[:40]} names a file, which a coordinate system here may not"
            if _PROJ_PARAM.fullmatch(token) is None:
                return f"the PROJ parameter {token[:40]!r} is not a plain +key=value (no paths or URLs)"
        return None
    return "a coordinate system in none of the accepted forms"


def _earth_frame(crs: pyproj.CRS) -> str | None:
    """Why the parsed ``crs`` is no frame for a survey on the Earth, None when it is one: its
    definition names no file (checked again on what PROJ made of the text) and its ellipsoid is
    the Earth's."""
    try:
        wkt = crs.to_wkt("WKT2_2019") or ""
    except ProjError as e:
        return f"PROJ cannot write it out ({e})"
    if _WKT_FILES.search(wkt):
        return "it names a grid or definition file, which a coordinate system here may not"
    ellipsoid = crs.ellipsoid
    if ellipsoid is None:
        return "it has no ellipsoid"
    a = float(ellipsoid.semi_major_metre)
    if not EARTH_SEMI_MAJOR_M[0] <= a <= EARTH_SEMI_MAJOR_M[1]:
        return f"its ellipsoid ({ellipsoid.name}, semi-major axis {a:g} m) is not the Earth's"
    return None


def parse_crs(text: str) -> pyproj.CRS:
    spec = text.strip()
    if spec.upper() == "WGS84":
        spec = "EPSG:4326"
    shown = spec if len(spec) <= 80 else spec[:77] + "..."
    why = _allowed_crs_text(spec)
    if why is not None:
        raise GcpError(f"line 1: unknown coordinate system {shown!r}: {why}; {CRS_FORMS}")
    try:
        crs = pyproj.CRS.from_user_input(spec)
    except (CRSError, ProjError) as e:
        raise GcpError(f"line 1: unknown coordinate system {shown!r} ({_short(e)})") from None
    why = _earth_frame(crs)
    if why is not None:
        raise GcpError(f"line 1: unusable coordinate system {shown!r}: {why}")
    if not (crs.is_projected or crs.is_geographic):
        # a geocentric (Earth-centred XYZ) or engineering system: its x and y are neither
        # longitude/latitude nor map metres, and reading them as either places points anywhere
        raise GcpError(
            f"line 1: {crs.name} is not a map projection or longitude/latitude: give the points in a"
            " projected system (e.g. their UTM zone's EPSG code) or in WGS84"
        )
    return crs


def _short(e: Exception, limit: int = 200) -> str:
    text = " ".join(str(e).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def degenerate(xyz: np.ndarray, min_spread: float = MIN_SPREAD_M) -> str | None:
    """Why the points ``xyz`` (N, 3) cannot fix a similarity, None when they can: they must spread
    over more than ``min_spread`` (metres in a survey's frame) and not lie on one line (their
    second principal extent at least MIN_SPREAD_RATIO of their first)."""
    pts = np.asarray(xyz, np.float64)
    if not np.isfinite(pts).all():
        return "a point's coordinates are not finite"
    if len(pts) < MIN_POINTS:
        return f"{len(pts)} points: a similarity needs {MIN_POINTS}"
    centred = pts - pts.mean(axis=0)
    extents = np.linalg.svd(centred, compute_uv=False) / np.sqrt(len(pts))
    if not extents[0] > min_spread:
        return f"the points lie within {extents[0]:.3g} of one another: they are one point"
    if not extents[1] > MIN_SPREAD_RATIO * extents[0]:
        return "the points lie on one line: the turn about it is not fixed"
    return None


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
    try:
        to_frame = pyproj.Transformer.from_crs(crs, frame, always_xy=True)
    except (CRSError, ProjError) as e:  # a datum PROJ cannot take to the points' UTM zone
        raise GcpError(f"line 1: PROJ cannot take {crs.name} to {frame.name} ({_short(e)})") from None
    scale = float(frame.axis_info[0].unit_conversion_factor) if frame.axis_info else 1.0

    points: dict[str, ControlPoint] = {}
    for name, xyz, obs in raw:
        with np.errstate(over="ignore", invalid="ignore"):
            if crs.is_projected:
                metric = xyz * scale
            else:
                try:
                    east, north = to_frame.transform(xyz[0], xyz[1], errcheck=True)
                except ProjError as err:
                    problems.append(f"line {obs.line}: {name}: PROJ cannot place it ({_short(err, 80)})")
                    continue
                metric = np.array([east, north, xyz[2]], np.float64)
        why = _off_the_earth(metric)
        if why is not None:
            problems.append(f"line {obs.line}: {name}: {why}")
            continue
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
    why = degenerate(np.stack([p.xyz for p in points.values()]))
    if why is not None:
        raise GcpError(f"the GCP file's {len(points)} usable points cannot georeference a model: {why}")
    return GcpFile(crs, frame, points, problems, unusable)


def _off_the_earth(metric: np.ndarray) -> str | None:
    """Why a point's metric coordinates are no place on the Earth, None when they are one."""
    if not np.isfinite(metric).all():
        return "its coordinates are not finite in the metric frame (past the range of numbers)"
    if max(abs(float(metric[0])), abs(float(metric[1]))) > MAX_EASTING_NORTHING_M:
        where = f"({metric[0]:.6g}, {metric[1]:.6g}) m"
        return f"{where} is past {MAX_EASTING_NORTHING_M:g} m: no place on the Earth"
    if not HEIGHT_RANGE_M[0] <= float(metric[2]) <= HEIGHT_RANGE_M[1]:
        return f"height {metric[2]:.6g} m is outside [{HEIGHT_RANGE_M[0]:g}, {HEIGHT_RANGE_M[1]:g}] m"
    return None
