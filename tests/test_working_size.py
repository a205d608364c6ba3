"""Photos larger than the working size are read, matched and hashed at it, and what is matched
comes back in the photos' own pixels: a drone's 4000 px originals cost what their 2000 px copies
cost, and the database and the mapper see the photo's pixels as before."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from geomatch.imagefolder import Images
from geomatch.imageio import read_image, working_size
from geomatch.pipeline.database import PairMatches
from geomatch.synth.photos import warped_pair

pytestmark = pytest.mark.unit


def _jpeg(path: Path, width: int, height: int) -> np.ndarray:
    photo = cv2.resize(warped_pair("astronaut", seed=5, strength=0.1).image0, (width, height))
    cv2.imwrite(str(path), cv2.cvtColor(photo, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
    return read_image(path)


def test_a_large_photo_is_read_at_the_working_size_as_a_resize_of_its_full_decode(tmp_path: Path) -> None:
    full = _jpeg(tmp_path / "big.jpg", 1600, 900)
    small = read_image(tmp_path / "big.jpg", 800)
    assert small.shape == (450, 800, 3) and working_size(1600, 900, 800) == (800, 450)
    reference = cv2.resize(full, (800, 450), interpolation=cv2.INTER_AREA).astype(np.float32)
    assert np.abs(small.astype(np.float32) - reference).mean() < 3.0  # of 255
    # a photo within the working size is read as stored
    assert read_image(tmp_path / "big.jpg", 4000).shape == full.shape


def test_the_folder_says_how_working_pixels_map_to_the_photo(tmp_path: Path) -> None:
    _jpeg(tmp_path / "big.jpg", 1600, 900)
    _jpeg(tmp_path / "small.jpg", 640, 360)
    images = Images(tmp_path, 64.0, max_side=800)
    assert images["big.jpg"].shape == (450, 800, 3) and images["small.jpg"].shape == (360, 640, 3)
    assert images.to_photo("big.jpg") == (2.0, 2.0, (1600, 900))
    assert images.to_photo("small.jpg") is None
    assert Images(tmp_path, 64.0).to_photo("big.jpg") is None


def test_matches_in_working_pixels_land_on_the_same_spot_of_the_photo() -> None:
    # pixel centres at integers on both sizes: working pixel 0 covers photo pixels 0 and 1, whose
    # centre is at 0.5
    m = PairMatches(
        np.array([[0.0, 0.0], [399.5, 224.5]], np.float32),
        np.array([[10.0, 20.0], [5.0, 5.0]], np.float32),
        np.ones(2, np.float32),
        ((800, 450), (640, 360)),
    )
    back = m.in_photo_pixels((2.0, 2.0, (1600, 900)), None)
    np.testing.assert_allclose(back.keypoints0, [[0.5, 0.5], [799.5, 449.5]])
    np.testing.assert_array_equal(back.keypoints1, m.keypoints1)
    assert back.sizes == ((1600, 900), (640, 360)) and back.source is None
    assert m.in_photo_pixels(None, None) is m


def test_the_plan_reads_the_photos_through_the_callers_folder_even_before_it_decoded_any(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An Images that has decoded nothing yet has length 0: a plan that took it for absent read the
    photos again at their stored size, so a survey's turn probes hashed other pixels than its
    matching and every photo's features were extracted twice."""
    from geomatch.pipeline import plan as planning
    from geomatch.pipeline.project import PlanRequest, ProjectImages

    _jpeg(tmp_path / "a.jpg", 1600, 900)
    _jpeg(tmp_path / "b.jpg", 1600, 900)
    images = Images(tmp_path, 64.0, max_side=800)
    assert len(images) == 0
    seen: list[Images] = []

    def probe(p: planning.PlanInputs, k: int) -> list[tuple[str, str]]:
        seen.append(p.images)
        return [("a.jpg", "b.jpg")]

    monkeypatch.setitem(planning.PLANNERS, "exhaustive", probe)
    request = PlanRequest("exhaustive")
    planning.plan(ProjectImages(tmp_path, ["a.jpg", "b.jpg"], {}, None), set(), request, decoded=images)
    assert seen and seen[0] is images
    assert seen[0]["a.jpg"].shape == (450, 800, 3)
