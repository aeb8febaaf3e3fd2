"""`cadreg site build | info | show` through the real entry point."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import pytest

from cadreg.cli.main import main

pytestmark = pytest.mark.realdata


def test_info_json_has_the_documented_keys(scene0470_site_dir, capsys):
    assert main(["site", "info", str(scene0470_site_dir), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert {"site_id", "version", "nodes", "edges", "points"} <= set(info)
    assert info["site_id"] == "scene0470" and len(info["version"]) == 12
    assert isinstance(info["edges"], int) and info["points"] > 100000
    for node in info["nodes"]:
        assert {"id", "class", "centroid", "source"} <= set(node)
        assert node["source"] in ("cad", "cluster") and len(node["centroid"]) == 3
    assert sum(n["source"] == "cad" for n in info["nodes"]) == 7
    assert len(info["cad_fit"]) == 7 and all(f["median_distance_to_scan_m"] <= 0.07 for f in info["cad_fit"])


def test_info_text_and_show_png(scene0470_site_dir, tmp_path, capsys):
    assert main(["site", "info", str(scene0470_site_dir)]) == 0
    out = capsys.readouterr().out
    assert "scene0470" in out and "cad-0" in out and "otherfurniture" in out
    assert "CAD samples to scan" in out
    png = tmp_path / "pics" / "site.png"
    assert main(["site", "show", str(scene0470_site_dir), "--png", str(png)]) == 0
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 50_000
    from PIL import Image

    with Image.open(png) as im:
        assert im.width > 600 and im.height > 500
        # a picture, not a blank canvas: many distinct colours
        assert len(im.convert("RGB").getcolors(maxcolors=1 << 20)) > 100


def test_build_labels_only_then_info(scene0470_dir, tmp_path, capsys):
    out = tmp_path / "labels_only"
    rc = main(["site", "build", "--scan", str(scene0470_dir / "scene0470_00_vh_clean_2.ply"),
               "--labels", str(scene0470_dir / "scene0470_00_vh_clean_2.labels.ply"), "--out", str(out)])
    assert rc == 0
    assert "site scene0470_00_vh_clean_2 version" in capsys.readouterr().out
    assert main(["site", "info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["site_id"] == "scene0470_00_vh_clean_2" and all(n["source"] == "cluster" for n in info["nodes"])
    # built again into the folder an auto-CAD build left its alignments in: they are not this site's, and go
    (out / "auto_cad.scan2cad.json").write_text("[]")
    assert main(["site", "build", "--scan", str(scene0470_dir / "scene0470_00_vh_clean_2.ply"),
                 "--labels", str(scene0470_dir / "scene0470_00_vh_clean_2.labels.ply"), "--out", str(out)]) == 0
    assert not (out / "auto_cad.scan2cad.json").exists()
    assert "removed" in capsys.readouterr().err


def test_errors_name_the_file_and_exit_2(scene0470_dir, scene0470_site_dir, tmp_path, capsys):
    bad = tmp_path / "broken.json"
    bad.write_text("[{")
    rc = main(["site", "build", "--scan", str(scene0470_dir / "scene0470_00_vh_clean_2.ply"), "--scan2cad", str(bad),
               "--cad-root", str(scene0470_dir / "shapenet"), "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert rc == 2 and "broken.json" in err and "invalid_file" in err
    tampered = tmp_path / "tampered"
    shutil.copytree(scene0470_site_dir, tampered)
    with open(tampered / "graph.json", "a") as fh:
        fh.write(" ")
    assert main(["site", "info", str(tampered)]) == 2
    err = capsys.readouterr().err
    assert "bundle_integrity" in err and "graph.json" in err
    with pytest.raises(SystemExit):
        main(["site", "build", "--scan", "a.ply", "--scan2cad", "b.json", "--out", str(tmp_path / "y")])
    assert "--cad-root" in capsys.readouterr().err


def test_a_reader_that_leaves_early_gets_no_traceback(scene0470_site_dir):
    """`cadreg site info SITE | head -1`: the command's output goes to a pipe nobody reads any more; it stops
    quietly (exit 141, as a shell reports a command SIGPIPE ended) where it printed a BrokenPipeError traceback."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        proc = subprocess.run([sys.executable, "-m", "cadreg.cli.main", "site", "info", str(scene0470_site_dir)],
                              stdout=write_end, stderr=subprocess.PIPE, timeout=300)
    finally:
        os.close(write_end)
    assert proc.returncode == 141, proc.stderr.decode()
    assert b"Traceback" not in proc.stderr and b"BrokenPipe" not in proc.stderr
