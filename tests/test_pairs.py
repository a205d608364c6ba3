from __future__ import annotations

import numpy as np
import pytest

from geomatch.metadata import ImageMeta, read_metadata
from geomatch.options import PairSpecError, parse_plan, parse_spec
from geomatch.pipeline import pair_sources as pairs
from geomatch.pipeline.aerial import aerial_set, captures
from geomatch.pipeline.retrieval import vlad
from geomatch.synth.aerial import write_scene

pytestmark = pytest.mark.unit

NAMES = ["a0.jpg", "a1.jpg", "g0.jpg", "g1.jpg", "g2.jpg"]


def test_specs() -> None:
    assert parse_spec("exhaustive") == ("exhaustive", 0)
    assert parse_spec("sequential:3") == ("sequential", 3)
    assert parse_spec("retrieval:10") == ("retrieval", 10)
    for bad in ("exhaustive:2", "sequential", "retrieval:0", "nearest:3", ""):
        with pytest.raises(PairSpecError):
            parse_spec(bad)
    assert len(pairs.exhaustive(NAMES)) == 10
    assert pairs.sequential(NAMES, 2) == [
        ("a0.jpg", "a1.jpg"),
        ("a0.jpg", "g0.jpg"),
        ("a1.jpg", "g0.jpg"),
        ("a1.jpg", "g1.jpg"),
        ("g0.jpg", "g1.jpg"),
        ("g0.jpg", "g2.jpg"),
        ("g1.jpg", "g2.jpg"),
    ]


def test_explicit_pairs_are_checked() -> None:
    assert pairs.explicit([["a0.jpg", "g1.jpg"]], NAMES) == [("a0.jpg", "g1.jpg")]
    with pytest.raises(PairSpecError, match="not among the images"):
        pairs.explicit([["a0.jpg", "nope.jpg"]], NAMES)
    with pytest.raises(PairSpecError, match="itself"):
        pairs.explicit([["a0.jpg", "a0.jpg"]], NAMES)
    assert pairs.read_pairs_file("# comment\na0.jpg g0.jpg\n\ng1.jpg g2.jpg\n") == [
        ["a0.jpg", "g0.jpg"],
        ["g1.jpg", "g2.jpg"],
    ]


def test_tiling_marks_aerial_x_ground_only() -> None:
    aerial = {"a0.jpg", "a1.jpg"}
    out = pairs.finalize(
        [("a0.jpg", "a1.jpg"), ("g0.jpg", "a1.jpg"), ("a1.jpg", "g0.jpg"), ("g0.jpg", "g1.jpg")], aerial
    )
    assert [(p.key, p.tiled, p.aerial_first) for p in out] == [
        (("a0.jpg", "a1.jpg"), False, True),
        (("g0.jpg", "a1.jpg"), True, False),  # duplicate in the other order dropped
        (("g0.jpg", "g1.jpg"), False, True),
    ]
    assert not any(p.tiled for p in pairs.finalize([("g0.jpg", "a1.jpg")], aerial, "off"))
    assert all(p.tiled for p in pairs.finalize([("g0.jpg", "g1.jpg")], aerial, "on"))


def test_retrieval_ranks_by_global_descriptor() -> None:
    rng = np.random.default_rng(0)
    centres = rng.normal(size=(2, 8, 16))  # two "places", each with its own descriptor distribution
    local = []
    for i in range(6):
        place = centres[i % 2]
        d = place[rng.integers(0, 8, 300)] + 0.1 * rng.normal(size=(300, 16))
        local.append(d / np.linalg.norm(d, axis=1, keepdims=True))
    g = vlad(local, words=8)
    nn = pairs.nearest_neighbours(g, [f"i{i}" for i in range(6)], k=2)
    assert all(int(a[1]) % 2 == int(b[1]) % 2 for a, b in nn)  # neighbours are from the same place
    cross = pairs.cross_view(NAMES, {"a0.jpg", "a1.jpg"})
    assert len(cross) == 6


def test_aerial_from_synthetic_exif_and_xmp(tmp_path) -> None:
    cams = write_scene(tmp_path, 2, 2, seed=3, size=(96, 72))
    names = [c.name for c in cams]
    metas = {n: read_metadata(tmp_path / "images" / n) for n in names}
    for c in cams:
        m = metas[c.name]
        assert m.focal_px == pytest.approx(c.K[0, 0])
        assert m.aerial_hint is (True if c.aerial else None)
        assert m.model == ("synth-drone" if c.aerial else "synth-handheld")
    inferred = aerial_set(captures(names), metas)
    assert inferred == {c.name for c in cams if c.aerial}
    glob = captures(names, aerial_glob="ground_0*")
    assert aerial_set(glob, metas) == {"ground_00.png", "ground_01.png"}
    assert aerial_set(captures(names, aerial_names=["ground_00.png"]), {}) == {"ground_00.png"}
    with pytest.raises(ValueError, match="not in the folder"):
        captures(names, aerial_names=["x.png"])
    # the rules: relative altitude decides, else gimbal pitch
    assert ImageMeta(1, 1, relative_altitude_m=3.0, gimbal_pitch_deg=-90).aerial_hint is False
    assert ImageMeta(1, 1, gimbal_pitch_deg=-45).aerial_hint is True
    assert ImageMeta(1, 1, gimbal_pitch_deg=-5).aerial_hint is False


@pytest.mark.unit
def test_auto_plans_exhaustive_for_a_small_project_and_gps_neighbours_for_a_located_flight() -> None:
    few = [f"{i:03d}.jpg" for i in range(pairs.AUTO_EXHAUSTIVE_MAX)]
    many = [f"{i:03d}.jpg" for i in range(pairs.AUTO_EXHAUSTIVE_MAX + 1)]
    located = {n: np.array([i * 5.0, 0.0, 0.0]) for i, n in enumerate(many)}
    assert pairs.auto_pairs(few, {})[1] == "exhaustive"
    raw, plan = pairs.auto_pairs(many, located)
    assert plan == f"gps:{pairs.AUTO_GPS_K}" and len(raw) < len(pairs.exhaustive(many)) / 2
    half = {n: located[n] for n in many[: len(many) // 2]}
    assert pairs.auto_pairs(many, half)[1] == "exhaustive"  # most without a fix
    assert parse_plan("auto") == [("auto", 0)]
    with pytest.raises(PairSpecError, match="auto stands alone"):
        parse_plan("auto+gps:3")


@pytest.mark.unit
def test_known_turns_are_relative_and_leave_tiled_pairs_to_their_probe() -> None:
    plan = pairs.finalize([("a", "b"), ("b", "c"), ("a", "g"), ("c", "d")], {"a", "b", "c", "d"})
    turned = {p.key: p for p in pairs.with_turns(plan, {"a": 0, "b": 2, "c": 3})}
    assert turned[("a", "b")].turns == (0, 2)
    assert turned[("b", "c")].turns == (2, 3)
    assert turned[("a", "g")].tiled and turned[("a", "g")].turns is None
    assert turned[("c", "d")].turns is None and turned[("c", "d")].rotate  # d undecided: probed


@pytest.mark.unit
def test_auto_leaves_out_small_pairs_whose_footprints_do_not_meet() -> None:
    names = [f"{i}.jpg" for i in range(6)]
    enu = {n: np.array([i * 40.0, 0.0, 50.0]) for i, n in enumerate(names)}
    square = np.array([[-30.0, -30.0], [30.0, -30.0], [30.0, 30.0], [-30.0, 30.0]])
    footprints = {n: square + enu[n][:2] for n in names}  # 60 m wide, 40 m apart: neighbours meet
    raw, plan = pairs.auto_pairs(names, enu, footprints)
    assert plan.startswith("footprints")
    assert ("0.jpg", "1.jpg") in raw and ("0.jpg", "5.jpg") not in raw
    # every image keeps its nearest partners however little they share
    assert all(sum(n in p for p in raw) >= pairs.AUTO_NEAREST for n in names)


def test_the_plan_records_what_each_pair_is_matched_by() -> None:
    """Tiling, turns and the project's kind are the pair's fields, kept in plan.json whole."""
    from geomatch.pipeline.match_pairs import pair_matcher
    from geomatch.pipeline.plan import Plan

    mixed = pairs.finalize([("a", "g"), ("g", "h")], {"a"}, "auto")
    assert [(p.tiled, p.aerial_project, p.survey) for p in mixed] == [
        (True, True, False),
        (False, True, False),
    ]
    survey = pairs.with_turns(pairs.finalize([("a", "b")], {"a", "b"}, "auto", survey=True), {"a": 1, "b": 3})
    assert survey[0].turns == (1, 3) and survey[0].survey and survey[0].aerial_project
    ground = pairs.finalize([("g", "h")], set(), "auto")
    assert not ground[0].aerial_project
    plan = Plan(mixed + survey, ["a", "b"], "exhaustive", False)
    again = Plan.from_json(plan.to_json())
    assert [(p.key, p.tiled, p.aerial_first, p.rotate, p.turns) for p in again.pairs] == [
        (p.key, p.tiled, p.aerial_first, p.rotate, p.turns) for p in plan.pairs
    ]
    assert again.tiled and again.summary_fields()["tiled_pairs"] == 1
    # under auto the fields choose the pair's matcher: geo for a mixed project's pairs, the light
    # anchors for a ground-only project's
    from geomatch.matching.matcher import Matcher

    m = Matcher(method="auto")
    assert pair_matcher(m, mixed[1]).config.method == "geo"
    assert pair_matcher(m, ground[0]).config.method == "sparse"


def test_the_tiled_images_are_the_aerial_sides_of_tiled_pairs_only() -> None:
    """What a join of two models may rest on alone: an aerial image matched by crops against a
    ground photo, on whichever side of the pair it is; not an aerial image only ever paired with
    other aerial images, and nothing when tiling is off."""
    from geomatch.pipeline.plan import Plan

    aerial = {"a0", "a1", "a2"}
    planned = pairs.finalize([("g0", "a1"), ("a0", "g1"), ("a1", "a2"), ("g0", "g1")], aerial, "auto")
    assert Plan(planned, sorted(aerial), "exhaustive", False).tiled_images == ("a0", "a1")
    untiled = pairs.finalize([("g0", "a1"), ("a0", "g1")], aerial, "off")
    assert Plan(untiled, sorted(aerial), "exhaustive", False).tiled_images == ()
