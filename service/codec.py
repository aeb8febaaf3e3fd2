"""One codec for frames and results, used by HTTP, zenoh and the clients.

A frame on the wire is a set of image parts plus a `FrameMeta`:
    color  : PNG or JPEG, 8-bit RGB, size (w, h) = colour camera
    depth  : PNG, 16-bit grayscale, `depth_scale` units per metre, 0 = invalid; size = depth camera
    labels : optional PNG, 8- or 16-bit grayscale label ids, colour's size
Over HTTP the parts are multipart/form-data fields of these names and `meta` is the JSON text of FrameMeta.
Over zenoh they travel in one envelope:
    b"CDRG" | version (1 byte, = 1) | L (uint32 little-endian) | L bytes of JSON header | part bytes
    header = {"meta": FrameMeta, "parts": {"color": [offset, length], "depth": [...], "labels": [...]}}
    offsets count from the first byte after the header.
Results and error bodies are UTF-8 JSON objects; non-finite floats become null (JSON has no NaN). Over zenoh
the two carry distinct encodings, so that a receiver never guesses which it got (service/zenoh_wire.py).
Every decoding failure raises `InvalidFrame` naming what is wrong.
"""

from __future__ import annotations

import io
import json
import math
import re
import struct
import warnings
from typing import Any

import numpy as np
from PIL import Image
from pydantic import ValidationError

from cadreg.camera import CameraIntrinsics
from cadreg.errors import CadregError, InvalidFrame
from cadreg.frame import Frame
from cadreg.site.regions import SearchRegion

from .schemas import FrameMeta, Intrinsics, SearchRegionIn

MAGIC = b"CDRG"
ENVELOPE_VERSION = 1
_PREFIX = struct.Struct("<4sBI")  # magic, version, header length
MAX_HEADER_BYTES = 1 << 20
# A 16k x 16k image is far beyond any RGB-D sensor; refusing it before decoding keeps a decompression bomb out.
MAX_IMAGE_PIXELS = 16384 * 16384 // 4
PART_NAMES = ("color", "depth", "labels")
REQUIRED_PARTS = ("color", "depth")
PNG_COMPRESS_LEVEL = 1  # DESIGN §9: level 1 costs ~20-30 ms per 640x480 image, Pillow's default ~90 ms


# --- meta ---------------------------------------------------------------------------------------------------------

# A FrameMeta is under 2 KiB and nests 3 deep. json.loads recurses once per level (RecursionError, a 500, past ~1000),
# so text is measured and its nesting counted before any parser sees it.
MAX_META_BYTES = 64 * 1024
MAX_META_DEPTH = 32
_JSON_STRING = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*"', re.DOTALL)
_NOT_BRACKETS = bytes(b for b in range(256) if b not in b"[]{}")


def check_json_bounds(text: str | bytes | bytearray, what: str, max_bytes: int, max_depth: int) -> None:
    """Refuse (InvalidFrame naming the limit) JSON text over `max_bytes` bytes or nesting deeper than `max_depth`
    arrays/objects, without parsing it: brackets are counted outside strings (one regex pass, then a loop over the
    brackets alone). An unterminated string only makes the count larger; the parser refuses that text anyway."""
    size = len(text) if isinstance(text, (bytes, bytearray)) else len(text.encode("utf-8", "surrogatepass"))
    if size > max_bytes:
        raise InvalidFrame(f"{what} is {size} bytes, over the {max_bytes}-byte limit",
                           detail={"limit_bytes": max_bytes})
    data = text if isinstance(text, (bytes, bytearray)) else text.encode("utf-8", "surrogatepass")
    depth = 0
    for bracket in _JSON_STRING.sub(b'""', bytes(data)).translate(None, _NOT_BRACKETS):
        depth += 1 if bracket in b"[{" else -1
        if depth > max_depth:
            raise InvalidFrame(f"{what} nests deeper than the {max_depth}-level limit",
                               detail={"limit_depth": max_depth})


MAX_LISTED_ERRORS = 20  # validation errors an error body lists (`error_count` counts them all)


def parse_meta(raw: str | bytes | dict[str, Any] | FrameMeta) -> FrameMeta:
    """Validate the meta document (JSON text or dict) into a FrameMeta; any problem raises InvalidFrame."""
    if isinstance(raw, FrameMeta):
        return raw
    if isinstance(raw, (str, bytes, bytearray)):
        check_json_bounds(raw, "meta", MAX_META_BYTES, MAX_META_DEPTH)
        raw = _json_object(raw, "meta", InvalidFrame)
    elif not isinstance(raw, dict):
        raise InvalidFrame("meta must be a JSON object")
    try:
        return FrameMeta.model_validate(raw)
    except ValidationError as exc:
        errors = [{"loc": [str(p) for p in e["loc"]], "msg": e["msg"], "type": e["type"]} for e in exc.errors()]
        first = errors[0]
        # The first MAX_LISTED_ERRORS and their count: a meta of 5,400 unknown keys (under the 64 KiB cap) had an
        # answer of 442 KB listing each.
        raise InvalidFrame(f"meta.{'.'.join(first['loc'])}: {first['msg']}",
                           detail={"errors": errors[:MAX_LISTED_ERRORS], "error_count": len(errors)}) from None


# --- images -------------------------------------------------------------------------------------------------------


def _png(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG", compress_level=PNG_COMPRESS_LEVEL)
    return buf.getvalue()


def _open_image(data: bytes, part: str, formats: tuple[str, ...]) -> Image.Image:
    if not isinstance(data, (bytes, bytearray)) or len(data) == 0:
        raise InvalidFrame(f"{part} is empty")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            img = Image.open(io.BytesIO(data), formats=list(formats))
            w, h = img.size
            if w * h > MAX_IMAGE_PIXELS:
                raise InvalidFrame(f"{part} is {w}x{h}: too large an image")
            img.load()
    except InvalidFrame:
        raise
    except Exception as exc:  # Pillow raises a zoo of types (OSError, SyntaxError, ValueError...) for bad files
        raise InvalidFrame(f"{part} is not a readable {'/'.join(formats)} image: {_pillow_reason(exc)}") from None
    return img


def _pillow_reason(exc: Exception) -> str:
    """Pillow's reason for refusing an image, without the repr of our in-memory buffer it names ("cannot identify
    image file <_io.BytesIO object at 0x7f...>": an address of the server's memory, and nothing the client sent)."""
    return re.sub(r"\s*<_io\.BytesIO object at 0x[0-9a-fA-F]+>", "", str(exc)).strip() or type(exc).__name__


_PART_FORMATS = {"color": ("PNG", "JPEG"), "depth": ("PNG",), "labels": ("PNG",)}


def check_image_sizes(parts: dict[str, bytes], max_pixels: int) -> None:
    """Refuse (InvalidFrame naming the cap) any image part whose header declares more than `max_pixels` pixels.
    Only headers are read (Pillow opens lazily; no pixel is decoded), so the service checks this before a worker
    spends seconds and gigabytes inflating a small file. An unreadable header is refused here too."""
    for name, formats in _PART_FORMATS.items():
        data = parts.get(name)
        if not data:
            continue
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # the cap below is ours
                with Image.open(io.BytesIO(data), formats=list(formats)) as img:
                    w, h = img.size
        except Image.DecompressionBombError:
            # (Pillow's own message names its own limit, not ours)
            raise InvalidFrame(f"{name} is over the {max_pixels}-pixel cap (max_frame_pixels)",
                               detail={"part": name, "max_pixels": max_pixels}) from None
        except Exception as exc:  # Pillow raises a zoo of types for bad files
            raise InvalidFrame(f"{name} is not a readable {'/'.join(formats)} image: {_pillow_reason(exc)}") from None
        if w * h > max_pixels:
            raise InvalidFrame(f"{name} is {w}x{h} = {w * h} pixels, over the {max_pixels}-pixel cap (max_frame_pixels)",
                               detail={"part": name, "width": w, "height": h, "max_pixels": max_pixels})


def _decode_color(data: bytes) -> np.ndarray:
    img = _open_image(data, "color", ("PNG", "JPEG"))
    if img.mode == "RGB":
        arr = np.asarray(img)
    elif img.mode in ("RGBA", "L", "P", "LA"):
        # 8-bit images in other layouts carry the same information; alpha is dropped
        arr = np.asarray(img.convert("RGB"))
    else:
        raise InvalidFrame(f"color must be an 8-bit RGB image, got mode {img.mode}")
    return np.ascontiguousarray(arr, dtype=np.uint8)


def _uint16(img, what: str) -> np.ndarray | None:
    """A 16-bit grayscale image as uint16 (Pillow reads some as 32-bit "I"), None for any other mode."""
    if img.mode in ("I;16", "I;16B", "I;16L"):
        return np.asarray(img).astype(np.uint16, copy=False)
    if img.mode == "I":
        arr = np.asarray(img)
        if arr.size and (arr.min() < 0 or arr.max() > 65535):
            raise InvalidFrame(f"{what} must fit 16 bits")
        return arr.astype(np.uint16)
    return None


def _decode_depth(data: bytes) -> np.ndarray:
    img = _open_image(data, "depth", ("PNG",))
    arr = _uint16(img, "depth values")
    if arr is None:
        raise InvalidFrame(f"depth must be a 16-bit grayscale PNG, got mode {img.mode}")
    return np.ascontiguousarray(arr)


def _decode_labels(data: bytes) -> np.ndarray:
    img = _open_image(data, "labels", ("PNG",))
    if img.mode in ("L", "P"):
        arr = np.asarray(img).astype(np.uint8, copy=False)  # palette images: the indices are the labels
    else:
        arr = _uint16(img, "label ids")
        if arr is None:
            raise InvalidFrame(f"labels must be an 8- or 16-bit grayscale PNG, got mode {img.mode}")
    return np.ascontiguousarray(arr)


# --- frames -------------------------------------------------------------------------------------------------------


def _intrinsics_out(K: CameraIntrinsics) -> Intrinsics:
    return Intrinsics(fx=float(K.fx), fy=float(K.fy), cx=float(K.cx), cy=float(K.cy))


def encode_frame_parts(frame: Frame, *, top_k: int = 5) -> tuple[dict[str, bytes], FrameMeta]:
    """Encode a Frame into wire parts (PNG, compress_level=1) and its FrameMeta (`frame_meta`).

    Returns parts {"color": PNG RGB, "depth": PNG uint16, "labels": PNG uint8/uint16 (only when the frame has
    labels)} and the meta.
    """
    parts = {"color": _png(np.ascontiguousarray(frame.color, dtype=np.uint8)), "depth": _png(frame.depth)}
    if frame.labels is not None:
        parts["labels"] = _png(frame.labels)
    return parts, frame_meta(frame, top_k=top_k)


def frame_meta(frame: Frame, *, top_k: int = 5) -> FrameMeta:
    """The FrameMeta describing a Frame (T_color_depth sent only when not the identity; colour intrinsics only when
    they differ)."""
    T = np.asarray(frame.T_color_depth, dtype=float)
    same_camera = frame.color_intrinsics == frame.depth_intrinsics
    return FrameMeta(
        frame_id=frame.frame_id,
        depth_intrinsics=_intrinsics_out(frame.depth_intrinsics),
        color_intrinsics=None if same_camera else _intrinsics_out(frame.color_intrinsics),
        T_color_depth=None if np.allclose(T, np.eye(4), atol=0.0) else T.tolist(),
        depth_scale=float(frame.depth_scale),
        label_set=frame.label_set,
        gravity=None if frame.gravity_camera is None else [float(x) for x in frame.gravity_camera],
        pose_prior=None if frame.T_map_camera_prior is None else np.asarray(frame.T_map_camera_prior).tolist(),
        top_k=top_k,
        search_region=None if frame.search_region is None else frame.search_region.to_dict(),
        depth_range_m=frame.depth_range_m,
    )


def _camera(intr: Intrinsics, width: int, height: int, which: str) -> CameraIntrinsics:
    try:
        return CameraIntrinsics(int(width), int(height), intr.fx, intr.fy, intr.cx, intr.cy)
    except InvalidFrame as exc:
        raise InvalidFrame(f"{which} intrinsics: {exc.message}", detail=exc.detail) from None


def check_parts(parts: dict[str, bytes | None]) -> None:
    """Refuse (InvalidFrame naming it) an unknown part, a required one missing, or one sent with no bytes (a zenoh
    envelope's [offset, 0], an empty HTTP file part: "missing" named it wrongly). The service checks this on
    arrival, `decode_frame` again for any other caller."""
    unknown = sorted(set(parts) - set(PART_NAMES))
    if unknown:
        raise InvalidFrame(f"unknown part(s): {', '.join(unknown)}", detail={"parts": unknown})
    for name in REQUIRED_PARTS:
        if parts.get(name) is None:
            raise InvalidFrame(f"missing part: {name}", detail={"part": name})
        if not parts[name]:
            raise InvalidFrame(f"part {name} is empty", detail={"part": name})


def decode_frame(parts: dict[str, bytes], meta: FrameMeta | dict[str, Any] | str | bytes) -> Frame:
    """Decode wire parts + meta into a validated Frame (raises InvalidFrame on any problem).

    The depth camera's size is the depth PNG's; the colour camera's the colour image's. With no colour intrinsics
    the colour image must have the depth image's size (same camera).
    """
    meta = parse_meta(meta)
    check_parts(parts)
    color = _decode_color(parts["color"])
    depth = _decode_depth(parts["depth"])
    labels = _decode_labels(parts["labels"]) if parts.get("labels") is not None else None
    dh, dw = depth.shape
    ch, cw = color.shape[:2]
    depth_K = _camera(meta.depth_intrinsics, dw, dh, "depth")
    if meta.color_intrinsics is None:
        if (cw, ch) != (dw, dh):
            raise InvalidFrame(
                f"color is {cw}x{ch} but depth is {dw}x{dh}: send color_intrinsics when the cameras differ"
            )
        color_K = _camera(meta.depth_intrinsics, cw, ch, "color")
    else:
        color_K = _camera(meta.color_intrinsics, cw, ch, "color")
    if labels is not None and labels.shape != (ch, cw):
        raise InvalidFrame(f"labels are {labels.shape[1]}x{labels.shape[0]} but colour is {cw}x{ch}")
    try:
        return Frame(
            depth=depth,
            color=color,
            depth_intrinsics=depth_K,
            color_intrinsics=color_K,
            T_color_depth=np.eye(4) if meta.T_color_depth is None else np.asarray(meta.T_color_depth, dtype=float),
            depth_scale=meta.depth_scale,
            labels=labels,
            label_set=meta.label_set,
            gravity_camera=None if meta.gravity is None else np.asarray(meta.gravity, dtype=float),
            T_map_camera_prior=None if meta.pose_prior is None else np.asarray(meta.pose_prior, dtype=float),
            frame_id=meta.frame_id,
            search_region=_search_region(meta.search_region),
            depth_range_m=meta.depth_range_m,
        )
    except CadregError:
        raise
    except (TypeError, ValueError) as exc:
        raise InvalidFrame(f"invalid frame: {exc}") from None


def _search_region(wire: SearchRegionIn | None) -> SearchRegion | None:
    if wire is None:
        return None
    if wire.region_ids is not None:
        return SearchRegion(region_ids=tuple(wire.region_ids))
    return SearchRegion(center=np.asarray(wire.center, dtype=float), radius_m=float(wire.radius_m))


# --- zenoh envelope -----------------------------------------------------------------------------------------------


def pack_envelope(parts: dict[str, bytes], meta: FrameMeta | dict[str, Any]) -> bytes:
    """One binary payload for a frame (layout in the module docstring)."""
    meta = parse_meta(meta)
    offsets: dict[str, list[int]] = {}
    blobs: list[bytes] = []
    pos = 0
    for name in PART_NAMES:
        data = parts.get(name)
        if data is None:
            continue
        data = bytes(data)
        offsets[name] = [pos, len(data)]
        blobs.append(data)
        pos += len(data)
    header = json.dumps(
        {"meta": meta.model_dump(mode="json"), "parts": offsets}, separators=(",", ":"), allow_nan=False
    ).encode()
    return b"".join([_PREFIX.pack(MAGIC, ENVELOPE_VERSION, len(header)), header, *blobs])


def unpack_envelope(payload: bytes | bytearray | memoryview) -> tuple[dict[str, bytes], FrameMeta]:
    """Split an envelope into parts and validated meta; a malformed envelope raises InvalidFrame."""
    data = bytes(payload)
    if len(data) < _PREFIX.size:
        raise InvalidFrame("envelope too short")
    magic, version, header_len = _PREFIX.unpack_from(data)
    if magic != MAGIC:
        raise InvalidFrame("not a cadreg frame envelope (bad magic)")
    if version != ENVELOPE_VERSION:
        raise InvalidFrame(f"envelope version {version} not supported (expected {ENVELOPE_VERSION})")
    body_start = _PREFIX.size + header_len
    if header_len > MAX_HEADER_BYTES or body_start > len(data):
        raise InvalidFrame("envelope header length out of range")
    # the header is the meta plus a few part offsets: the meta's bounds, one level deeper, checked before parsing
    check_json_bounds(data[_PREFIX.size : body_start], "envelope header", MAX_META_BYTES + 1024, MAX_META_DEPTH + 1)
    try:
        header = json.loads(data[_PREFIX.size : body_start])
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InvalidFrame(f"envelope header is not valid JSON: {exc}") from None
    if not isinstance(header, dict) or not isinstance(header.get("parts"), dict) or "meta" not in header:
        raise InvalidFrame("envelope header must be {\"meta\": ..., \"parts\": {...}}")
    meta = parse_meta(header["meta"])
    body_len = len(data) - body_start
    parts: dict[str, bytes] = {}
    for name, span in header["parts"].items():
        if name not in PART_NAMES:
            raise InvalidFrame(f"unknown part in envelope: {name}")
        if (
            not isinstance(span, list)
            or len(span) != 2
            or not all(isinstance(x, int) and not isinstance(x, bool) for x in span)
        ):
            raise InvalidFrame(f"envelope part {name} must be [offset, length]")
        offset, length = span
        if offset < 0 or length < 0 or offset + length > body_len:
            raise InvalidFrame(f"envelope part {name} lies outside the payload")
        parts[name] = data[body_start + offset : body_start + offset + length]
    return parts, meta


# --- results ------------------------------------------------------------------------------------------------------


def _finite(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if isinstance(value, np.generic):
        return _finite(value.item())
    if isinstance(value, np.ndarray):
        return _finite(value.tolist())
    return value


def encode_result(result: dict[str, Any]) -> bytes:
    """A result (or error body) dict as compact UTF-8 JSON; NaN/inf become null."""
    return json.dumps(_finite(result), separators=(",", ":"), allow_nan=False).encode()


def decode_result(payload: bytes | bytearray | str) -> dict[str, Any]:
    """Parse a result (or error body) JSON payload into a dict; a malformed one raises CadregError (`internal`)."""
    return _json_object(payload, "result", CadregError)


def _json_object(text: bytes | bytearray | str, what: str, error: type[CadregError]) -> dict[str, Any]:
    """A JSON object from its text; raises `error` naming `what` for anything else."""
    try:
        value = json.loads(text)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise error(f"{what} is not valid JSON: {exc}") from None
    if not isinstance(value, dict):
        raise error(f"{what} must be a JSON object")
    return value
