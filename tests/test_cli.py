from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from geomatch.synth.photos import warped_pair


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "geomatch.cli", *args], capture_output=True, text=True, timeout=600
    )


@pytest.fixture(scope="module")
def pair_files(tmp_path_factory) -> tuple[Path, Path, np.ndarray]:
    d = tmp_path_factory.mktemp("pair")
    p = warped_pair("coffee", seed=4, strength=0.15)
    cv2.imwrite(str(d / "a.jpg"), p.image0[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
    cv2.imwrite(str(d / "b.png"), p.image1[:, :, ::-1])
    return d / "a.jpg", d / "b.png", p.H


@pytest.mark.nets
def test_good_pair_writes_npz_and_picture(pair_files, tmp_path) -> None:
    a, b, H = pair_files
    out, viz = tmp_path / "m.npz", tmp_path / "m.png"
    res = run(
        "match", str(a), str(b), "--resize", "400", "--device", "cpu", "--out", str(out), "--viz", str(viz)
    )
    assert res.returncode == 0, res.stderr
    assert "matches (sparse)" in res.stdout  # the default auto matches a plain pair by its anchors
    z = np.load(out)
    n = z["keypoints0"].shape[0]
    assert n > 50 and z["keypoints1"].shape == (n, 2) and z["scores"].shape == (n,) and z["F"].shape == (3, 3)
    from geomatch.eval.homography import reprojection_errors

    assert np.median(reprojection_errors(H, z["keypoints0"], z["keypoints1"])) < 2.0
    picture = cv2.imread(str(viz))
    assert picture is not None and picture.shape[0] == 600


@pytest.mark.unit
def test_bad_file_exits_2_with_one_line(pair_files, tmp_path) -> None:
    a, _, _ = pair_files
    bad = tmp_path / "notes.jpg"
    bad.write_text("this is not a picture")
    res = run("match", str(a), str(bad), "--out", str(tmp_path / "x.npz"))
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "notes.jpg" in lines[0] and "not a readable image" in lines[0]
    assert not (tmp_path / "x.npz").exists()


@pytest.mark.unit
def test_truncated_and_empty_files(pair_files, tmp_path) -> None:
    a, _, _ = pair_files
    trunc = tmp_path / "t.jpg"
    trunc.write_bytes(a.read_bytes()[:2000])
    empty = tmp_path / "e.png"
    empty.write_bytes(b"")
    for f in (trunc, empty):
        res = run("match", str(a), str(f), "--out", str(tmp_path / "x.npz"))
        assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr


@pytest.mark.unit
def test_missing_file_exits_2(pair_files, tmp_path) -> None:
    a, _, _ = pair_files
    res = run("match", str(tmp_path / "nope.jpg"), str(a), "--out", str(tmp_path / "x.npz"))
    assert res.returncode == 2
    assert res.stderr.strip() == f"geomatch: error: {tmp_path / 'nope.jpg'}: no such file"


@pytest.mark.unit
def test_unavailable_device_is_a_one_line_error(pair_files, tmp_path) -> None:
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    a, b, _ = pair_files
    res = run("match", str(a), str(b), "--device", "cuda", "--out", str(tmp_path / "x.npz"))
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        "geomatch: error: device 'cuda' requested but CUDA is not available here (use --device cpu)"
    ]


@pytest.mark.unit
def test_export_of_a_folder_without_a_model_is_a_one_line_error(tmp_path) -> None:
    """The command as installed (tests/test_export.py exports a real run, every format)."""
    res = run("export", str(tmp_path), "--format", "nerfstudio")
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        f"geomatch: error: {tmp_path} is not a run folder (no summary.json): make one with `geomatch run`"
    ]
    assert not (tmp_path / "export").exists()
    formats = "{nerfstudio,colmap-text,ply,hloc,openmvs,odm,laz,orthophoto,dsm,map-preview}"
    assert formats in run("export", "--help").stdout


@pytest.mark.unit
def test_localize_against_a_folder_without_a_model_is_a_one_line_error(pair_files, tmp_path) -> None:
    """tests/test_localize.py localizes against a real run; here only the command's refusals."""
    a, _, _ = pair_files
    res = run("localize", str(tmp_path), str(a))
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        f"geomatch: error: {tmp_path}: no model (sparse/0 or model/sparse/0): reconstruct the project first"
    ]
    res = run("localize", str(tmp_path), str(tmp_path / "nope.jpg"), "--json")
    assert res.returncode == 2
    assert res.stderr.strip() == f"geomatch: error: no such photo: {tmp_path / 'nope.jpg'}"
