"""The node's pure parts, without a server: its options as WebODM reads them and a task's options
as WebODM and PyODM send them, the status and progress of a task's jobs, the token's redaction."""

from __future__ import annotations

import json
from datetime import UTC, datetime, timedelta

import pytest

from geomatch.options import OPTIONS, PROJECT_OPTIONS
from geomatch_core.errors import InvalidRequest, NotFound
from service.nodeodm.app import redacted
from service.nodeodm.options import NODE_DEFAULTS, node_options, parse_options
from service.nodeodm.tasks import (
    CANCELED,
    COMPLETED,
    FAILED,
    QUEUED,
    RUNNING,
    Cycle,
    project_of,
    task_status,
    task_uuid,
)
from service.usecases.views import JobView

pytestmark = pytest.mark.unit
T0 = datetime(2026, 1, 1, tzinfo=UTC)


def test_every_project_option_is_offered_with_nodeodms_five_keys() -> None:
    listed = {o["name"]: o for o in node_options()}
    assert all(set(o) == {"name", "type", "value", "domain", "help"} for o in listed.values())
    for name in PROJECT_OPTIONS:  # a new option of the table appears here without an edit
        o = listed[name.replace("_", "-")]
        assert o["value"] == str(NODE_DEFAULTS.get(name, OPTIONS[name].default))
        assert (o["type"] == "enum") == bool(OPTIONS[name].choices)
        assert o["domain"] == list(OPTIONS[name].choices) or not OPTIONS[name].choices
    assert "checkpoints" in listed
    assert listed["ortho"]["value"] == "on"  # WebODM shows a task's map first: made unless told off


def test_task_options_drop_unknown_names_and_take_text_values() -> None:
    sent = [
        {"name": "resize", "value": "480"},
        {"name": "snap-radius", "value": 2},
        {"name": "orthophoto-resolution", "value": 5},  # ODM's: dropped
        {"name": "checkpoints", "value": "gcp01, gcp03"},
    ]
    opts = parse_options(json.dumps(sent))
    assert opts.project == {"resize": 480, "snap_radius": 2.0, "ortho": "on"}
    assert opts.checkpoints == ["gcp01", "gcp03"]
    assert [o["name"] for o in opts.given] == ["resize", "snap-radius", "checkpoints"]
    assert parse_options(json.dumps({"mapper": "global"})).project == {"mapper": "global", "ortho": "on"}
    assert parse_options(json.dumps({"ortho": "off", "ortho-gsd": "0.05"})).project == {
        "ortho": "off",
        "ortho_gsd": 0.05,
    }
    assert (
        parse_options(None).project == {"ortho": "on"}
        and parse_options('[{"name": "checkpoints", "value": 2}]').checkpoints == 2
    )


@pytest.mark.parametrize(
    "bad",
    ['[{"name": "resize", "value": 5}]', '[{"name": "method", "value": "magic"}]', "not json", '[{"x": 1}]'],
)
def test_a_known_option_with_a_bad_value_is_refused(bad: str) -> None:
    with pytest.raises(InvalidRequest):
        parse_options(bad)


def test_task_uuid_is_the_project_id_in_either_spelling() -> None:
    pid = "0123456789abcdef0123456789abcdef"
    assert task_uuid(pid) == "01234567-89ab-cdef-0123-456789abcdef"
    assert project_of(task_uuid(pid)) == project_of(pid) == pid
    with pytest.raises(NotFound):
        project_of("../etc/passwd")


def _job(kind: str, state: str, done: int = 0, total: int = 0, minutes: int = 0) -> JobView:
    started = T0 if state != "queued" else None
    finished = T0 + timedelta(minutes=minutes) if state in ("succeeded", "failed", "cancelled") else None
    return JobView(kind + state, "p", kind, state, done, total, None, {}, None, None, T0, started, finished)


def test_status_and_progress_follow_the_jobs_and_never_go_back() -> None:
    steps = [
        (Cycle(_job("match", "queued"), _job("reconstruct", "queued")), QUEUED),
        (Cycle(_job("match", "running", 0, 10), _job("reconstruct", "queued")), RUNNING),
        (Cycle(_job("match", "running", 5, 10), _job("reconstruct", "queued")), RUNNING),
        (Cycle(_job("match", "succeeded", 10, 10, 1), _job("reconstruct", "queued")), RUNNING),
        (Cycle(_job("match", "succeeded", 10, 10, 1), _job("reconstruct", "running")), RUNNING),
        (Cycle(_job("match", "succeeded", 10, 10, 1), _job("reconstruct", "succeeded", 1, 1, 2)), COMPLETED),
    ]
    progress = []
    for cycle, code in steps:
        got, error, p, _ = task_status(cycle)
        assert got == code and error is None
        progress.append(p)
    assert progress == sorted(progress) and progress[-1] == 100 and progress[0] == 0
    assert task_status(steps[-1][0])[3] == 2 * 60 * 1000  # processing time: start of matching to the end
    failed = task_status(Cycle(_job("match", "failed", 3, 10, 1), _job("reconstruct", "cancelled")))
    assert failed[0] == FAILED and failed[1] is not None and failed[1].startswith("matching failed")
    assert (
        task_status(Cycle(_job("match", "cancelled", 3, 10, 1), _job("reconstruct", "cancelled")))[0]
        == CANCELED
    )
    assert task_status(None)[0] == QUEUED


def test_the_token_is_redacted_from_what_is_logged() -> None:
    assert redacted("with_output=3&token=gm_secret&x=1") == "with_output=3&token=***&x=1"
    assert redacted("TOKEN=gm_secret") == "TOKEN=***"
