"""The metadata tables' columns added since tables were first created, brought to a database made
before them: ``create_all`` creates missing tables only, never a missing column.

Each entry is a column of ``models`` (added with its server default) and the statement that gives
the rows written before it their value. Small on purpose: an additive column is all the schema has
needed; a change that rewrites a table needs Alembic.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, cast

from sqlalchemy import Column, Executable, inspect, select, text, update
from sqlalchemy.engine import Connection, Engine
from sqlalchemy.exc import DBAPIError

from .models import Image, Job, JobPair


def _rotate_backfill(conn: Connection) -> Executable | None:
    """A pair not done yet turns when a side is aerial, as the plan decides (planning.plan)."""
    aerial_side = (
        select(Image.id)
        .join(Job, Job.project_id == Image.project_id)
        .where(
            Job.id == JobPair.job_id,
            Image.aerial.is_(True),
            Image.name.in_([JobPair.name0, JobPair.name1]),
        )
        .exists()
    )
    return update(JobPair).where(JobPair.done.is_(False), aerial_side).values(rotate=True)


def _project_has(aerial: bool) -> Any:
    """Whether the pair's project has an image of that kind (as its plan step marked them)."""
    return (
        select(Image.id)
        .join(Job, Job.project_id == Image.project_id)
        .where(Job.id == JobPair.job_id, Image.aerial.is_(aerial))
        .exists()
    )


def _aerial_project_backfill(conn: Connection) -> Executable | None:
    """A pair not done yet of a project with aerial images, as the plan records it now."""
    return update(JobPair).where(JobPair.done.is_(False), _project_has(True)).values(aerial_project=True)


def _survey_backfill(conn: Connection) -> Executable | None:
    """A pair not done yet of a project whose every image is aerial."""
    survey = _project_has(True) & ~_project_has(False)
    return update(JobPair).where(JobPair.done.is_(False), survey).values(survey=True)


def _turns_backfill(conn: Connection) -> Executable | None:
    """Pairs planned while both turns were one column (4 * turn0 + turn1; -1: probed) get them
    apart; pairs planned before the plan decided turns keep their probe (-1)."""
    if "turn" not in {c["name"] for c in inspect(conn).get_columns(JobPair.__tablename__)}:
        return None
    return text(
        "UPDATE job_pairs SET turn0 = CASE WHEN turn < 0 THEN -1 ELSE turn / 4 END, "
        "turn1 = CASE WHEN turn < 0 THEN -1 ELSE turn % 4 END"
    )


def _dispatched_backfill(conn: Connection) -> Executable | None:
    """A job planned before the window queued every pair it had at once."""
    return update(Job).where(Job.planned.is_(True)).values(dispatched=Job.total)


# the table's columns are typed loosely by SQLAlchemy's declarative stubs
ADDED: tuple[tuple[Column[object], Callable[[Connection], Executable | None] | None], ...] = (
    (cast("Column[object]", JobPair.__table__.c.rotate), _rotate_backfill),
    (cast("Column[object]", JobPair.__table__.c.turn1), None),  # filled with turn0, next
    (cast("Column[object]", JobPair.__table__.c.turn0), _turns_backfill),
    (cast("Column[object]", Job.__table__.c.dispatched), _dispatched_backfill),
    (cast("Column[object]", JobPair.__table__.c.aerial_project), _aerial_project_backfill),
    (cast("Column[object]", JobPair.__table__.c.survey), _survey_backfill),
)


def add_missing_columns(engine: Engine) -> list[str]:
    """Add the columns of :data:`ADDED` that the database lacks, then fill them; returns the
    ``table.column`` names added. An API and its workers starting together may race: the loser
    finds the column there on its second look."""
    try:
        return _add(engine)
    except DBAPIError:
        return _add(engine)


def _add(engine: Engine) -> list[str]:
    added = []
    with engine.begin() as conn:
        for column, backfill in ADDED:
            if _has(conn, column):
                continue
            table = column.table.name
            kind = column.type.compile(dialect=engine.dialect)
            default = column.server_default.arg.compile(dialect=engine.dialect)  # type: ignore[union-attr]
            conn.execute(
                text(f"ALTER TABLE {table} ADD COLUMN {column.name} {kind} NOT NULL DEFAULT {default}")
            )
            statement = backfill(conn) if backfill is not None else None
            if statement is not None:
                conn.execute(statement)
            added.append(f"{table}.{column.name}")
    return added


def _has(conn: Connection, column: Column[object]) -> bool:
    return column.name in {c["name"] for c in inspect(conn).get_columns(column.table.name)}
