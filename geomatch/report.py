"""The survey report: what a survey team checks before it delivers a model.

A run's summary.json holds everything measured, keyed as the stages wrote it; the report picks
what decides whether a survey is usable (photos left out, points and their track lengths,
reprojection error, how well the model fits the photos' GPS and the ground control points, the
check-point RMSE, pairs the view-graph checks dropped, time per stage) into one JSON (the
summary's ``report``, also a job's result) and one Markdown page (``geomatch report OUT``), as
OpenDroneMap's quality report does for a task. It reads a summary only: a report of an older run
is built the same way from its summary.json.

Names in a report are the clients' (project, image and point names, a GCP file's coordinate system
and its problems), and a Markdown page is rendered by whatever reads it: every such text goes into
the page through ``escape_markdown``, so ``<script>``, ``[c](javascript:...)`` or a ``|`` in a
name shows as those characters instead of markup, HTML or a broken table.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

# GPS residuals beyond this many times the fit's median are listed by name: the fixes a survey
# team looks at first (a photo taken during take-off, a fix from before the lock)
GPS_OUTLIER_FACTOR = 3.0
MIN_GPS_OUTLIER_M = 1.0


# what opens markup inside a line: HTML and autolinks (<, >, &), links and images ([, ], !), code,
# emphasis and strikethrough (*, ~, and _ at a word's edge: inside a word it opens nothing, and
# IMG_0001.JPG stays readable), table cells (|), and the escape itself
_MARKUP = re.compile(r"[\\`*\[\]<>|~&!]|(?<![0-9A-Za-z])_|_(?![0-9A-Za-z])")


def escape_markdown(value: Any) -> str:
    """``value`` as text that renders as itself in Markdown (CommonMark, GitHub's tables) and
    holds no HTML: one line (line breaks and other control characters become spaces), every
    character that could open markup escaped with a backslash."""
    text = "".join(ch if ch.isprintable() else " " for ch in str(value))
    return _MARKUP.sub(lambda m: "\\" + m.group(0), text)


def survey_report(summary: Mapping[str, Any]) -> dict[str, Any]:
    """The report of a run or a reconstruct job from its summary."""
    out: dict[str, Any] = {
        "photos": _photos(summary),
        "model": _model(summary),
        "pairs": _pairs(summary),
        "georeferencing": _georeferencing(summary),
        "timings_s": _timings(summary),
    }
    if summary.get("ortho"):
        out["map"] = _map(summary["ortho"])
    return out


def _map(o: Mapping[str, Any]) -> dict[str, Any]:
    """The orthophoto and DSM (geomatch.ortho's record): what a team checks before sending a map."""
    if o.get("skipped"):
        return {"skipped": o["skipped"]}
    extent = o.get("extent_m") or [None, None]
    return {
        "gsd_cm": _round(100.0 * float(o["gsd_m"]), 2) if o.get("gsd_m") is not None else None,
        "dsm_cell_m": _round(o.get("dsm_cell_m"), 3),
        "extent_m": [_round(extent[0], 1), _round(extent[1], 1)],
        "area_ha": _round(float(o["area_m2"]) / 1e4, 3) if o.get("area_m2") is not None else None,
        "size_px": o.get("size_px"),
        "crs": o.get("crs"),
        "bounds_wgs84": o.get("bounds_wgs84"),
        "photos": o.get("photos"),
        "seconds": (o.get("seconds") or {}).get("total"),
        # the preview's size, the cameras and GCPs on it (fractions of it): the console's map
        "preview": o.get("preview") if isinstance(o.get("preview"), dict) else None,
        "gcp_targets": _targets(o.get("gcp_targets")),
    }


def _targets(t: Any) -> dict[str, Any] | None:
    """The GCP targets found on the orthophoto: how many, and the check points' RMSE on it."""
    if not isinstance(t, Mapping):
        return None
    return {
        "found": t.get("found"),
        "points": len(t.get("points") or []),
        "check_rmse_horizontal_m": t.get("check_rmse_horizontal_m"),
        "model_check_rmse_horizontal_m": t.get("model_check_rmse_horizontal_m"),
    }


def _photos(s: Mapping[str, Any]) -> dict[str, Any]:
    return {
        "images": s.get("images"),
        "registered": s.get("registered"),
        "unregistered": list(s.get("unregistered_names", [])),
        "left_out": _left_out(s),
        "aerial": len(s.get("aerial", [])),
        "with_gps": s.get("gps_images"),
    }


def _left_out(s: Mapping[str, Any]) -> list[dict[str, str]]:
    """The photos the mapping registered and then kept out of the model on purpose, each with why:
    a user should know a photo is missing because its place could not be vouched for, not only
    that it is missing."""
    out = [
        {"name": str(n), "why": "its own pairs do not vouch for where the mapper placed it"}
        for n in s.get("unvouched_left_out") or []
    ]
    for j in s.get("joins_refused") or []:
        why = f"joined to the model through {j.get('via')} only: {j.get('reason', 'refused')}"
        out += [{"name": str(n), "why": why} for n in j.get("images", [])]
    return out


def _model(s: Mapping[str, Any]) -> dict[str, Any]:
    return {
        "models": s.get("models"),
        "points3D": s.get("points3D"),
        "observations": s.get("observations"),
        "mean_track_length": _round(s.get("mean_track_length"), 3),
        "track_lengths": dict(s.get("track_lengths", {})),
        "mean_reprojection_error_px": _round(s.get("mean_reprojection_error"), 3),
    }


def _pairs(s: Mapping[str, Any]) -> dict[str, Any]:
    db = s.get("database") or {}
    vg = s.get("view_graph") or {}
    dropped = [
        {"pair": d["pair"], "check": "loops", "why": f"{d['broken_loops']} of {d['loops']} loops broken"}
        for d in vg.get("dropped", [])
    ] + [
        {"pair": d["pair"], "check": "tree", "why": f"{d['degrees']} deg from the rest over {d['hops']} hops"}
        for d in vg.get("tree_dropped", [])
    ]
    return {
        "planned": s.get("pairs"),
        "plan": s.get("pair_plan"),
        "tiled": s.get("tiled_pairs"),
        "verified": db.get("verified_pairs"),
        "dropped_by_view_graph": dropped,
    }


def _georeferencing(s: Mapping[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {"georeferenced": bool(s.get("georeferenced")), "frame": s.get("frame")}
    al = s.get("alignment")
    if al:
        rows = al.get("per_image", [])
        median = al.get("median_m") or 0.0
        limit = max(GPS_OUTLIER_FACTOR * median, MIN_GPS_OUTLIER_M)
        out["gps"] = {
            "images": al.get("correspondences"),
            "inliers": al.get("inliers"),
            "median_m": _round(al.get("median_m"), 3),
            "rmse_m": _round(al.get("rmse_m"), 3),
            "max_inlier_m": _round(al.get("max_inlier_m"), 3),
            "largest": sorted(
                (r for r in rows if r["residual_m"] > limit or not r["inlier"]),
                key=lambda r: -r["residual_m"],
            ),
        }
    held = s.get("gps_check")
    if held:
        out["gps_check"] = held
    gcp = s.get("gcp")
    if gcp:
        g: dict[str, Any] = {"crs": gcp.get("crs"), "points": [_gcp_point(p) for p in gcp.get("points", [])]}
        if "error" in gcp:
            g["error"] = gcp["error"]
            g["problems"] = gcp.get("problems", [])
            g["unusable"] = gcp.get("unusable", {})
        for key in ("control", "check"):
            for dim in ("horizontal", "3d"):
                k = f"{key}_rmse_{dim}_m"
                if k in gcp:
                    g[k] = gcp[k]
        # what the adjustment weighed the control points by, and what it did at the check points
        for k in ("accuracy_m", "check_rmse_similarity_only_m"):
            if k in gcp:
                g[k] = gcp[k]
        out["gcp"] = g
    return out


def _gcp_point(p: Any) -> dict[str, Any]:
    """A point of the summary's ``gcp`` as every report reads it: a dict with its role. A summary
    written before the points had one shape in every outcome holds bare names where the GCPs did
    not georeference the model."""
    if isinstance(p, Mapping):
        return dict(p)
    return {
        "name": str(p),
        "role": "unused",
        "observations": None,
        "observations_registered": None,
        "reason": "not placed: the GCPs did not georeference the model",
    }


def _timings(s: Mapping[str, Any]) -> dict[str, float]:
    t = dict(s.get("timings", {}))
    stages = {k: t[k] for k in ("plan", "matching", "writing", "mapping", "total") if k in t}
    for k, v in (s.get("mapping_seconds") or {}).items():
        stages[f"mapping: {k}"] = v
    return {k: round(float(v), 2) for k, v in stages.items()}


def _round(v: Any, nd: int) -> float | None:
    return None if v is None else round(float(v), nd)


def to_markdown(r: Mapping[str, Any], title: str = "Survey report") -> str:
    """The report as a page a survey team reads (and pastes into a delivery note); every text that
    came from a client goes through ``escape_markdown``."""
    e = escape_markdown
    ph, mo, pa, ge = r["photos"], r["model"], r["pairs"], r["georeferencing"]
    lines = [f"# {e(title)}", ""]
    lines += ["## Photos", ""]
    lines += [
        f"- registered: {ph['registered']} of {ph['images']}"
        + (f" (aerial: {ph['aerial']})" if ph.get("aerial") else ""),
        f"- with GPS: {ph['with_gps'] if ph.get('with_gps') is not None else 'none'}",
    ]
    if ph["unregistered"]:
        lines.append(f"- not registered: {', '.join(e(n) for n in ph['unregistered'])}")
    for o in ph.get("left_out", []):
        lines.append(f"  - {e(o['name'])}: left out, {e(o['why'])}")
    lines += ["", "## Model", ""]
    lines += [
        f"- models: {mo['models']} (the largest is reported)",
        f"- 3D points: {mo['points3D']}, observations: {mo['observations']}",
        f"- mean track length: {mo['mean_track_length']}, mean reprojection error: "
        f"{mo['mean_reprojection_error_px']} px",
    ]
    if mo["track_lengths"]:
        lines += ["", "| track length | " + " | ".join(e(k) for k in mo["track_lengths"]) + " |"]
        lines += ["|---|" + "---:|" * len(mo["track_lengths"])]
        lines += ["| points | " + " | ".join(e(v) for v in mo["track_lengths"].values()) + " |"]
    lines += ["", "## Pairs", ""]
    lines += [
        f"- planned: {pa['planned']} ({e(pa['plan'])})"
        + (f", tiled: {pa['tiled']}" if pa.get("tiled") else ""),
        f"- verified: {pa['verified']}",
        f"- dropped by the view-graph checks: {len(pa['dropped_by_view_graph'])}",
    ]
    lines += [
        f"  - {' x '.join(e(n) for n in d['pair'])}: {e(d['why'])}" for d in pa["dropped_by_view_graph"]
    ]
    lines += ["", "## Georeferencing", ""]
    frame = {"ENU": "ENU metres around the photos' GPS", "GCP": "the GCPs' coordinate system"}
    lines.append(
        f"- frame: {e(frame.get(ge['frame'], ge['frame']))}" if ge["georeferenced"] else "- not georeferenced"
    )
    if "gps" in ge:
        gp = ge["gps"]
        lines.append(
            f"- camera centres vs GPS: median {gp['median_m']} m, RMSE {gp['rmse_m']} m, largest inlier "
            f"{gp['max_inlier_m']} m ({gp['inliers']} of {gp['images']} fixes used)"
        )
        for row in gp["largest"]:
            note = "" if row["inlier"] else " (not used: outlier)"
            lines.append(f"  - {e(row['name'])}: {row['residual_m']} m{note}")
    if "gps_check" in ge:
        lines += _gps_check_markdown(ge["gps_check"])
    if "gcp" in ge:
        lines += _gcp_markdown(ge["gcp"])
    if r.get("map"):
        lines += _map_markdown(r["map"])
    lines += ["", "## Time per stage (s)", "", "| stage | s |", "|---|---:|"]
    lines += [f"| {e(k)} | {v} |" for k, v in r["timings_s"].items()]
    return "\n".join(lines) + "\n"


def _map_markdown(m: Mapping[str, Any]) -> list[str]:
    e = escape_markdown
    if m.get("skipped"):
        return ["", "## Map", "", f"- no map: {e(m['skipped'])}"]
    size = m.get("size_px") or [None, None]
    ext = m.get("extent_m") or [None, None]
    return [
        "",
        "## Map",
        "",
        f"- orthophoto: {m['gsd_cm']} cm per pixel (GSD), {size[0]} x {size[1]} pixels, "
        f"{ext[0]} x {ext[1]} m, {m['area_ha']} ha mapped",
        f"- surface model (DSM): {m['dsm_cell_m']} m cells, from the sparse points",
        f"- coordinate system: {e(m['crs'])}",
        *_targets_markdown(m.get("gcp_targets")),
    ]


def _targets_markdown(t: Mapping[str, Any] | None) -> list[str]:
    if not t:
        return []
    line = f"- GCP targets found on the orthophoto: {t['found']} of {t['points']}"
    if t.get("check_rmse_horizontal_m") is not None:
        line += (
            f"; check points measured on it: RMSE {t['check_rmse_horizontal_m']} m horizontal "
            f"(the model's: {t['model_check_rmse_horizontal_m']} m)"
        )
    return [line]


def _gps_check_markdown(g: Mapping[str, Any]) -> list[str]:
    """The cameras the mapping found beyond the fixes' fitted noise, and what it did with them."""
    e = escape_markdown
    lines = [
        f"- cameras held to their GPS fixes: fitted noise {g['sigma_m']} m (horizontal), limit "
        f"{g['limit_m']} m; {len(g['found']) + len(g.get('kept_fix_off_track', []))} camera(s) beyond it"
    ]
    lines += [
        f"  - {e(o['name'])}: placed again, {o['residual_m']} m from its fix" for o in g["placed_again"]
    ]
    lines += [
        f"  - {e(o['name'])}: taken out of the model, {o['residual_m']} m from its fix"
        for o in g["taken_out"]
    ]
    lines += [
        f"  - {e(o['name'])}: kept, {o['residual_m']} m from its fix, which lies off the flight track of the "
        "photos before and after it while the camera lies on it (a stale or wild fix)"
        for o in g.get("kept_fix_off_track", [])
    ]
    return lines


def _gcp_markdown(g: Mapping[str, Any]) -> list[str]:
    """The GCP section in every outcome: georeferenced (the RMSEs, the accuracy, a row per point) or
    not (why, and a row per point with why it was not used)."""
    e = escape_markdown
    lines = ["", "### Ground control points", ""]
    if g.get("crs"):
        lines.append(f"- coordinate system: {e(g['crs'])}")
    if g.get("error"):
        lines.append(f"- not georeferenced by the GCPs: {e(g['error'])}")
    for key, label in (("check", "check-point RMSE"), ("control", "control-point RMSE")):
        if f"{key}_rmse_horizontal_m" in g:
            lines.append(
                f"- {label}: {g[f'{key}_rmse_horizontal_m']} m horizontal, {g[f'{key}_rmse_3d_m']} m 3D"
            )
    sim = g.get("check_rmse_similarity_only_m")
    if sim:
        lines.append(
            f"- check-point RMSE before the adjustment: {sim['horizontal']} m horizontal, {sim['3d']} m 3D"
        )
    acc = g.get("accuracy_m")
    if acc:
        how = "as given" if acc["source"] == "given" else "estimated from their residuals"
        if acc.get("note"):
            how += f"; {acc['note']}"
        lines.append(
            f"- control points held to {acc['horizontal']} m horizontal, {acc['vertical']} m vertical "
            f"({e(how)})"
        )
    points = [_gcp_point(p) for p in g.get("points") or []]
    if points:
        lines += ["", "| point | role | photos (registered) | dx m | dy m | dz m | 3D m | note |"]
        lines += ["|---|---|---:|---:|---:|---:|---:|---|"]
        for p in points:
            cells = [_cell(p.get(k)) for k in ("dx_m", "dy_m", "dz_m", "3d_m")]
            note = p.get("reason") or (
                f"reprojection {p['reprojection_px']} px" if p.get("reprojection_px") is not None else ""
            )
            seen = p.get("observations")
            photos = "" if seen is None else f"{seen} ({p.get('observations_registered') or 0})"
            lines.append(
                f"| {e(p.get('name'))} | {e(p.get('role'))} | {photos} | "
                + " | ".join(cells)
                + f" | {e(note)} |"
            )
    return lines


def _cell(v: Any) -> str:
    return "" if not isinstance(v, int | float) else f"{v:.3f}"
