"""Recorded RGB-D frames on disk: the ScanNet export layout (read and write) and the 7-Scenes layout (read).

ScanNet export layout (DESIGN §4)::

    color/<i>.jpg|png   depth/<i>.png (uint16)   label/<i>.png (uint16, optional)   pose/<i>.txt (4x4, optional)
    intrinsic/intrinsic_depth.txt  intrinsic/intrinsic_color.txt  (4x4 or 3x3 K)
    intrinsic/extrinsic_depth.txt  intrinsic/extrinsic_color.txt  (4x4, camera -> rig; identity when missing)
    frames.json  {"depth_scale": 1000.0, "label_set": "nyu40", "depth_size": [W, H], "color_size": [W, H],
                  "depth_range_m": 6.0 (optional: the depth camera's range, `Frame.depth_range_m`)}

Frames: `extrinsic_color.txt` = T_rig_color, `extrinsic_depth.txt` = T_rig_depth, `pose/<i>.txt` = T_map_rig, so
`T_color_depth = inv(T_rig_color) @ T_rig_depth` and `T_map_camera = T_map_rig @ T_rig_color` (camera = colour
camera). `FramesWriter` takes the colour camera as the rig, so its pose files hold T_map_camera as they are.

7-Scenes layout (also the 3DMatch/SUN3D sample)::

    frame-NNNNNN.color.jpg|png  frame-NNNNNN.depth.png (uint16 mm; 0 and 65535 invalid)  frame-NNNNNN.pose.txt
    camera-intrinsics.txt (3x3 K, in the folder or its parent; shared by depth and colour)

Missing or malformed files raise `InvalidFileError(path, reason)`.
"""

from __future__ import annotations

import io
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from PIL import Image

from ..camera import CameraIntrinsics
from ..errors import InvalidArgument, InvalidFileError, InvalidFrame
from ..frame import Frame, depth_range_metres
from ..geometry import invert_T, nearest_rotation

Layout = Literal["scannet", "7scenes"]

_SEVEN_SCENES_RE = re.compile(r"^frame-(\d+)\.depth\.png$")
_COLOR_EXTS = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class RawFrame:
    """One recorded frame's files as encoded on disk (what a load tester sends as is).

    color, depth, labels : encoded image bytes (labels None when the folder has none).
    color_name, depth_name, labels_name : the file names, whose suffix tells the encoding.
    """

    color: bytes
    depth: bytes
    labels: bytes | None
    color_name: str
    depth_name: str
    labels_name: str | None


# --- small readers ---------------------------------------------------------------------------------------------


def read_matrix(
    path: Path, shapes: tuple[tuple[int, int], ...] | None = ((4, 4),), *, finite: bool = True
) -> np.ndarray:
    """A whitespace-separated float matrix of one of `shapes` (None = any 2-D shape); InvalidFileError otherwise."""
    path = Path(path)
    if not path.is_file():
        raise InvalidFileError(path, "file is missing")
    try:
        M = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (ValueError, OSError) as exc:
        raise InvalidFileError(path, f"not a numeric matrix ({exc})") from exc
    if shapes is not None and M.shape not in shapes:
        raise InvalidFileError(path, f"expected a matrix of shape {' or '.join(map(str, shapes))}, got {M.shape}")
    if finite and not np.all(np.isfinite(M)):
        raise InvalidFileError(path, "matrix has non-finite entries")
    return M


def read_K(path: Path) -> np.ndarray:
    """3x3 calibration from a 3x3 or 4x4 (ScanNet) text matrix."""
    return read_matrix(path, ((3, 3), (4, 4)))[:3, :3]


def read_image(path: Path) -> np.ndarray:
    """Decode an image file to an array: (H, W, 3) uint8 for colour, (H, W) uint16/uint8 for depth and labels."""
    path = Path(path)
    if not path.is_file():
        raise InvalidFileError(path, "file is missing")
    try:
        with Image.open(path) as im:
            im.load()
            return _image_to_array(im)
    except (OSError, ValueError, SyntaxError) as exc:
        raise InvalidFileError(path, f"cannot decode image ({exc})") from exc


def decode_image(data: bytes) -> np.ndarray:
    """Decode encoded image bytes as `read_image` does (raises ValueError/OSError on garbage)."""
    with Image.open(io.BytesIO(data)) as im:
        im.load()
        return _image_to_array(im)


def _image_to_array(im: Image.Image) -> np.ndarray:
    if im.mode in ("I;16", "I;16B", "I;16L"):
        return np.asarray(im, dtype=np.uint16).copy()
    if im.mode == "I":
        a = np.asarray(im)
        if a.min() < 0 or a.max() > 65535:
            raise ValueError("32-bit image with values outside uint16")
        return a.astype(np.uint16)
    if im.mode == "L":
        return np.asarray(im, dtype=np.uint8).copy()
    return np.asarray(im.convert("RGB"), dtype=np.uint8).copy()


def _image_size(path: Path) -> tuple[int, int]:
    try:
        with Image.open(path) as im:
            return im.size
    except (OSError, ValueError) as exc:
        raise InvalidFileError(path, f"cannot read image header ({exc})") from exc


# --- reader ----------------------------------------------------------------------------------------------------


class RecordedFrames:
    """A folder of recorded RGB-D frames; `open` detects the layout.

    indices : sorted list of the frame numbers present (ints, as in the file names).
    depth_intrinsics, color_intrinsics : CameraIntrinsics of the two cameras.
    T_color_depth : (4, 4) float64, depth camera -> colour camera.
    depth_scale : depth units per metre; label_set : name of the label ids in label images.
    depth_range_m : the depth camera's range (metres, frames.json's "depth_range_m"), None when the folder does not
    say (`Frame.depth_range_m`).
    calibration : the folder's files that describe its cameras (frames.json, intrinsic/*.txt, camera-intrinsics.txt).
    """

    def __init__(
        self,
        root: Path,
        layout: Layout,
        indices: list[int],
        depth_intrinsics: CameraIntrinsics,
        color_intrinsics: CameraIntrinsics,
        T_color_depth: np.ndarray,
        T_rig_color: np.ndarray,
        depth_scale: float,
        label_set: str,
        files: dict[int, dict[str, Path | None]],
        depth_range_m: float | None = None,
        calibration: tuple[Path, ...] = (),
    ) -> None:
        self.root = Path(root)
        self.layout = layout
        self.indices = list(indices)
        self.depth_intrinsics = depth_intrinsics
        self.color_intrinsics = color_intrinsics
        self.T_color_depth = np.asarray(T_color_depth, dtype=np.float64)
        self._T_rig_color = np.asarray(T_rig_color, dtype=np.float64)
        self.depth_scale = float(depth_scale)
        self.label_set = label_set
        self.depth_range_m = depth_range_m
        self.calibration = tuple(calibration)
        self._files = files

    # construction ------------------------------------------------------------------------------------------
    @classmethod
    def open(cls, path: str | Path) -> "RecordedFrames":
        """Open a frames folder (ScanNet export layout or 7-Scenes/3DMatch layout)."""
        root = Path(path)
        if not root.is_dir():
            raise InvalidFileError(root, "frames folder is missing")
        if (root / "depth").is_dir():
            return cls._open_scannet(root)
        if any(_SEVEN_SCENES_RE.match(p.name) for p in root.iterdir()):
            return cls._open_7scenes(root)
        seqs = sorted(p for p in root.iterdir() if p.is_dir() and any(_SEVEN_SCENES_RE.match(q.name) for q in p.iterdir()))
        if len(seqs) == 1:  # the 3DMatch sample: intrinsics beside one seq-XX folder
            return cls._open_7scenes(seqs[0])
        if seqs:
            raise InvalidFileError(root, f"holds {len(seqs)} sequences ({', '.join(s.name for s in seqs)}); open one of them")
        raise InvalidFileError(root, "not a frames folder: no depth/ sub-folder and no frame-NNNNNN.depth.png files")

    @classmethod
    def _open_scannet(cls, root: Path) -> "RecordedFrames":
        files: dict[int, dict[str, Path | None]] = {}
        for p in (root / "depth").iterdir():
            if p.suffix.lower() == ".png" and p.stem.isdigit():
                i = int(p.stem)
                color = next((root / "color" / f"{p.stem}{e}" for e in _COLOR_EXTS if (root / "color" / f"{p.stem}{e}").is_file()), None)
                label = root / "label" / f"{p.stem}.png"
                pose = root / "pose" / f"{p.stem}.txt"
                files[i] = {
                    "depth": p,
                    "color": color or root / "color" / f"{p.stem}.jpg",
                    "label": label if label.is_file() else None,
                    "pose": pose if pose.is_file() else None,
                }
        if not files:
            raise InvalidFileError(root / "depth", "no <i>.png depth images")
        indices = sorted(files)
        meta: dict = {}
        meta_path = root / "frames.json"
        if meta_path.is_file():
            try:
                meta = json.loads(meta_path.read_text())
            except (json.JSONDecodeError, UnicodeDecodeError) as exc:
                raise InvalidFileError(meta_path, f"not valid JSON ({exc})") from exc
            if not isinstance(meta, dict):
                raise InvalidFileError(meta_path, "must hold a JSON object")
        first = files[indices[0]]
        depth_size = _size_from(meta, "depth_size", meta_path) or _image_size(first["depth"])  # type: ignore[arg-type]
        color_size = _size_from(meta, "color_size", meta_path) or _image_size(first["color"])  # type: ignore[arg-type]
        intr = root / "intrinsic"
        K_depth = read_K(intr / "intrinsic_depth.txt")
        K_color = read_K(intr / "intrinsic_color.txt") if (intr / "intrinsic_color.txt").is_file() else K_depth
        T_rig_depth = read_matrix(intr / "extrinsic_depth.txt") if (intr / "extrinsic_depth.txt").is_file() else np.eye(4)
        T_rig_color = read_matrix(intr / "extrinsic_color.txt") if (intr / "extrinsic_color.txt").is_file() else np.eye(4)
        try:
            depth_intr = CameraIntrinsics.from_K(K_depth, *depth_size)
            color_intr = CameraIntrinsics.from_K(K_color, *color_size)
            depth_scale = float(meta.get("depth_scale", 1000.0))
            if not (np.isfinite(depth_scale) and depth_scale > 0):
                raise InvalidFrame(f"depth_scale must be positive, got {depth_scale}")
        except (InvalidFrame, TypeError, ValueError) as exc:
            raise InvalidFileError(intr, f"bad camera description ({exc})") from exc
        try:
            depth_range_m = None if meta.get("depth_range_m") is None else depth_range_metres(meta["depth_range_m"])
        except InvalidFrame as exc:
            raise InvalidFileError(meta_path, exc.message) from exc
        return cls(
            root, "scannet", indices, depth_intr, color_intr,
            T_color_depth=invert_T(T_rig_color) @ T_rig_depth, T_rig_color=T_rig_color,
            depth_scale=depth_scale, label_set=str(meta.get("label_set", "nyu40")), files=files,
            depth_range_m=depth_range_m,
            calibration=tuple(p for p in (meta_path, *(intr / f"{n}.txt" for n in (
                "intrinsic_depth", "intrinsic_color", "extrinsic_depth", "extrinsic_color"))) if p.is_file()),
        )

    @classmethod
    def _open_7scenes(cls, root: Path) -> "RecordedFrames":
        files: dict[int, dict[str, Path | None]] = {}
        for p in root.iterdir():
            m = _SEVEN_SCENES_RE.match(p.name)
            if not m:
                continue
            stem = f"frame-{m.group(1)}"
            color = next((root / f"{stem}.color{e}" for e in _COLOR_EXTS if (root / f"{stem}.color{e}").is_file()), None)
            pose = root / f"{stem}.pose.txt"
            files[int(m.group(1))] = {
                "depth": p,
                "color": color or root / f"{stem}.color.jpg",
                "label": None,
                "pose": pose if pose.is_file() else None,
            }
        indices = sorted(files)
        intr_path = root / "camera-intrinsics.txt"
        if not intr_path.is_file() and (root.parent / "camera-intrinsics.txt").is_file():
            intr_path = root.parent / "camera-intrinsics.txt"
        K = read_K(intr_path)
        first = files[indices[0]]
        try:
            depth_intr = CameraIntrinsics.from_K(K, *_image_size(first["depth"]))  # type: ignore[arg-type]
            color_intr = CameraIntrinsics.from_K(K, *_image_size(first["color"]))  # type: ignore[arg-type]
        except InvalidFrame as exc:
            raise InvalidFileError(intr_path, f"bad camera description ({exc})") from exc
        # 7-Scenes colour is not registered to depth (a few pixels off); no calibration ships, so identity.
        return cls(root, "7scenes", indices, depth_intr, color_intr, np.eye(4), np.eye(4), 1000.0, "nyu40", files,
                   calibration=(intr_path,))

    # access ------------------------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.indices)

    def __contains__(self, i: object) -> bool:
        return i in self._files

    def _entry(self, i: int) -> dict[str, Path | None]:
        try:
            return self._files[int(i)]
        except (KeyError, ValueError, TypeError):
            raise InvalidFileError(self.root, f"no frame with index {i} (have {len(self.indices)} frames)") from None

    def source_files(self, indices: list[int]) -> list[Path]:
        """The files frames `indices` are read from: the calibration, then each frame's depth, colour, labels and
        pose (those it has), in that order."""
        out = list(self.calibration)
        for i in indices:
            entry = self._entry(i)
            out += [entry[k] for k in ("depth", "color", "label", "pose") if entry[k] is not None]  # type: ignore[misc]
        return out

    def has_labels(self) -> bool:
        """True when the folder holds label images (checked on the first frame)."""
        return bool(self.indices) and self._files[self.indices[0]]["label"] is not None

    def pose(self, i: int) -> np.ndarray | None:
        """T_map_camera (colour camera -> map, 4x4 float64) of frame i, None when the folder has no pose for it.

        Poses with non-finite entries (ScanNet marks lost tracking with -inf) are returned as None. Rotations are
        projected onto the nearest true rotation: text files round them (7-Scenes' are ~5e-5 off orthonormal),
        and every rigid-transform helper assumes R⁻¹ = Rᵀ. A matrix that is no rotation at all is refused.
        """
        path = self._entry(i)["pose"]
        if path is None:
            return None
        T_map_rig = read_matrix(path, finite=False)
        if not np.all(np.isfinite(T_map_rig)):
            return None
        R = nearest_rotation(T_map_rig[:3, :3])
        if np.abs(R - T_map_rig[:3, :3]).max() > 1e-2:
            raise InvalidFileError(path, "pose rotation is not a rotation matrix (off by more than 1e-2)")
        T_map_rig = T_map_rig.copy()
        T_map_rig[:3, :3] = R
        return T_map_rig @ self._T_rig_color

    def load(self, i: int) -> tuple[Frame, np.ndarray | None]:
        """(Frame, T_map_camera or None) of frame i; depth 65535 (7-Scenes "no reading") becomes 0."""
        entry = self._entry(i)
        depth_path, color_path, label_path = entry["depth"], entry["color"], entry["label"]
        depth = read_image(depth_path)  # type: ignore[arg-type]
        if depth.ndim != 2:
            raise InvalidFileError(depth_path, f"depth must be a single-channel image, got shape {depth.shape}")
        depth = depth.astype(np.uint16, copy=False)
        if self.layout == "7scenes":
            depth = np.where(depth == 65535, 0, depth).astype(np.uint16)
        color = read_image(color_path)  # type: ignore[arg-type]
        if color.ndim != 3:
            color = np.repeat(color[..., None], 3, axis=2).astype(np.uint8)
        labels = None
        if label_path is not None:
            labels = read_image(label_path)
            if labels.ndim != 2:
                raise InvalidFileError(label_path, f"labels must be a single-channel image, got shape {labels.shape}")
        try:
            frame = Frame(
                depth=depth, color=color, labels=labels,
                depth_intrinsics=self.depth_intrinsics, color_intrinsics=self.color_intrinsics,
                T_color_depth=self.T_color_depth, depth_scale=self.depth_scale, label_set=self.label_set,
                frame_id=str(i), depth_range_m=self.depth_range_m,
            )
        except InvalidFrame as exc:
            raise InvalidFileError(depth_path, f"frame {i} is not a valid RGB-D frame: {exc.message}") from exc  # type: ignore[arg-type]
        return frame, self.pose(i)

    def read_raw(self, i: int) -> RawFrame:
        """The encoded files of frame i, unchanged."""
        entry = self._entry(i)

        def _bytes(p: Path | None) -> bytes | None:
            if p is None:
                return None
            try:
                return Path(p).read_bytes()
            except OSError as exc:
                raise InvalidFileError(p, f"cannot read ({exc})") from exc

        color_b, depth_b = _bytes(entry["color"]), _bytes(entry["depth"])
        assert color_b is not None and depth_b is not None
        label = entry["label"]
        return RawFrame(
            color=color_b, depth=depth_b, labels=_bytes(label),
            color_name=Path(entry["color"]).name, depth_name=Path(entry["depth"]).name,  # type: ignore[arg-type]
            labels_name=None if label is None else label.name,
        )

    def meta(self, i: int | None = None) -> dict:
        """JSON-able camera description of the folder (and the frame id when i is given)."""
        out = {
            "depth_intrinsics": self.depth_intrinsics.to_dict(),
            "color_intrinsics": self.color_intrinsics.to_dict(),
            "T_color_depth": self.T_color_depth.tolist(),
            "depth_scale": self.depth_scale,
            "label_set": self.label_set,
        }
        if self.depth_range_m is not None:
            out["depth_range_m"] = self.depth_range_m
        if i is not None:
            out["frame_id"] = str(i)
        return out


def _size_from(meta: dict, key: str, path: Path) -> tuple[int, int] | None:
    if key not in meta:
        return None
    v = meta[key]
    if not (isinstance(v, (list, tuple)) and len(v) == 2 and all(isinstance(x, int) and x > 0 for x in v)):
        raise InvalidFileError(path, f"{key} must be [width, height] positive integers, got {v!r}")
    return int(v[0]), int(v[1])


# --- writer ----------------------------------------------------------------------------------------------------


class FramesWriter:
    """Write a recorded-frames folder in the ScanNet export layout.

    The colour camera is the rig: extrinsic_color.txt = identity, extrinsic_depth.txt = T_color_depth, and each
    pose/<i>.txt holds T_map_camera (colour camera -> map) as is.
    color_format : "png" (lossless, compress_level=1 for speed) or "jpg" (quality 95, as ScanNet ships).
    depth_range_m : the depth camera's range (metres), written to frames.json when given (`Frame.depth_range_m`).
    """

    def __init__(
        self,
        root: str | Path,
        depth_intrinsics: CameraIntrinsics,
        color_intrinsics: CameraIntrinsics,
        T_color_depth: np.ndarray | None = None,
        *,
        depth_scale: float = 1000.0,
        label_set: str = "nyu40",
        color_format: Literal["png", "jpg"] = "png",
        depth_range_m: float | None = None,
        extra_meta: dict | None = None,
    ) -> None:
        self.root = Path(root)
        self.depth_intrinsics = depth_intrinsics
        self.color_intrinsics = color_intrinsics
        self.T_color_depth = np.eye(4) if T_color_depth is None else np.asarray(T_color_depth, dtype=np.float64)
        self.depth_scale = float(depth_scale)
        self.label_set = label_set
        if color_format not in ("png", "jpg"):
            raise InvalidArgument(f"color_format must be png or jpg, got {color_format!r}")
        self.color_format = color_format
        for sub in ("color", "depth", "label", "pose", "intrinsic"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)
        intr = self.root / "intrinsic"
        np.savetxt(intr / "intrinsic_depth.txt", _K44(depth_intrinsics), fmt="%.9f")
        np.savetxt(intr / "intrinsic_color.txt", _K44(color_intrinsics), fmt="%.9f")
        np.savetxt(intr / "extrinsic_depth.txt", self.T_color_depth, fmt="%.12f")
        np.savetxt(intr / "extrinsic_color.txt", np.eye(4), fmt="%.12f")
        meta = {
            "depth_scale": self.depth_scale,
            "label_set": label_set,
            "depth_size": [depth_intrinsics.width, depth_intrinsics.height],
            "color_size": [color_intrinsics.width, color_intrinsics.height],
            **({} if depth_range_m is None else {"depth_range_m": float(depth_range_m)}),
            **(extra_meta or {}),
        }
        (self.root / "frames.json").write_text(json.dumps(meta, indent=2))

    def write(self, i: int, frame: Frame, T_map_camera: np.ndarray | None = None) -> None:
        """Write frame i (its cameras must be the writer's) and its pose when given."""
        if frame.depth_intrinsics != self.depth_intrinsics or frame.color_intrinsics != self.color_intrinsics:
            raise InvalidFrame("frame intrinsics differ from the folder's")
        if not np.allclose(frame.T_color_depth, self.T_color_depth, atol=1e-9):
            raise InvalidFrame("frame T_color_depth differs from the folder's")
        Image.fromarray(frame.depth.astype(np.uint16)).save(self.root / "depth" / f"{i}.png", compress_level=1)
        color_img = Image.fromarray(frame.color)
        if self.color_format == "png":
            color_img.save(self.root / "color" / f"{i}.png", compress_level=1)
        else:
            color_img.save(self.root / "color" / f"{i}.jpg", quality=95)
        if frame.labels is not None:
            Image.fromarray(frame.labels.astype(np.uint16)).save(self.root / "label" / f"{i}.png", compress_level=1)
        if T_map_camera is not None:
            np.savetxt(self.root / "pose" / f"{i}.txt", np.asarray(T_map_camera, dtype=np.float64), fmt="%.12f")


def _K44(intr: CameraIntrinsics) -> np.ndarray:
    K = np.eye(4)
    K[:3, :3] = intr.K
    return K


def read_poses(path: str | Path) -> list[np.ndarray]:
    """Camera poses (T_map_camera, 4x4 float64 each) from a recorded-frames folder (its pose files, in index
    order), a folder of 4x4 text files (sorted by name), or one text file of stacked 4x4 matrices (4N rows)."""
    path = Path(path)
    if path.is_dir():
        try:
            frames = RecordedFrames.open(path)
        except InvalidFileError:
            files = sorted(path.glob("*.txt"), key=lambda p: (len(p.stem), p.stem))
            if not files:
                raise InvalidFileError(path, "no pose files (*.txt) and not a frames folder") from None
            return [read_matrix(p) for p in files]
        poses = [frames.pose(i) for i in frames.indices]
        kept = [T for T in poses if T is not None]
        if not kept:
            raise InvalidFileError(path, "frames folder has no pose files")
        return kept
    M = read_matrix(path, shapes=None)
    if M.shape[1] != 4 or M.shape[0] % 4 != 0 or M.shape[0] == 0:
        raise InvalidFileError(path, f"expected stacked 4x4 matrices (4N rows, 4 columns), got {M.shape}")
    return [M[4 * k:4 * k + 4].copy() for k in range(len(M) // 4)]


def write_indexed_poses(directory: str | Path, poses: dict[int, np.ndarray]) -> None:
    """`directory/<index>.txt`, one 4x4 T_map_camera per frame index (what `read_indexed_poses` reads)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    for i, T_map_camera in poses.items():
        np.savetxt(directory / f"{int(i)}.txt", np.asarray(T_map_camera, dtype=np.float64), fmt="%.12f")


def read_indexed_poses(directory: str | Path) -> dict[int, np.ndarray]:
    """{frame index: 4x4 T_map_camera} from a folder of `<index>.txt` files (`write_indexed_poses`)."""
    directory = Path(directory)
    if not directory.is_dir():
        raise InvalidFileError(directory, "not a folder of <index>.txt pose files")
    poses = {int(p.stem): read_matrix(p) for p in directory.glob("*.txt") if p.stem.isdigit()}
    if not poses:
        raise InvalidFileError(directory, "no <index>.txt pose files")
    return poses
