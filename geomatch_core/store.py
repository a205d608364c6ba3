"""The metadata store: one SQLAlchemy engine and session factory for the API, workers and CLI.

SQLite (the default) is shared by several processes on one host: WAL mode lets readers go on
while a writer commits, and a busy timeout makes concurrent writers wait instead of failing.
PostgreSQL (``DATABASE_URL=postgresql://...``) is for deployments whose workers run elsewhere.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sqlalchemy import create_engine, event, text
from sqlalchemy.engine import Engine
from sqlalchemy.exc import DBAPIError, InterfaceError, OperationalError
from sqlalchemy.orm import Session, sessionmaker

from .errors import Unavailable
from .migrate import add_missing_columns
from .models import Base


def _normalise(url: str) -> str:
    # plain postgresql:// means psycopg2 to SQLAlchemy; the dependency installed is psycopg 3
    if url.startswith("postgresql://") or url.startswith("postgres://"):
        return "postgresql+psycopg://" + url.split("://", 1)[1]
    return url


class MetadataStore:
    def __init__(self, url: str) -> None:
        self.url = _normalise(url)
        kwargs: dict[str, Any] = {"pool_pre_ping": True}
        if self.url.startswith("sqlite"):
            path = self.url.split("///", 1)[-1]
            if path and path != ":memory:":
                Path(path).parent.mkdir(parents=True, exist_ok=True)
            kwargs["connect_args"] = {"timeout": 60, "check_same_thread": False}
        self.engine: Engine = create_engine(self.url, **kwargs)
        if self.url.startswith("sqlite"):
            event.listen(self.engine, "connect", _sqlite_pragmas)
        self._sessions = sessionmaker(self.engine, expire_on_commit=False)

    def create_all(self) -> None:
        """Idempotent; an API and its workers starting together may race to create a table, and the
        loser's second look finds it there. A database made before a column was added gets it
        (``migrate``)."""
        try:
            Base.metadata.create_all(self.engine)
        except DBAPIError:
            Base.metadata.create_all(self.engine)
        add_missing_columns(self.engine)

    @contextmanager
    def session(self) -> Iterator[Session]:
        """One transaction: committed on success, rolled back on any exception.

        A server database that cannot be reached (down, restarting, the connection dropped
        mid-transaction) raises ``Unavailable``: a retry may succeed (the pool pings connections
        before use, so the next session after a restart reconnects). A connection lost during
        COMMIT leaves the outcome unknown (the commit may have landed, its acknowledgement lost):
        callers keep what a landed commit would need and make their retries idempotent. SQLite's
        own errors (a full disk, a lock) pass through as they are."""
        try:
            with self._sessions() as s, s.begin():
                yield s
        except DBAPIError as e:
            if not self._lost_connection(e):
                raise
            raise Unavailable(
                f"the metadata database is not reachable ({type(e.orig).__name__}); retry"
            ) from e

    def _lost_connection(self, e: DBAPIError) -> bool:
        if e.connection_invalidated:
            return True
        return not self.url.startswith("sqlite") and isinstance(e, OperationalError | InterfaceError)

    def ping(self) -> None:
        with self.engine.connect() as c:
            c.execute(text("SELECT 1"))

    def dispose(self) -> None:
        self.engine.dispose()


def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    cur = dbapi_connection.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute("PRAGMA busy_timeout=60000")
    cur.execute("PRAGMA foreign_keys=ON")
    cur.execute("PRAGMA synchronous=NORMAL")
    cur.close()
