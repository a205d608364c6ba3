"""kombu's Redis transport, with a Redis that is failing over counted as a lost connection.

A Redis made a replica for a few seconds (a failover: ``replicaof`` elsewhere, then back) answers
every write with READONLY, one loading its data with LOADING, one whose master is gone with
MASTERDOWN. kombu counts those as channel errors, which Celery's consumer does not recover from:
both workers of a deployment logged ``ReadOnlyError``, rejected the step in flight and exited
with ``Unrecoverable error``, and the job stayed running until someone restarted them. As
connection errors they make the consumer reconnect (with Celery's back-off) until Redis takes
writes again, and the steps it held come back (``workers.lifeline``: its own leases are restored
once it is connected again; ``workers.sweep`` re-dispatches a job left without a step).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

import redis.exceptions
from kombu.transport import redis as kombu_redis
from redis._parsers.base import BaseParser

T = TypeVar("T")


class UnblockedError(redis.exceptions.ResponseError):
    """UNBLOCKED: a blocking read (the consumer's BRPOP) cut off because the server turned replica
    under it. redis-py knows no class for that reply and raises a plain ResponseError, which kombu
    counts as a channel error: a worker waiting for a step when the failover began exited with
    ``Unrecoverable error`` before any write could answer READONLY."""


# redis-py picks an error reply's exception class by its first word (both parsers, hiredis too)
BaseParser.EXCEPTION_CLASSES.setdefault("UNBLOCKED", UnblockedError)

# what a Redis that is failing over or starting answers: retry the connection, do not give up
FAILOVER_ERRORS: tuple[type[Exception], ...] = (
    UnblockedError,
    redis.exceptions.ReadOnlyError,
    redis.exceptions.BusyLoadingError,
    redis.exceptions.MasterDownError,
    redis.exceptions.TryAgainError,
)


class Transport(kombu_redis.Transport):
    # class attributes: kombu's Connection reads them off the class
    connection_errors: tuple[type[Exception], ...] = (
        *kombu_redis.Transport.connection_errors,
        *FAILOVER_ERRORS,
    )
    # what a publish (Connection.ensure, Celery's task_publish_retry_policy) retries after a fresh
    # connection: without these kombu's ensure gives up at the second error after it reconnected
    # ("the transport cannot tell recoverable errors apart"), and a PING answers on a replica, so
    # a step's publish failed at once in a failover and Celery rejected the step unqueued
    # (publish_through_failover paces the tries of the steps' own publishes)
    recoverable_connection_errors = connection_errors
    recoverable_channel_errors: tuple[type[Exception], ...] = ()


FAILOVER_PAUSE_S = 1.0  # between two tries of a publish that met a failover
FAILOVER_TRIES = 20  # so a publish waits out about 20 s of one
LOST_PAUSE_S, LOST_TRIES = 0.2, 4  # a lost connection: kombu's default publish retry, about 1 s


def _caused_by(exc: BaseException, kinds: tuple[type[BaseException], ...]) -> bool:
    """Whether ``exc`` or what it was raised from (kombu's OperationalError wraps Redis's) is one
    of ``kinds``."""
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, kinds):
            return True
        seen = seen.__cause__ or seen.__context__
    return False


def publish_through_failover(publish: Callable[[], T]) -> T:
    """``publish()`` (a send without kombu's own retry), tried again every FAILOVER_PAUSE_S while
    Redis answers as a failing-over server does (FAILOVER_TRIES times), and a few times when the
    connection was lost. Not kombu's retry (``Connection.ensure``): it tries again at once once it
    has a fresh connection, and a replica's connections open and answer PING, so its tries were
    spent in 0.1 s; and its reconnect left a pooled producer on a closed channel now and then
    (AttributeError on the next publish)."""
    failovers = lost = 0
    while True:
        try:
            return publish()
        except Exception as e:
            if _caused_by(e, FAILOVER_ERRORS) and failovers < FAILOVER_TRIES - 1:
                failovers += 1
                time.sleep(FAILOVER_PAUSE_S)
            elif _caused_by(
                e, (redis.exceptions.ConnectionError, redis.exceptions.TimeoutError, OSError)
            ) and (lost < LOST_TRIES - 1):
                lost += 1
                time.sleep(LOST_PAUSE_S)
            else:
                raise


TRANSPORT = f"{__name__}:Transport"  # Celery's broker_transport: kombu imports it by this name
