"""Frames into wire parts: from numpy arrays (`cadreg.Frame`) or from the files of a recorded-frames folder.

An `EncodedFrame` is what goes on the wire (DESIGN §6, `service/codec.py`): image parts as encoded bytes
(`color` PNG/JPEG, `depth` 16-bit PNG, optional `labels` PNG) and one `FrameMeta`. Encode once, send many times:
the load tester encodes a whole folder up front so that no encoding happens in its timed loop.

From a recorded folder the files travel as they are on disk (no re-encoding, DESIGN §9: PNG encoding costs
20–90 ms an image) whenever they decode to exactly the arrays `RecordedFrames.load` gives; a part that does not
(7-Scenes marks "no reading" with depth 65535, which the reader turns into 0) is re-encoded from the loaded array.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Union

import numpy as np
from PIL import Image

from cadreg.errors import CadregError
from cadreg.frame import Frame
from cadreg.io.frames import RecordedFrames
import service.codec as codec
from service.schemas import FrameMeta

_CONTENT_TYPES = {"PNG": "image/png", "JPEG": "image/jpeg"}


@dataclass(frozen=True)
class EncodedFrame:
    """One frame ready to send.

    parts : {"color": bytes, "depth": bytes, "labels": bytes (optional)}, encoded images.
    content_types : MIME type of each part (image/png or image/jpeg).
    meta : FrameMeta (intrinsics, T_color_depth, depth_scale, label set, frame id, top_k).
    T_map_camera : (4, 4) float64 ground-truth pose (colour camera -> map) when the source had one, else None;
        never sent, used to score the answer.
    source : where it came from, for messages ("folder:index" or "array").
    """

    parts: dict[str, bytes]
    content_types: dict[str, str]
    meta: FrameMeta
    T_map_camera: np.ndarray | None = None
    source: str = "array"
    raw_parts: tuple[str, ...] = field(default=())  # parts sent as the files on disk, unchanged

    @property
    def frame_id(self) -> str | None:
        return self.meta.frame_id

    @property
    def nbytes(self) -> int:
        return sum(len(b) for b in self.parts.values())

    def with_frame_id(self, frame_id: str | None) -> "EncodedFrame":
        return replace(self, meta=self.meta.model_copy(update={"frame_id": frame_id}))

    def with_top_k(self, top_k: int) -> "EncodedFrame":
        return replace(self, meta=FrameMeta.model_validate({**self.meta.model_dump(), "top_k": top_k}))

    def meta_json(self) -> str:
        return json.dumps(self.meta.model_dump(mode="json"), separators=(",", ":"))

    def multipart(self) -> tuple[dict[str, tuple[str, bytes, str]], dict[str, str]]:
        """(files, data) for httpx: one file field per part, `meta` as a text field."""
        files = {
            name: (f"{name}{_suffix(self.content_types[name])}", data, self.content_types[name])
            for name, data in self.parts.items()
        }
        return files, {"meta": self.meta_json()}

    def envelope(self) -> bytes:
        """The zenoh payload (`codec.pack_envelope`)."""
        return codec.pack_envelope(self.parts, self.meta)


FrameLike = Union[Frame, EncodedFrame, tuple]  # tuple = (folder path or RecordedFrames, index)


def encode_frame(frame: Frame, *, top_k: int = 5, T_map_camera: np.ndarray | None = None) -> EncodedFrame:
    """Encode a Frame's arrays (PNG, compress_level=1, through the service codec)."""
    parts, meta = codec.encode_frame_parts(frame, top_k=top_k)
    return EncodedFrame(
        parts=parts,
        content_types={name: "image/png" for name in parts},
        meta=meta,
        T_map_camera=None if T_map_camera is None else np.asarray(T_map_camera, dtype=float),
    )


def encode_recorded(
    frames: RecordedFrames | str | Path, index: int, *, top_k: int = 5, raw: bool = True
) -> EncodedFrame:
    """Encode frame `index` of a recorded-frames folder (ScanNet export or 7-Scenes layout).

    raw=True sends each file's bytes as they are when they decode to the arrays the reader gives; raw=False
    re-encodes everything from the arrays. The folder's pose (T_map_camera), when present, rides along for scoring.
    Raises cadreg's InvalidFileError for missing or malformed files.
    """
    rf = frames if isinstance(frames, RecordedFrames) else RecordedFrames.open(frames)
    frame, T_map_camera = rf.load(index)
    source = f"{rf.root}:{index}"
    if not raw:
        return replace(encode_frame(frame, top_k=top_k, T_map_camera=T_map_camera), source=source)
    meta = codec.frame_meta(frame, top_k=top_k)
    files = rf.read_raw(index)
    wanted = {"color": frame.color, "depth": frame.depth}
    raw_parts = {"color": files.color, "depth": files.depth}
    if frame.labels is not None and files.labels is not None:
        wanted["labels"] = frame.labels
        raw_parts["labels"] = files.labels
    same = _parts_matching(raw_parts, meta, wanted)
    if frame.labels is not None and "labels" not in wanted:
        wanted["labels"] = frame.labels
    parts: dict[str, bytes] = {}
    types: dict[str, str] = {}
    for name, array in wanted.items():
        if name in same:
            parts[name], types[name] = raw_parts[name], same[name]
        else:
            parts[name], types[name] = _png(array), "image/png"
    return EncodedFrame(parts, types, meta, T_map_camera, source, tuple(sorted(same)))


def encode_folder(
    frames: RecordedFrames | str | Path,
    *,
    limit: int | None = None,
    top_k: int = 5,
    raw: bool = True,
    progress: Any = None,
) -> list[EncodedFrame]:
    """Encode the first `limit` frames of a folder (all when None), in index order.

    progress : optional callable(done, total).
    """
    rf = frames if isinstance(frames, RecordedFrames) else RecordedFrames.open(frames)
    indices = rf.indices if limit is None else rf.indices[: max(0, int(limit))]
    out = []
    for k, i in enumerate(indices):
        out.append(encode_recorded(rf, i, top_k=top_k, raw=raw))
        if progress is not None:
            progress(k + 1, len(indices))
    return out


class FolderCache:
    """Opened RecordedFrames by path, so that `(folder, index)` frames do not re-scan the folder each call."""

    def __init__(self) -> None:
        self._open: dict[Path, RecordedFrames] = {}

    def get(self, folder: RecordedFrames | str | Path) -> RecordedFrames:
        if isinstance(folder, RecordedFrames):
            return folder
        key = Path(folder).resolve()
        if key not in self._open:
            self._open[key] = RecordedFrames.open(key)
        return self._open[key]


def to_encoded(frame: FrameLike, *, top_k: int | None = None, cache: FolderCache | None = None) -> EncodedFrame:
    """Any accepted frame form -> EncodedFrame: an EncodedFrame, a cadreg Frame, or (folder, index)."""
    if isinstance(frame, EncodedFrame):
        return frame if top_k is None else frame.with_top_k(top_k)
    if isinstance(frame, Frame):
        return encode_frame(frame, top_k=5 if top_k is None else top_k)
    if isinstance(frame, tuple) and len(frame) == 2:
        folder, index = frame
        rf = (cache or FolderCache()).get(folder)
        return encode_recorded(rf, int(index), top_k=5 if top_k is None else top_k)
    raise TypeError(f"frame must be a cadreg Frame, an EncodedFrame or (folder, index), got {type(frame).__name__}")


def _parts_matching(raw_parts: dict[str, bytes], meta: FrameMeta, wanted: dict[str, np.ndarray]) -> dict[str, str]:
    """{part: MIME type} of the raw files that the service's decoder turns into exactly the wanted arrays."""
    types: dict[str, str] = {}
    for name, data in raw_parts.items():
        try:
            with Image.open(io.BytesIO(data)) as im:
                fmt = im.format
        except (OSError, ValueError):
            continue
        if fmt in _CONTENT_TYPES and (name == "color" or fmt == "PNG"):
            types[name] = _CONTENT_TYPES[fmt]
    try:
        decoded = codec.decode_frame(raw_parts, meta)
    except CadregError:
        return {}
    arrays = {"color": decoded.color, "depth": decoded.depth, "labels": decoded.labels}
    return {
        name: t for name, t in types.items()
        if arrays[name] is not None and arrays[name].shape == wanted[name].shape and np.array_equal(arrays[name], wanted[name])
    }


def _png(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(array)).save(buf, format="PNG", compress_level=codec.PNG_COMPRESS_LEVEL)
    return buf.getvalue()


def _suffix(content_type: str) -> str:
    return ".jpg" if content_type == "image/jpeg" else ".png"
