"""What every stage of a project reads first: its photos as read once (names, metadata, GPS fixes)
and what the run or match job asks of the plan. Their own module so that the plan, the stage that
prepares a project and the steps that spread the plan over the workers share them without
importing one another."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..geo import gps
from ..geo.gps import GpsFixes
from ..metadata import ImageMeta, read_metadata
from ..options import DEFAULTS


@dataclass(frozen=True)
class ProjectImages:
    """A project's photos as every stage after reading them sees them: their names (relative to
    ``folder``, in order), each one's metadata, and the GPS fixes (None: not georeferenced, or too
    few photos with a fix: geo.gps.fixes)."""

    folder: Path
    names: list[str]
    metas: dict[str, ImageMeta]
    fixes: GpsFixes | None

    @classmethod
    def read(cls, folder: Path, names: Sequence[str], georeference: bool = True) -> ProjectImages:
        metas = {n: read_metadata(folder / n) for n in names}
        fixes = gps.fixes(list(names), metas) if georeference else None
        return cls(folder, list(names), metas, fixes)

    def sizes(self) -> dict[str, tuple[int, int]]:
        """(width, height) of each photo."""
        return {n: (m.width, m.height) for n, m in self.metas.items()}

    def plan_points(self) -> dict[str, np.ndarray]:
        """The east-north point each located photo is paired by (gps.plan_points); none without
        fixes."""
        return gps.plan_points(self.fixes, self.metas) if self.fixes is not None else {}

    def footprints(self) -> dict[str, np.ndarray] | None:
        """The located photos' footprints on the ground (gps.footprints); None without fixes."""
        return gps.footprints(self.fixes, self.metas) if self.fixes is not None else None


@dataclass(frozen=True)
class PlanRequest:
    """What a run or a match job asks of the plan: ``spec`` (options.PAIR_KINDS; ignored with
    ``pairs_list``), an explicit pair list, and ``tiling`` (auto | on | off)."""

    spec: str = DEFAULTS["pairs"]
    pairs_list: Sequence[Sequence[str]] | None = None
    tiling: str = DEFAULTS["tiling"]
