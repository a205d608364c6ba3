"""Where domain errors become gRPC status codes, and where every call is authenticated.

The one table of the gRPC side, as ``service/http/api.py`` holds the HTTP one. A method of the servicer
is written as ``method(self, request, context, tenant_id)``; ``rpc`` (unary responses) and
``rpc_stream`` (streamed responses) check the bearer key, hand the tenant in, and turn what the use
cases raise into ``context.abort(code, message)``.
"""

from __future__ import annotations

import functools
import logging
import uuid
from collections.abc import Callable, Iterator
from typing import Any, NoReturn, TypeVar

import grpc

from geomatch_core import errors

log = logging.getLogger("geomatch.service.grpc")

CODES: dict[type[errors.DomainError], grpc.StatusCode] = {
    errors.NotFound: grpc.StatusCode.NOT_FOUND,
    errors.Unauthenticated: grpc.StatusCode.UNAUTHENTICATED,
    errors.PlanTooLarge: grpc.StatusCode.RESOURCE_EXHAUSTED,  # before its base, InvalidRequest
    errors.InvalidRequest: grpc.StatusCode.INVALID_ARGUMENT,
    errors.BadFile: grpc.StatusCode.INVALID_ARGUMENT,
    errors.UnsupportedFormat: grpc.StatusCode.INVALID_ARGUMENT,
    # a bomb is a bad image; a big file is a limit (its own subclass first: the MRO decides)
    errors.DecompressionBomb: grpc.StatusCode.INVALID_ARGUMENT,
    errors.TooLarge: grpc.StatusCode.RESOURCE_EXHAUSTED,
    errors.Overloaded: grpc.StatusCode.RESOURCE_EXHAUSTED,  # RateLimited included
    errors.QuotaExceeded: grpc.StatusCode.RESOURCE_EXHAUSTED,
    errors.Conflict: grpc.StatusCode.FAILED_PRECONDITION,
    errors.Unavailable: grpc.StatusCode.UNAVAILABLE,
    errors.InsufficientStorage: grpc.StatusCode.RESOURCE_EXHAUSTED,
}


class Malformed:
    """What a request that does not parse becomes (see ``server.safe_deserializer``): gRPC's
    default for those is INTERNAL, and inside a stream it ends the stream as if the client had
    finished it, which would let half an upload through."""

    def __init__(self, error: Exception) -> None:
        self.error = error

    @property
    def message(self) -> str:
        return f"malformed request: the message does not parse ({self.error})"


def code_of(exc: errors.DomainError) -> grpc.StatusCode:
    for cls in type(exc).__mro__:
        if cls in CODES:
            return CODES[cls]
    return grpc.StatusCode.INVALID_ARGUMENT


def bearer_key(context: grpc.ServicerContext) -> str | None:
    return bearer_key_in(context.invocation_metadata())


def bearer_key_in(metadata: Any) -> str | None:
    """The key of ``authorization: Bearer KEY`` in a call's metadata, None without one."""
    for key, value in metadata or ():
        if key == "authorization" and isinstance(value, str):
            scheme, _, token = value.strip().partition(" ")
            if scheme.lower() == "bearer" and token.strip():
                return token.strip()
    return None


def abort(context: grpc.ServicerContext, exc: errors.DomainError) -> NoReturn:
    context.abort(code_of(exc), exc.message)
    raise AssertionError("context.abort returned")  # it raises; this line tells type checkers so


def _unexpected(context: grpc.ServicerContext, name: str, exc: Exception) -> NoReturn:
    """A bug's message stays in the log: it may hold the server's paths (an OSError names its
    files), which are none of the client's business. The incident id ties the two together."""
    if not context.is_active():  # the client left (cancelled, deadline): nobody hears an answer
        context.abort(grpc.StatusCode.CANCELLED, "the call ended before the server answered")
    incident = uuid.uuid4().hex[:12]
    log.exception("%s failed (incident %s)", name, incident)
    context.abort(grpc.StatusCode.INTERNAL, f"internal error (incident {incident} in the server's log)")
    raise AssertionError("context.abort returned")


S = TypeVar("S")  # the servicer
Req = TypeVar("Req")  # a request, or an iterator of them for a client stream
R = TypeVar("R")  # a response


def _tenant(servicer: Any, request: Any, context: grpc.ServicerContext) -> str:
    tenant_id = servicer.service.authenticate(bearer_key(context))
    if isinstance(request, Malformed):
        raise errors.InvalidRequest(request.message)
    return str(tenant_id)


def rpc(
    method: Callable[[S, Req, grpc.ServicerContext, str], R],
) -> Callable[[S, Req, grpc.ServicerContext], R]:
    @functools.wraps(method)
    def wrapper(self: S, request: Req, context: grpc.ServicerContext) -> R:
        try:
            return method(self, request, context, _tenant(self, request, context))
        except Exception as e:
            _answer(context, method.__name__, e)

    return wrapper


def rpc_stream(
    method: Callable[[S, Req, grpc.ServicerContext, str], Iterator[R]],
) -> Callable[[S, Req, grpc.ServicerContext], Iterator[R]]:
    @functools.wraps(method)
    def wrapper(self: S, request: Req, context: grpc.ServicerContext) -> Iterator[R]:
        try:
            yield from method(self, request, context, _tenant(self, request, context))
        except Exception as e:
            _answer(context, method.__name__, e)

    return wrapper


def _answer(context: grpc.ServicerContext, name: str, exc: Exception) -> NoReturn:
    """The status of a call that raised ``exc`` (``context.abort`` raises; an abort goes through)."""
    if isinstance(exc, errors.DomainError):
        abort(context, exc)
    elif isinstance(exc, grpc.RpcError):  # reading a request stream the client abandoned
        context.abort(grpc.StatusCode.CANCELLED, "the client cancelled the call")
        raise AssertionError("context.abort returned")  # it raises; this line tells type checkers so
    elif _is_abort(exc):
        raise exc
    else:
        _unexpected(context, name, exc)


def _is_abort(exc: Exception) -> bool:
    """``context.abort`` raises a bare Exception after setting the status: let it through."""
    return type(exc) is Exception
