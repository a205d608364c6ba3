"""The images a tiled project's first model lacks or misplaces, after COLMAP's mapper is done.

The incremental mapper leaves out an image that sees too few of the model's 3D points, and now
and then registers one in a wrong pose on right pairs (docs/pipeline.md, "Mapping"). Four
passes follow it, each only where it helps: a block of images the first model turns against
their pairs taken from it and joined again from the mapper's other model that holds them, the
mapper again at a lower PnP minimum, images placed from their pairs' relative poses (pairpose.py),
and images the model turns against their own pairs (modelagree.py) taken out and placed again.
What the pairs still do not vouch for at the end is left out of the model (:func:`leave_out_unvouched`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pycolmap

from ..geo.gpscheck import GpsCheck, beyond
from ..geo.similarity import umeyama
from ..options import LEFTOVER_MIN_POSE_INLIERS
from .modelagree import agreement, misplaced, misplaced_blocks, most_outvoted, unvouched, weakest_tied
from .modeljoin import Join, adjust, join_models
from .pairpose import Placement, place
from .viewgraph_filter import ViewGraphReport


@dataclass(frozen=True)
class Continuation:
    """What carrying the mapper on from a model needs: the mapper's database copy, the photos,
    the mapper's options, the project's image count and the images a join may rest on alone
    (modeljoin.join_models)."""

    database: Path
    image_dir: Path
    options: pycolmap.IncrementalPipelineOptions
    n_images: int
    bridges: frozenset[str] | None = None


def _deregister(model: pycolmap.Reconstruction, names: set[str]) -> None:
    """The posed images of ``model`` named in ``names`` taken out of it (in place)."""
    for im in list(model.images.values()):
        if im.name in names and im.has_pose:
            model.deregister_frame(im.frame_id)


def _posed_only(model: pycolmap.Reconstruction, work: Path) -> pycolmap.Reconstruction:
    """``model`` without its unposed images (written and read back, a model keeps its posed
    images), so that a join can add them again."""
    work.mkdir(parents=True, exist_ok=True)
    model.write_binary(str(work))
    return pycolmap.Reconstruction(str(work))


def rejoin_blocks(
    models: list[pycolmap.Reconstruction], report: ViewGraphReport, more: Continuation, work: Path
) -> tuple[list[pycolmap.Reconstruction], list[Join]]:
    """``models`` (largest first) with the blocks the first turns against their pairs
    (modelagree.misplaced_blocks) taken out of it and the later models joined into what is left
    (modeljoin.join_models), where that gives the blocks back and the first model then agrees with
    its pairs better; ``models`` as they were otherwise. Why: the mapper's second model often holds
    the block right (it started from those images, and stopped where the first already had them),
    and re-registering the block in the first would find the same wrong pose again; the joins, for
    the summary."""
    if len(models) < 2:
        return models, []
    first = models[0]
    blocks = misplaced_blocks(first, report.kept_rotations, report.kept_inliers)
    out = {name for block in blocks for name in block}
    if not out or 2 * len(out) >= first.num_reg_images():
        return models, []
    trimmed = pycolmap.Reconstruction(first)
    _deregister(trimmed, out)
    trimmed = _posed_only(trimmed, work / "trimmed")
    joined, joins = join_models(
        [trimmed, *models[1:]], more.database, more.image_dir, work / "joined", more.options, more.bridges
    )
    back = {im.name for im in joined[0].images.values() if im.has_pose}
    before = agreement(first, report.kept_rotations, report.kept_inliers)
    after = agreement(joined[0], report.kept_rotations, report.kept_inliers)
    if not out <= back or after.score <= before.score:
        return models, []
    return joined, joins


def register_leftovers(
    model: pycolmap.Reconstruction, more: Continuation, work: Path
) -> pycolmap.Reconstruction:
    """``model`` continued by the incremental mapper at LEFTOVER_MIN_POSE_INLIERS for the images
    of the project it lacks (options.py says why); ``model`` itself when that registers nothing
    more. ``work``: a scratch folder."""
    database, image_dir, options = more.database, more.image_dir, more.options
    if model.num_reg_images() == 0 or model.num_reg_images() >= more.n_images:
        return model
    start, cont = work / "leftovers_in", work / "leftovers_out"
    start.mkdir(parents=True, exist_ok=True)
    cont.mkdir(parents=True, exist_ok=True)
    model.write_binary(str(start))
    again = pycolmap.IncrementalPipelineOptions(options.todict())
    floor = options.mapper.abs_pose_min_num_inliers
    again.mapper.abs_pose_min_num_inliers = min(LEFTOVER_MIN_POSE_INLIERS, floor)
    again.multiple_models = False
    found = pycolmap.incremental_mapping(
        str(database), str(image_dir), str(cont), again, input_path=str(start)
    )
    best = max(found.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()), default=None)
    return best if best is not None and best.num_reg_images() > model.num_reg_images() else model


def place_leftovers(
    model: pycolmap.Reconstruction, more: Continuation, work: Path
) -> tuple[pycolmap.Reconstruction, list[Placement]]:
    """``model`` with the images it lacks placed from their pairs' relative poses where no 3D
    point reaches them (pairpose.py), one at a time: each placed image's matches are triangulated
    with the poses held and the mapper carries on from there (:func:`register_leftovers`), which
    may register others the new points reach; the placements made, for the summary."""
    database, n_images = more.database, more.n_images
    placements: list[Placement] = []
    db = pycolmap.Database.open(str(database))
    try:
        names = {im.image_id: im.name for im in db.read_all_images()}
        pair_ids, geometries = db.read_two_view_geometries()
        pairs = [
            (*pycolmap.pair_id_to_image_pair(p), len(g.inlier_matches))
            for p, g in zip(pair_ids, geometries, strict=True)
        ]
    finally:
        db.close()
    for step in range(n_images):
        registered = {i for i, im in model.images.items() if im.has_pose}
        if model.num_reg_images() == 0 or len(registered) >= n_images:
            break
        # the images most tied to the model first: their poses rest on the most inliers
        mass: dict[int, int] = {}
        for a, b, n in pairs:
            for x, y in ((a, b), (b, a)):
                if x not in registered and y in registered:
                    mass[x] = mass.get(x, 0) + n
        trial = pycolmap.Reconstruction(model)
        placed = None
        for image_id in sorted(mass, key=lambda i: -mass[i]):
            placed = place(trial, database, names[image_id])
            if placed is not None:
                break
        if placed is None:
            break
        out = work / f"placed_{step}"
        out.mkdir(parents=True, exist_ok=True)
        trial = pycolmap.triangulate_points(
            trial, str(database), str(more.image_dir), str(out), clear_points=False, options=more.options
        )
        adjust(trial)
        grown = register_leftovers(trial, more, out)
        placements.append(placed)
        model = grown
    return model, placements


def replace_misplaced(
    model: pycolmap.Reconstruction, report: ViewGraphReport, more: Continuation, work: Path
) -> tuple[pycolmap.Reconstruction, list[Placement]]:
    """``model`` with the images it places against their own pairs (modelagree.misplaced) taken
    out and placed again from those pairs (:func:`place_leftovers`), where the model then agrees
    with its pairs better; ``model`` itself otherwise."""
    off = set(misplaced(model, report.kept_rotations, report.kept_inliers))
    if not off or 2 * len(off) >= model.num_reg_images():
        return model, []
    before = agreement(model, report.kept_rotations, report.kept_inliers)
    trial = pycolmap.Reconstruction(model)
    _deregister(trial, off)
    trial, placed = place_leftovers(trial, more, work)
    if agreement(trial, report.kept_rotations, report.kept_inliers).score <= before.score:
        return model, []
    if any(not im.has_pose for im in trial.images.values()):
        # an image taken out and not placed again stays out, as the mapper's own models leave
        # out what they do not register
        trial = _posed_only(trial, work / "posed")
    return trial, placed


def leave_out_unvouched(
    model: pycolmap.Reconstruction, report: ViewGraphReport, work: Path
) -> tuple[pycolmap.Reconstruction, list[str]]:
    """``model`` without the cameras its own pairs do not vouch for (modelagree.unvouched), and
    their names. Why: the passes above and the mapping attempts keep what holds its pairs best,
    and a camera still held by no pair with the rest of the model is one whose place nothing
    checks; a user cannot tell it from the right ones, and a photo localized against it lands
    wherever it is. The cameras the pairs speak against go first, then those tied between two
    rotations (a camera held wrong bends its neighbours' pairs into ties, which go with it).
    Where the doubted are half of what is left or more, only the worst goes (the most outvoted,
    else the tied one held by the fewest inliers), and the rest are judged again without it; never
    half of the model in all: then which side is right is no longer clear, and the attempts'
    agreement decided."""
    rotations, inliers = report.kept_rotations, report.kept_inliers
    start = model.num_reg_images()
    left_out: list[str] = []
    for ties in (False, True):
        while True:
            out = set(unvouched(model, rotations, inliers, ties=ties))
            if out and 2 * len(out) >= model.num_reg_images():
                worst = most_outvoted(model, rotations, inliers)
                if worst is None and ties:
                    worst = weakest_tied(model, rotations, inliers)
                out = {worst} if worst is not None else set()
            if not out or 2 * (len(left_out) + len(out)) >= start:
                break
            trimmed = pycolmap.Reconstruction(model)
            _deregister(trimmed, out)
            model = _posed_only(trimmed, work / f"vouched_{len(left_out)}")
            left_out += sorted(out)
    return model, sorted(left_out)


def hold_to_fixes(
    model: pycolmap.Reconstruction,
    enu: Mapping[str, np.ndarray],
    found: GpsCheck,
    more: Continuation,
    work: Path,
) -> tuple[pycolmap.Reconstruction, GpsCheck]:
    """``model`` (in the fixes' ENU frame) with the cameras ``found`` beyond the fitted GPS limit
    taken out and the mapper carried on at the leftovers' PnP minimum (:func:`register_leftovers`)
    for them and for every image the model lacks, then each camera still beyond the limit taken out
    for good; ``found`` with what was placed again and what was taken out. Why carry on rather than
    only take out: the wrong pose came from the mapper's order (a photo registered from a wrong
    pair before its right neighbours were in); with those in, the photo's PnP against the model's
    points finds its true pose, and the limit judges it again. The images the model never held
    come along (the ends of flight lines, photos in turns), judged by the same limit."""
    trial = pycolmap.Reconstruction(model)
    off = {o.name for o in found.offenders}
    _deregister(trial, off)
    if off:
        trial = _posed_only(trial, work / "trimmed")
    grown = register_leftovers(trial, more, work)
    wild = {o.name for o in found.wild_fixes}  # kept where they are: their fixes are off the track
    if grown is not trial:
        _back_to_fixes(grown, enu, [n for n in found.residuals if n not in off and n not in wild])
    still = [o for o in beyond(grown, enu, found.limit_m) if o.name not in wild]
    if still:
        out = {o.name for o in still}
        _deregister(grown, out)
    grown = _posed_only(grown, work / "held")
    posed = {im.name for im in grown.images.values() if im.has_pose}
    replaced = tuple(
        replace(o, residual_m=float(np.linalg.norm(c - enu[o.name])))
        for o in found.offenders
        if o.name in posed
        for c in [_centre(grown, o.name)]
    )
    return grown, replace(found, replaced=replaced, taken_out=tuple(still))


def _back_to_fixes(model: pycolmap.Reconstruction, enu: Mapping[str, np.ndarray], trusted: list[str]) -> None:
    """``model`` moved back into the fixes' frame after the mapper carried it on (its bundle
    adjustment lets the frame go and COLMAP normalises the model's scale and centre), by the least
    squares similarity of the cameras that agreed with their fixes before."""
    centres = {im.name: im.projection_center() for im in model.images.values() if im.has_pose}
    names = [n for n in trusted if n in centres]
    if len(names) < 3:
        return
    src = np.stack([np.asarray(centres[n], np.float64) for n in names])
    dst = np.stack([np.asarray(enu[n], np.float64) for n in names])
    model.transform(umeyama(src, dst).to_pycolmap())


def _centre(model: pycolmap.Reconstruction, name: str) -> np.ndarray:
    im = model.find_image_with_name(name)
    return np.asarray(im.projection_center(), np.float64)
