"""A localized photo put into its project, so a later reconstruct maps it."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .project import LocalizeError, Project

if TYPE_CHECKING:
    from .localizer import Evidence


def add_to_project(project: Project, photo: Path, evidence: Evidence, matcher: Any, snap: float) -> int:
    """The photo into the project's COLMAP database (its image row, keypoints and its verified
    matches to the model images it was matched with) and into its images folder, so a later
    reconstruct maps it (the mapper reads the photos: track refinement). Idempotent: an image and
    a pair already there are left as they are. Returns the photo's image id."""
    from ..metadata import read_metadata
    from ..pipeline.database import write
    from ..sfm.colmapdb import ColmapDatabase

    photo = Path(photo)
    dest = project.images_dir / photo.name
    if not dest.exists():
        shutil.copyfile(photo, dest)
    elif dest.read_bytes() != photo.read_bytes():
        raise LocalizeError(f"{photo.name}: the project has another image of that name")
    meta = read_metadata(dest)
    share = project.run_options.get("share_camera")
    with ColmapDatabase(project.database) as db:
        photo_id = db.add_image(photo.name, meta, share if isinstance(share, bool) else None)
        for name, m in evidence.pairs.items():
            other = db.image_id(name)
            if other is None or name == photo.name:
                continue
            write(db, photo_id, other, m, snap, matcher.config.resize)
    return photo_id
