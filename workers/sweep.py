"""The sweep: a job left without a step is dispatched again, without waiting for a process restart.

Steps are lost with Redis in ways no single process sees: a failover that answered writes with
READONLY for a few seconds made both workers of a deployment reject the step in flight and exit,
and the job stayed running with its pairs handed out and never done (``workers.recovery`` runs
when a worker connects, so it took a restart). Every worker's lifeline (``workers.lifeline``)
therefore sweeps, one worker at a time (a Redis key taken with SET NX for a period): an unfinished
job (``recovery.unfinished``) is stranded when no message of the queue, queued or delivered and
unacknowledged, names it. A job found stranded by two sweeps in a row (a period apart: a job
created between its row and its message, or a message moving from the queue to a worker, is seen
by the next one) has its entry step queued again, which is what a restarted worker would do: a
match job re-dispatches the pairs handed out and not done, a reconstruct or localize job starts
over. Steps are idempotent (``workers.jobs``), so a sweep that is wrong costs a duplicate step.
"""

from __future__ import annotations

import base64
import json
import logging
from collections.abc import Callable, Iterable
from typing import Any

from geomatch_core.queue import ENTRY_STEP

from . import recovery
from .context import StepContext

log = logging.getLogger("geomatch.workers")


def message_job(raw: bytes | str) -> str | None:
    """The job a queued or unacknowledged kombu message names (its task's first argument), None
    for a message that names none or does not parse. ``raw``: a queue list's item (the message) or
    an unacknowledged hash's value (``[message, exchange, routing key]``)."""
    try:
        data = json.loads(raw)
        message = data[0] if isinstance(data, list) else data
        body = message["body"]
        if message.get("properties", {}).get("body_encoding") == "base64":
            body = base64.b64decode(body)
        args = json.loads(body)[0]
    except (ValueError, KeyError, IndexError, TypeError):
        return None
    return args[0] if isinstance(args, list) and args and isinstance(args[0], str) else None


def live_jobs(client: Any, prefix: str, channel: Any, queues: Iterable[str]) -> set[str]:
    """Jobs named by a message waiting in ``queues`` (every priority's list, named as kombu's
    ``channel`` names them) or delivered and not acknowledged; ``client`` is Redis without kombu's
    key prefix (its prefixing client leaves LRANGE and HVALS alone), so ``prefix`` is added here."""
    raw: list[bytes] = []
    for q in queues:
        for pri in channel.priority_steps:
            raw += client.lrange(prefix + (q if not pri else f"{q}{channel.sep}{pri}"), 0, -1)
    raw += client.hvals(prefix + channel.unacked_key)
    return {j for j in map(message_job, raw) if j is not None}


class Sweep:
    def __init__(
        self,
        context: Callable[[], StepContext],
        prefix: str,
        queues: list[str],
        period_s: float,
        worker_id: str,
    ) -> None:
        self.context = context
        self.prefix = prefix
        self.turn_key = f"{prefix}sweep"
        self.seen_key = f"{prefix}stranded"
        self.queues = queues
        self.period_s = period_s
        self.worker_id = worker_id

    def run(self, channel: Any, client: Any) -> list[str]:
        """One sweep if it is this worker's turn (``client``: Redis without kombu's prefix); the
        jobs dispatched again."""
        if not client.set(self.turn_key, self.worker_id, nx=True, px=int(self.period_s * 1000)):
            return []
        ctx = self.context()
        jobs = dict(recovery.unfinished(ctx.store))
        live = live_jobs(client, self.prefix, channel, self.queues)
        stranded = set(jobs) - live
        before = {v.decode() if isinstance(v, bytes) else str(v) for v in client.smembers(self.seen_key)}
        again = sorted(stranded & before)
        for job_id in again:
            ctx.queue.enqueue(ENTRY_STEP[jobs[job_id]], job_id)
        pipe = client.pipeline()
        pipe.delete(self.seen_key)
        if stranded - set(again):
            pipe.sadd(self.seen_key, *sorted(stranded - set(again)))
            pipe.expire(self.seen_key, int(4 * self.period_s) + 1)
        pipe.execute()
        if again:
            log.warning("dispatched again %d job(s) left without a step: %s", len(again), again)
        return again
