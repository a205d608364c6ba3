"""The sweep's reading of queued and unacknowledged messages: the job a kombu message names, as
kombu writes it to Redis (a message in a queue's list; ``[message, exchange, routing key]`` in the
unacknowledged hash), made here by Celery itself over kombu's in-memory transport."""

from __future__ import annotations

import base64
import json

import pytest
from celery import Celery

from workers.sweep import message_job

pytestmark = pytest.mark.unit


def test_the_job_a_step_message_names_is_read_from_either_form() -> None:
    app = Celery("t", broker="memory://", set_as_current=False)
    with app.connection_for_write() as conn:
        app.send_task("geomatch.match_pair", args=["a" * 32, 7], queue="q", connection=conn)
        raw = conn.default_channel.basic_get("q", no_ack=True)
    # as kombu's Redis transport stores it: the body base64-encoded, as its properties say
    message = {
        "body": base64.b64encode(raw.body).decode(),
        "properties": raw.properties,
        "headers": raw.headers,
    }
    assert message["properties"]["body_encoding"] == "base64"
    assert message_job(json.dumps(message)) == "a" * 32
    assert message_job(json.dumps([message, "", "q"]).encode()) == "a" * 32
    for junk in (b"", b"not json", b"[]", b'{"body": "!!"}', json.dumps({**message, "body": "W10="})):
        assert message_job(junk) is None
