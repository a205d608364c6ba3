"""Helpers shared by the benchmark scripts (run as ``python bench/NAME.py``)."""

from __future__ import annotations

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
        method, *kvs = spec.split()
        options = {k: parse_value(v) for k, v in (kv.split("=", 1) for kv in kvs)}
        cfg = config_from_options(method=method, **options)
        named = set(options) | {"geo", "refine"}  # optimizer/refinement fields travel inside these two
        overrides = {k: getattr(cfg, k) for k in cfg.__dataclass_fields__ if k in named and k != "method"}
        out.append((spec.strip(), method, overrides))
    return out


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
            cells.append(f"{100 * v:.1f}" if spec == "%" else format(v, spec))
        print("| " + " | ".join(cells) + " |")
