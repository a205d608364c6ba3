"""The map (geomatch.ortho) on a small synthetic survey with an exact model (tests/ortho_scene.py):
the orthophoto against the ground's true texture, its COG, alpha and CRS, the DSM against the true
ground with wrong points thrown in, tiles against one piece, the photo cache's bound, refusals."""

from __future__ import annotations

import json
import shutil
import tracemalloc
from pathlib import Path

import numpy as np
import pycolmap
import pyproj
import pytest
import rasterio

from geomatch.export.georef import utm_zone
from geomatch.ortho import DSM_PATH, ORTHO_PATH, MapOptions, OrthoError, make_map
from geomatch.ortho.accuracy import patch_offsets
from geomatch.ortho.cog import is_cog
from geomatch.ortho.dsm import NODATA, build_dsm
from geomatch.ortho.photos import PhotoCache
from geomatch.ortho.survey import open_survey, within_reach
from geomatch.synth.sensors import GPS_ORIGIN
from tests.ortho_scene import OrthoScene, make_scene, truth_image

pytestmark = pytest.mark.unit


@pytest.fixture(scope="module")
def flat(tmp_path_factory: pytest.TempPathFactory) -> OrthoScene:
    return make_scene(tmp_path_factory.mktemp("flat"), photos=6, width=240, height=180, altitude=40.0)


@pytest.fixture(scope="module")
def flat_map(flat: OrthoScene) -> dict[str, object]:
    return make_map(flat.run).record


def read(path: Path) -> tuple[np.ndarray, rasterio.Affine, str]:
    with rasterio.open(path) as src:
        return np.moveaxis(src.read(), 0, -1), src.transform, src.crs.to_string()


def test_orthophoto_lies_on_the_true_ground(flat: OrthoScene, flat_map: dict[str, object]) -> None:
    ortho, truth = truth_image(flat, flat.run / ORTHO_PATH)
    off = patch_offsets(ortho, truth, patch=48)
    s = off.summary()
    assert s["patches"] >= 10, s
    assert s["median_gsd"] <= 0.5 and s["p95_gsd"] <= 1.5, s
    # a shift of the map by two pixels is seen as two pixels: the measure can fail
    shifted = np.roll(ortho, 2, axis=1)
    s2 = patch_offsets(shifted, truth, patch=48).summary()
    assert 1.5 <= s2["median_gsd"] <= 2.5, s2


def test_the_gsd_is_the_surveys(flat: OrthoScene, flat_map: dict[str, object]) -> None:
    assert flat_map["gsd_m"] == pytest.approx(flat.gsd, rel=0.03)


def test_cogs_with_alpha_in_the_models_crs(flat: OrthoScene, flat_map: dict[str, object]) -> None:
    for rel in (ORTHO_PATH, DSM_PATH):
        valid, errors, _ = is_cog(flat.run / rel)
        assert valid, (rel, errors)
    ortho, t, crs = read(flat.run / ORTHO_PATH)
    want = utm_zone(GPS_ORIGIN.lat, GPS_ORIGIN.lon)
    assert pyproj.CRS.from_user_input(crs) == want
    assert ortho.shape[2] == 4
    alpha = ortho[..., 3]
    assert set(np.unique(alpha)) == {0, 255}
    assert 0.3 < (alpha == 255).mean() < 1.0
    assert not ortho[alpha == 0, :3].any()  # nothing under the transparent part
    with rasterio.open(flat.run / ORTHO_PATH) as src:
        assert src.overviews(1), "no overviews"
        assert src.colorinterp[3] == rasterio.enums.ColorInterp.alpha
    assert abs(t.a - flat_map["gsd_m"]) < 1e-9 and t.e == -t.a
    summary = json.loads((flat.run / "summary.json").read_text())
    assert summary["ortho"]["crs"] == want.to_string()
    assert (flat.run / "odm_orthophoto" / "preview.png").is_file()
    preview = summary["ortho"]["preview"]
    assert max(preview["width"], preview["height"]) <= 1024
    assert len(preview["cameras"]) == len(flat.cams)  # all of them over the map
    assert all(0 <= c["x"] <= 1 and 0 <= c["y"] <= 1 for c in preview["cameras"])
    # the first camera's marker is where its centre is on the map: east of west by its share
    first = next(c for c in preview["cameras"] if c["name"] == flat.cams[0].name)
    lat, lon, _ = GPS_ORIGIN.to_geodetic(flat.cams[0].centre[None])
    e, n = pyproj.Transformer.from_crs("EPSG:4326", want, always_xy=True).transform(lon[0], lat[0])
    w, s, east, north = summary["ortho"]["bounds"]
    assert first["x"] == pytest.approx((e - w) / (east - w), abs=1e-3)
    assert first["y"] == pytest.approx((north - n) / (north - s), abs=1e-3)


def test_dsm_is_the_ground_with_outliers_rejected(flat: OrthoScene, flat_map: dict[str, object]) -> None:
    dsm, _, _ = read(flat.run / DSM_PATH)
    h = dsm[..., 0]
    valid = h != NODATA
    assert valid.mean() > 0.3 and (~valid).any()
    # the flat scene's ground is at the GPS origin's height; points 5-30 m off were thrown in
    err = np.abs(h[valid] - GPS_ORIGIN.alt)
    assert err.max() < 0.5, err.max()
    assert flat_map["dsm_points_rejected"] > 0


def test_dsm_median_survives_a_spike_cluster() -> None:
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(0, 100, 4000), rng.uniform(0, 100, 4000), np.zeros(4000)])
    pts[:40, :2] = rng.uniform(48, 52, (40, 2))
    pts[:40, 2] = 25.0  # a tight cluster of wrong points
    dsm = build_dsm(pts, min_cell=0.1)
    assert np.abs(dsm.height[dsm.valid]).max() < 1.0
    assert dsm.points_rejected >= 35
    # and a real step (a building 30 m wide) stays
    pts[:, 2] = np.where((np.abs(pts[:, 0] - 50) < 15) & (np.abs(pts[:, 1] - 50) < 15), 10.0, 0.0)
    dsm = build_dsm(pts, min_cell=0.1)
    assert dsm.at(np.array([50.0]), np.array([50.0]))[0] == pytest.approx(10.0, abs=0.5)


def test_tiles_agree_with_one_piece(flat: OrthoScene, tmp_path: Path) -> None:
    one = make_map(flat.run, out=tmp_path / "one", options=MapOptions(tile=8192))
    tiled = make_map(flat.run, out=tmp_path / "tiled", options=MapOptions(tile=96, cache_mb=0.5))
    a, _, _ = read(one.orthophoto)
    b, _, _ = read(tiled.orthophoto)
    assert a.shape == b.shape and a.shape[0] > 2 * 96  # several tiles a side
    assert np.array_equal(a[..., 3], b[..., 3])
    assert np.abs(a.astype(int) - b.astype(int)).max() <= 1
    # the small cache had to decode photos again: the bound held
    assert tiled.record["photos_decoded"] > one.record["photos_decoded"]


def test_photo_cache_stays_in_its_bytes(flat: OrthoScene) -> None:
    survey = open_survey(flat.run)
    one = flat.cams[0].width * flat.cams[0].height * 3
    cache = PhotoCache(flat.images, budget_mb=2.5 * one / 2**20)
    for v in survey.views:
        cache.get(v, 1.0)
        assert cache.nbytes() <= 2.5 * one
    assert cache.decoded == len(survey.views)


def test_peak_memory_follows_the_tile_not_the_map(flat: OrthoScene, tmp_path: Path) -> None:
    def peak(tile: int) -> int:
        tracemalloc.start()
        try:
            make_map(flat.run, out=tmp_path / f"t{tile}", options=MapOptions(tile=tile, cache_mb=1.0))
            return tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()

    small, big = peak(64), peak(8192)
    assert small < 0.6 * big, (small, big)


def test_a_model_without_georeferencing_is_refused(tmp_path: Path) -> None:
    scene = make_scene(tmp_path, photos=2, width=96, height=72, points_per_photo=50, georeferenced=False)
    with pytest.raises(OrthoError, match="georeferenced"):
        make_map(scene.run)
    assert not (scene.run / "odm_orthophoto").exists() and not (scene.run / "odm_dem").exists()
    # as a stage of a run or a job: the model stays, the summary and its report say why
    from geomatch.ortho import map_step
    from geomatch.report import survey_report, to_markdown

    record = map_step(scene.run)
    assert "georeferenced" in record["skipped"]
    summary = json.loads((scene.run / "summary.json").read_text())
    assert summary["ortho"] == record
    assert "- no map: the map needs a georeferenced model" in to_markdown(survey_report(summary))
    assert not (scene.run / "odm_orthophoto").exists()


def test_a_gcp_models_map_is_in_the_gcp_files_crs(flat: OrthoScene, tmp_path: Path) -> None:
    run = tmp_path / "run"
    shutil.copytree(flat.run / "sparse", run / "sparse")
    origin = [2683000.0, 1247000.0, 400.0]  # Swiss LV95 (EPSG:2056), as a GCP file names it
    summary = {
        "image_dir": str(flat.images),
        "georeferenced": True,
        "frame": "GCP",
        "gcp": {"frame": "EPSG:2056", "origin": origin},
    }
    (run / "summary.json").write_text(json.dumps(summary))
    rec = make_map(run).record
    _, _, crs = read(run / ORTHO_PATH)
    assert pyproj.CRS.from_user_input(crs) == pyproj.CRS.from_epsg(2056)
    w, s, e, n = rec["bounds"]
    assert w < origin[0] < e and s < origin[1] < n  # the scene's origin is in the middle of it


def test_clear_errors(flat: OrthoScene, tmp_path: Path) -> None:
    with pytest.raises(OrthoError, match="not a run folder"):
        make_map(tmp_path)
    with pytest.raises(OrthoError, match="photos"):
        make_map(flat.run, images=tmp_path / "nowhere", out=tmp_path / "x")
    with pytest.raises(OrthoError, match="GSD"):
        make_map(flat.run, out=tmp_path / "y", options=MapOptions(gsd=-1.0))
    empty = tmp_path / "empty"
    (empty / "sparse" / "0").mkdir(parents=True)
    pycolmap.Reconstruction().write(str(empty / "sparse" / "0"))
    (empty / "summary.json").write_text(
        json.dumps({"georeferenced": True, "frame": "ENU", "origin": GPS_ORIGIN.as_dict()})
    )
    with pytest.raises(OrthoError):
        make_map(empty)


def test_sloped_ground(tmp_path: Path) -> None:
    """Slopes up to 17 %: the DSM follows them and the map stays on the ground."""
    scene = make_scene(tmp_path, photos=6, width=240, height=180, altitude=40.0, relief=(150.0, 4.0))
    rec = make_map(scene.run).record
    ortho, truth = truth_image(scene, scene.run / ORTHO_PATH)
    s = patch_offsets(ortho, truth, patch=48).summary()
    assert s["patches"] >= 8 and s["median_gsd"] <= 0.5 and s["p95_gsd"] <= 1.5, s
    dsm, t, _ = read(scene.run / DSM_PATH)
    h = dsm[..., 0]
    rows, cols = np.nonzero(h != NODATA)
    e, n = t.c + (cols + 0.5) * t.a, t.f + (rows + 0.5) * t.e
    lon, lat = pyproj.Transformer.from_crs(rec["crs"], "EPSG:4326", always_xy=True).transform(e, n)
    enu = GPS_ORIGIN.from_geodetic(np.asarray(lat), np.asarray(lon), np.zeros(len(e)))
    ground = scene.world.terrain.height(enu[:, 0], enu[:, 1]) + GPS_ORIGIN.alt
    assert np.ptp(ground) > 2.0  # the scene is not flat
    err = np.abs(h[rows, cols] - ground)
    # the edges (the hull grown by two cells) are extrapolated: the bulk is held tight
    assert np.median(err) < 0.2 and np.percentile(err, 90) < 0.5, (np.median(err), np.percentile(err, 90))


def test_the_map_in_the_exports_and_the_report(
    flat: OrthoScene, flat_map: dict[str, object], tmp_path: Path
) -> None:
    from geomatch.export import ExportError, export, open_run
    from geomatch.report import survey_report, to_markdown

    source = open_run(flat.run)
    odm = export(source, "odm", tmp_path / "odm")
    rel = {p.relative_to(tmp_path / "odm").as_posix() for p in odm}
    assert {"odm_orthophoto/odm_orthophoto.tif", "odm_dem/dsm.tif"} <= rel
    assert (tmp_path / "odm" / ORTHO_PATH).read_bytes() == (flat.run / ORTHO_PATH).read_bytes()
    [tif] = export(source, "orthophoto", tmp_path / "o")
    assert tif.name == "odm_orthophoto.tif" and is_cog(tif)[0]
    [dem] = export(source, "dsm", tmp_path / "d")
    assert dem.name == "dsm.tif"

    summary = json.loads((flat.run / "summary.json").read_text())
    report = survey_report(summary)
    assert report["map"]["gsd_cm"] == pytest.approx(100 * flat_map["gsd_m"], abs=0.01)
    assert report["map"]["crs"] == flat_map["crs"]
    page = to_markdown(report)
    assert "## Map" in page and f"{report['map']['gsd_cm']} cm per pixel" in page

    bare = tmp_path / "bare"
    shutil.copytree(flat.run / "sparse", bare / "sparse")
    (bare / "summary.json").write_text(json.dumps({k: v for k, v in summary.items() if k != "ortho"}))
    with pytest.raises(ExportError, match="geomatch ortho"):
        export(open_run(bare), "orthophoto", tmp_path / "none")
    files = {
        p.relative_to(tmp_path / "odm2").as_posix() for p in export(open_run(bare), "odm", tmp_path / "odm2")
    }
    assert "odm_orthophoto/odm_orthophoto.tif" not in files and "odm_report/shots.geojson" in files


def test_model_coordinates_between_nodes_are_exact(flat: OrthoScene, flat_map: dict[str, object]) -> None:
    from geomatch.ortho.grid import Grid
    from geomatch.ortho.mosaic import model_grid

    survey = open_survey(flat.run)
    w, s, e, n = flat_map["bounds"]
    grid = Grid.covering(w, s, e, n, flat_map["gsd_m"])
    ee, nn = grid.centres(3, 203, 5, 180)
    z = GPS_ORIGIN.alt + np.random.default_rng(1).normal(0.0, 20.0, ee.shape)  # far off its median
    got = model_grid(survey, ee, nn, z)
    want = survey.model_from_projected(np.column_stack([ee.ravel(), nn.ravel(), z.ravel()]))
    assert np.abs(got.reshape(-1, 3) - want).max() < 1e-4


def test_the_map_as_a_stage_and_as_a_command(flat: OrthoScene, tmp_path: Path) -> None:
    import subprocess
    import sys

    from geomatch.pipeline.orthomap import add_map

    run = tmp_path / "run"
    shutil.copytree(flat.run / "sparse", run / "sparse")
    summary = {**json.loads((flat.run / "summary.json").read_text()), "timings": {"mapping": 1.0}}
    summary.pop("ortho", None)
    assert add_map(run, dict(summary), flat.images, "off") == summary  # off: nothing, not even a file
    assert not (run / "summary.json").exists()
    done = add_map(run, dict(summary), flat.images, "on", 2 * flat.gsd)
    assert done["ortho"]["gsd_m"] == pytest.approx(2 * flat.gsd) and done["timings"]["map"] > 0
    assert is_cog(run / ORTHO_PATH)[0]
    broken = tmp_path / "broken"  # photos that do not decode: the map fails, the model stands
    broken.mkdir()
    for cam in flat.cams:
        (broken / cam.name).write_bytes(b"not a photo")
    failed = add_map(run, dict(summary), broken, "on", explain=lambda e: type(e).__name__)
    assert failed["ortho"] == {"skipped": "the map failed (ImageReadError)"}
    assert failed["registered"] == summary["registered"]

    cmd = [sys.executable, "-m", "geomatch_app", "ortho", str(run), "--ortho-gsd", str(3 * flat.gsd)]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith("map: orthophoto ") and "odm_orthophoto.tif" in res.stdout
    assert json.loads((run / "summary.json").read_text())["ortho"]["gsd_m"] == pytest.approx(3 * flat.gsd)
    bare = tmp_path / "bare"
    (bare / "sparse").mkdir(parents=True)
    res = subprocess.run([*cmd[:4], str(bare)], capture_output=True, text=True, timeout=300)
    assert res.returncode == 2 and res.stderr.startswith("geomatch: error: ") and "run folder" in res.stderr


def test_photos_that_do_not_look_down_get_no_map(flat: OrthoScene, tmp_path: Path) -> None:
    """A ground project (photos looking along the street) is georeferenced but has no map."""
    import dataclasses

    from geomatch.synth.camera import look_at
    from geomatch.synth.groundtruth import write_gt

    cams = []
    for c in flat.cams:
        R, t = look_at(c.centre, c.centre + np.array([1.0, 0.0, -0.1]))
        cams.append(dataclasses.replace(c, R=R, t=t))
    text = tmp_path / "text"
    write_gt(cams, text)
    shutil.copy(flat.run.parent / "model_text" / "points3D.txt", text / "points3D.txt")
    run = tmp_path / "run"
    (run / "sparse" / "0").mkdir(parents=True)
    pycolmap.Reconstruction(str(text)).write(str(run / "sparse" / "0"))
    shutil.copy(flat.run / "summary.json", run / "summary.json")
    with pytest.raises(OrthoError, match="do not look down"):
        make_map(run)


def test_a_gcp_target_is_found_and_a_dark_bush_is_not() -> None:
    import cv2

    from geomatch.ortho.targets import find_target

    res = 0.01  # 1 cm a pixel
    rng = np.random.default_rng(0)
    sand = np.clip(rng.normal(150, 12, (300, 300)), 0, 255).astype(np.uint8)
    img = np.dstack([sand, sand, sand, np.full_like(sand, 255)])
    cv2.circle(img, (70, 80), 30, (35, 40, 30, 255), -1)  # a dark bush, no cross
    assert find_target(img, res) is None
    cx, cy = 181.5, 162.5  # a 50 cm black square with a 6 cm white cross, centred here
    cv2.rectangle(img, (157, 138), (206, 187), (10, 10, 10, 255), -1)
    cv2.line(img, (159, 140), (204, 185), (250, 250, 250, 255), 6)
    cv2.line(img, (204, 140), (159, 185), (250, 250, 250, 255), 6)
    found = find_target(img, res)
    assert found is not None and abs(found[0] - cx) < 1.5 and abs(found[1] - cy) < 1.5, found
    img[..., 3] = 0  # outside the map: nothing
    assert find_target(img, res) is None


def test_points_beyond_the_photos_reach_make_no_surface() -> None:
    """A block of cameras 45 m over the ground maps what lies under it: a low-parallax point
    hundreds of metres out or below (a sparse model has a few) would stretch the DSM, and the
    photos' edges with it, over ground no photo sees from above."""
    rng = np.random.default_rng(0)
    centres = np.column_stack([rng.uniform(0, 80, 18), rng.uniform(0, 80, 18), np.full(18, 45.0)])
    ground = np.column_stack([rng.uniform(-20, 100, 500), rng.uniform(-20, 100, 500), rng.normal(0, 2, 500)])
    far_out = np.array([[450.0, 40.0, 1.0], [40.0, -300.0, -3.0]])
    far_below = np.array([[40.0, 40.0, -500.0], [20.0, 60.0, -80.0]])
    keep = within_reach(np.concatenate([ground, far_out, far_below]), centres)
    assert keep[:500].all() and not keep[500:].any()
