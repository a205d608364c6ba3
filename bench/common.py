"""Helpers shared by the benchmark scripts (run as ``python bench/NAME.py``)."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from collections.abc import Callable
from typing import Any

from geomatch.matching.matcher import config_from_options


def parse_variants(variants: str | None, methods: str) -> list[tuple[str, str, dict[str, Any]]]:
    """(label, method, Matcher.derive overrides) per table row.

    ``variants`` is ';'-separated ``METHOD [option=value ...]`` with option names as accepted by
    ``match_pair`` (``tau=50``, ``iterations=0``, ``epipolar_sigma=none`` ...); without it, one row
    per comma-separated method.
    """
    if not variants:
        return [(m, m, {}) for m in methods.split(",")]
    out = []
    for spec in variants.split(";"):
        method, options = parse_method(spec)
        cfg = config_from_options(method=method, **options)
        named = set(options) | {"geo", "refine"}  # optimizer/refinement fields travel inside these two
        overrides = {k: getattr(cfg, k) for k in cfg.__dataclass_fields__ if k in named and k != "method"}
        out.append((spec.strip(), method, overrides))
    return out


def parse_method(spec: str) -> tuple[str, dict[str, Any]]:
    """``METHOD [option=value ...]``: the method and its options, values parsed as ``parse_value``."""
    method, *kvs = spec.split()
    return method, {k: parse_value(v) for k, v in (kv.split("=", 1) for kv in kvs)}


def parse_value(v: str) -> Any:
    for cast in (int, float):
        try:
            return cast(v)
        except ValueError:
            pass
    return {"true": True, "false": False, "none": None}.get(v.lower(), v)


def print_table(title: str, columns: list[tuple[str, str, str]], rows: list[dict[str, Any]]) -> None:
    """A markdown table: ``columns`` are (header, row key, format spec); '%' specs print x100."""
    print(f"\n{title}\n")
    print("| " + " | ".join(h for h, _, _ in columns) + " |")
    print("|---|" + "---:|" * (len(columns) - 1))
    for r in rows:
        cells = []
        for _, key, spec in columns:
            v = r[key]
            if v is None:
                cells.append("-")
            else:
                cells.append(f"{100 * v:.1f}" if spec == "%" else format(v, spec))
        print("| " + " | ".join(cells) + " |")


# -- one subprocess per (size, method) row ---------------------------------------------------------
def parse_args_or_run_row(
    ap: argparse.ArgumentParser, worker: Callable[[argparse.Namespace], None]
) -> argparse.Namespace:
    """The script's arguments; in the process ``run_rows`` starts for a row (hidden ``--worker``,
    ``--size``, ``--method``), ``worker`` runs that row instead and the process ends with it."""
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--size", type=int, default=640, help=argparse.SUPPRESS)
    ap.add_argument("--method", default="geo", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        worker(args)
        sys.exit(0)
    return args


def run_rows(script: str, sizes: str, methods: str, extra: list[str]) -> list[dict[str, Any]]:
    """Each (size, method) row run by ``script --worker`` in a fresh process, so that the peak
    memory it reports is its own; the row is what the worker printed after ``RESULT ``, echoed
    as it comes. ``extra``: the worker's other arguments."""
    rows = []
    for size in (int(s) for s in sizes.split(",")):
        for method in methods.split(","):
            cmd = [sys.executable, script, "--worker", "--size", str(size), "--method", method, *extra]
            res = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy())
            line = [ln for ln in res.stdout.splitlines() if ln.startswith("RESULT ")]
            if res.returncode or not line:
                sys.exit(f"worker failed for {size}/{method}:\n{res.stderr[-3000:]}")
            rows.append(json.loads(line[0][7:]))
            print(json.dumps(rows[-1]), flush=True)
    return rows
