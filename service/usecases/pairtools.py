"""Pair tools: two images matched where the networks run (a worker, or the embedded runner),
nothing kept."""

from __future__ import annotations

import os
import shutil
import time
import uuid
from collections.abc import Iterable
from typing import Any

import numpy as np

from geomatch.options import (
    CAPTURES,
    PAIR_OPTIONS,  # what match_two accepts of DEFAULTS
)
from geomatch_core.errors import InvalidRequest, Unavailable
from geomatch_core.queue import MATCH_TWO

from ..validation import check_name
from .base import DEFAULTS, UseCases, check_config, choice
from .views import PairMatchView, Upload


class PairToolUseCases(UseCases):
    def match_two(
        self,
        tenant_id: str,
        uploads: Iterable[Upload],
        options: dict[str, Any] | None = None,
        timeout_s: float = 600.0,
    ) -> PairMatchView:
        """Two images in, matches out, nothing kept. The images pass the upload checks, then the
        queue's interactive path matches them where heavy work runs (a worker, or the embedded
        runner), so this process never loads a network. ``timeout_s`` also reaches the worker,
        which drops the pair once it has passed."""
        opts = check_config(options or {})
        extra = sorted(set(opts) - set(PAIR_OPTIONS))
        if extra:
            raise InvalidRequest(f"option(s) {', '.join(extra)} do not apply to a single pair")
        opts = {k: opts.get(k, DEFAULTS[k]) for k in PAIR_OPTIONS}
        work = self.ctx.storage.tmp_dir / f"pair-{uuid.uuid4().hex}"  # shared with the workers
        work.mkdir(parents=True)
        try:
            captures: list[str] = []
            for up in uploads:
                if len(captures) == 2:
                    raise InvalidRequest("a pair is two images; a third was sent")
                name = check_name(up.name)
                captures.append(choice("capture", up.capture or "auto", CAPTURES))
                os.replace(self._stage(name, up.stream).path, work / str(len(captures) - 1))
            if len(captures) != 2:
                raise InvalidRequest(f"a pair is two images; {len(captures)} were sent")
            deadline = time.time() + timeout_s
            try:
                out = self.ctx.queue.call(MATCH_TWO, work.name, captures, opts, deadline, timeout=timeout_s)
            except TimeoutError:
                raise Unavailable(f"no worker matched the pair within {timeout_s:.0f}s") from None
            if out.get("error"):
                raise Unavailable(f"matching the pair failed: {out['error']}")
            with np.load(work / out["file"]) as z:
                return PairMatchView(
                    keypoints0=z["keypoints0"],
                    keypoints1=z["keypoints1"],
                    scores=z["scores"],
                    F=z["F"],
                    sizes=(_size(z["size0"]), _size(z["size1"])),
                    method=str(z["method"]),
                    tiled=bool(z["tiled"]),
                    timings={k: float(v) for k, v in out.get("timings", {}).items()},
                )
        finally:
            shutil.rmtree(work, ignore_errors=True)


def _size(a: np.ndarray) -> tuple[int, int]:
    return int(a[0]), int(a[1])
