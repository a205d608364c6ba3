"""A failure's reason as clients see it: the server's paths, its SQL and its drivers' text taken out.

A step's exception names files by their absolute paths (the reader's ``/srv/.../projects/<id>/
images/a.jpg: not a readable image``, Pillow's ``cannot identify image file '...'``, COLMAP's
messages), and the reason becomes the job's ``error``, which REST and gRPC show as stored. Where
the storage root lies is the server's business, and a client knows its files by the names it
uploaded them under. So a path in the project's images folder becomes the image's name, another
path under the project's folder or the storage root becomes its path relative to that folder,
and any other absolute path (a library's file, a temporary folder) its last component. The
server's log keeps the reason as raised.

An error of the metadata store or of Redis names neither the client's data nor anything it can act
on, and it carries the statement and its parameters (PostgreSQL's refusal of a NaN in a job's result
reached a client as ``invalid input syntax for type json ... [SQL: UPDATE jobs SET ...]``): those
become one line naming the part that failed. ``client_message`` is the one mapping from an
exception to what a client reads; messages are cut to MAX_MESSAGE characters.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import redis
import sqlalchemy.exc

from .context import PermanentError

MAX_MESSAGE = 2000  # characters of a reason a client reads (a job's error is stored up to 4000)

# An absolute path: a "/" that starts a word (not the one of "0/0", "and/or" or a URL's "//"),
# then components up to white space, a quote or punctuation; group 1 is its last component.
_ABSOLUTE = re.compile(r"(?<![\w.:/~-])/(?:[^\s'\"/:,;()\[\]{}<>]+/)*([^\s'\"/:,;()\[\]{}<>]+)")


def without_paths(text: str, root: Path, project_dir: Path | None = None) -> str:
    """``text`` with every path under ``root`` (the storage root) relative: to the project's
    images folder, then to ``project_dir``, then to ``root``; other absolute paths as their
    last component. Each folder is tried as given, absolute and with its links resolved: a
    relative GEOMATCH_HOME and a linked /tmp both occur."""
    folders = ([project_dir / "images", project_dir] if project_dir is not None else []) + [root]
    for folder in folders:
        forms = {str(folder), os.path.abspath(folder), os.path.realpath(folder)}
        for form in sorted(forms, key=len, reverse=True):  # the longest first: it holds the others
            text = text.replace(form.rstrip("/") + "/", "")
    return _ABSOLUTE.sub(lambda m: m.group(1), text)


def client_message(exc: BaseException, root: Path, project_dir: Path | None = None) -> str:
    """What a client reads of ``exc``: a step's own reason as written, a store's or Redis's error as
    the part that failed (no statement, no driver's text), anything else as its type and message;
    server paths out (``without_paths``), cut to MAX_MESSAGE characters."""
    own = isinstance(exc, PermanentError)
    text = str(exc) if own else _dependency(exc) or f"{type(exc).__name__}: {exc}"
    text = without_paths(text, root, project_dir)
    return text if len(text) <= MAX_MESSAGE else text[: MAX_MESSAGE - 3] + "..."


def _dependency(exc: BaseException) -> str | None:
    """The failing part's line for a metadata store's or Redis's error, None for any other."""
    if isinstance(exc, sqlalchemy.exc.SQLAlchemyError):
        kind = type(getattr(exc, "orig", None) or exc).__name__
        return f"the metadata store refused or lost the operation ({kind})"
    if isinstance(exc, redis.RedisError):
        return f"the queue (Redis) refused or lost the operation ({type(exc).__name__})"
    return None
