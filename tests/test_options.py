"""``geomatch.options`` holds every option once: the command line, the REST schema, the proto and
the library's own dataclasses agree with it, and importing it costs no torch."""

from __future__ import annotations

import dataclasses
import re
import subprocess
import sys
from pathlib import Path

import pytest

from geomatch import options
from geomatch.options import DEFAULTS, OPTIONS, PAIR_OPTIONS, PROJECT_OPTIONS

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[1]
PROTO = ROOT / "proto" / "geomatch" / "v1" / "geomatch.proto"
PROTO_TYPES = {"string": str, "int32": int, "double": float}


def test_import_is_torch_free() -> None:
    code = (
        "import sys, geomatch.options; "
        "print(sorted(m for m in ('torch', 'numpy', 'cv2', 'pycolmap', 'kornia') if m in sys.modules))"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert r.stdout.strip() == "[]"


def test_methods_are_rows_of_flags() -> None:
    assert options.METHODS == ("sparse", "dense", "concat", "geo-noanchor", "geo", "auto")
    for m in options.METHOD_TABLE:
        assert m.anchors or m.dense, m.name
        assert not m.anchor_init or (m.anchors and m.optimise), m.name
        assert not m.optimise or m.dense, m.name
    assert OPTIONS["method"].choices == options.METHODS


# -- the command line ----------------------------------------------------------------------------
def _parse(argv: list[str]) -> object:
    from geomatch_app.cli import build_parser  # the whole `geomatch` command

    return build_parser().parse_args(argv)


RUN = ["run", "images", "--out", "out"]
RUN_NAMES = options.MATCH_OPTIONS + options.OPTIMIZER_OPTIONS + options.RUN_OPTIONS


def test_cli_defaults_are_the_options() -> None:
    args = _parse(RUN)
    for name in RUN_NAMES:
        assert getattr(args, name) == DEFAULTS[name], name
    match = _parse(["match", "a.png", "b.png", "--out", "m.npz"])
    for name in options.MATCH_OPTIONS + options.OPTIMIZER_OPTIONS:
        assert getattr(match, name) == DEFAULTS[name], name
    demo = _parse(["demo"])
    assert (demo.method, demo.resize) == (DEFAULTS["method"], DEFAULTS["resize"])


@pytest.mark.parametrize("name", [n for n in RUN_NAMES if OPTIONS[n].choices])
def test_cli_choices_are_the_options(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    flag = OPTIONS[name].flag
    for choice in OPTIONS[name].choices:
        assert getattr(_parse([*RUN, flag, choice]), name) == choice
    with pytest.raises(SystemExit):
        _parse([*RUN, flag, "no-such-choice"])
    assert "invalid choice" in capsys.readouterr().err


def test_submit_leaves_defaults_to_the_server() -> None:
    args = _parse(["submit", "images", "--key", "k"])
    assert (args.pairs, args.method, args.resize, args.mapper) == (None, None, None, None)


# -- the service ---------------------------------------------------------------------------------
def test_rest_schema_is_the_options() -> None:
    from service.http import schemas

    assert tuple(schemas.ProjectConfig.model_fields) == PROJECT_OPTIONS
    assert set(schemas.MatchIn.model_fields) == {*PROJECT_OPTIONS, "reconstruct"}
    assert set(schemas.ReconstructIn.model_fields) == {*options.RECONSTRUCT_OPTIONS, "checkpoints"}
    for name in PROJECT_OPTIONS:
        field = schemas.ProjectConfig.model_fields[name]
        assert field.default is None, name  # unset: the project's, else the default
        assert OPTIONS[name].type in typing_args(field.annotation), name
        for choice in OPTIONS[name].choices:
            assert choice in (field.description or ""), (name, choice)


def typing_args(annotation: object) -> tuple[object, ...]:
    """The types of a union, each without its ``Annotated`` metadata."""
    import typing

    args = typing.get_args(annotation) or (annotation,)
    return tuple(typing.get_args(a)[0] if typing.get_origin(a) is typing.Annotated else a for a in args)


def test_use_case_defaults_are_the_options() -> None:
    from service.grpcapi import convert
    from service.usecases import base

    assert {n: DEFAULTS[n] for n in PROJECT_OPTIONS} == base.DEFAULTS
    assert tuple(convert.CONFIG_FIELDS) == PROJECT_OPTIONS


def _proto_fields(message: str) -> dict[str, str]:
    text = PROTO.read_text()
    body = re.search(rf"message {message} \{{(.*?)\n\}}", text, re.S)
    assert body is not None, message
    return dict(
        (name, kind)
        for kind, name in re.findall(r"^\s*(?:optional\s+)?(\w+)\s+(\w+)\s*=\s*\d+;", body.group(1), re.M)
    )


def test_proto_is_the_options() -> None:
    config = _proto_fields("ProjectConfig")
    assert tuple(config) == PROJECT_OPTIONS
    for name, kind in config.items():
        assert PROTO_TYPES[kind] is OPTIONS[name].type, name
    submit = _proto_fields("SubmitMatchingRequest")
    for name in PROJECT_OPTIONS:
        if name != "pairs":  # a oneof there: pair_spec (the option) or pair_list
            assert PROTO_TYPES[submit[name]] is OPTIONS[name].type, name
    assert "pair_spec" in submit and "pair_list" in submit
    reconstruct = _proto_fields("SubmitReconstructionRequest")
    for name in options.RECONSTRUCT_OPTIONS:  # what the job takes of a project's options
        assert PROTO_TYPES[reconstruct[name]] is OPTIONS[name].type, name
    pair = _proto_fields("MatchPairOptions")
    assert tuple(pair) == PAIR_OPTIONS
    for name, kind in pair.items():
        assert PROTO_TYPES[kind] is OPTIONS[name].type, name


# -- the library's dataclasses (their defaults must be the options') ------------------------------
def test_library_defaults_are_the_options() -> None:
    from geomatch.matching.matcher import MatcherConfig
    from geomatch.matching.optimizer import GeoOptions
    from geomatch.pipeline import RunOptions
    from geomatch.sfm.mapping import MappingSettings

    config = MatcherConfig()
    for name in options.MATCH_OPTIONS:
        assert getattr(config, name) == DEFAULTS[name], name
    geo = {f.name: f.default for f in dataclasses.fields(GeoOptions)}
    for name in options.OPTIMIZER_OPTIONS:
        assert geo[name] == DEFAULTS[name], name
    run = RunOptions()
    for name in (
        "method",
        "resize",
        "device",
        "pairs",
        "tiling",
        "snap_radius",
        "mapper",
        "min_pose_inliers",
    ):
        assert getattr(run, name) == DEFAULTS[name], name
    settings = MappingSettings()
    assert settings.mapper == DEFAULTS["mapper"]
    assert settings.min_pose_inliers == DEFAULTS["min_pose_inliers"]


# -- checks --------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("name", "value", "ok"),
    [
        ("method", "geo", True),
        ("method", "magic", False),
        ("resize", 0, True),
        ("resize", 63, False),
        ("resize", 640, True),
        ("resize", True, False),
        ("resize", 640.0, False),
        ("snap_radius", 0, True),
        ("snap_radius", 50.5, False),
        ("pairs", "sequential:3", True),
        ("pairs", "sequential:0", False),
        ("mapper", "global", True),
        ("min_pose_inliers", 0, True),
        ("min_pose_inliers", 2, False),
        ("min_pose_inliers", 60, True),
        ("min_pose_inliers", 10001, False),
        ("camera", "per-image", True),
        ("tiling", "maybe", False),
    ],
)
def test_checks(name: str, value: object, ok: bool) -> None:
    if ok:
        options.check(name, value)
    else:
        with pytest.raises(options.OptionError, match=name):
            options.check(name, value)


# -- values as the library takes them -------------------------------------------------------------
def test_resolve_is_the_one_place_of_full_size_and_camera() -> None:
    assert options.resolve({"resize": 0, "camera": "per-image"}) == {"resize": None, "share_camera": False}
    assert options.resolve({"resize": 320, "camera": "auto"}) == {"resize": 320, "share_camera": None}
    assert options.resolve({}, ("resize", "camera", "tiling")) == {
        "resize": DEFAULTS["resize"],
        "share_camera": None,
        "tiling": DEFAULTS["tiling"],
    }
    assert options.resolve({"resize": None}, ("resize",)) == {"resize": None}  # given stays given


def test_run_options_of_option_values() -> None:
    from geomatch.pipeline import RunOptions

    run = RunOptions.of({"method": "geo", "resize": 0, "camera": "per-image", "tau": 5.0}, verbose=True)
    assert (run.method, run.resize, run.share_camera, run.verbose) == ("geo", None, False, True)
    assert run.matcher == {"tau": 5.0}  # not a field of RunOptions: the matcher's
    args = _parse([*RUN, "--resize", "0", "--camera", "per-image", "--tau", "5"])
    cli = RunOptions.of(options.given(args, RUN_NAMES))
    assert (cli.resize, cli.share_camera, cli.matcher["tau"]) == (None, False, 5.0)
