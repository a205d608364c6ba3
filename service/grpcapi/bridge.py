"""The Matching servicer's synchronous methods, served by grpc.aio.

grpcio's synchronous server gives every call a pool thread the moment it arrives, and a unary
call's thread then waits for the request message: calls that send their headers and never their
message (no key needed) can hold every thread, and health checks and every tenant's GetProject go
unanswered for as long as they are held. Under grpc.aio a call waiting for its message is a
coroutine on the event loop; a thread is taken only to run the method, once there is a request.

The servicer's methods stay synchronous (the use cases are: SQLAlchemy, files, the queue). Each
runs on the server's pool with a ``SyncCall`` as its context, the part of grpcio's synchronous
``ServicerContext`` they use (``invocation_metadata``, ``time_remaining``, ``is_active``, ``abort``,
``cancel``). A request stream is read from the thread one message at a time (``SyncCall.read``: the
message is awaited on the loop), a response stream is pulled from its generator one item at a time
on the pool and written on the loop, so a WatchJob between events holds no thread.

Two rules keep the thread and the call consistent:

- a coroutine awaiting one of gRPC's core operations is never cancelled by this module (the
  operation's buffers belong to it until gRPC completes it): a thread that gives up on a read
  leaves the read to finish on its own, once the call is over;
- a call's coroutine does not end while its thread still runs (the call's core object is released
  when the coroutine ends): a call cancelled by its client or its deadline waits for its thread,
  which sees ``is_active()`` false and its reads fail, and unwinds.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
from collections.abc import Awaitable, Callable, Coroutine, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any, NoReturn, TypeVar

import grpc
from grpc import aio

T = TypeVar("T")
_DONE = object()  # what a response generator's ``next`` returns at its end


class CallEnded(grpc.RpcError):
    """A read of a call that ended (cancelled by its client or by the server, or past its
    deadline): what grpcio's synchronous request iterator raises then (``status._answer``)."""


class SyncCall:
    """One call, as its method's thread sees it; the loop side is ``end``, ``send_status``."""

    def __init__(self, context: aio.ServicerContext[Any, Any], loop: asyncio.AbstractEventLoop) -> None:
        self._ctx = context
        self._loop = loop
        self._over: concurrent.futures.Future[None] = concurrent.futures.Future()  # threads wait on it
        self._finished = False  # (loop) a status is out, or the call ended: nothing more is sent
        self.aborted = False  # (loop) this side sent an error status
        self._headers_sent = False  # (loop)

    # -- what the servicer's methods call, from their thread -------------------------------------
    def invocation_metadata(self) -> Any:
        return self._ctx.invocation_metadata()

    def time_remaining(self) -> float | None:
        return self._ctx.time_remaining()

    def peer(self) -> str:
        return str(self._ctx.peer())

    def is_active(self) -> bool:
        if self._over.done():
            return False
        left = self._ctx.time_remaining()
        return left is None or left > 0

    def abort(self, code: grpc.StatusCode, details: str = "") -> NoReturn:
        """Ends the call with ``code`` (a no-op on a call already over) and raises, as grpcio's
        synchronous ``abort`` does: a bare ``Exception``, which ``status.rpc`` lets through."""
        sending = self._on_loop(self.send_status(code, details))
        if sending is not None:
            with contextlib.suppress(CallEnded):
                self._wait(sending)
        raise Exception()  # grpcio's own signal of an abort (status._is_abort)

    def cancel(self) -> None:
        """Ends the call with CANCELLED (any thread but the loop's; returns at once): a thread
        blocked reading the call's next message wakes with ``CallEnded``."""
        sending = self._on_loop(self.send_status(grpc.StatusCode.CANCELLED, "cancelled"))
        if sending is not None:
            consume(sending)

    def read(self) -> Any:
        """The next request message, ``aio.EOF`` when the client closed its side; ``CallEnded``
        when the call is over (a cancelled call reads as EOF in grpc.aio: that is checked)."""
        if self._over.done():
            raise CallEnded()
        reading = self._on_loop(self._read())
        if reading is None:
            raise CallEnded()
        try:
            self._wait(reading, self._over)
        finally:
            if not reading.done():  # the call ended meanwhile: the read finishes once gRPC ends it
                consume(reading)
        if not reading.done():
            raise CallEnded()
        try:
            return reading.result()
        except Exception:
            raise CallEnded() from None

    def _on_loop(self, coro: Coroutine[Any, Any, T]) -> concurrent.futures.Future[T] | None:
        """``coro`` run on the server's loop; None once the loop is closed (the server stopped)."""
        try:
            return asyncio.run_coroutine_threadsafe(coro, self._loop)
        except RuntimeError:
            coro.close()
            return None

    def _wait(self, f: concurrent.futures.Future[Any], *also: concurrent.futures.Future[Any]) -> None:
        """Until ``f`` or one of ``also`` is done; ``CallEnded`` if the loop stops meanwhile (a
        stopping server: what was scheduled on it may never run, and a thread waiting for it
        would keep the process from exiting)."""
        while not f.done() and not any(a.done() for a in also):
            concurrent.futures.wait([f, *also], timeout=1.0, return_when=concurrent.futures.FIRST_COMPLETED)
            if not f.done() and not self._loop.is_running():
                raise CallEnded()

    # -- the loop's side --------------------------------------------------------------------------
    def end(self) -> None:
        """The call was cancelled (its client, its deadline): wake its thread."""
        self._finished = True
        if not self._over.done():
            self._over.set_result(None)

    async def send_status(self, code: grpc.StatusCode, details: str) -> None:
        if self._finished:
            return
        self.aborted = True
        self.end()
        # abort raises once the status is out (ExecuteBatchError: the client is gone)
        with contextlib.suppress(Exception):
            await self._ctx.abort(code, details)

    async def _read(self) -> Any:
        if self._finished:
            raise CallEnded()
        message = await self._ctx.read()
        if message is aio.EOF and not await self._alive():
            raise CallEnded()
        return message

    async def _alive(self) -> bool:
        """Whether the call is still open after a read gave EOF: its client closed its side (the
        end of its stream), or it was cancelled, which grpc.aio reads as EOF too. Sending the
        response headers tells the two apart (it fails on a cancelled call); it is what the
        answer starts with anyway."""
        if self._finished:
            return False
        if not self._headers_sent:
            try:
                await self._ctx.send_initial_metadata(())
            except Exception:
                return False
            self._headers_sent = True
        left = self._ctx.time_remaining()
        return not self._finished and (left is None or left > 0)

    async def run(self, pool: ThreadPoolExecutor, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)`` on the pool. Cancelled meanwhile (the client, the deadline), the call ends
        for the thread, and this returns only when the thread has returned."""
        work = pool.submit(fn, *args)
        try:
            return await asyncio.wrap_future(work)
        except asyncio.CancelledError:
            self.end()
            if not work.cancel():  # running: it may still use the call, which must outlive it
                waited = asyncio.wrap_future(work)
                consume(waited)  # its outcome (an abort that found the call over) goes nowhere
                await asyncio.wait([waited])
            raise


class SyncRequests(Iterator[Any]):
    """A request stream as grpcio's synchronous iterator: StopIteration at the client's end of
    stream, ``CallEnded`` (a ``grpc.RpcError``) when the call ended."""

    def __init__(self, call: SyncCall) -> None:
        self._call = call

    def __next__(self) -> Any:
        message = self._call.read()
        if message is aio.EOF:
            raise StopIteration
        return message


def consume(task: concurrent.futures.Future[Any] | asyncio.Future[Any]) -> None:
    """A background read or status whose outcome nobody awaits: its exception is retrieved, so
    that asyncio does not log it as never retrieved."""

    def done(t: Any) -> None:
        if not t.cancelled():
            t.exception()

    task.add_done_callback(done)


Behavior = Callable[..., Any]


def unary_unary(fn: Behavior, pool: ThreadPoolExecutor) -> Callable[[Any, Any], Awaitable[Any]]:
    async def handle(request: Any, context: aio.ServicerContext[Any, Any]) -> Any:
        call = SyncCall(context, asyncio.get_running_loop())
        try:
            return await call.run(pool, fn, request, call)
        except Exception:
            if call.aborted:  # the status is out; grpc.aio raises the abort it recorded
                return None
            raise

    return handle


def stream_unary(fn: Behavior, pool: ThreadPoolExecutor) -> Callable[[Any, Any], Awaitable[Any]]:
    async def handle(requests: Any, context: aio.ServicerContext[Any, Any]) -> Any:
        # grpc.aio's own iterator (``requests``) is left unread: the thread reads through the call
        call = SyncCall(context, asyncio.get_running_loop())
        try:
            return await call.run(pool, fn, SyncRequests(call), call)
        except Exception:
            if call.aborted:
                return None
            raise

    return handle


def unary_stream(fn: Behavior, pool: ThreadPoolExecutor) -> Callable[[Any, Any], Awaitable[None]]:
    async def handle(request: Any, context: aio.ServicerContext[Any, Any]) -> None:
        call = SyncCall(context, asyncio.get_running_loop())
        responses = fn(request, call)  # a generator: nothing of it runs before the first next()
        try:
            while (item := await call.run(pool, next, responses, _DONE)) is not _DONE:
                await context.write(item)
        except Exception:
            if not call.aborted:
                raise
        finally:  # its finally blocks (slots given back) run on the pool too
            await call.run(pool, responses.close)

    return handle
