"""Recorded-frames folders: ScanNet layout round trip and rig semantics, 7-Scenes and 3DMatch real data, errors."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cadreg.camera import CameraIntrinsics
from cadreg.errors import InvalidFileError
from cadreg.frame import Frame
from cadreg.geometry import invert_T, make_T
from cadreg.io.frames import FramesWriter, RecordedFrames, decode_image, read_poses
from scipy.spatial.transform import Rotation

DEPTH = CameraIntrinsics(64, 48, 57.0, 58.0, 31.5, 23.5)
COLOR = CameraIntrinsics(96, 72, 90.0, 91.0, 47.5, 35.5)


def _frame(rng: np.random.Generator, T_color_depth: np.ndarray) -> Frame:
    return Frame(
        depth=rng.integers(0, 5000, size=(48, 64)).astype(np.uint16),
        color=_smooth_color(rng),
        labels=rng.integers(0, 41, size=(72, 96)).astype(np.uint16),
        depth_intrinsics=DEPTH, color_intrinsics=COLOR, T_color_depth=T_color_depth,
    )


def _smooth_color(rng: np.random.Generator) -> np.ndarray:
    """A gradient (JPEG keeps it within a few levels) with a random offset per frame."""
    v, u = np.mgrid[0:72, 0:96]
    base = np.stack([u * 2, v * 3, (u + v)], axis=-1) + rng.integers(0, 40, size=3)
    return np.clip(base, 0, 255).astype(np.uint8)


def _pose(rng: np.random.Generator) -> np.ndarray:
    return make_T(Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix(), rng.normal(size=3))


@pytest.mark.parametrize("color_format", ["png", "jpg"])
def test_scannet_round_trip(tmp_path: Path, color_format: str) -> None:
    rng = np.random.default_rng(0)
    T_cd = make_T(Rotation.from_euler("xyz", [1, -2, 3], degrees=True).as_matrix(), [-0.025, 0.001, 0.002])
    writer = FramesWriter(tmp_path / "f", DEPTH, COLOR, T_cd, label_set="nyu40", color_format=color_format)
    written = {}
    for i in (0, 3, 10):
        fr, T = _frame(rng, T_cd), _pose(rng)
        writer.write(i, fr, T)
        written[i] = (fr, T)
    frames = RecordedFrames.open(tmp_path / "f")
    assert frames.layout == "scannet" and frames.indices == [0, 3, 10] and len(frames) == 3
    assert frames.depth_intrinsics == DEPTH and frames.color_intrinsics == COLOR
    np.testing.assert_allclose(frames.T_color_depth, T_cd, atol=1e-9)
    for i, (fr, T) in written.items():
        got, T_got = frames.load(i)
        np.testing.assert_array_equal(got.depth, fr.depth)
        np.testing.assert_array_equal(got.labels, fr.labels)
        if color_format == "png":
            np.testing.assert_array_equal(got.color, fr.color)
        else:  # JPEG is lossy: close on average
            assert np.abs(got.color.astype(int) - fr.color.astype(int)).mean() < 3
        np.testing.assert_allclose(T_got, T, atol=1e-9)
        assert got.frame_id == str(i) and got.label_set == "nyu40" and got.depth_scale == 1000.0
        raw = frames.read_raw(i)
        assert raw.depth == (tmp_path / "f" / "depth" / f"{i}.png").read_bytes()
        np.testing.assert_array_equal(decode_image(raw.depth), fr.depth)
        np.testing.assert_array_equal(decode_image(raw.labels), fr.labels)
        assert raw.color_name == f"{i}.{color_format}"
    assert frames.meta(3)["frame_id"] == "3"
    assert [np.allclose(a, b[1]) for a, b in zip(read_poses(tmp_path / "f"), written.values())] == [True] * 3


def test_scannet_rig_semantics_and_defaults(tmp_path: Path) -> None:
    """extrinsic_* are camera -> rig, pose is rig -> map; frames.json missing -> mm, nyu40, image sizes."""
    rng = np.random.default_rng(1)
    root = tmp_path / "scan"
    for sub in ("color", "depth", "pose", "intrinsic"):
        (root / sub).mkdir(parents=True)
    depth = rng.integers(1, 4000, size=(48, 64)).astype(np.uint16)
    Image.fromarray(depth).save(root / "depth" / "7.png")
    Image.fromarray(rng.integers(0, 256, size=(72, 96, 3)).astype(np.uint8)).save(root / "color" / "7.jpg")
    T_rig_depth, T_rig_color, T_map_rig = _pose(rng), _pose(rng), _pose(rng)
    np.savetxt(root / "intrinsic" / "intrinsic_depth.txt", np.pad(DEPTH.K, ((0, 1), (0, 1))))
    np.savetxt(root / "intrinsic" / "intrinsic_color.txt", COLOR.K)  # a 3x3 K is read as well
    np.savetxt(root / "intrinsic" / "extrinsic_depth.txt", T_rig_depth)
    np.savetxt(root / "intrinsic" / "extrinsic_color.txt", T_rig_color)
    np.savetxt(root / "pose" / "7.txt", T_map_rig)
    frames = RecordedFrames.open(root)
    assert frames.depth_scale == 1000.0 and frames.label_set == "nyu40" and not frames.has_labels()
    assert (frames.depth_intrinsics.width, frames.depth_intrinsics.height) == (64, 48)
    assert (frames.color_intrinsics.width, frames.color_intrinsics.height) == (96, 72)
    np.testing.assert_allclose(frames.T_color_depth, invert_T(T_rig_color) @ T_rig_depth, atol=1e-9)
    fr, T_map_camera = frames.load(7)
    np.testing.assert_allclose(T_map_camera, T_map_rig @ T_rig_color, atol=1e-9)
    np.testing.assert_array_equal(fr.depth, depth)
    assert fr.labels is None and frames.read_raw(7).labels is None
    # A depth-camera point lands at the same map point through either camera's pose.
    p_depth = np.array([0.1, -0.2, 1.5, 1.0])
    T_map_depth = T_map_camera @ frames.T_color_depth
    np.testing.assert_allclose(T_map_depth @ p_depth, T_map_rig @ T_rig_depth @ p_depth, atol=1e-9)
    # ScanNet marks lost tracking with -inf poses: no pose, not an error.
    np.savetxt(root / "pose" / "7.txt", np.full((4, 4), -np.inf))
    assert frames.pose(7) is None


def test_frames_json_overrides(tmp_path: Path) -> None:
    FramesWriter(tmp_path, DEPTH, COLOR, depth_scale=5000.0, label_set="scannet20", depth_range_m=4.5).write(0, Frame(
        depth=np.full((48, 64), 7, np.uint16), color=np.zeros((72, 96, 3), np.uint8),
        depth_intrinsics=DEPTH, color_intrinsics=COLOR, depth_scale=5000.0, label_set="scannet20"))
    meta = json.loads((tmp_path / "frames.json").read_text())
    assert meta == {"depth_scale": 5000.0, "label_set": "scannet20", "depth_size": [64, 48], "color_size": [96, 72],
                    "depth_range_m": 4.5}
    frames = RecordedFrames.open(tmp_path)
    assert frames.depth_scale == 5000.0 and frames.label_set == "scannet20" and frames.depth_range_m == 4.5
    assert frames.load(0)[0].depth_range_m == 4.5 and frames.meta()["depth_range_m"] == 4.5
    assert frames.load(0)[1] is None and frames.pose(0) is None
    for bad in (0, -1.0, "far", True, 10**400):
        (tmp_path / "frames.json").write_text(json.dumps({**meta, "depth_range_m": bad}))
        with pytest.raises(InvalidFileError, match="depth_range_m"):
            RecordedFrames.open(tmp_path)


@pytest.mark.realdata
def test_7scenes_redkitchen(redkitchen_dir: Path) -> None:
    frames = RecordedFrames.open(redkitchen_dir)
    assert frames.layout == "7scenes" and len(frames) == 500 and frames.indices[:3] == [0, 1, 2]
    K = frames.depth_intrinsics
    assert (K.width, K.height, K.fx, K.fy, K.cx, K.cy) == (640, 480, 585.0, 585.0, 320.0, 240.0)
    assert frames.color_intrinsics == K and np.allclose(frames.T_color_depth, np.eye(4))
    fr, T = frames.load(42)
    np.testing.assert_allclose(T, np.loadtxt(redkitchen_dir / "frame-000042.pose.txt"), atol=1e-4)  # rotation projected onto SO(3)
    assert fr.depth.dtype == np.uint16 and fr.color.shape == (480, 640, 3) and fr.labels is None
    valid = fr.depth[fr.depth > 0] / 1000.0
    assert 0.05 < 1 - valid.size / fr.depth.size < 0.4 and 0.4 < np.median(valid) < 4.5
    raw = frames.read_raw(42)
    assert raw.color == (redkitchen_dir / "frame-000042.color.jpg").read_bytes() and raw.labels is None


@pytest.mark.realdata
def test_3dmatch_sample_and_65535_invalid(tmp_path: Path) -> None:
    root = Path(__file__).resolve().parents[2] / "shared" / "data" / "3dmatch-sample" / "3dmatch"
    frames = RecordedFrames.open(root)  # the parent of one seq-XX folder
    assert frames.indices == [0, 1, 2, 116, 422]
    assert frames.depth_intrinsics.fx == pytest.approx(570.342205)
    fr, T = frames.load(116)
    np.testing.assert_allclose(T, np.loadtxt(root / "seq-01" / "frame-000116.pose.txt"), atol=1e-4)
    # 7-Scenes writes 65535 for "no reading": it must come out as 0.
    seq = tmp_path / "seq"
    shutil.copytree(root / "seq-01", seq)
    shutil.copy(root / "camera-intrinsics.txt", seq)
    d = np.array(Image.open(seq / "frame-000000.depth.png"))
    d[:10] = 65535
    Image.fromarray(d).save(seq / "frame-000000.depth.png")
    fr, _ = RecordedFrames.open(seq).load(0)
    assert np.all(fr.depth[:10] == 0) and fr.depth.max() < 65535


def test_missing_and_corrupt_files(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    root = tmp_path / "f"
    w = FramesWriter(root, DEPTH, COLOR)
    for i in range(3):
        w.write(i, _frame(rng, np.eye(4)), _pose(rng))
    frames = RecordedFrames.open(root)
    (root / "color" / "1.png").unlink()
    with pytest.raises(InvalidFileError, match=r"color.1\.(png|jpg): file is missing"):
        frames.load(1)
    (root / "depth" / "2.png").write_bytes(b"not a png")
    with pytest.raises(InvalidFileError, match=r"depth.2\.png: cannot decode"):
        frames.load(2)
    with pytest.raises(InvalidFileError, match="no frame with index 9"):
        frames.load(9)
    (root / "pose" / "0.txt").write_text("1 2 3\n")
    with pytest.raises(InvalidFileError, match=r"0\.txt: expected a matrix of shape"):
        frames.pose(0)
    (root / "frames.json").write_text("{not json")
    with pytest.raises(InvalidFileError, match="frames.json: not valid JSON"):
        RecordedFrames.open(root)
    (root / "frames.json").unlink()
    (root / "intrinsic" / "intrinsic_depth.txt").unlink()
    with pytest.raises(InvalidFileError, match="intrinsic_depth.txt: file is missing") as err:
        RecordedFrames.open(root)
    assert err.value.code == "invalid_file" and err.value.path.endswith("intrinsic_depth.txt")
    with pytest.raises(InvalidFileError, match="frames folder is missing"):
        RecordedFrames.open(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InvalidFileError, match="not a frames folder"):
        RecordedFrames.open(tmp_path / "empty")


def test_read_poses_formats(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    poses = [_pose(rng) for _ in range(3)]
    np.savetxt(tmp_path / "stack.txt", np.concatenate(poses))
    got = read_poses(tmp_path / "stack.txt")
    assert len(got) == 3 and all(np.allclose(a, b) for a, b in zip(got, poses))
    (tmp_path / "dir").mkdir()
    for k, T in enumerate(poses):
        np.savetxt(tmp_path / "dir" / f"{k}.txt", T)
    assert all(np.allclose(a, b) for a, b in zip(read_poses(tmp_path / "dir"), poses))
    np.savetxt(tmp_path / "bad.txt", np.ones((5, 4)))
    with pytest.raises(InvalidFileError, match="stacked 4x4"):
        read_poses(tmp_path / "bad.txt")


def test_recorded_rotations_are_projected_onto_so3(redkitchen_dir) -> None:
    """7-Scenes stores rotations ~5e-5 off orthonormal; read as they are, a pose is 1° "away" from itself."""
    from cadreg.geometry import pose_errors

    raw = np.loadtxt(redkitchen_dir / "frame-000000.pose.txt")
    assert abs(np.linalg.det(raw[:3, :3]) - 1.0) > 1e-5  # the file really is off
    T = RecordedFrames.open(redkitchen_dir).pose(0)
    np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(T, raw, atol=1e-3)
    assert pose_errors(T, T) == (0.0, 0.0)
    # and the angle itself no longer reads round-off as rotation
    assert pose_errors(raw, raw)[1] < 0.01


def test_a_pose_that_is_no_rotation_is_refused(tmp_path) -> None:
    from cadreg.camera import CameraIntrinsics
    from cadreg.errors import InvalidFileError
    from cadreg.frame import Frame
    from cadreg.io.frames import FramesWriter

    K = CameraIntrinsics(8, 6, 10.0, 10.0, 3.5, 2.5)
    w = FramesWriter(tmp_path / "f", K, K)
    w.write(0, Frame(depth=np.full((6, 8), 1000, np.uint16), color=np.zeros((6, 8, 3), np.uint8),
                     depth_intrinsics=K, color_intrinsics=K), np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(InvalidFileError, match="not a rotation"):
        RecordedFrames.open(tmp_path / "f").pose(0)
