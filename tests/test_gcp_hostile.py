"""GCP files as an attacker or an unlucky survey writes them: coordinate systems that name files,
FIFOs, devices, grids and URLs, PROJ's own errors, coordinates past any place on the Earth, and
control sets that cannot fix a similarity. Every one is refused naming its line, no text of the
file reaches the file system (watched with inotify, which sees PROJ's C-level opens, and with an
audit hook on Python's), and a model the points cannot georeference is left exactly as mapped."""

from __future__ import annotations

import json
import os
import threading
from pathlib import Path

import numpy as np
import pycolmap
import pyproj
import pytest

from geomatch.geo.gcp import apply_to_model, georeference
from geomatch.geo.gcpfile import GcpError, GcpFile, parse_crs, read_gcp_file
from geomatch.geo.gcpreport import GeoreferenceError

from .fswatch import watched

pytestmark = pytest.mark.unit

SIZES = {"a.jpg": (1600, 1067), "b.jpg": (1600, 1067), "c.jpg": (1600, 1067)}


def _points(crs: str, xyz: list[tuple[float, float, float]]) -> str:
    """A file of ``xyz`` each seen in a.jpg and b.jpg."""
    lines = [crs]
    for k, (x, y, z) in enumerate(xyz):
        lines += [f"{x!r} {y!r} {z!r} {10 + k} 20 a.jpg p{k}", f"{x!r} {y!r} {z!r} {30 + k} 40 b.jpg p{k}"]
    return "\n".join(lines) + "\n"


SPREAD = [(465000.0, 5247000.0, 400.0), (465030.0, 5247010.0, 402.0), (465010.0, 5247040.0, 405.0)]


def make_targets(d: Path) -> dict[str, Path]:
    """Files a hostile coordinate system might name, in ``d``: a secret holding ``<x>`` (an +init
    file PROJ would parse), a FIFO (an open of it blocks), a grid."""
    d.mkdir(parents=True)
    (d / "secret").write_text("<x> +proj=longlat +datum=WGS84 <>\n")
    os.mkfifo(d / "fifo")
    (d / "grid.gsb").write_bytes(b"\0" * 64)
    return {p.name: p for p in d.iterdir()}


@pytest.fixture
def targets(tmp_path: Path) -> dict[str, Path]:
    return make_targets(tmp_path / "targets")


def hostile(t: dict[str, Path]) -> list[str]:
    secret, fifo, grid = t["secret"], t["fifo"], t["grid.gsb"]
    wkt = pyproj.CRS("EPSG:32632").to_wkt("WKT1_GDAL")
    return [
        f"+init={secret}:x",
        f"+init=FILE:x +init={secret}:x",
        f"+init={fifo}:x",
        f"init={fifo}:x",
        "+init=/etc/shadow:x",
        "+init=/dev/kmsg:x",
        f"+proj=longlat +datum=WGS84 +nadgrids={grid}",
        f"+proj=longlat +datum=WGS84 +geoidgrids={grid}",
        "+proj=longlat +datum=WGS84 +nadgrids=@grid.gsb",
        "+proj=utm +zone=32 +datum=WGS84 +nadgrids=http://127.0.0.1:9/x.gsb",
        f"+proj=hgridshift +grids={grid}",
        f"+proj=tinshift +file={secret}",
        f"+proj=utm +zone=32 +datum=WGS84 +xy_grids={grid}",
        f"+proj=utm +zone=32 +towgs84={secret}",
        wkt[:-1] + f',EXTENSION["PROJ4","+init={secret}:x"]]',
        wkt[:-1] + f',EXTENSION["PROJ4_GRIDS","{grid}"]]',
        'BOUNDCRS[SOURCECRS[GEOGCRS["x",DATUM["WGS 84",ELLIPSOID["WGS 84",6378137,298.257223563]],'
        'CS[ellipsoidal,2],AXIS["lat",north],AXIS["lon",east],ANGLEUNIT["degree",0.0174532925199433]]],'
        'TARGETCRS[GEOGCRS["WGS 84",DATUM["WGS 84",ELLIPSOID["WGS 84",6378137,298.257223563]],'
        'CS[ellipsoidal,2],AXIS["lat",north],AXIS["lon",east],ANGLEUNIT["degree",0.0174532925199433]]],'
        f'ABRIDGEDTRANSFORMATION["x",METHOD["NTv2"],PARAMETERFILE["Latitude and longitude difference '
        f'file","{grid}"]]]',
        f'{{"type": "GeographicCRS", "name": "{secret}"}}',
        f"urn:ogc:def:crs:EPSG::4326 {secret}",
        f"{secret}",
        "IAU_2015:49900",
        "+proj=longlat +a=1 +b=1",
        "EPSG:4978",  # geocentric
        "x" * 9000,
        "EPSG:4326\x1b[2J",
    ]


def test_hostile_coordinate_systems_are_refused_naming_line_1_and_open_nothing(
    targets: dict[str, Path],
) -> None:
    body = "".join(
        f"{x} {y} {z} 10 20 a.jpg p{k}\n{x} {y} {z} 30 40 b.jpg p{k}\n" for k, (x, y, z) in enumerate(SPREAD)
    )
    folder = targets["secret"].parent
    errors: list[str] = []

    def read_all() -> None:
        for crs in hostile(targets):
            try:
                read_gcp_file(crs + "\n" + body, SIZES)
            except GcpError as e:
                errors.append(str(e))
            else:
                errors.append(f"ACCEPTED {crs[:80]!r}")

    with watched(folder) as seen:
        t = threading.Thread(target=read_all, daemon=True)
        t.start()
        t.join(60)  # an open of the FIFO would block here for good
        assert not t.is_alive(), "reading a hostile coordinate system blocked (a FIFO opened?)"
    assert seen == [], seen
    assert len(errors) == len(hostile(targets)), errors
    assert all(e.startswith("line 1: ") for e in errors), errors
    assert all(len(e) < 600 for e in errors), max(errors, key=len)

    # the watch sees what it is there to see: a read of the secret, in C or in Python
    with watched(folder) as seen:
        targets["secret"].read_text()
    assert any("secret" in s for s in seen), seen


@pytest.mark.parametrize(
    "crs",
    [
        "WGS84",
        "EPSG:4326",
        "epsg:32632",
        "EPSG:4326+5773",
        "ESRI:102100",
        "+proj=utm +zone=32 +datum=WGS84 +units=m +no_defs",
        "proj=utm zone=32 ellps=WGS84 towgs84=0,0,0",
        pyproj.CRS("EPSG:32632").to_wkt(),
        pyproj.CRS("EPSG:32632").to_wkt("WKT1_GDAL"),
    ],
)
def test_earth_frames_in_every_accepted_form_are_read(crs: str) -> None:
    c = parse_crs(crs)
    assert c.is_projected or c.is_geographic


def test_proj_network_is_off() -> None:
    import pyproj.network

    assert not pyproj.network.is_network_enabled()


def test_coordinates_past_any_place_on_the_earth_are_problems_not_numbers() -> None:
    huge = [(465000.0 + 1e300, 5247000.0, 400.0), (465030.0, 5247010.0, 1e308), *SPREAD]
    g = read_gcp_file(_points("EPSG:32632", huge), SIZES)
    assert sorted(g.points) == ["p2", "p3", "p4"]
    assert any("p0: (1e+300, 5.247e+06) m is past" in p for p in g.problems), g.problems
    assert any("p1: height 1e+308 m is outside" in p for p in g.problems), g.problems
    # kilometres scaled to metres: 1e306 km is past the range of numbers
    g = read_gcp_file(
        _points(
            "+proj=utm +zone=32 +datum=WGS84 +units=km",
            [(1e306, 5247.0, 0.4)] + [(x / 1000, y / 1000, z / 1000) for x, y, z in SPREAD],
        ),
        SIZES,
    )
    assert any("p0: its coordinates are not finite" in p for p in g.problems), g.problems
    with pytest.raises(GcpError, match=r"leaves 0 usable points.*height 1e\+308 m is outside"):
        read_gcp_file(_points("EPSG:32632", [(465000.0 + 10 * k, 5247000.0, 1e308) for k in range(8)]), SIZES)


def test_points_at_one_coordinate_or_on_one_line_are_refused() -> None:
    with pytest.raises(GcpError, match=r"8 usable points cannot georeference a model: .*one point"):
        read_gcp_file(_points("EPSG:32632", [SPREAD[0]] * 8), SIZES)
    line = [(465000.0 + 10 * k, 5247000.0 + 5 * k, 400.0 + k) for k in range(5)]
    with pytest.raises(GcpError, match="on one line"):
        read_gcp_file(_points("EPSG:32632", line), SIZES)


# -- a control set the model cannot take leaves the model as mapped --------------------------------
def _model() -> pycolmap.Reconstruction:
    opts = pycolmap.SyntheticDatasetOptions()
    opts.num_rigs, opts.num_frames_per_rig, opts.num_points3D = 1, 6, 60
    return pycolmap.synthesize_dataset(opts)


def _gcps(rec: pycolmap.Reconstruction, n: int) -> GcpFile:
    lines = ["EPSG:32632"]
    chosen = [p for _, p in sorted(rec.points3D.items()) if p.track.length() >= 3][:n]
    for k, p in enumerate(chosen):
        world = 3.0 * np.asarray(p.xyz) + np.array([465000.0, 5247000.0, 400.0])
        for el in p.track.elements:
            im = rec.images[el.image_id]
            x, y = im.points2D[el.point2D_idx].xy - 0.5
            lines.append(f"{world[0]} {world[1]} {world[2]} {x} {y} {im.name} gcp{k:02d}")
    sizes = {
        im.name: (rec.cameras[im.camera_id].width, rec.cameras[im.camera_id].height)
        for im in rec.images.values()
    }
    return read_gcp_file("\n".join(lines), sizes)


@pytest.mark.parametrize(
    ("damage", "why"),
    [
        ("coincide", "one point"),
        ("infinite", "not finite"),
        ("swapped", "do not fit the model"),
    ],
)
def test_a_control_set_that_cannot_fix_the_model_leaves_it_as_mapped(
    tmp_path: Path, damage: str, why: str
) -> None:
    rec = _model()
    g = _gcps(rec, 7)
    names = sorted(g.points)
    if damage == "coincide":  # eight names at one coordinate (a file the reader would refuse)
        for p in g.points.values():
            p.xyz = g.points[names[0]].xyz.copy()
    elif damage == "infinite":  # heights past the range of numbers, however they got in
        for p in g.points.values():
            p.xyz = np.array([p.xyz[0], p.xyz[1], np.inf])
    else:  # the surveyed coordinates given to other names: a fit of nothing
        xyz = [g.points[n].xyz for n in names]
        for n, x in zip(names, xyz[3:] + xyz[:3], strict=True):
            g.points[n].xyz = x
    with pytest.raises(GeoreferenceError, match=why) as e:
        georeference(rec, g)
    assert {p.role for p in e.value.points} == {"unused"}

    model = tmp_path / "sparse" / "0"
    model.mkdir(parents=True)
    rec.write_binary(str(model))
    before = {f.name: f.read_bytes() for f in model.iterdir()}
    out = apply_to_model(model, g, ply=tmp_path / "points.ply")
    assert why in out["error"], out
    assert {f.name: f.read_bytes() for f in model.iterdir()} == before  # not a byte written
    assert not (tmp_path / "points.ply").exists()
    json.dumps(out, allow_nan=False)  # no NaN for a store to refuse
    # the one shape of ``points``, whatever the outcome: a dict per point, with its role and why
    assert [p["name"] for p in out["points"]] == names and all(p["role"] == "unused" for p in out["points"])
    assert all(isinstance(p.get("reason"), str) for p in out["points"]), out["points"]


# -- generated first lines: whatever line 1 holds, a refusal naming it or a usable file -------------
FRAGMENTS = [
    "+proj=utm",
    "+zone=32",
    "+datum=WGS84",
    "+units=km",
    "+init=",
    "+nadgrids=",
    "+geoidgrids=",
    "+grids=",
    "+file=",
    "+towgs84=0,0,0",
    "proj=longlat",
    "+a=1",
    "+b=1",
    "+proj=pipeline",
    "+step",
    "+inv",
    "EPSG:",
    "ESRI:",
    "IAU_2015:",
    "IGNF:",
    "urn:ogc:def:crs:EPSG::",
    "WGS84",
    "PROJCS[",
    "GEOGCRS[",
    "BOUNDCRS[",
    "PARAMETERFILE[",
    "EXTENSION[",
    '"',
    "]",
    ",",
    "/etc/shadow",
    "/dev/kmsg",
    "/dev/zero",
    "http://127.0.0.1:9/g.tif",
    "file:///etc/passwd",
    "@null",
    "~/.proj",
    "..",
    "\\\\server\\share",
    "%s%n",
    "\u202e",
    "\x7f",
    "9" * 30,
    "-1e308",
    "nan",
    ":",
    "=",
    " ",
    "+",
]


def generated_first_lines(seed: int, n: int) -> list[str]:
    """``n`` first lines made of FRAGMENTS and numbers, reproducible by ``seed``."""
    import random

    rng = random.Random(seed)
    lines = []
    for _ in range(n):
        parts = [rng.choice(FRAGMENTS) for _ in range(rng.randint(1, 6))]
        parts += [str(rng.randint(0, 99999))] * rng.randint(0, 1)
        lines.append(("" if rng.random() < 0.5 else " ").join(parts).replace("\n", " "))
    return lines


def test_generated_first_lines_are_read_or_refused_and_open_nothing(targets: dict[str, Path]) -> None:
    body = "".join(
        f"{x} {y} {z} 10 20 a.jpg p{k}\n{x} {y} {z} 30 40 b.jpg p{k}\n" for k, (x, y, z) in enumerate(SPREAD)
    )
    lines = generated_first_lines(1, 200)
    outcomes: list[str] = []

    def read_all() -> None:
        for crs in lines:
            try:
                read_gcp_file(crs + "\n" + body, SIZES)
                outcomes.append("read")
            except GcpError as e:
                outcomes.append(
                    "refused" if str(e).startswith("line 1: ") or "usable point" in str(e) else str(e)
                )

    with watched(targets["secret"].parent) as seen:
        t = threading.Thread(target=read_all, daemon=True)
        t.start()
        t.join(120)
        assert not t.is_alive(), "a generated first line blocked the reader"
    assert seen == [], seen
    assert set(outcomes) <= {"read", "refused"}, [o for o in outcomes if o not in ("read", "refused")]
    assert len(outcomes) == len(lines)


def test_unknown_check_points_are_named_up_to_ten_and_messages_are_capped() -> None:
    from geomatch.geo.gcp import choose_checkpoints
    from geomatch_core.errors import MAX_MESSAGE, InvalidRequest

    names = [f"{i:04d}" + "x" * 996 for i in range(3500)]
    with pytest.raises(GcpError) as e:
        choose_checkpoints(["gcp01", "gcp02", "gcp03", "gcp04"], names)
    assert len(str(e.value)) < 1000 and str(e.value).endswith("and 3490 more"), str(e.value)[-80:]
    long = InvalidRequest("y" * 10**6)
    assert len(long.message) == MAX_MESSAGE and long.message.endswith("more characters)"), long.message[-60:]
