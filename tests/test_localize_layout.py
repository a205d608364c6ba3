"""Where geomatch.localize finds a project's parts: a ``geomatch run`` folder and a project stored
by the service (geomatch_core/storage.py's layout), on empty stand-in files."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from geomatch.localize import LocalizeError, Project

pytestmark = pytest.mark.unit


def _touch(path: Path, text: str = "") -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_a_run_folder(tmp_path: Path) -> None:
    images = tmp_path / "photos"
    images.mkdir()
    run = tmp_path / "run"
    _touch(run / "database.db")
    _touch(run / "sparse" / "0" / "images.bin")
    summary = {
        "image_dir": str(images),
        "georeferenced": True,
        "origin": {"lat": 47.0, "lon": 8.0, "alt": 400.0},
    }
    _touch(run / "summary.json", json.dumps({**summary, "options": {"method": "geo", "resize": 480}}))
    p = Project.find(run)
    assert (p.model_dir, p.images_dir, p.database) == (run / "sparse" / "0", images, run / "database.db")
    assert p.run_options["resize"] == 480
    frame = p.frame()
    assert frame is not None and (frame.lat, frame.lon, frame.alt) == (47.0, 8.0, 400.0)


def test_a_stored_project(tmp_path: Path) -> None:
    project = tmp_path / "projects" / "p1"
    _touch(project / "database.db")
    _touch(project / "images" / "a.jpg")
    _touch(project / "model" / "sparse" / "0" / "images.bin")
    _touch(project / "model" / "summary.json", json.dumps({"georeferenced": False}))
    p = Project.find(project)
    assert (p.model_dir, p.images_dir) == (project / "model" / "sparse" / "0", project / "images")
    assert p.run_options == {} and p.frame() is None


def test_missing_parts_are_named(tmp_path: Path) -> None:
    with pytest.raises(LocalizeError, match="no model"):
        Project.find(tmp_path)
    _touch(tmp_path / "sparse" / "0" / "images.bin")
    with pytest.raises(LocalizeError, match="images are not there"):
        Project.find(tmp_path)
    (tmp_path / "images").mkdir()
    with pytest.raises(LocalizeError, match="no COLMAP database"):
        Project.find(tmp_path)
    other = tmp_path / "elsewhere"
    _touch(other / "images.bin")
    _touch(tmp_path / "database.db")
    assert Project.find(tmp_path, model_dir=other).model_dir == other
