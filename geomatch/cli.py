"""The library's commands of ``geomatch``: match, synth, run, eval, demo, export, localize.

``register`` adds them to a parser: the ``geomatch`` command (``geomatch_app.cli``) adds the service's
beside them. ``python -m geomatch.cli`` runs the library's commands alone. Imports stay light
here (the library is imported inside each command), so parsing costs no torch.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from . import options
from .export.formats import FORMATS, choices_help
from .options import EXIT_BAD_INPUT, EXIT_FAILED
from .synth.command import register as register_synth

if TYPE_CHECKING:
    from .pipeline import RunOptions

# the demo's scene: 2 aerial + 4 ground (15 pairs, 8 tiled), small enough to run in minutes on a
# CPU; its times and results: docs/benchmarks.md, "The demo scene"
DEMO_AERIAL, DEMO_GROUND = 2, 4


def _add_matching_options(p: argparse.ArgumentParser) -> None:
    options.add_arguments(p, options.MATCH_OPTIONS)
    options.add_arguments(p.add_argument_group("optimizer (paper defaults)"), options.OPTIMIZER_OPTIONS)


def _add_verbose(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--verbose", action="store_true", help="also print COLMAP's own log (glog lines of pycolmap)"
    )


def _matching_options(args: argparse.Namespace) -> dict[str, object]:
    return options.resolve(options.given(args, options.MATCH_OPTIONS + options.OPTIMIZER_OPTIONS))


def cmd_match(args: argparse.Namespace) -> int:
    from .imageio import ImageReadError, read_image
    from .matching.matcher import match_pair

    try:
        image0, image1 = read_image(args.image0), read_image(args.image1)
    except ImageReadError as e:
        print(f"geomatch: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    t0 = time.perf_counter()
    try:
        result = match_pair(image0, image1, **_matching_options(args))
    except ValueError as e:  # bad option values: unknown device, CUDA absent ...
        print(f"geomatch: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    elapsed = time.perf_counter() - t0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    result.save_npz(args.out)
    if args.viz is not None:
        from .viz import save_matches

        args.viz.parent.mkdir(parents=True, exist_ok=True)
        save_matches(args.viz, image0, image1, result)
    stages = ", ".join(f"{k} {v:.2f}s" for k, v in result.timings.items() if k != "total")
    print(f"{len(result)} matches ({result.method}) in {elapsed:.2f}s [{stages}] -> {args.out}")
    return 0


def _run_options(args: argparse.Namespace) -> RunOptions:
    from .pipeline import RunOptions
    from .pipeline.pair_sources import read_pairs_file

    values = options.given(args, options.MATCH_OPTIONS + options.OPTIMIZER_OPTIONS + options.RUN_OPTIONS)
    pairs_list = None
    if Path(values["pairs"]).is_file():
        pairs_list, values["pairs"] = read_pairs_file(Path(values["pairs"]).read_text()), "exhaustive"
    aerial_names = None
    if args.aerial_list is not None:
        aerial_names = [ln.strip() for ln in args.aerial_list.read_text().splitlines() if ln.strip()]
    spec = args.checkpoints.strip()
    checkpoints: list[str] | int = (
        int(spec) if spec.isdigit() else [n.strip() for n in spec.split(",") if n.strip()]
    )
    return RunOptions.of(
        values,
        pairs_list=pairs_list,
        aerial_glob=args.aerial,
        aerial_names=aerial_names,
        verbose=args.verbose,
        gcp=str(args.gcp) if args.gcp is not None else None,
        checkpoints=checkpoints,
    )


def cmd_run(args: argparse.Namespace) -> int:
    from .pipeline import run

    try:
        summary = run(args.images, args.out, _run_options(args))
    except (ValueError, OSError) as e:  # PipelineError, PairSpecError, ImageReadError, bad device
        print(f"geomatch: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(format_summary(summary))
    if "gcp" in summary:
        print(format_gcp(summary["gcp"]))
    print(f"model: {args.out}/sparse/0 (binary + text), {args.out}/points.ply, {args.out}/summary.json")
    if "ortho" in summary:
        print(format_map(summary["ortho"], args.out))
    return 0


def format_map(record: Mapping[str, Any], out: Path) -> str:
    """The map's lines (geomatch.ortho's record), or why there is none."""
    if record.get("skipped"):
        return f"map: none: {record['skipped']}"
    w, h = record["size_px"]
    ew, eh = record["extent_m"]
    return (
        f"map: orthophoto {w} x {h} px at {100 * record['gsd_m']:.1f} cm ({ew:.0f} x {eh:.0f} m), "
        f"DSM {record['dsm_cell_m']:.2f} m cells, {record['crs']}\n"
        f"  {out}/{record['orthophoto']}, {out}/{record['dsm']}"
    )


def cmd_ortho(args: argparse.Namespace) -> int:
    from .ortho import MapOptions, OrthoError, make_map

    try:
        result = make_map(args.out, images=args.images, options=MapOptions(gsd=args.ortho_gsd or None))
    except (OrthoError, OSError) as e:
        print(f"geomatch: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(format_map(result.record, args.out))
    print(
        f"  {result.record['seconds']['total']:.1f} s; preview: {args.out}/{result.record['preview']['path']}"
    )
    return 0


def format_gcp(g: Mapping[str, Any]) -> str:
    """The GCP lines a surveyor reads first: what the fit used, how the check points came out,
    and every point left out with its reason."""
    lines = []
    if "error" in g:
        lines.append(f"GCPs: not georeferenced: {g['error']}")
    else:
        roles = [p["role"] for p in g["points"]]
        head = f"GCPs ({g['crs']}): {roles.count('control')} control, {roles.count('check')} check"
        if "check_rmse_horizontal_m" in g:
            head += (
                f"; check-point RMSE {g['check_rmse_horizontal_m']:.3f} m horizontal,"
                f" {g['check_rmse_3d_m']:.3f} m 3D"
            )
        if "control_rmse_3d_m" in g:
            head += f"; control RMSE {g['control_rmse_3d_m']:.3f} m 3D"
        lines.append(head)
        lines += [f"  {p['name']}: not used: {p['reason']}" for p in g["points"] if p["role"] == "unused"]
    lines += [
        f"  {problem}"
        for problem in g.get("problems", [])
        if problem.split(":")[0] not in g.get("unusable", {})
    ]
    return "\n".join(lines)


def format_summary(s: Mapping[str, Any]) -> str:
    t = s.get("timings", {})
    total = f" in {t['total']:.0f}s" if isinstance(t, dict) and "total" in t else ""
    return (
        f"registered {s['registered']}/{s['images']} images, {s['points3D']} 3D points, "
        f"mean track length {float(s['mean_track_length']):.2f}, "
        f"mean reprojection error {float(s['mean_reprojection_error']):.3f} px{total}"
    )


def cmd_eval(args: argparse.Namespace) -> int:
    from .eval.evaluate import evaluate_run

    try:
        result = evaluate_run(args.out, args.gt)
    except (ValueError, OSError) as e:
        print(f"geomatch: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(result.table())
    print(f"-> {args.out}/eval.json")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from .export import ExportError, export, open_run

    dest = args.to or args.out / "export" / args.format
    try:
        written = export(open_run(args.out, images=args.images), args.format, dest)
    except (ExportError, OSError) as e:
        print(f"geomatch: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(f"{args.format}: {len(written)} files -> {dest}")
    top = [p for p in written if p.parent == dest]
    for p in top:
        print(f"  {p.name}")
    folders = sorted({p.relative_to(dest).parts[0] for p in written if p.parent != dest})
    if folders:
        print(f"  and {len(written) - len(top)} files in {', '.join(f + '/' for f in folders)}")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    import json

    from .report import survey_report, to_markdown

    path = args.out / "summary.json" if args.out.is_dir() else args.out
    try:
        summary = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        print(f"geomatch: error: {path}: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if not isinstance(summary, dict) or "registered" not in summary:
        print(f"geomatch: error: {path} is not the summary of a run or a reconstruct job", file=sys.stderr)
        return EXIT_BAD_INPUT
    report = summary.get("report") or survey_report(summary)  # older runs carry no report
    print(json.dumps(report, indent=2) if args.json else to_markdown(report), end="\n" if args.json else "")
    return 0


def cmd_localize(args: argparse.Namespace) -> int:
    import json

    from .localize import LocalizeError, localizations_json, localize_photos

    missing = [str(p) for p in args.photos if not p.is_file()]
    if missing:
        print(f"geomatch: error: no such photo: {', '.join(missing)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        results = localize_photos(args.out, args.photos, add=args.add, images_dir=args.images)
    except (LocalizeError, ValueError, OSError) as e:
        print(f"geomatch: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.json:
        print(json.dumps(localizations_json(results), indent=2))
        return 0
    for r in results:
        print(format_localization(r.to_json()))
    if args.add:
        print(f"added to {args.out}/database.db: run `geomatch run` on the images again to map them")
    return 0


def format_localization(r: Mapping[str, Any]) -> str:
    """One photo's answer for a terminal: where it is, how sure, or why it was not placed."""
    if not r["localized"]:
        return f"{r['name']}: not localized ({r['reason']}) [{r['seconds']:.1f}s]"
    c = r["center"]
    lines = [
        f"{r['name']}: localized, confidence {r['confidence']}: centre ({c[0]:.3f}, {c[1]:.3f}, {c[2]:.3f}), "
        f"{r['inliers']}/{r['matches']} inliers, reprojection error {r['reprojection_error_px']:.2f} px "
        f"[{r['seconds']:.1f}s]"
    ]
    if r["wgs84"]:
        g = r["wgs84"]
        lines.append(
            f"  lat {g['lat']:.7f} lon {g['lon']:.7f} alt {g['alt']:.2f} m, "
            f"heading {g['heading_deg']:.1f} deg"
        )
    lines.append(f"  supported by {', '.join(r['supporting_images'])}")
    return "\n".join(lines)


def cmd_demo(args: argparse.Namespace) -> int:
    from .demo import run_demo

    return run_demo(
        args.out, args.aerial, args.ground, args.seed, args.method, args.resize, verbose=args.verbose
    )


def build_parser() -> argparse.ArgumentParser:
    """The library's commands alone (``geomatch_app.cli.build_parser`` is the whole ``geomatch`` command)."""
    parser = argparse.ArgumentParser(prog="geomatch", description="Geometry-aware matching for SfM")
    register(parser.add_subparsers(dest="command", required=True))
    return parser


def register(sub: Any) -> None:
    m = sub.add_parser("match", help="match two images")
    m.add_argument("image0", type=Path)
    m.add_argument("image1", type=Path)
    m.add_argument("--out", type=Path, required=True, help="output .npz")
    m.add_argument("--viz", type=Path, default=None, help="also draw the matches into this PNG")
    _add_matching_options(m)
    m.set_defaults(func=cmd_match)

    register_synth(sub)

    r = sub.add_parser("run", help="images to a sparse COLMAP model, in one process")
    r.add_argument("images", type=Path, help="folder of images (searched recursively)")
    r.add_argument("--out", type=Path, required=True)
    air = r.add_mutually_exclusive_group()
    air.add_argument("--aerial", default=None, metavar="GLOB", help="aerial images by name pattern")
    air.add_argument(
        "--aerial-list", type=Path, default=None, metavar="FILE", help="aerial names, one per line"
    )
    r.add_argument(
        "--gcp",
        type=Path,
        default=None,
        metavar="FILE",
        help="ground control points (OpenDroneMap's gcp_list.txt): the model is written in their frame",
    )
    r.add_argument(
        "--checkpoints",
        default="",
        metavar="NAMES|N",
        help="with --gcp: GCPs held out of the fit to judge it, by name (comma-separated) or how many",
    )
    options.add_arguments(
        r, options.RUN_OPTIONS, pairs=options.PAIR_SPEC_HELP + " | a file of pairs (two names per line)"
    )
    _add_matching_options(r)
    _add_verbose(r)
    r.set_defaults(func=cmd_run)

    e = sub.add_parser("eval", help="compare a run's model with ground truth")
    e.add_argument("out", type=Path, help="the run's output folder")
    e.add_argument("--gt", type=Path, required=True, help="ground-truth COLMAP model folder")
    e.set_defaults(func=cmd_eval)

    x = sub.add_parser("export", help="write a run's model for another tool (nerfstudio, hloc, OpenMVS ...)")
    x.add_argument("out", type=Path, help="the run's output folder (of geomatch run or demo)")
    x.add_argument("--format", required=True, choices=tuple(FORMATS), help=choices_help())
    x.add_argument("--to", type=Path, default=None, help="folder to write (default OUT/export/FORMAT)")
    x.add_argument(
        "--images", type=Path, default=None, help="the run's images (default: the folder the run read)"
    )
    x.set_defaults(func=cmd_export)

    om = sub.add_parser(
        "ortho", help="a run's map: DSM and orthophoto (Cloud-Optimized GeoTIFFs) of a georeferenced model"
    )
    om.add_argument("out", type=Path, help="the run's output folder (of geomatch run)")
    options.add_arguments(om, ("ortho_gsd",))
    om.add_argument(
        "--images", type=Path, default=None, help="the run's images (default: the folder the run read)"
    )
    om.set_defaults(func=cmd_ortho)

    rp = sub.add_parser("report", help="a run's survey report (photos, points, GPS, GCP and check points)")
    rp.add_argument("out", type=Path, help="the run's output folder, or a summary.json")
    rp.add_argument("--json", action="store_true", help="the report as JSON instead of Markdown")
    rp.set_defaults(func=cmd_report)

    lo = sub.add_parser(
        "localize", help="place new photos in a run's model (pose, and WGS84 when georeferenced)"
    )
    lo.add_argument("out", type=Path, help="the run's output folder (of geomatch run), or a stored project")
    lo.add_argument("photos", type=Path, nargs="+", metavar="PHOTO")
    lo.add_argument("--json", action="store_true", help="print one JSON document instead of lines")
    lo.add_argument(
        "--add",
        action="store_true",
        help="also add the photos to the project (database and images folder) for the next run",
    )
    lo.add_argument(
        "--images", type=Path, default=None, help="the project's images (default: the folder the run read)"
    )
    lo.set_defaults(func=cmd_localize)

    d = sub.add_parser("demo", help="synthetic air-to-ground scene -> run -> eval, in one command")
    d.add_argument("--out", type=Path, default=Path("geomatch-data/demo"))
    d.add_argument("--aerial", type=int, default=DEMO_AERIAL)
    d.add_argument("--ground", type=int, default=DEMO_GROUND)
    d.add_argument("--seed", type=int, default=0)
    options.add_arguments(d, ("method", "resize"))
    _add_verbose(d)
    d.set_defaults(func=cmd_demo)


def run(args: argparse.Namespace) -> int:
    """Run a parsed command; missing weights end it with one line naming the file."""
    try:
        return int(args.func(args))
    except Exception as e:
        weights = sys.modules.get(f"{__package__}.weights")  # loaded by whatever raised it
        if weights is None or not isinstance(e, weights.WeightsNotFoundError):
            raise
        print(f"geomatch: error: {e}", file=sys.stderr)
        return EXIT_FAILED


def main(argv: list[str] | None = None) -> int:
    return run(build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
