"""``ground_control_points.geojson``: the survey's control and check points on WGS84, with what
the georeferencing made of each (role, residual), which WebODM offers for download and GIS tools
draw over the map. The points are where the GCP file puts them (its metric frame to WGS84); the
residuals are the summary's (``gcp.points``)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pyproj

from ..geo.gcpfile import GcpError, read_gcp_file
from .georef import WGS84


def gcp_geojson(
    text: str, sizes: Mapping[str, tuple[int, int]], summary_gcp: Mapping[str, Any]
) -> dict[str, Any]:
    """The points of a gcp_list.txt (``text``, read against the images' ``sizes``) with the
    summary's verdict on each; GcpError when the file cannot be read."""
    gcps = read_gcp_file(text, sizes)
    to_wgs = pyproj.Transformer.from_crs(gcps.frame, WGS84, always_xy=True)
    verdict = {str(p.get("name")): p for p in summary_gcp.get("points", []) if isinstance(p, Mapping)}
    features = []
    for name in sorted(gcps.points):
        p = gcps.points[name]
        lon, lat = to_wgs.transform(float(p.xyz[0]), float(p.xyz[1]))
        v = verdict.get(name, {})
        props: dict[str, Any] = {
            "id": name,
            "role": v.get("role"),
            "observations_count": len(p.observations),
            "observations_list": [
                {"image": o.image, "x": o.pixel[0], "y": o.pixel[1]} for o in p.observations
            ],
            "error_x": v.get("dx_m"),
            "error_y": v.get("dy_m"),
            "error_z": v.get("dz_m"),
            "projected": [float(c) for c in p.xyz],
        }
        features.append(
            {
                "type": "Feature",
                "properties": props,
                "geometry": {"type": "Point", "coordinates": [float(lon), float(lat), float(p.xyz[2])]},
            }
        )
    return {"type": "FeatureCollection", "crs_of_projected": gcps.frame.to_string(), "features": features}


def write_gcp_geojson(
    path: Path, text: str, sizes: Mapping[str, tuple[int, int]], summary_gcp: Mapping[str, Any]
) -> Path | None:
    """The file, or None when the GCP file no longer reads against the model's images."""
    try:
        doc = gcp_geojson(text, sizes, summary_gcp)
    except GcpError:
        return None
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1))
    return path
