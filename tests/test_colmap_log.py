"""``geomatch run`` is quiet by default: progress bars and a table, no COLMAP log unless --verbose.

The real process, its real stderr (pycolmap's C++ writes to fd 2, which no Python-level capture
sees, hence a subprocess). No networks: the database is filled beforehand with ground-truth
correspondences of a small synthetic scene, so ``run`` finds every pair matched and goes
straight to mapping, which is where COLMAP logs.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from geomatch.metadata import read_metadata
from geomatch.sfm.colmapdb import ColmapDatabase
from geomatch.synth.aerial import Scene
from geomatch.synth.sensors import save_png

pytestmark = pytest.mark.pipeline

GLOG_LINE = re.compile(r"^[IWEF]\d{8} \d\d:\d\d:\d\d\.\d+ +\d+ [\w.]+:\d+\]", re.M)


def _true_tracks(scene: Scene, cams: list, step: int = 12) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Scene points sampled on every image's pixel grid, with their pixel and visibility in every image."""
    renders = [scene.render(c, supersample=1)[1] for c in cams]
    points = []
    for c, depth in zip(cams, renders, strict=True):
        v, u = np.mgrid[step // 2 : c.height : step, step // 2 : c.width : step]
        d = depth[v, u]
        ok = np.isfinite(d)
        pix = np.stack([u[ok] + 0.5, v[ok] + 0.5, np.ones(ok.sum())], 1)
        points.append((pix @ np.linalg.inv(c.K).T * d[ok, None] - c.t) @ c.R)
    X = np.concatenate(points)
    uvs, vis = [], []
    for c, depth in zip(cams, renders, strict=True):
        uv, z = c.project(X)
        ui, vi = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
        inside = (z > 0) & (ui >= 0) & (ui < c.width) & (vi >= 0) & (vi < c.height)
        seen = inside.copy()
        seen[inside] = np.abs(depth[vi[inside], ui[inside]] - z[inside]) < 0.01 * z[inside]
        uvs.append(uv)
        vis.append(seen)
    return uvs, vis


@pytest.fixture(scope="module")
def project(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("quiet")
    scene = Scene(3)
    cams = scene.cameras(0, 5, 320, 240)
    images = root / "images"
    images.mkdir()
    for c in cams:
        save_png(images / c.name, scene.render(c)[0], c)
    uvs, vis = _true_tracks(scene, cams)
    out = root / "out"
    with ColmapDatabase(out / "database.db") as db:
        ids = [db.add_image(c.name, read_metadata(images / c.name)) for c in cams]
        for i in range(len(cams)):
            for j in range(i + 1, len(cams)):
                both = vis[i] & vis[j]
                db.write_pair(ids[i], ids[j], uvs[i][both], uvs[j][both], np.ones(both.sum()), 0.5, 0.5)
    return images, out


def _run(images: Path, out: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "geomatch.cli",
            "run",
            str(images),
            "--out",
            str(out),
            "--device",
            "cpu",
            *extra,
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )


def test_run_is_quiet_by_default(project) -> None:
    images, out = project
    res = _run(images, out)
    assert res.returncode == 0, res.stderr
    assert "registered 5/5 images" in res.stdout, res.stdout
    assert not GLOG_LINE.search(res.stderr) and not GLOG_LINE.search(res.stdout), res.stderr[:2000]
    assert "mapping (incremental)" in res.stderr  # the stage's progress bar


def test_verbose_shows_colmaps_log(project) -> None:
    images, out = project
    res = _run(images, out, "--verbose")
    assert res.returncode == 0, res.stderr
    lines = GLOG_LINE.findall(res.stderr)
    assert len(lines) > 10 and any("incremental_pipeline.cc" in ln for ln in lines), res.stderr[:2000]
