"""A small synthetic survey with an exact model, for the map's tests: a flight over synth.world's
ground (flat or rolling, with or without buildings), photos rendered by its ray caster, the true
cameras as the model and 3D points where the rays of random pixels meet the rendered surface
(some of them thrown metres off, as a matcher's wrong points are), georeferenced in ENU around
synth.sensors' GPS origin as a GPS run's model is; and the truth to judge an orthophoto by (the
ground texture at any position)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
from PIL import Image

from geomatch.synth.camera import Camera
from geomatch.synth.flightplan import FOCAL_PER_WIDTH, FlightPlan, aerial_cameras
from geomatch.synth.groundtruth import write_gt
from geomatch.synth.sensors import GPS_ORIGIN
from geomatch.synth.world import World


@dataclass
class OrthoScene:
    run: Path
    images: Path
    world: World
    cams: list[Camera]
    gsd: float  # the photos' own, metres


def make_scene(
    root: Path,
    photos: int = 9,
    width: int = 320,
    height: int = 240,
    altitude: float = 50.0,
    flat: bool = True,
    buildings: bool = False,
    seed: int = 3,
    points_per_photo: int = 400,
    outliers: float = 0.02,
    georeferenced: bool = True,
    relief: tuple[float, float] | None = None,
) -> OrthoScene:
    """``flat``: the ground at height 0; ``relief`` (wavelength, amplitude in metres): one long
    wave instead of the world's rolling ground (slopes up to 2 pi amplitude / wavelength)."""
    plan = FlightPlan.make(photos, width, height, altitude)
    gsd = altitude / (FOCAL_PER_WIDTH * width)
    world = World(seed, texel_m=gsd / 2, building_share=0.6 if buildings else 0.0)
    if flat or relief is not None:
        world.terrain.amp[:] = 0.0
        world.terrain.offset = 0.0
    if relief is not None:
        wavelength, amplitude = relief
        world.terrain.k[0] = [2 * np.pi / wavelength * 0.8, 2 * np.pi / wavelength * 0.6]
        world.terrain.amp[0] = amplitude
        world.terrain.phase[0] = 0.0
    cams, _ = aerial_cameras(plan, seed)
    images = root / "images"
    if (root / "run" / "summary.json").is_file():  # made before with these arguments: kept
        return OrthoScene(root / "run", images, world, cams, gsd)
    images.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    lines = []
    pid = 0
    for cam in cams:
        img, depth = world.render(cam)
        Image.fromarray(img).save(images / cam.name, format="JPEG", quality=95)
        v = rng.integers(0, height, points_per_photo)
        u = rng.integers(0, width, points_per_photo)
        d = depth[v, u]
        fin = np.isfinite(d)
        rays = np.column_stack([u[fin] + 0.5, v[fin] + 0.5, np.ones(fin.sum())]) @ np.linalg.inv(cam.K).T
        xyz = (rays * d[fin, None] - cam.t) @ cam.R
        bad = rng.random(len(xyz)) < outliers
        xyz[bad, 2] += rng.choice([-1.0, 1.0], bad.sum()) * rng.uniform(5.0, 30.0, bad.sum())
        for p in xyz:
            pid += 1
            lines.append(f"{pid} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f} 128 128 128 0.5\n")
    text = root / "model_text"
    write_gt(cams, text)
    (text / "points3D.txt").write_text("# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]\n" + "".join(lines))
    run = root / "run"
    model = run / "sparse" / "0"
    model.mkdir(parents=True, exist_ok=True)
    pycolmap.Reconstruction(str(text)).write(str(model))
    summary: dict[str, object] = {"image_dir": str(images), "registered": len(cams), "images": len(cams)}
    if georeferenced:
        summary |= {"georeferenced": True, "frame": "ENU", "origin": GPS_ORIGIN.as_dict()}
    else:
        summary |= {"georeferenced": False}
    (run / "summary.json").write_text(json.dumps(summary))
    return OrthoScene(run, images, world, cams, gsd)


def truth_image(scene: OrthoScene, ortho: Path) -> tuple[np.ndarray, np.ndarray]:
    """The orthophoto (H, W, 4) and the truth on its grid (H, W, 3): the ground texture at each
    pixel's position (the map's CRS back to the scene's ENU metres)."""
    import pyproj
    import rasterio

    with rasterio.open(ortho) as src:
        data = np.moveaxis(src.read(), 0, -1)
        t = src.transform
        crs = pyproj.CRS.from_user_input(src.crs.to_wkt())
    h, w = data.shape[:2]
    cols, rows = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    e = t.c + cols * t.a
    n = t.f + rows * t.e
    lon, lat = pyproj.Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(e.ravel(), n.ravel())
    enu = GPS_ORIGIN.from_geodetic(np.asarray(lat), np.asarray(lon), np.zeros(lat.size))
    truth = scene.world.ground.sample(enu[:, 0], enu[:, 1]).reshape(h, w, 3)
    return data, np.clip(truth + 0.5, 0, 255).astype(np.uint8)
