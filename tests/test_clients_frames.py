"""Frames into wire parts: from arrays, from recorded folders (files sent as they are when they decode the same)."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cadreg.camera import CameraIntrinsics
from cadreg.frame import Frame
from cadreg.geometry import make_T
from cadreg.io.frames import FramesWriter, RecordedFrames
from clients.frames import EncodedFrame, encode_folder, encode_frame, encode_recorded, to_encoded
from service import codec


def small_frame(seed: int = 0, *, color_size: tuple[int, int] = (64, 48), frame_id: str | None = "f0") -> Frame:
    rng = np.random.default_rng(seed)
    dK = CameraIntrinsics(64, 48, 57.0, 57.0, 31.5, 23.5)
    cK = dK if color_size == (64, 48) else dK.scaled_to(*color_size)
    w, h = color_size
    return Frame(
        depth=rng.integers(500, 4000, (48, 64)).astype(np.uint16),
        color=rng.integers(0, 255, (h, w, 3)).astype(np.uint8),
        labels=rng.integers(0, 40, (h, w)).astype(np.uint16),
        depth_intrinsics=dK,
        color_intrinsics=cK,
        T_color_depth=make_T(t=np.array([0.02, 0.0, 0.0])),
        gravity_camera=np.array([0.0, 1.0, 0.0]),
        frame_id=frame_id,
    )


def _same(a: Frame, b: Frame) -> None:
    assert np.array_equal(a.depth, b.depth) and np.array_equal(a.color, b.color)
    assert (a.labels is None) == (b.labels is None)
    if a.labels is not None:
        assert np.array_equal(a.labels, b.labels)
    assert a.depth_intrinsics == b.depth_intrinsics and a.color_intrinsics == b.color_intrinsics
    assert np.allclose(a.T_color_depth, b.T_color_depth)


def test_encode_frame_round_trips_through_the_service_codec() -> None:
    f = small_frame(color_size=(96, 72))
    enc = encode_frame(f, top_k=3)
    assert set(enc.parts) == {"color", "depth", "labels"}
    assert enc.meta.top_k == 3 and enc.meta.frame_id == "f0" and enc.meta.color_intrinsics is not None
    _same(codec.decode_frame(enc.parts, enc.meta), f)
    parts, meta = codec.unpack_envelope(enc.envelope())
    _same(codec.decode_frame(parts, meta), f)
    assert enc.with_frame_id("x").frame_id == "x" and enc.frame_id == "f0"
    files, data = enc.multipart()
    assert files["depth"][2] == "image/png" and json.loads(data["meta"])["top_k"] == 3


def _write_folder(root: Path, n: int, color_format: str) -> list[tuple[Frame, np.ndarray]]:
    frames = [small_frame(seed=i, frame_id=str(i)) for i in range(n)]
    w = FramesWriter(root, frames[0].depth_intrinsics, frames[0].color_intrinsics, frames[0].T_color_depth,
                     color_format=color_format)  # type: ignore[arg-type]
    out = []
    for i, f in enumerate(frames):
        T = make_T(t=np.array([0.1 * i, 0.2, 1.0]))
        w.write(i, f, T)
        out.append((f, T))
    return out


@pytest.mark.parametrize("color_format,ctype", [("png", "image/png"), ("jpg", "image/jpeg")])
def test_recorded_folder_files_travel_as_they_are(tmp_path: Path, color_format: str, ctype: str) -> None:
    written = _write_folder(tmp_path, 3, color_format)
    rf = RecordedFrames.open(tmp_path)
    enc = encode_recorded(rf, 1)
    assert enc.raw_parts == ("color", "depth", "labels")
    raw = rf.read_raw(1)
    assert enc.parts["color"] == raw.color and enc.parts["depth"] == raw.depth and enc.parts["labels"] == raw.labels
    assert enc.content_types["color"] == ctype
    loaded, T = rf.load(1)
    _same(codec.decode_frame(enc.parts, enc.meta), loaded)
    assert np.allclose(enc.T_map_camera, written[1][1]) and enc.frame_id == "1"
    # re-encoding gives the same arrays
    _same(codec.decode_frame(encode_recorded(rf, 1, raw=False).parts, enc.meta), loaded)
    all_frames = encode_folder(tmp_path, limit=2)
    assert [f.frame_id for f in all_frames] == ["0", "1"]
    assert to_encoded((tmp_path, 2)).frame_id == "2"


def test_a_file_that_decodes_differently_is_reencoded(tmp_path: Path) -> None:
    # 7-Scenes marks "no reading" as 65535 in depth; the reader makes it 0, so the file cannot go as it is
    f = small_frame()
    depth = f.depth.copy()
    depth[:5, :5] = 65535
    Image.fromarray(depth).save(tmp_path / "frame-000000.depth.png")
    Image.fromarray(f.color).save(tmp_path / "frame-000000.color.png")
    np.savetxt(tmp_path / "frame-000000.pose.txt", np.eye(4))
    np.savetxt(tmp_path / "camera-intrinsics.txt", f.depth_intrinsics.K)
    enc = encode_recorded(tmp_path, 0)
    assert enc.raw_parts == ("color",)
    decoded = codec.decode_frame(enc.parts, enc.meta)
    assert np.all(decoded.depth[:5, :5] == 0) and np.array_equal(decoded.depth[5:], f.depth[5:])


def test_real_7scenes_frame_goes_as_jpeg_and_png(redkitchen_dir: Path) -> None:
    enc = encode_recorded(redkitchen_dir, 0)
    assert enc.content_types == {"color": "image/jpeg", "depth": "image/png"}
    assert enc.raw_parts == ("color", "depth")
    assert enc.parts["color"] == (redkitchen_dir / "frame-000000.color.jpg").read_bytes()
    assert enc.T_map_camera is not None and enc.T_map_camera.shape == (4, 4)
    frame = codec.decode_frame(enc.parts, enc.meta)
    assert frame.depth.shape == (480, 640) and frame.depth_intrinsics.fx == 585


def test_to_encoded_rejects_other_things() -> None:
    with pytest.raises(TypeError):
        to_encoded("frames/3")  # type: ignore[arg-type]
    enc = encode_frame(small_frame())
    assert to_encoded(enc) is enc and to_encoded(enc, top_k=7).meta.top_k == 7
    assert isinstance(to_encoded(small_frame()), EncodedFrame)
    assert Image.open(io.BytesIO(enc.parts["depth"])).mode.startswith("I")
