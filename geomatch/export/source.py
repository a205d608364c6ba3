"""What every export format reads: the shared input of the package's writers, in a module of its
own so that the writers need not import the package that dispatches to them."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


class ExportError(ValueError):
    """The run folder cannot give what the format needs (no model, no images, no database)."""


@dataclass(frozen=True)
class Source:
    """Where an export reads from: the model folder (COLMAP binary), the database, the images."""

    model: Path
    database: Path | None = None
    images: Path | None = None
    summary: Path | None = None
