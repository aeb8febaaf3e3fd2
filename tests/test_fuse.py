"""TSDF fusion: real 7-Scenes frames land on the fused map; labels voted from rendered frames; sites from fusion."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from cadreg.cli.main import main
from cadreg.cli.render_cmd import parse_range
from cadreg.config import FuseConfig, RenderConfig
from cadreg.errors import ConfigError
from cadreg.geometry import make_T, pose_errors, transform_points
from cadreg.io.frames import FramesWriter, RecordedFrames
from cadreg.render import LabelledMesh, render_frames
from cadreg.site.bundle import Site
from cadreg.localize.localizer import Localizer
from cadreg.site.fuse import (color_in_depth_camera, frames_sha256, fuse_frames, fuse_site, map_accuracy, pose_offset,
                              pose_offset_by_window)


def median_distance_to_map(map_points: np.ndarray, frames: RecordedFrames, indices) -> float:
    return map_accuracy(map_points, frames, indices)["median_m"]


@pytest.mark.realdata
def test_fuse_redkitchen_few_frames(redkitchen_dir: Path) -> None:
    frames = RecordedFrames.open(redkitchen_dir)
    cloud = fuse_frames(frames, range(0, 20), config=FuseConfig(voxel_size_m=0.03))
    assert cloud.labels is None and len(cloud.points) > 5000
    assert cloud.colors.shape == cloud.points.shape and cloud.colors.dtype == np.uint8
    assert 40 < cloud.colors.mean() < 220 and cloud.colors.std() > 10  # real colours, not black or saturated
    np.testing.assert_allclose(np.linalg.norm(cloud.normals, axis=1), 1.0, atol=1e-3)
    # The fused frames' own depth lies on the map (coarse voxel: within about a voxel).
    assert median_distance_to_map(cloud.points, frames, [0, 9, 19]) < 0.02
    # Frames far away in the sequence see other parts of the kitchen: clearly farther on average.
    assert median_distance_to_map(cloud.points, frames, [400]) > 0.05
    # The same frames fuse to the same arrays in the same order, run after run: the grid hands its blocks out in
    # thread order, and the site build keeps the first point per voxel, so an unsorted fusion built another site.
    again = fuse_frames(frames, range(0, 20), config=FuseConfig(voxel_size_m=0.03))
    for a, b in ((cloud.points, again.points), (cloud.colors, again.colors), (cloud.normals, again.normals)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.realdata
def test_pose_offset_measures_how_far_recorded_poses_disagree_with_the_map(redkitchen_dir: Path) -> None:
    frames = RecordedFrames.open(redkitchen_dir)
    config = FuseConfig(voxel_size_m=0.03)
    cloud = fuse_frames(frames, range(0, 20), config=config)
    points, normals = cloud.points.astype(np.float64), cloud.normals.astype(np.float64)
    # The map's own frames agree with it.
    same = pose_offset(points, normals, frames, range(5, 15), config=config)
    assert same["frames"] == 10 and same["camera_offset_m"] < 0.01 and same["rotation_deg"] < 0.5
    assert same["fitness"] > 0.8
    # A map moved by 4 cm and turned by 1.5° about its z axis, as if its frames' poses had drifted: the frames' recorded
    # poses are off from it by what the move does to their cameras.
    centres = np.array([frames.pose(i)[:3, 3] for i in range(5, 15)])
    angle = np.radians(1.5)
    R = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    pivot = centres.mean(axis=0)
    T_moved_map = make_T(R, pivot - R @ pivot + np.array([0.04, 0.0, 0.0]))
    moved = pose_offset(transform_points(T_moved_map, points), normals @ R.T, frames, range(5, 15), config=config)
    expected = np.median(np.linalg.norm(transform_points(T_moved_map, centres) - centres, axis=1))
    assert abs(moved["camera_offset_m"] - expected) < 0.01 and abs(moved["rotation_deg"] - 1.5) < 0.4
    # Window by window: every checked frame of the moved map is placed more than 3 cm from its record, none of the
    # map's own.
    corrected: dict[int, np.ndarray] = {}
    windows = pose_offset_by_window(transform_points(T_moved_map, points), normals @ R.T, frames, range(5, 15), 5,
                                    config=config, offset_limit_m=0.03, corrected=corrected)
    assert [(w["first"], w["last"]) for w in windows["windows"]] == [(5, 9), (10, 14)]
    assert windows["frames_checked"] == 10 and windows["frames_over_limit"] == 10
    # Where the moved map puts each frame: its recorded pose, moved with the map.
    assert sorted(corrected) == list(range(5, 15))
    for i, T in corrected.items():
        te, re_ = pose_errors(T, T_moved_map @ frames.pose(i))
        assert te < 0.01 and re_ < 0.4
    same = pose_offset_by_window(points, normals, frames, range(5, 15), 5, config=config, offset_limit_m=0.03)
    assert same["frames_checked"] == 10 and same["frames_over_limit"] == 0
    with pytest.raises(ConfigError):
        pose_offset_by_window(points, normals, frames, range(5, 15), 0, config=config)


@pytest.fixture(scope="session")
def rendered_labelled(scene0470_dir: Path, tmp_path_factory) -> tuple[Path, LabelledMesh]:
    mesh = LabelledMesh.from_ply(scene0470_dir / "scene0470_00_vh_clean_2.ply",
                                 scene0470_dir / "scene0470_00_vh_clean_2.labels.ply")
    out = tmp_path_factory.mktemp("fuse_frames")
    # A colour camera of another size and position exercises colour registration into the depth camera.
    render_frames(mesh, out, 10, seed=4, noise=None, config=RenderConfig(color_width=320, color_height=240))
    return out, mesh


@pytest.mark.realdata
def test_fused_labels_match_the_mesh(rendered_labelled) -> None:
    out, mesh = rendered_labelled
    frames = RecordedFrames.open(out)
    cloud = fuse_frames(frames, config=FuseConfig(voxel_size_m=0.02, label_frame_stride=1))
    d, idx = cKDTree(mesh.vertices).query(cloud.points)
    assert np.median(d) < 0.02
    assert cloud.labels is not None
    seen = cloud.labels > 0
    assert seen.mean() > 0.6
    agree = cloud.labels[seen] == mesh.labels[idx[seen]]
    assert agree.mean() > 0.85
    # Colours come from the mesh through the registered colour camera.
    diff = np.abs(cloud.colors.astype(int) - mesh.colors[idx].astype(int)).mean()
    assert diff < 25


@pytest.mark.realdata
def test_cli_site_fuse_with_labels(rendered_labelled, tmp_path: Path, capsys) -> None:
    out, _ = rendered_labelled
    assert main(["site", "fuse", "--frames", str(out), "--range", "0:8", "--out", str(tmp_path / "site"),
                 "--voxel-m", "0.02", "--site-id", "fused0470", "--check-range", "0:8", "--check-window", "4",
                 "--write-poses", str(tmp_path / "truth")]) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    # the poses where the map puts the frames of the windows that lie on it, one file each
    written = report["check"]["poses_written"]
    assert written["frames"] == report["check"]["pose_offset_windows"]["frames_checked"]
    assert len(list((tmp_path / "truth").glob("*.txt"))) == written["frames"]
    assert main(["site", "fuse", "--frames", str(out), "--out", str(tmp_path / "site2"),
                 "--check-range", "0:8", "--write-poses", str(tmp_path / "truth")]) == 2  # needs --check-window
    assert report["site_id"] == "fused0470"
    # the fused frames themselves (random views of a room, no held-out frame sees the same parts) lie on the map
    assert report["check"]["frames"] == 8 and report["check"]["median_m"] < 0.02
    # rendered poses are exact: they agree with the map they fused
    assert report["check"]["pose_offset"]["camera_offset_m"] < 0.01
    # four random views of a room see little of it twice: such a window fuses to nothing and checks no frame
    windows = report["check"]["pose_offset_windows"]
    assert len(windows["windows"]) == 2 and windows["frames_over_limit"] == 0
    assert all(w["fitness"] == 0.0 or w["camera_offset_m"] < 0.01 for w in windows["windows"])
    site = Site.load(tmp_path / "site")
    assert site.site_id == "fused0470" and len(site.map.points) > 10_000
    classes = {n.cls for n in site.graph.nodes}
    assert "chair" in classes and all(n.source == "cluster" for n in site.graph.nodes)
    assert site.manifest["inputs"]["frames"]["count"] == 8
    # DESIGN §3: the bundle names its inputs with their sha256, here the digest of the fused frames' files
    assert site.manifest["inputs"]["frames"]["sha256"] == frames_sha256(RecordedFrames.open(out), range(8))


def test_the_digest_of_fused_frames_follows_their_files_not_their_folder(rendered_labelled, tmp_path: Path) -> None:
    import shutil

    out, _ = rendered_labelled
    frames = RecordedFrames.open(out)
    digest = frames_sha256(frames, range(4))
    assert len(digest) == 64 and digest != frames_sha256(frames, range(5))  # another frame: another digest
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    assert frames_sha256(RecordedFrames.open(copy), range(4)) == digest  # the same files elsewhere
    pose = copy / "pose" / "2.txt"
    pose.write_text(pose.read_text().replace("0.", "0.0", 1))  # the same pose, written otherwise
    assert frames_sha256(RecordedFrames.open(copy), range(4)) != digest
    (copy / "intrinsic" / "intrinsic_depth.txt").write_text("500 0 320\n0 500 240\n0 0 1\n")  # the calibration too
    assert frames_sha256(RecordedFrames.open(copy), range(2)) != frames_sha256(frames, range(2))


def test_color_registration_and_errors(tmp_path: Path) -> None:
    from cadreg.camera import CameraIntrinsics
    from cadreg.frame import Frame
    from cadreg.geometry import make_T

    K = CameraIntrinsics(40, 30, 40.0, 40.0, 19.5, 14.5)
    color = np.zeros((30, 40, 3), np.uint8)
    color[:, :, 0] = np.arange(40)[None, :] * 5  # red encodes the colour column
    # A 2 m wall; the colour camera sits 0.1 m to the right: it sees each point 2 px further left.
    frame = Frame(depth=np.full((30, 40), 2000, np.uint16), color=color, depth_intrinsics=K, color_intrinsics=K,
                  T_color_depth=make_T(t=(-0.1, 0, 0)))
    reg = color_in_depth_camera(frame)
    assert np.all(reg[5, 10:30, 0] == (np.arange(10, 30) - 2) * 5)
    # No poses: nothing to fuse.
    w = FramesWriter(tmp_path / "np", K, K)
    w.write(0, frame.__class__(depth=frame.depth, color=color, depth_intrinsics=K, color_intrinsics=K))
    with pytest.raises(ConfigError, match="pose"):
        fuse_frames(RecordedFrames.open(tmp_path / "np"))
    assert parse_range("2:4", [0, 1, 2, 3, 4, 5]) == [2, 3] and parse_range(":2", [0, 1, 2]) == [0, 1]
    assert parse_range(None, [3, 4]) == [3, 4]
    for bad in ("7", "a:b", "9:10"):
        with pytest.raises(ConfigError):
            parse_range(bad, [0, 1, 2])


@pytest.mark.slow
@pytest.mark.realdata
def test_redkitchen_map_from_250_frames(redkitchen_dir: Path, tmp_path: Path) -> None:
    """Acceptance: `cadreg site fuse --range 0:250`; frames 250-499 land within 3 cm (median) of the map."""
    assert main(["site", "fuse", "--frames", str(redkitchen_dir), "--range", "0:250", "--check-range", "250:500",
                 "--out", str(tmp_path / "redkitchen")]) == 0
    site = Site.load(tmp_path / "redkitchen")
    frames = RecordedFrames.open(redkitchen_dir)
    median = median_distance_to_map(site.map.points, frames, range(250, 500, 5))
    assert median < 0.03, median


@pytest.mark.realdata
def test_a_site_fused_from_one_frame_of_a_new_room_states_its_up_and_places_it(threedmatch_dir: Path,
                                                                               tmp_path: Path) -> None:
    """A lounge recorded with a structured-light sensor (3DMatch/SUN3D), its world y up: one frame fuses to a map
    (the TSDF's weight threshold is kept under the frames fused), the site states its up from the frame's own
    surfaces, and that frame, without labels, is placed on the map. Judged by the map's normals alone, the
    map was z up (the wall and floor normals are all perpendicular to z) and no frame was placed."""
    frames = RecordedFrames.open(threedmatch_dir)
    site = fuse_site(frames, [116], site_id="lounge")
    up = site.up
    assert up is not None and np.degrees(np.arccos(up @ [0.0, 1.0, 0.0])) < 5.0
    site.save(tmp_path / "lounge")
    loaded = Site.load(tmp_path / "lounge")
    np.testing.assert_allclose(loaded.up, up)
    frame, T_map_camera = frames.load(116)
    result = Localizer.from_site(loaded).localize(frame)
    assert result.status.value == "ok"
    t_err, r_err = pose_errors(result.T_map_camera, T_map_camera)
    assert t_err < 0.05 and r_err < 5.0
