"""Every in-memory cache of a job is bounded in bytes by one setting (GEOMATCH_CACHE_MB)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from geomatch.imagefolder import Images
from geomatch.matching.matcher import MatcherConfig
from geomatch.memory import ByteLRU, cache_budget
from geomatch.options import OptionError

pytestmark = pytest.mark.unit

MB = 2**20


def test_byte_lru_forgets_the_least_recently_used_beyond_its_budget() -> None:
    lru: ByteLRU[str, np.ndarray] = ByteLRU(2.5)
    for k in "abc":
        lru.put(k, np.zeros(MB, np.uint8))
    assert "a" not in lru and len(lru) == 2 and lru.nbytes() == 2 * MB
    assert lru.get("b") is not None  # b is now the most recent: d pushes c out
    lru.put("d", np.zeros(MB, np.uint8))
    assert "c" not in lru and "b" in lru and "d" in lru
    lru.put("b", np.zeros(MB // 2, np.uint8))  # replacing an entry counts its new size only
    assert lru.nbytes() == MB + MB // 2


def test_byte_lru_keeps_the_newest_entry_even_over_budget() -> None:
    lru: ByteLRU[str, np.ndarray] = ByteLRU(1.0)
    lru.put("small", np.zeros(10, np.uint8))
    lru.put("big", np.zeros(3 * MB, np.uint8))
    assert len(lru) == 1 and "big" in lru


def test_emptied_caches_go_back_to_the_system_before_mapping() -> None:
    """The mapper's peak must not land on caches a finished stage no longer needs: emptied, a
    cache counts nothing, and on glibc the heap pages those caches held are handed back."""
    import platform

    from geomatch.memory import return_freed_memory

    lru: ByteLRU[str, np.ndarray] = ByteLRU(64.0)
    for k in "abcd":
        lru.put(k, np.ones(4 * MB, np.uint8))
    lru.clear()
    assert len(lru) == 0 and lru.nbytes() == 0 and lru.get("a") is None
    trimmed = return_freed_memory()
    assert trimmed or platform.libc_ver()[0] != "glibc"


def test_cache_budget_default_is_the_matchers_own_and_follows_the_environment(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv("GEOMATCH_CACHE_MB", raising=False)
    b = cache_budget()
    assert (b.images_mb, b.features_mb, b.anchors_mb) == (256, 1024, 256)
    cfg = MatcherConfig()
    assert (cfg.cache_features_mb, cfg.cache_anchors_mb) == (b.features_mb, b.anchors_mb)
    monkeypatch.setenv("GEOMATCH_CACHE_MB", "768")
    b = cache_budget()
    assert b.images_mb + b.features_mb + b.anchors_mb == pytest.approx(768)
    two = cache_budget(768, matchers=2)
    assert two.images_mb == b.images_mb and two.features_mb == pytest.approx(b.features_mb / 2)
    monkeypatch.setenv("GEOMATCH_CACHE_MB", "lots")
    with pytest.raises(OptionError, match="GEOMATCH_CACHE_MB"):
        cache_budget()


def test_pipeline_images_are_bounded_in_bytes(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    for i in range(5):  # 1 MB each once decoded (512 x 683 x 3)
        Image.fromarray(rng.integers(0, 255, (512, 683, 3), np.uint8)).save(tmp_path / f"{i}.png")
    images = Images(tmp_path, budget_mb=2.5)
    first = images["0.png"]
    for i in range(5):
        assert images[f"{i}.png"].shape == (512, 683, 3)
    assert images.nbytes() <= 2.5 * MB and len(images) == 2
    assert images["0.png"] is not first  # evicted, decoded again
