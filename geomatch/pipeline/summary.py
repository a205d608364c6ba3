"""summary.json's fields, whoever writes them (the mapping, the plan, the GCP fit, the runners) and
whoever reads them (the report, the console, ``geomatch export``, the service's clients): one
record, so that a field a reader expects is one a writer is known to give."""

from __future__ import annotations

from typing import Any, TypedDict


class Summary(TypedDict, total=False):
    # the model (geomatch.sfm.mapping)
    mapper: str
    mapper_requested: str
    models: int
    mapping_settings: dict[str, Any]  # reconstruction.MappingSettings.as_dict
    registered: int
    images: int
    points3D: int
    observations: int
    mean_track_length: float
    mean_observations_per_image: float
    mean_reprojection_error: float
    track_lengths: dict[str, int]
    registered_names: list[str]
    unregistered_names: list[str]
    view_graph: dict[str, Any] | None
    joined_models: list[dict[str, Any]]
    joins_refused: list[dict[str, Any]]
    placed_from_pairs: list[dict[str, Any]]
    mapping_attempts: int
    pair_agreement: dict[str, Any] | None
    unvouched_left_out: list[str]
    track_refinement: dict[str, Any] | None
    thinning: dict[str, Any] | None
    mapping_seconds: dict[str, float]
    prior_adjustment: dict[str, Any] | None
    gps_check: dict[str, Any] | None
    # its frame (geomatch.geo.georef.summary_fields; geomatch.geo.gcp over it)
    georeferenced: bool
    gps_images: int
    frame: str
    origin: dict[str, Any]
    ecef_from_enu: list[list[float]]
    vertical: str
    alignment: dict[str, Any]
    gcp: dict[str, Any]
    gps_frame_before_gcp: dict[str, Any]
    # the plan (plan.Plan.summary_fields) and the database it filled
    pairs: int
    pair_plan: str
    tiled_pairs: int
    aerial: list[str]
    database: dict[str, int]
    pose_priors: int
    # what it took, and the report made of all of it (geomatch.report)
    timings: dict[str, float]
    report: dict[str, Any]
    # the map of a georeferenced model (geomatch.ortho)
    ortho: dict[str, Any]
    # ``geomatch run``'s own
    image_dir: str
    method: str
    pairs_matched_now: int
    options: dict[str, Any]
    # a reconstruct job's own
    job_id: str


FIELDS = frozenset(Summary.__annotations__)
RUN_FIELDS = frozenset({"image_dir", "method", "pairs_matched_now", "options"})
JOB_FIELDS = frozenset({"job_id"})
