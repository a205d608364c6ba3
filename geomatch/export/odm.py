"""``geomatch export --format odm``: a model laid out as OpenDroneMap lays out a task's results, so
that WebODM, PyODM scripts and the other drone tools find each file where they look (the NodeODM
node's ``all.zip`` is this folder plus the task's console output):

- ``odm_georeferencing/odm_georeferenced_model.laz``: the point cloud, absolute in the model's
  projected CRS, with colours (``laz``); georeferenced models only;
- ``odm_report/shots.geojson``: the registered photos on the map (``shots``); georeferenced only;
- ``cameras.json`` (OpenSfM's camera format, ``opensfm``) and ``images.json`` (``photos``);
- ``odm_report/stats.json`` (``stats``), ``odm_report/report.md`` and ``report.pdf`` (the survey
  report, ``reportpdf``);
- ``odm_georeferencing/ground_control_points.geojson`` (``gcpjson``) when the model's folder holds
  the GCP file it was georeferenced by (``gcp_list.txt``);
- ``odm_orthophoto/odm_orthophoto.tif`` and ``odm_dem/dsm.tif`` when the run's map was made
  (``mapfiles``: geomatch.ortho writes them into the run folder at these places), from which
  WebODM shows the map and takes the task's CRS.

No mesh and no dense cloud: geomatch makes a sparse model, and WebODM shows what exists.
"""

from __future__ import annotations

import json
from pathlib import Path

import pycolmap

from ..report import survey_report, to_markdown
from .gcpjson import write_gcp_geojson
from .georef import model_frame
from .laz import LAZ_NAME, model_points, write_laz
from .mapfiles import copy_map
from .opensfm import write_cameras_json
from .photos import read_photos, write_images_json
from .reportpdf import write_pdf
from .shots import write_shots
from .source import ExportError, Source
from .stats import write_stats

GEOREF, REPORT = "odm_georeferencing", "odm_report"
GCP_FILE = "gcp_list.txt"  # beside summary.json: the file a model was georeferenced by


def write(source: Source, dest: Path) -> list[Path]:
    if source.summary is None:
        raise ExportError("the odm export needs the run's summary.json")
    summary = json.loads(source.summary.read_text())
    rec = pycolmap.Reconstruction(str(source.model))
    photos = read_photos(rec, source.images)
    written = [
        write_cameras_json(dest / "cameras.json", rec, photos),
        write_images_json(dest / "images.json", rec, photos),
        write_stats(dest / REPORT / "stats.json", summary),
    ]
    markdown = to_markdown(summary.get("report") or survey_report(summary))
    (dest / REPORT / "report.md").write_text(markdown)
    written += [dest / REPORT / "report.md", write_pdf(dest / REPORT / "report.pdf", markdown)]
    frame = model_frame(summary)
    if frame is not None:
        xyz, rgb = model_points(source.model)
        written.append(write_laz(dest / GEOREF / LAZ_NAME, xyz, rgb, frame))
        written.append(write_shots(dest / REPORT / "shots.geojson", rec, frame, photos))
        written += copy_map(source, dest)
    gcp_file = source.summary.parent / GCP_FILE
    if summary.get("gcp") and gcp_file.is_file():
        sizes = {name: (p.width, p.height) for name, p in photos.items()}
        out = write_gcp_geojson(
            dest / GEOREF / "ground_control_points.geojson", gcp_file.read_text(), sizes, summary["gcp"]
        )
        if out is not None:
            written.append(out)
    return written
