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

import redis.exceptions
from kombu.transport import redis as kombu_redis

# what a Redis that is failing over or starting answers: retry the connection, do not give up
FAILOVER_ERRORS: tuple[type[Exception], ...] = (
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
    recoverable_connection_errors = connection_errors
    recoverable_channel_errors: tuple[type[Exception], ...] = ()


TRANSPORT = f"{__name__}:Transport"  # Celery's broker_transport: kombu imports it by this name
