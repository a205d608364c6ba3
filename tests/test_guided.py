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


@pytest.mark.parametrize("low", [False, True])  # float32 throughout; bfloat16 blocks where the CPU has them
@pytest.mark.parametrize("block_bytes", [64 * 2**20, 4 * 40])  # one block; blocks of 4 rows
def test_mutual_neighbours_match_a_pair_by_pair_reference(
    block_bytes: int, low: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(guided, "LOW_PRECISION", low)
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


@pytest.mark.parametrize("low", [False, True])
def test_two_identical_rows_do_not_both_take_one_column(low: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(guided, "LOW_PRECISION", low)
    db = unit(10, 4)
    da = torch.cat([db[:5], db[2:3]])  # rows 2 and 5 are the same descriptor
    _, ib, _ = mutual_ratio(da, db, 0.99)
    assert ib.tolist().count(2) == 1
    assert len(set(ib.tolist())) == len(ib)


@pytest.mark.skipif(not guided._cpu_bf16(), reason="this CPU has no bfloat16 units: float32 is used")
def test_bfloat16_blocks_keep_float32s_matches_on_survey_sized_sets(monkeypatch: pytest.MonkeyPatch) -> None:
    """4096 x 4096 128-d descriptors, noisy copies: the rounded product may let through only a pair
    whose column has another row within its rounding, and the ratio test and similarities are
    float32's."""
    g = torch.Generator().manual_seed(7)
    db = torch.nn.functional.normalize(torch.randn(4096, 128, generator=g), dim=1)
    da = torch.nn.functional.normalize(db + 0.5 * torch.randn(4096, 128, generator=g), dim=1)
    monkeypatch.setattr(guided, "LOW_PRECISION", False)
    ea, eb, _ = mutual_ratio(da, db, 0.9)
    monkeypatch.setattr(guided, "LOW_PRECISION", True)
    la, lb, sim = mutual_ratio(da, db, 0.9)
    exact = set(zip(ea.tolist(), eb.tolist(), strict=True))
    low = set(zip(la.tolist(), lb.tolist(), strict=True))
    assert len(exact) > 500
    assert len(exact - low) <= len(exact) // 100
    assert len(low - exact) <= len(exact) // 50
    s = da @ db.T
    for i, j in low - exact:
        assert s[:, j].max() - s[i, j] < 0.01
    assert torch.allclose(sim, (da[la] * db[lb]).sum(1), atol=1e-6)
