"""Every step a runner knows, registered statically. ``workers.local`` (embedded) and
``workers.tasks`` (Celery) run exactly this table, so every step exists in every mode."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from geomatch_core.queue import (
    LOCALIZE,
    MATCH_PAIR,
    MATCH_TWO,
    PLAN_FEATURES,
    PLAN_MATCH,
    RECONSTRUCT,
    RENDER_PAIR,
)

from . import jobs, localize, pairmatch, photosteps

STEPS: dict[str, Callable[..., Any]] = {
    PLAN_MATCH: jobs.plan_match,
    PLAN_FEATURES: photosteps.plan_features,
    MATCH_PAIR: jobs.match_pair,
    RECONSTRUCT: jobs.reconstruct,
    LOCALIZE: localize.localize,
    RENDER_PAIR: pairmatch.render_pair,
    MATCH_TWO: pairmatch.match_two,
}
ANSWERED = frozenset({RENDER_PAIR, MATCH_TWO})  # their results go back to a waiting caller
# acknowledged at once and never retried: the caller waits with a deadline, a redelivery is wasted
ONE_SHOT = frozenset({MATCH_TWO})
