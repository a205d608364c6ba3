"""What every call meets before its method runs (a grpc.aio server interceptor, on the event loop,
so none of it takes a thread):

- a call of ``geomatch.v1.Matching`` without a bearer key is UNAUTHENTICATED at once, before its
  request is read (a key that is there is checked against the store by the method, on its thread);
- a call with a single request message (every unary call, health checks included) gets that
  message within ``first_message_s`` or ends with DEADLINE_EXCEEDED: a client that opens calls and
  never sends them holds nothing for longer than that (request streams have their own idle
  timeout: ``limits.IdleStreams``).
"""

from __future__ import annotations

import asyncio
import inspect
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any

import grpc
from grpc import aio

from .bridge import consume
from .status import bearer_key_in

if TYPE_CHECKING:  # grpc's stubs make it generic; at run time it is not
    Handler = grpc.RpcMethodHandler[Any, Any]
_KINDS = {
    False: grpc.stream_unary_rpc_method_handler,
    True: grpc.stream_stream_rpc_method_handler,
}


class Gate(aio.ServerInterceptor):
    def __init__(self, keyed_service: str, missing_key: str, first_message_s: float) -> None:
        self.prefix = f"/{keyed_service}/"
        self.missing_key = missing_key
        self.first_message_s = first_message_s

    async def intercept_service(
        self,
        continuation: Callable[[grpc.HandlerCallDetails], Awaitable[Handler | None]],
        details: grpc.HandlerCallDetails,
    ) -> Handler | None:
        handler = await continuation(details)
        if handler is None:  # an unknown method: UNIMPLEMENTED, as grpc answers it
            return handler
        if details.method.startswith(self.prefix) and bearer_key_in(details.invocation_metadata) is None:
            return refuse(handler, grpc.StatusCode.UNAUTHENTICATED, self.missing_key)
        if not handler.request_streaming:
            return first_message_within(handler, self.first_message_s)
        return handler


def refuse(handler: Handler, code: grpc.StatusCode, details: str) -> Handler:
    """The call ends with ``code`` before anything is read (a request-streaming handler: grpc.aio
    waits for nothing before running it)."""

    async def deny(requests: Any, context: aio.ServicerContext[Any, Any]) -> None:
        await context.abort(code, details)

    make: Any = _KINDS[handler.response_streaming]
    return make(deny, response_serializer=handler.response_serializer)  # type: ignore[no-any-return]


def first_message_within(handler: Handler, seconds: float) -> Handler:
    """``handler`` (one request message) as a request-streaming handler that reads that message
    itself, for at most ``seconds``. Handlers whose behaviour is not a coroutine are left as they
    are (this server registers none)."""
    inner = handler.unary_stream if handler.response_streaming else handler.unary_unary
    if not inspect.iscoroutinefunction(inner):
        return handler

    async def first(requests: Any, context: aio.ServicerContext[Any, Any]) -> Any:
        message = await read_first(context, seconds)
        return await inner(message, context)

    make: Any = _KINDS[handler.response_streaming]
    return make(  # type: ignore[no-any-return]
        first,
        request_deserializer=handler.request_deserializer,
        response_serializer=handler.response_serializer,
    )


async def read_first(context: aio.ServicerContext[Any, Any], seconds: float) -> Any:
    reading = asyncio.ensure_future(context.read())
    try:
        done, _ = await asyncio.wait({reading}, timeout=seconds)
    finally:
        if not reading.done():  # never cancelled (bridge.py): it ends with the call
            consume(reading)
    if not done:
        await context.abort(
            grpc.StatusCode.DEADLINE_EXCEEDED,
            f"no request message within {seconds:g} s of the call's start (GEOMATCH_GRPC_FIRST_MESSAGE_S)",
        )
    message = reading.result()
    if message is aio.EOF:
        await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "the call ended without its request message")
    return message
