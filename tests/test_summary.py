"""summary.json's fields are one record (geomatch.pipeline.summary.Summary): the fields the console
and the report read are fields a writer gives, and a run writes no field the record lacks."""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path

import pytest

from geomatch.pipeline.summary import FIELDS

ROOT = Path(__file__).resolve().parents[1]
CONSOLE = ROOT / "service" / "http" / "console" / "static"


def console_fields() -> set[str]:
    """The fields the console reads of a model's summary (``summary.NAME``): the model card
    (app.js) and its GCP line (gcp.js's describeGcp; the rest of gcp.js reads the GCP file's own
    summary, another record)."""
    gcp = (CONSOLE / "gcp.js").read_text()
    text = (CONSOLE / "app.js").read_text() + gcp[gcp.index("export function describeGcp") :]
    return set(re.findall(r"\bsummary\.([A-Za-z_][A-Za-z0-9_]*)", text))


def report_fields() -> set[str]:
    """The fields geomatch.report reads of a summary: ``s.get("NAME")`` and ``s["NAME"]``."""
    tree = ast.parse((ROOT / "geomatch" / "report.py").read_text())
    out: set[str] = set()
    for node in ast.walk(tree):
        key = None
        if isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name) and node.value.id == "s":
            key = node.slice
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "get"
            and isinstance(node.func.value, ast.Name)
            and node.func.value.id == "s"
            and node.args
        ):
            key = node.args[0]
        if isinstance(key, ast.Constant) and isinstance(key.value, str):
            out.add(key.value)
    return out


@pytest.mark.unit
def test_what_the_console_and_the_report_read_is_in_the_record() -> None:
    console, report = console_fields(), report_fields()
    assert {"registered", "images", "points3D", "registered_names"} <= console  # the parse finds them
    assert {"registered", "timings"} <= report
    assert console - FIELDS == set(), "the console reads fields no summary has"
    assert report - FIELDS == set(), "geomatch.report reads fields no summary has"


@pytest.mark.pipeline
def test_a_run_writes_the_record_once(small_run: Path) -> None:
    summary = json.loads((small_run / "summary.json").read_text())
    assert set(summary) - FIELDS == set(), "fields the record lacks"
    assert {"mapping_settings", "pairs", "tiled_pairs", "pair_plan", "report"} <= set(summary)
    plan = json.loads((small_run / "plan.json").read_text())
    assert len(plan["pairs"]) == summary["pairs"]
    assert sum(p["tiled"] for p in plan["pairs"]) == summary["tiled_pairs"]
    assert summary["mapping_settings"]["tiled"] is (summary["tiled_pairs"] > 0)
