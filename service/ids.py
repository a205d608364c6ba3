"""The ids a client names a resource by, checked before any store is asked about them.

Project and job ids are what ``geomatch_core.models.new_id`` makes (32 lowercase hex digits), and
an image is named by its file name (``validation.check_name``'s rule). A value of another shape
names nothing, so it is NotFound, as an unknown id is (404 / NOT_FOUND, the answer the API gives
for any id it does not know, another tenant's included): a 400 or 422 would tell the client only
that no resource could have it, which it cannot act on differently. Checking the shape first keeps
what a store cannot hold away from it: PostgreSQL refuses a NUL byte in text with an error of its
own, which would answer 500 on every route that looks one up.
"""

from __future__ import annotations

import re

from geomatch_core.errors import BadFile, NotFound

from .validation import check_name

ID = re.compile(r"[0-9a-f]{32}")
_SHOWN = 80  # characters of a malformed value a message repeats: a client may send megabytes


def shown(value: str) -> str:
    """``value`` for a message: escaped (it may hold control characters) and cut short."""
    text = ascii(value)
    return text if len(text) <= _SHOWN else text[: _SHOWN - 3] + "..."


def known_id(kind: str, value: str) -> str:
    """``value`` if it has the shape of an id the service makes, else NotFound for ``kind``."""
    if not ID.fullmatch(value):
        raise NotFound(f"{kind} {shown(value)} not found")
    return value


def known_name(project_id: str, name: str) -> str:
    """``name`` if an upload could have stored an image of that name, else NotFound."""
    try:
        return check_name(name)
    except BadFile:
        raise NotFound(f"image {shown(name)} not found in project {project_id}") from None
