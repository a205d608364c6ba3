"""The survey report: built from a run's summary alone (older runs too), naming what a survey team
checks first: photos left out, GPS fixes far from the model, unused GCPs, the check-point RMSE."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest

from geomatch.cli import main
from geomatch.report import survey_report, to_markdown

pytestmark = pytest.mark.unit


def _summary() -> dict[str, Any]:
    per_image = [{"name": f"IMG_{i:02d}.JPG", "residual_m": 0.3 + 0.01 * i, "inlier": True} for i in range(9)]
    per_image.append({"name": "IMG_09.JPG", "residual_m": 14.2, "inlier": False})
    return {
        "registered": 10,
        "images": 11,
        "registered_names": [f"IMG_{i:02d}.JPG" for i in range(10)],
        "unregistered_names": ["IMG_10.JPG"],
        "points3D": 5000,
        "observations": 20000,
        "mean_track_length": 4.0,
        "mean_reprojection_error": 0.81234,
        "track_lengths": {"2": 1000, "3": 1500, "4": 1200, "5": 800, "6-10": 500, "11-20": 0, "21+": 0},
        "models": 1,
        "gps_images": 11,
        "georeferenced": True,
        "frame": "GCP",
        "alignment": {
            "correspondences": 10,
            "inliers": 9,
            "median_m": 0.35,
            "rmse_m": 0.4,
            "max_inlier_m": 0.9,
            "per_image": per_image,
        },
        "gcp": {
            "crs": "EPSG:32611",
            "points": [
                {
                    "name": "gcp01",
                    "role": "control",
                    "observations": 3,
                    "observations_registered": 3,
                    "reprojection_px": 0.8,
                    "dx_m": 0.1,
                    "dy_m": -0.2,
                    "dz_m": 0.3,
                    "horizontal_m": 0.224,
                    "3d_m": 0.374,
                },
                {
                    "name": "gcp02",
                    "role": "check",
                    "observations": 2,
                    "observations_registered": 2,
                    "reprojection_px": 1.1,
                    "dx_m": 0.5,
                    "dy_m": 0.0,
                    "dz_m": -0.4,
                    "horizontal_m": 0.5,
                    "3d_m": 0.64,
                },
                {
                    "name": "gcp03",
                    "role": "unused",
                    "observations": 1,
                    "observations_registered": 0,
                    "reason": "in 1 registered photo(s): a point needs two",
                },
            ],
            "check_rmse_horizontal_m": 0.5,
            "check_rmse_3d_m": 0.64,
        },
        "view_graph": {
            "pairs": 40,
            "loops": 12,
            "dropped": [{"pair": ["a", "b"], "broken_loops": 3, "loops": 4}],
            "tree_dropped": [],
        },
        "pairs": 45,
        "pair_plan": "gps:10",
        "tiled_pairs": 0,
        "database": {"verified_pairs": 41},
        "timings": {"plan": 1.0, "matching": 30.0, "mapping": 10.0, "total": 42.0},
        "mapping_seconds": {"mapper": 8.0},
    }


def test_the_report_names_what_a_survey_team_checks_first() -> None:
    r = survey_report(_summary())
    assert r["photos"]["unregistered"] == ["IMG_10.JPG"]
    # only the fix far from the rest is listed, not the nine within centimetres of the median
    assert [row["name"] for row in r["georeferencing"]["gps"]["largest"]] == ["IMG_09.JPG"]
    assert r["georeferencing"]["gcp"]["check_rmse_horizontal_m"] == 0.5
    assert r["pairs"]["dropped_by_view_graph"][0]["why"] == "3 of 4 loops broken"
    md = to_markdown(r)
    for text in (
        "registered: 10 of 11",
        "not registered: IMG_10.JPG",
        "IMG_09.JPG: 14.2 m (not used: outlier)",
        "check-point RMSE: 0.5 m horizontal, 0.64 m 3D",
        "| gcp03 | unused | 1 (0) |",
        "a point needs two",
        "| 6-10 |",
        "a x b: 3 of 4 loops broken",
    ):
        assert text in md, text


def test_photos_kept_out_of_the_model_on_purpose_are_named_with_why() -> None:
    """A camera whose pairs do not vouch for it and a block whose join was refused are not just
    'not registered': the team reads why each is missing."""
    s = {
        "registered": 4,
        "images": 7,
        "unregistered_names": ["a.jpg", "b.jpg", "c.jpg"],
        "unvouched_left_out": ["a.jpg"],
        "joins_refused": [
            {
                "via": "g2.jpg",
                "images": ["b.jpg", "c.jpg"],
                "reason": "only g2.jpg ties these cameras to the rest, and no pair of theirs checks it",
            }
        ],
    }
    r = survey_report(s)
    assert [o["name"] for o in r["photos"]["left_out"]] == ["a.jpg", "b.jpg", "c.jpg"]
    md = to_markdown(r)
    assert "a.jpg: left out, its own pairs do not vouch" in md
    assert "c.jpg: left out, joined to the model through g2.jpg only: only g2.jpg ties" in md
    assert survey_report({"registered": 3, "images": 3})["photos"]["left_out"] == []


def test_a_summary_without_gps_gcps_or_stages_still_reports() -> None:
    # an older run's summary, or a reconstruct job's, carries fewer keys
    r = survey_report({"registered": 3, "images": 3, "points3D": 10})
    md = to_markdown(r)
    assert "registered: 3 of 3" in md and "not georeferenced" in md and "Ground control" not in md


def test_geomatch_report_prints_a_runs_report_and_refuses_what_is_not_a_summary(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "summary.json").write_text(json.dumps(_summary()))
    assert main(["report", str(tmp_path)]) == 0
    assert "# Survey report" in capsys.readouterr().out
    assert main(["report", str(tmp_path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["photos"]["registered"] == 10
    (tmp_path / "other.json").write_text("[1, 2]")
    assert main(["report", str(tmp_path / "other.json")]) != 0
    assert "not the summary" in capsys.readouterr().err


FAILED_GCP_POINTS = [
    {
        "name": "gcp01",
        "role": "unused",
        "observations": 2,
        "observations_registered": 2,
        "reason": "its observations do not meet: 41.0 px from the point they place (> 5)",
        "reprojection_px": 41.0,
    },
    {
        "name": "gcp02",
        "role": "unused",
        "observations": 1,
        "observations_registered": 0,
        "reason": "seen in one",
    },
]


@pytest.mark.parametrize(
    "gcp",
    [
        # the documented case: clicks that do not meet leave fewer than 3 control points
        {"crs": "EPSG:32632", "points": FAILED_GCP_POINTS, "error": "1 control points placed in the model"},
        # a summary from before the points had one shape: bare names where the GCPs failed
        {"crs": "EPSG:32632", "points": ["gcp01", "gcp02"], "error": "1 control points placed in the model"},
        # the file no longer fits the project's images: no point at all
        {"error": "the project's GCP file: the GCP file leaves 0 usable points"},
        {"crs": "EPSG:32632", "points": [], "error": "no model to georeference"},
    ],
)
def test_every_gcp_outcome_renders_as_json_and_markdown(gcp: dict[str, Any]) -> None:
    r = survey_report({"registered": 3, "images": 3, "georeferenced": True, "frame": "ENU", "gcp": gcp})
    g = r["georeferencing"]["gcp"]
    assert g["error"] == gcp["error"]
    assert all(isinstance(p, dict) and p["role"] == "unused" and p["reason"] for p in g["points"]), g
    json.dumps(r, allow_nan=False)
    md = to_markdown(r)
    assert f"- not georeferenced by the GCPs: {gcp['error']}" in md
    rows = [line for line in md.splitlines() if line.startswith("| gcp")]
    assert len(rows) == len(gcp.get("points", [])), md
    assert all(row.count(" | ") == 7 for row in rows), rows  # eight cells, none broken
    section = md[md.index("### Ground control points") :]
    assert "None" not in section and "null" not in section, section


def test_names_from_clients_render_as_text_in_the_markdown() -> None:
    """Project, image and point names and a coordinate system as a client may send them: no HTML, no
    link, no broken table in the page, and each shows as its own characters once rendered."""
    hostile = [
        "<script>alert(1)</script>",
        "<img src=x onerror=alert(1)>.jpg",
        "[c](javascript:alert(1))",
        "a|b",
    ]
    summary = {
        "registered": 1,
        "images": 5,
        "unregistered_names": hostile,
        "georeferenced": False,
        "gcp": {
            "crs": "<b>EPSG:32632</b>",
            "error": "check points not among the usable GCPs: <i>x</i>",
            "points": [
                {
                    "name": n,
                    "role": "unused",
                    "observations": 2,
                    "observations_registered": 0,
                    "reason": f"r {n}",
                }
                for n in hostile
            ],
        },
    }
    md = to_markdown(survey_report(summary), title=f"Survey report: {hostile[0]}")
    assert not re.search(r"(?<!\\)[<>\[\]]", md), md  # every bracket escaped: no tag, no link
    assert "a|b" not in md
    rows = [line for line in md.splitlines() if line.startswith("| \\<") or line.startswith("| \\[")]
    rows += [line for line in md.splitlines() if line.startswith("| a\\|b")]
    assert len(rows) == len(hostile), md
    for row in rows:  # eight cells: the escaped pipes are not cell borders
        assert len([c for c in row.replace("\\|", "").split("|")]) == 10, row
    assert md.startswith("# Survey report: \\<script\\>alert(1)\\</script\\>\n"), md
    # once the escapes are read back (as a Markdown renderer does), the names are as sent
    assert f"- not registered: {', '.join(hostile)}" in md.replace("\\", "")
