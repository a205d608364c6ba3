"""Publishing through a Redis failover: what kombu raises for a replica's READONLY is tried again,
paced, for about 20 s; a lost connection a few times; anything else at once."""

from __future__ import annotations

from collections.abc import Callable

import pytest
import redis.exceptions
from kombu.exceptions import OperationalError

from workers import celery_transport
from workers.celery_transport import FAILOVER_TRIES, LOST_TRIES, Transport, publish_through_failover

pytestmark = pytest.mark.unit


def wrapped(exc: Exception) -> OperationalError:
    """As kombu raises it: its OperationalError, raised from Redis's."""
    try:
        raise OperationalError(str(exc)) from exc
    except OperationalError as e:
        return e


def publisher(errors: list[Exception]) -> tuple[list[int], Callable[[], str]]:
    calls: list[int] = []

    def publish() -> str:
        calls.append(1)
        if errors:
            raise errors.pop(0)
        return "sent"

    return calls, publish


def test_a_failover_is_waited_out_and_other_errors_are_not(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(celery_transport, "FAILOVER_PAUSE_S", 0.0)
    monkeypatch.setattr(celery_transport, "LOST_PAUSE_S", 0.0)
    readonly = redis.exceptions.ReadOnlyError("You can't write against a read only replica.")
    calls, publish = publisher([wrapped(readonly)] * 5 + [redis.exceptions.BusyLoadingError("loading")])
    assert publish_through_failover(publish) == "sent" and len(calls) == 7

    calls, publish = publisher([wrapped(readonly)] * FAILOVER_TRIES)
    with pytest.raises(OperationalError):
        publish_through_failover(publish)
    assert len(calls) == FAILOVER_TRIES

    calls, publish = publisher([wrapped(redis.exceptions.ConnectionError("refused"))] * 10)
    with pytest.raises(OperationalError):
        publish_through_failover(publish)
    assert len(calls) == LOST_TRIES

    calls, publish = publisher([wrapped(redis.exceptions.ResponseError("WRONGTYPE"))])
    with pytest.raises(OperationalError):
        publish_through_failover(publish)
    assert len(calls) == 1


def test_the_consumer_counts_a_failover_as_a_lost_connection() -> None:
    for kind in (
        redis.exceptions.ReadOnlyError,
        redis.exceptions.BusyLoadingError,
        redis.exceptions.MasterDownError,
    ):
        assert issubclass(kind, Transport.connection_errors) and issubclass(
            kind, Transport.recoverable_connection_errors
        )
    assert not issubclass(redis.exceptions.ResponseError, Transport.connection_errors)


def test_a_blocking_read_cut_off_by_the_failover_is_a_lost_connection() -> None:
    """The consumer waits for steps in BRPOP; when the server turns replica the wait ends with an
    UNBLOCKED error reply, which redis-py raised as a plain ResponseError (a channel error to
    kombu: the worker exited). It is read as the failover it is, so the consumer reconnects."""
    from redis.connection import DefaultParser  # the parser a connection reads replies with

    reply = "UNBLOCKED force unblock from blocking operation, instance state changed (master -> replica?)"
    err = DefaultParser(socket_read_size=65536).parse_error(reply)
    assert isinstance(err, celery_transport.UnblockedError)
    assert isinstance(err, Transport.connection_errors)
    # anything else a server says stays what it was: an error of the request, not of the link
    parser = DefaultParser(socket_read_size=65536)
    other = parser.parse_error("WRONGTYPE Operation against a key holding the wrong kind of value")
    assert not isinstance(other, Transport.connection_errors)
