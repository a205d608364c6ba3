"""COLMAP's own log: quiet unless asked for.

pycolmap's C++ writes glog lines (``I20261123 09:05:49.900130 ... incremental_pipeline.cc:353]
Loading database``) straight to file descriptor 2, dozens of them per model, between our
progress bars and our table. In pycolmap 4.2, setting ``pycolmap.logging.minloglevel``
at run time silences them (the flag is read at every LOG statement, from every thread);
``GLOG_minloglevel`` in the environment works too but only when set before pycolmap is first
imported, which a library cannot promise. So the level is set around each call and put back.

Quiet means level 2: INFO and WARNING lines go, ERROR lines stay, since an error of COLMAP's is
news a user needs even without ``--verbose`` (none is printed on a normal run).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import pycolmap

QUIET_LEVEL = 2  # glog: 0 INFO, 1 WARNING, 2 ERROR, 3 FATAL


@contextmanager
def colmap_log(verbose: bool) -> Iterator[None]:
    """COLMAP's INFO/WARNING lines inside the block only when ``verbose``."""
    old = int(pycolmap.logging.minloglevel)
    pycolmap.logging.minloglevel = 0 if verbose else max(old, QUIET_LEVEL)
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old
