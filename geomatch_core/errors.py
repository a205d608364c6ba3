"""Typed domain errors raised by the use cases. Each transport maps them to its own status
(HTTP here, gRPC codes in the gRPC servicer) so the application layer never names a protocol."""

from __future__ import annotations

from geomatch.options import PAIR_KINDS

# characters of a message a client reads: a message repeats what the request said (names, values),
# and a reconstruct naming 3500 unknown check points of 1000 characters each answered 3.5 MB
MAX_MESSAGE = 2000


def capped(message: str, limit: int = MAX_MESSAGE) -> str:
    """``message`` cut to ``limit`` characters, saying how much was left out."""
    if len(message) <= limit:
        return message
    tail = f"... ({len(message) - limit} more characters)"
    return message[: limit - len(tail)] + tail


class DomainError(Exception):
    """Base: ``message`` is meant for the client, as is (cut to MAX_MESSAGE characters)."""

    def __init__(self, message: str) -> None:
        message = capped(message)
        super().__init__(message)
        self.message = message


class NotFound(DomainError):
    """Unknown, deleted, or another tenant's resource: indistinguishable on purpose."""


class Unauthenticated(DomainError):
    pass


class InvalidRequest(DomainError):
    """The request is well-formed but its values do not make sense for this project."""


class PlanTooLarge(InvalidRequest):
    """A job would plan more work than one job may hold (pairs per job): the message says how to
    split it. REST 422, as any invalid request; gRPC RESOURCE_EXHAUSTED, a limit."""


class BadFile(DomainError):
    """An uploaded file is not a usable image or has an unacceptable name."""


class UnsupportedFormat(DomainError):
    pass


class TooLarge(DomainError):
    """Bytes or pixels over a configured limit (decompression bombs land here)."""


class DecompressionBomb(TooLarge):
    """Pixels over the limit: a bad image rather than a big upload (gRPC tells them apart)."""


class Overloaded(DomainError):
    """Too many calls of one kind open at once (a tenant's streams): retry when one has ended."""


class RateLimited(Overloaded):
    """The tenant made more calls than its rate allows: retry after ``retry_after_s``."""

    def __init__(self, message: str, retry_after_s: int) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s


class WorkQueued(RateLimited):
    """The tenant's unfinished match jobs already hold as many pairs as it may queue: retry once
    some have finished, or cancel one. REST 429 with Retry-After, gRPC RESOURCE_EXHAUSTED."""


class JobsOpen(RateLimited):
    """The tenant has as many unfinished localize and reconstruct jobs as it may: retry once one
    has ended, or cancel one. REST 429 with Retry-After, gRPC RESOURCE_EXHAUSTED."""


class QuotaExceeded(DomainError):
    """The call would take the tenant past a quota (projects, images, stored bytes): nothing was
    kept; deleting what the tenant no longer needs makes room."""


class Conflict(DomainError):
    """The request contradicts the project's current state."""


class Unavailable(DomainError):
    """A dependency (workers, Redis) did not answer in time; retrying later may succeed."""


class InsufficientStorage(DomainError):
    """The storage root is full (ENOSPC): nothing of the request was kept; retry when space is
    freed."""


# -- the refusals of a match past a plan-size limit, for the API and the plan step alike ----------
def too_many_pairs(pairs: int, n: int, limit: int, plan: str, exact: bool = True) -> str:
    """The refusal of a match job whose plan is over ``limit`` pairs, with how to split the work."""
    k = max(1, limit // max(n, 1))
    count = f"{pairs}" if exact else f"at least {pairs}"
    return (
        f"this match would plan {count} pairs ({plan} over {n} images), over the limit of {limit} "
        f"pairs per job (GEOMATCH_MAX_PAIRS_PER_JOB). Split the work: pair each image with its K "
        f'nearest instead of every other, "gps:{k}" (photos with GPS), "retrieval:{k}" (by '
        f'appearance) or "sequential:{k}" (a video or a flight line), about {k * n} pairs here; '
        "or match the project in parts with explicit pair lists"
    )


def too_much_queued(queued: int, jobs: int, adding: int, limit: int, exact: bool = True) -> str:
    """The refusal of a match past a tenant's queued pairs (``GEOMATCH_MAX_QUEUED_PAIRS``)."""
    more = f"{adding}" if exact else f"at least {adding}"
    nearest = " or ".join(f'"{k.name}:K"' for k in PAIR_KINDS if k.takes_k)
    return (
        f"this tenant's unfinished match jobs ({jobs}) hold {queued} pairs not matched yet and this "
        f"match would add {more}, over the limit of {limit} queued pairs per tenant "
        "(GEOMATCH_MAX_QUEUED_PAIRS). Retry when some of them have finished, cancel one, or plan "
        f"fewer pairs ({nearest} instead of exhaustive)"
    )
