"""The one table of HTTP statuses for domain errors, and the headers some of them carry; read by
the app's exception handler and by the middleware that answers before the app runs
(``bodylimits.py``)."""

from __future__ import annotations

from geomatch_core import errors

STATUS: dict[type[errors.DomainError], int] = {
    errors.BadFile: 400,
    errors.Unauthenticated: 401,
    errors.QuotaExceeded: 403,
    errors.NotFound: 404,
    errors.Conflict: 409,
    errors.TooLarge: 413,
    errors.UnsupportedFormat: 415,
    errors.InvalidRequest: 422,
    errors.Overloaded: 429,
    errors.Unavailable: 503,
    errors.InsufficientStorage: 507,
}


def status_of(exc: errors.DomainError) -> int:
    for cls in type(exc).__mro__:
        if cls in STATUS:
            return STATUS[cls]
    return 400


def error_headers(exc: errors.DomainError) -> dict[str, str] | None:
    """401 names the scheme; 429 says when to come back (a slot or a token is usually free again
    within a second)."""
    if isinstance(exc, errors.Unauthenticated):
        return {"WWW-Authenticate": "Bearer"}
    if isinstance(exc, errors.Overloaded):
        return {"Retry-After": str(getattr(exc, "retry_after_s", 1))}
    return None
