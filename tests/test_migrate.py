"""A metadata database made before a column was added gets it, with the value its old rows would
have had, when the service or a worker starts (``MetadataStore.create_all``)."""

from __future__ import annotations

from pathlib import Path

import pytest
from sqlalchemy import select, text
from sqlalchemy.orm import Session

from geomatch_core.migrate import add_missing_columns
from geomatch_core.models import Image, Job, JobPair, Project, Tenant
from geomatch_core.store import MetadataStore

pytestmark = pytest.mark.unit


def _project(s: Session) -> Project:
    """A tenant's project in the store, flushed (its id known)."""
    tenant = Tenant(name="t")
    s.add(tenant)
    s.flush()
    project = Project(tenant_id=tenant.id, name="p")
    s.add(project)
    s.flush()
    return project


def test_job_pairs_get_rotate_and_their_project_from_the_aerial_images(tmp_path: Path) -> None:
    store = MetadataStore(f"sqlite:///{tmp_path / 'meta.sqlite'}")
    store.create_all()
    with store.engine.begin() as c:  # the table as a release before the columns made it
        for column in ("rotate", "turn0", "turn1", "aerial_project", "survey"):
            c.execute(text(f"ALTER TABLE job_pairs DROP COLUMN {column}"))
    with store.session() as s:
        project = _project(s)
        s.add_all(
            Image(
                project_id=project.id,
                name=name,
                sha256=name,
                width=8,
                height=8,
                size_bytes=1,
                format="png",
                capture="auto",
                aerial=name == "air",
            )
            for name in ("air", "g1", "g2")
        )
        job = Job(project_id=project.id, tenant_id=project.tenant_id, kind="match")
        s.add(job)
        s.flush()
        job_id = job.id
    with store.engine.begin() as c:
        for idx, (a, b, done) in enumerate((("g1", "air", 0), ("g1", "g2", 0), ("air", "g2", 1))):
            c.execute(
                text(
                    "INSERT INTO job_pairs (job_id, idx, name0, name1, tiled, aerial_first, done) "
                    "VALUES (:j, :i, :a, :b, 0, 1, :d)"
                ),
                {"j": job_id, "i": idx, "a": a, "b": b, "d": done},
            )
    store.create_all()
    with store.session() as s:
        rotate = dict(s.execute(select(JobPair.idx, JobPair.rotate).order_by(JobPair.idx)).all())
    assert rotate == {0: True, 1: False, 2: False}  # a pair done already is never matched again
    with store.session() as s:
        rows = s.execute(select(JobPair.turn0, JobPair.turn1, JobPair.aerial_project, JobPair.survey)).all()
    # planned before the plan decided turns: each pair probes its own; the project has an aerial
    # image (a pair done already is never matched again) and ground ones: no survey
    assert sorted(rows) == [(-1, -1, False, False), (-1, -1, True, False), (-1, -1, True, False)]
    assert add_missing_columns(store.engine) == []  # there now: nothing to add
    store.dispose()


def test_turns_stored_as_one_column_come_apart(tmp_path: Path) -> None:
    """Pairs planned while a survey pair's turns were one column (4 * turn0 + turn1) keep them."""
    store = MetadataStore(f"sqlite:///{tmp_path / 'meta.sqlite'}")
    store.create_all()
    with store.engine.begin() as c:
        c.execute(text("ALTER TABLE job_pairs DROP COLUMN turn0"))
        c.execute(text("ALTER TABLE job_pairs DROP COLUMN turn1"))
        c.execute(text("ALTER TABLE job_pairs ADD COLUMN turn INTEGER NOT NULL DEFAULT -1"))
    with store.session() as s:
        project = _project(s)
        job = Job(project_id=project.id, tenant_id=project.tenant_id, kind="match")
        s.add(job)
        s.flush()
        job_id = job.id
    with store.engine.begin() as c:
        for idx, turn in enumerate((-1, 0, 7, 14)):
            c.execute(
                text(
                    "INSERT INTO job_pairs (job_id, idx, name0, name1, tiled, aerial_first, rotate, turn, "
                    "done, aerial_project, survey) VALUES (:j, :i, 'a', 'b', 0, 1, 1, :t, 0, 1, 1)"
                ),
                {"j": job_id, "i": idx, "t": turn},
            )
    assert add_missing_columns(store.engine) == ["job_pairs.turn1", "job_pairs.turn0"]
    with store.session() as s:
        turns = s.execute(select(JobPair.turn0, JobPair.turn1).order_by(JobPair.idx)).all()
    assert [tuple(t) for t in turns] == [(-1, -1), (0, 0), (1, 3), (3, 2)]
    store.dispose()
