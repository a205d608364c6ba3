"""A failure's reason as clients see it: the server's paths taken out.

A step's exception names files by their absolute paths (the reader's ``/srv/.../projects/<id>/
images/a.jpg: not a readable image``, Pillow's ``cannot identify image file '...'``, COLMAP's
messages), and the reason becomes the job's ``error``, which REST and gRPC show as stored. Where
the storage root lies is the server's business, and a client knows its files by the names it
uploaded them under. So a path in the project's images folder becomes the image's name, another
path under the project's folder or the storage root becomes its path relative to that folder,
and any other absolute path (a library's file, a temporary folder) its last component. The
server's log keeps the reason as raised.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

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
