from __future__ import annotations

import pytest
import torch

from geomatch import Matcher, MatcherConfig
from geomatch.synth.photos import WarpedPair, warped_pair

torch.set_num_threads(2)

TIERS = ("unit", "nets", "pipeline", "service", "browser", "chaos")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """A test without a tier would silently drop out of `make test-fast` or be run where it does not
    belong; one with two would be counted twice by anyone timing the tiers."""
    wrong = []
    for item in items:
        tiers = sorted({m.name for m in item.iter_markers() if m.name in TIERS})
        if len(tiers) != 1:
            wrong.append(f"{item.nodeid}: {', '.join(tiers) or 'no tier'}")
    if wrong:
        raise pytest.UsageError(
            "every test needs exactly one tier marker (" + ", ".join(TIERS) + "):\n" + "\n".join(wrong)
        )


@pytest.fixture(scope="session")
def matcher() -> Matcher:
    """One set of real networks for the whole session (weights load once)."""
    return Matcher(MatcherConfig(resize=480, device="cpu"))


@pytest.fixture(scope="session")
def astronaut_pair() -> WarpedPair:
    return warped_pair("astronaut", seed=1, strength=0.15)
