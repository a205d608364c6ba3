"""The drone tools' outputs (geomatch/export/odm.py and its parts): the LAZ in the model's projected
CRS, shots.geojson, cameras.json, images.json, stats.json, the report PDF and the GCP GeoJSON, on
COLMAP's synthetic model given a frame (unit), and on the shared GPS run of the small scene
(pipeline): points and photos where the model and the photos' fixes put them."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import laspy
import numpy as np
import pycolmap
import pyproj
import pytest
from scipy.spatial.transform import Rotation

from geomatch.cli import main
from geomatch.export import export, export_zip, open_run
from geomatch.export.georef import model_frame, utm_zone
from geomatch.export.laz import LAZ_NAME
from geomatch.export.opensfm import opensfm_camera
from geomatch.export.reportpdf import markdown_pdf, plain_text, table_cells
from geomatch.geo.geodesy import EnuFrame
from geomatch.metadata import read_metadata
from geomatch.report import escape_markdown

from .colmap_synthetic import synthetic_database

ORIGIN = {"lat": 50.8225, "lon": -0.1372, "alt": 60.0}  # Brighton's beach: UTM zone 30 north


def _run(tmp_path: Path, summary: dict) -> Path:
    """A run folder around COLMAP's synthetic model (4 images, 60 points) with ``summary``."""
    rec = synthetic_database(tmp_path / "database.db", 4, 60)
    model = tmp_path / "run" / "sparse" / "0"
    model.mkdir(parents=True)
    rec.write_binary(str(model))
    base = {"images": 4, "registered": 4, "points3D": rec.num_points3D(), "models": 1}
    (tmp_path / "run" / "summary.json").write_text(json.dumps({**base, **summary}))
    return tmp_path / "run"


def _enu_run(tmp_path: Path) -> Path:
    return _run(tmp_path, {"georeferenced": True, "frame": "ENU", "origin": ORIGIN})


@pytest.mark.unit
def test_laz_is_in_the_utm_zone_of_the_site_with_colours(tmp_path: Path) -> None:
    run = _enu_run(tmp_path)
    files = export(open_run(run), "laz", tmp_path / "laz")
    las = laspy.read(files[0])
    crs = las.header.parse_crs()
    assert crs is not None and crs.to_epsg() == 32630 == utm_zone(ORIGIN["lat"], ORIGIN["lon"]).to_epsg()
    rec = pycolmap.Reconstruction(str(run / "sparse" / "0"))
    ids = sorted(rec.points3D)
    xyz = np.array([rec.points3D[i].xyz for i in ids])
    assert len(las.points) == len(ids)
    # each point where the ENU frame puts it, projected by PROJ independently of the writer
    lat, lon, h = EnuFrame(**ORIGIN).to_geodetic(xyz)
    e, n = pyproj.Transformer.from_crs(4326, 32630, always_xy=True).transform(lon, lat)
    got = np.column_stack([las.x, las.y, las.z])
    np.testing.assert_allclose(got, np.column_stack([e, n, h]), atol=0.002)
    assert 500_000 < float(np.mean(las.x)) < 800_000  # absolute eastings, not the model's metres
    rgb = np.array([rec.points3D[i].color for i in ids]).astype(np.uint16) * 257
    np.testing.assert_array_equal(np.column_stack([las.red, las.green, las.blue]), rgb)


@pytest.mark.unit
def test_odm_layout_of_a_gps_model(tmp_path: Path) -> None:
    run = _enu_run(tmp_path)
    dest = tmp_path / "odm"
    names = {p.relative_to(dest).as_posix() for p in export(open_run(run), "odm", dest)}
    assert names == {
        "cameras.json",
        "images.json",
        "odm_report/stats.json",
        "odm_report/report.md",
        "odm_report/report.pdf",
        f"odm_georeferencing/{LAZ_NAME}",
        "odm_report/shots.geojson",
    }
    assert (dest / "odm_report/report.pdf").read_bytes().startswith(b"%PDF-")
    stats = json.loads((dest / "odm_report/stats.json").read_text())
    assert stats["reconstruction_statistics"]["reconstructed_shots_count"] == 4
    rec = pycolmap.Reconstruction(str(run / "sparse" / "0"))
    frame = model_frame(json.loads((run / "summary.json").read_text()))
    assert frame is not None
    shots = json.loads((dest / "odm_report/shots.geojson").read_text())["features"]
    assert len(shots) == 4
    cams = json.loads((dest / "cameras.json").read_text())
    point = np.array(rec.points3D[sorted(rec.points3D)[0]].xyz)
    p_proj = frame.to_projected(point[None])[0]
    for f in shots:
        props = f["properties"]
        im = next(i for i in rec.images.values() if i.name == props["filename"])
        c = np.array(im.projection_center())
        lon, lat, h = f["geometry"]["coordinates"]
        np.testing.assert_allclose(
            [lat, lon, h], np.ravel(EnuFrame(**ORIGIN).to_geodetic(c[None])), atol=1e-9
        )
        np.testing.assert_allclose(props["translation"], frame.to_projected(c[None])[0], atol=1e-6)
        assert props["camera"] in cams and props["width"] == cams[props["camera"]]["width"]
        # OpenSfM's pose in the projected frame sees a point where COLMAP's sees it in the model
        # (the grid's turn from local east-north is a fraction of a degree here; the scale 0.9996+)
        r = Rotation.from_rotvec(props["rotation"]).as_matrix()
        in_cam = r @ (p_proj - np.array(props["translation"]))
        want = np.asarray(im.cam_from_world().matrix()) @ np.append(point, 1.0)
        np.testing.assert_allclose(in_cam / np.linalg.norm(in_cam), want / np.linalg.norm(want), atol=1e-4)


@pytest.mark.unit
def test_a_model_without_georeferencing_has_no_laz(tmp_path: Path) -> None:
    run = _run(tmp_path, {"georeferenced": False})
    dest = tmp_path / "odm"
    names = {p.name for p in export(open_run(run), "odm", dest)}
    assert LAZ_NAME not in names and "shots.geojson" not in names and "report.pdf" in names
    assert main(["export", str(run), "--format", "laz", "--to", str(tmp_path / "laz")]) == 2


@pytest.mark.unit
def test_gcp_frame_model_is_offset_into_the_files_crs(tmp_path: Path) -> None:
    origin = [691_200.0, 5_633_100.0, 12.0]
    gcp_summary = {
        "frame": "EPSG:32630",
        "origin": origin,
        "points": [
            {"name": "gcp0", "role": "control", "observations": 2, "observations_registered": 2, "dx_m": 0.01}
        ],
    }
    run = _run(tmp_path, {"georeferenced": True, "frame": "GCP", "gcp": gcp_summary})
    rec = pycolmap.Reconstruction(str(run / "sparse" / "0"))
    im = rec.images[sorted(rec.images)[0]]
    w, h = rec.cameras[im.camera_id].width, rec.cameras[im.camera_id].height
    lines = ["EPSG:32630"] + [
        f"{691_210 + 5 * k} {5_633_120 + 3 * k * k} {14.5 + k} {w / 2 + k} {h / 2} {i.name} gcp{k}"
        for k in range(3)
        for i in list(rec.images.values())[:2]
    ]
    (run / "gcp_list.txt").write_text("\n".join(lines) + "\n")
    dest = tmp_path / "odm"
    export(open_run(run), "odm", dest)
    las = laspy.read(dest / "odm_georeferencing" / LAZ_NAME)
    assert las.header.parse_crs().to_epsg() == 32630
    xyz = np.array([rec.points3D[i].xyz for i in sorted(rec.points3D)])
    np.testing.assert_allclose(np.column_stack([las.x, las.y, las.z]), xyz + origin, atol=0.002)
    gj = json.loads((dest / "odm_georeferencing" / "ground_control_points.geojson").read_text())
    assert [f["properties"]["id"] for f in gj["features"]] == ["gcp0", "gcp1", "gcp2"]
    lon, lat = pyproj.Transformer.from_crs(32630, 4326, always_xy=True).transform(691_210, 5_633_120)
    np.testing.assert_allclose(gj["features"][0]["geometry"]["coordinates"], [lon, lat, 14.5], atol=1e-9)


@pytest.mark.unit
def test_opensfm_camera_normalises_by_the_larger_side() -> None:
    cam = pycolmap.Camera.create_from_model_name(1, "SIMPLE_RADIAL", 800.0, 1000, 500)
    cam.params = [800.0, 510.0, 240.0, -0.05]
    o = opensfm_camera(cam)
    assert o["focal_x"] == o["focal_y"] == pytest.approx(0.8)
    assert o["c_x"] == pytest.approx(0.01) and o["c_y"] == pytest.approx(-0.01) and o["k1"] == -0.05


@pytest.mark.unit
def test_report_pdf_shows_escaped_names_as_they_are() -> None:
    """The Markdown escapes client-chosen names (report.escape_markdown); the PDF shows them plain."""
    assert plain_text(r"- not registered: DJI\_0027\*.JPG") == "- not registered: DJI_0027*.JPG"
    assert table_cells(r"| a\|b.jpg | control | 3 (3) |") == ["a|b.jpg", "control", "3 (3)"]
    for name in ("DJI_0027.JPG", "a|b*c[1](x)<img src=x>.jpg", "`x`#!\\y~"):
        assert plain_text(escape_markdown(name)) == name
        assert table_cells(f"| {escape_markdown(name)} | x |") == [name, "x"]


@pytest.mark.unit
def test_report_pdf_shows_names_beyond_latin1() -> None:
    pdf = markdown_pdf(
        "# Survey report\n\n- not registered: 照片.jpg\n\n| stage | s |\n|---|---:|\n| total | 1.5 |\n"
    )
    assert pdf.startswith(b"%PDF-") and len(pdf) > 1000


# -- the shared GPS run of the small scene ------------------------------------------------------
@pytest.mark.pipeline
def test_odm_export_of_the_gps_run_puts_points_and_photos_where_gps_does(
    small_scene: Path, small_run: Path, tmp_path: Path
) -> None:
    zip_path = export_zip(open_run(small_run), "odm", tmp_path / "odm.zip")
    with zipfile.ZipFile(zip_path) as z:
        z.extractall(tmp_path / "odm")
    dest = tmp_path / "odm"
    summary = json.loads((small_run / "summary.json").read_text())
    frame = model_frame(summary)
    assert frame is not None and frame.kind == "ENU"
    las = laspy.read(dest / "odm_georeferencing" / LAZ_NAME)
    assert las.header.parse_crs() == frame.crs and len(las.points) == summary["points3D"]
    rec = pycolmap.Reconstruction(str(small_run / "sparse" / "0"))
    xyz = np.array([rec.points3D[i].xyz for i in sorted(rec.points3D)])
    np.testing.assert_allclose(np.column_stack([las.x, las.y, las.z]), frame.to_projected(xyz), atol=0.002)
    # each photo with a fix lands within its GPS residual of the fix (the fit's per-image rows)
    residual = {r["name"]: r["residual_m"] for r in summary["alignment"]["per_image"]}
    shots = json.loads((dest / "odm_report" / "shots.geojson").read_text())["features"]
    assert len(shots) == summary["registered"]
    enu = EnuFrame(**summary["origin"])
    for f in shots:
        name = f["properties"]["filename"]
        meta = read_metadata(small_scene / "images" / name)
        if not meta.has_gps:
            continue
        lon, lat, h = f["geometry"]["coordinates"]
        fix = enu.from_geodetic(meta.latitude, meta.longitude, meta.altitude_m)
        at = enu.from_geodetic(lat, lon, h)
        # the fit's residual, as the model stands (5 cm for the refinements after the fit)
        assert float(np.linalg.norm(at - fix)) < residual[name] + 0.05, (name, residual[name])
