"""The pair kinds are one table (``options.PAIR_KINDS``): every place that plans, counts or names
them derives from it or agrees with it, so a new kind is a row and a planner, and a copy that
forgets one fails here."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from geomatch import options
from geomatch.imagefolder import Images
from geomatch.options import PAIR_KIND, PAIR_KINDS, PAIR_SPEC_LIST, fewest_pairs, parse_plan
from geomatch.pipeline import plan as planning
from geomatch.pipeline.project import PlanRequest, ProjectImages

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.unit


def test_every_kind_that_plans_by_itself_has_a_planner() -> None:
    assert set(planning.PLANNERS) | {"auto"} == set(PAIR_KIND)
    assert "auto" not in planning.PLANNERS  # auto chooses between the others (pairs.auto_pairs)


def test_the_grammar_reads_every_kind_as_the_table_spells_it() -> None:
    for kind in PAIR_KINDS:
        spec = f"{kind.name}:3" if kind.takes_k else kind.name
        assert parse_plan(spec) == [(kind.name, 3 if kind.takes_k else 0)]
        with pytest.raises(options.PairSpecError):
            parse_plan(kind.name if kind.takes_k else f"{kind.name}:3")
    with_k = [k.name for k in PAIR_KINDS if k.takes_k]
    assert parse_plan("+".join(f"{n}:2" for n in with_k)) == [(n, 2) for n in with_k]
    for alone in (k.name for k in PAIR_KINDS if not k.takes_k):
        with pytest.raises(options.PairSpecError, match="stands alone"):
            parse_plan(f"{alone}+{with_k[0]}:2")


def plan_inputs(names: list[str], kinds: set[str]) -> planning.PlanInputs:
    rng = np.random.default_rng(0)
    enu = {n: rng.normal(size=3) * 50 for n in names}
    return planning.PlanInputs(names, kinds, set(), enu, None, None, Images(ROOT), False)


@pytest.mark.parametrize("n", [2, 3, 5, 9])
@pytest.mark.parametrize("k", [1, 2, 4, 20])
def test_the_plan_size_arithmetic_is_what_the_planners_plan(n: int, k: int) -> None:
    """``fewest`` is exact where the table says so, a floor elsewhere (retrieval needs networks:
    its floor is the same k-nearest arithmetic as gps, whose planner runs here)."""
    names = [f"{i:02d}.jpg" for i in range(n)]
    for kind in PAIR_KINDS:
        if kind.name not in planning.PLANNERS or kind.needs_matcher:
            continue
        planned = {tuple(sorted(p)) for p in planning.PLANNERS[kind.name](plan_inputs(names, {kind.name}), k)}
        fewest, exact = fewest_pairs(f"{kind.name}:{k}" if kind.takes_k else kind.name, n)
        assert exact == kind.exact
        assert (len(planned) == fewest) if exact else (len(planned) >= fewest), (kind.name, n, k)


def test_the_proto_and_the_console_list_every_kind() -> None:
    proto = (ROOT / "proto" / "geomatch" / "v1" / "geomatch.proto").read_text()
    listing = [line for line in proto.splitlines() if "//" in line and "exhaustive" in line]
    assert listing, "the proto no longer lists the pair kinds in a comment"
    for line in listing:
        assert PAIR_SPEC_LIST in line, line
    page = (ROOT / "service" / "http" / "console" / "static" / "index.html").read_text()
    hint = re.search(r'<input id="pairs" placeholder="([^"]*)"', page)
    assert hint is not None and hint.group(1) == PAIR_SPEC_LIST


@pytest.mark.parametrize("doc", ["README.md", "docs/pipeline.md", "docs/service.md"])
def test_docs_that_list_the_kinds_list_all_of_them(doc: str) -> None:
    """A paragraph naming all kinds but one in backticks is a listing: it names every one."""
    spellings = {k.name: f"`{k.name}:K`" if k.takes_k else f"`{k.name}`" for k in PAIR_KINDS}
    for para in re.split(r"\n\s*\n", (ROOT / doc).read_text()):
        named = {n for n, s in spellings.items() if s in para}
        if len(named) >= len(spellings) - 1:
            assert named == set(spellings), (
                f"{doc}: names {sorted(named)}, not {sorted(spellings)}:\n{para[:300]}"
            )


def test_a_new_kind_is_a_row_and_a_planner(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """``every:K``, each image with every K-th after it by name: one row and one planner, and the
    grammar (alone and in a union), the plan-size arithmetic, the REST pattern and the plan take it."""
    from service.http.schemas import pair_spec_pattern

    def every(names: list[str], k: int) -> list[tuple[str, str]]:
        return [(a, b) for i, a in enumerate(names) for b in names[i + k :: k]]

    row = options.PairKind("every", True, "each image with every K-th after it", lambda n, k: 0, False)
    monkeypatch.setitem(PAIR_KIND, "every", row)
    monkeypatch.setitem(planning.PLANNERS, "every", lambda p, k: every(p.names, k))

    assert parse_plan("every:2+gps:3") == [("every", 2), ("gps", 3)]
    assert fewest_pairs("every:2", 6) == (0, False)
    assert not options.plan_needs_matcher("every:2")
    assert re.fullmatch(pair_spec_pattern((*PAIR_KINDS, row)), "every:2 + gps:3")
    names = [f"{i}.png" for i in range(6)]
    planned = planning.plan(ProjectImages(tmp_path, names, {}, None), set(), PlanRequest("every:2"))
    assert {p.key for p in planned} == set(every(names, 2))
