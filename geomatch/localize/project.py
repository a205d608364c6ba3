"""A project to localize against: where its parts are, and the matcher it ran with.

Two layouts are read: a ``geomatch run --out OUT`` folder (``database.db``, ``sparse/0``,
``summary.json`` naming the images folder, the options and the aerial images) and a project stored
by the service (``database.db``, ``images/``, ``model/sparse/0``, ``model/summary.json``);
explicit ``model_dir`` / ``images_dir`` override either.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..options import DEFAULTS


class LocalizeError(ValueError):
    """The project cannot be localized against: no model, no database, no images."""


@dataclass(frozen=True)
class Project:
    """Where a project's parts are and what its run recorded."""

    database: Path
    model_dir: Path
    images_dir: Path
    summary: dict[str, Any]

    @classmethod
    def find(cls, root: Path, model_dir: Path | None = None, images_dir: Path | None = None) -> Project:
        root = Path(root)
        if model_dir is None:
            model_dir = next(
                (
                    d
                    for d in (root / "sparse" / "0", root / "model" / "sparse" / "0")
                    if (d / "images.bin").is_file()
                ),
                None,
            )
        if model_dir is None or not (Path(model_dir) / "images.bin").is_file():
            raise LocalizeError(
                f"{root}: no model (sparse/0 or model/sparse/0): reconstruct the project first"
            )
        model_dir = Path(model_dir)
        summary_path = next(
            (p for p in (model_dir.parent.parent / "summary.json", root / "summary.json") if p.is_file()),
            None,
        )
        summary = json.loads(summary_path.read_text()) if summary_path is not None else {}
        if images_dir is None:
            recorded = summary.get("image_dir")
            images_dir = Path(recorded) if recorded else root / "images"
        if not Path(images_dir).is_dir():
            raise LocalizeError(f"{images_dir}: the project's images are not there (pass images_dir)")
        database = root / "database.db"
        if not database.is_file():
            raise LocalizeError(f"{root}: no COLMAP database (database.db)")
        return cls(database, model_dir, Path(images_dir), summary)

    @property
    def run_options(self) -> dict[str, Any]:
        """The options ``geomatch run`` recorded (empty for a service project: its caller knows)."""
        options = self.summary.get("options")
        return dict(options) if isinstance(options, dict) else {}

    def frame(self) -> Any:
        """The ENU frame the model is in, or None when it is not georeferenced."""
        from ..geo.geodesy import EnuFrame

        origin = self.summary.get("origin")
        if not self.summary.get("georeferenced") or not isinstance(origin, dict):
            return None
        return EnuFrame(float(origin["lat"]), float(origin["lon"]), float(origin["alt"]))


def project_matcher(project: Project, features: Path | None = None) -> Any:
    """The matcher the project ran with (method, resize and matcher options of its summary), or
    the defaults for a project that recorded none; it reads the features in ``features`` (default:
    the run folder's own ``features/``) and writes none."""
    from ..features.store import run_feature_store
    from ..matching.stored import build_matcher
    from ..memory import cache_budget

    recorded = project.run_options
    budget = cache_budget()
    options = {
        "method": recorded.get("method", DEFAULTS["method"]),
        "resize": recorded.get("resize", DEFAULTS["resize"]),
        "device": recorded.get("device", DEFAULTS["device"]),
        "cache_features_mb": budget.features_mb,
        "cache_anchors_mb": budget.anchors_mb,
        **dict(recorded.get("matcher") or {}),  # the run's further matcher and optimizer options
    }
    # a run's folder keeps its features: the model images are read, not extracted again (and
    # the folder is left as it is: a photo's own features are not written into it)
    folder = Path(features) if features is not None else project.database.parent / "features"
    store = run_feature_store(folder, writable=False) if folder.is_dir() else None
    return build_matcher(store, **options)
