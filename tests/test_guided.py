"""The guided matcher's mutual nearest neighbours: a row's best is kept only when it is also its
column's best, and a column claimed by two equal rows goes to one of them only."""

from __future__ import annotations

import pytest
import torch

from geomatch.matching import guided
from geomatch.matching.guided import mutual_ratio

pytestmark = pytest.mark.unit


def reference(da: torch.Tensor, db: torch.Tensor, ratio: float) -> set[tuple[int, int]]:
    """Mutual nearest neighbours with the ratio test, one pair at a time."""
    s = da @ db.T
    out = set()
    for i in range(s.shape[0]):
        top = s[i].topk(2)
        j = int(top.indices[0])
        if int(s[:, j].argmax()) == i and top.values[0] > 0 and top.values[1] < ratio * top.values[0]:
            out.add((i, j))
    return out


def unit(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(n, 16, generator=g), dim=1)


@pytest.mark.parametrize("block_bytes", [64 * 2**20, 4 * 40])  # one block; blocks of 4 rows
def test_mutual_neighbours_match_a_pair_by_pair_reference(
    block_bytes: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(guided, "CPU_BLOCK_BYTES", block_bytes)
    monkeypatch.setattr(guided, "BLOCK_BYTES", block_bytes)
    db = unit(40, 1)
    # half of A are noisy copies of B's points, so many mutual pairs exist
    da = torch.nn.functional.normalize(torch.cat([db[:30] + 0.1 * unit(30, 2), unit(30, 3)]), dim=1)
    ia, ib, sim = mutual_ratio(da, db, 0.95)
    got = set(zip(ia.tolist(), ib.tolist(), strict=True))
    assert got == reference(da, db, 0.95)
    assert len(got) >= 20
    assert torch.allclose(sim, (da[ia] * db[ib]).sum(1))


def test_two_identical_rows_do_not_both_take_one_column() -> None:
    db = unit(10, 4)
    da = torch.cat([db[:5], db[2:3]])  # rows 2 and 5 are the same descriptor
    _, ib, _ = mutual_ratio(da, db, 0.99)
    assert ib.tolist().count(2) == 1
    assert len(set(ib.tolist())) == len(ib)
