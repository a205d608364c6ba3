from __future__ import annotations

import pytest
import torch

from geomatch import Matcher, MatcherConfig
from geomatch.synth.photos import WarpedPair, warped_pair

torch.set_num_threads(2)


@pytest.fixture(scope="session")
def matcher() -> Matcher:
    """One set of real networks for the whole session (weights load once)."""
    return Matcher(MatcherConfig(resize=480, device="cpu"))


@pytest.fixture(scope="session")
def astronaut_pair() -> WarpedPair:
    return warped_pair("astronaut", seed=1, strength=0.15)
