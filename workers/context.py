"""What every step receives, and how a step's failure is judged: shared by the job steps
(``workers.jobs``), the interactive ones (``workers.pairmatch``) and both runners."""

from __future__ import annotations

from dataclasses import dataclass

from geomatch_core.config import Settings
from geomatch_core.locks import LockFactory
from geomatch_core.queue import JobQueue
from geomatch_core.storage import Storage
from geomatch_core.store import MetadataStore


class PermanentError(Exception):
    """Retrying cannot help: the job fails at once."""


@dataclass
class StepContext:
    settings: Settings
    store: MetadataStore
    storage: Storage
    locks: LockFactory
    queue: JobQueue


def is_permanent(exc: BaseException) -> bool:
    """Bad options, bad data and missing weights fail the job now; anything else (I/O, a busy
    database, a lost connection, memory) is worth retrying, possibly on another worker."""
    if isinstance(exc, PermanentError | ValueError | TypeError | LookupError | NotImplementedError):
        return True
    return any(c.__name__ == "WeightsNotFoundError" for c in type(exc).__mro__)
