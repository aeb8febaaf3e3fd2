"""CAD models from a ShapeNet-style library: `<cad_root>/<synset>/<model id>/models/model_normalized.obj`.

Other trimesh-readable files (`.ply`, `.stl`, `.glb`, `.off`) are found at `<cad_root>/<synset>/<model id>.<ext>`
or `<cad_root>/<synset>/<model id>/model.<ext>`; when listing a whole library (`list_cad_library`, for automatic
alignment) any such file in `<cad_root>/<synset>/<model id>/models/` counts too.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InvalidFileError

_EXTS = ("obj", "ply", "stl", "off", "glb", "gltf")


def cad_model_path(cad_root: str | Path, synset: str, model_id: str) -> Path:
    """Path of a CAD model in the library; raises InvalidFileError naming the expected file when missing."""
    root = Path(cad_root)
    base = root / synset / model_id
    candidates = [base / "models" / "model_normalized.obj"]
    candidates += [base / f"model.{e}" for e in _EXTS] + [root / synset / f"{model_id}.{e}" for e in _EXTS]
    for c in candidates:
        if c.is_file():
            return c
    raise InvalidFileError(candidates[0], f"CAD model {synset}/{model_id} not found under {root}")


@dataclass(frozen=True)
class CadLibraryEntry:
    """One model of a CAD library: ShapeNet synset (folder name), model id, and the file to load."""

    synset: str
    model_id: str
    path: Path

    @property
    def cad_id(self) -> str:
        return f"{self.synset}/{self.model_id}"


def _model_file(root: Path, synset: str, model_id: str) -> Path | None:
    try:
        return cad_model_path(root, synset, model_id)
    except InvalidFileError:
        pass
    models = root / synset / model_id / "models"
    if models.is_dir():
        found = sorted(p for p in models.iterdir() if p.is_file() and p.suffix.lower().lstrip(".") in _EXTS)
        if found:
            return found[0]
    return None


def list_cad_library(cad_root: str | Path) -> list[CadLibraryEntry]:
    """Every model of a library, sorted by synset and id: `<synset>/<id>/models/*.<ext>` (model_normalized.obj
    first), `<synset>/<id>/model.<ext>` or `<synset>/<id>.<ext>`. Files are found, not loaded.

    Raises InvalidFileError naming the folder when it is missing, not a folder, or holds no model.
    """
    root = Path(cad_root)
    if not root.is_dir():
        reason = "CAD library folder not found" if not root.exists() else "CAD library is not a folder"
        raise InvalidFileError(root, reason)
    entries: list[CadLibraryEntry] = []
    for synset_dir in sorted(p for p in root.iterdir() if p.is_dir()):
        ids = {p.name for p in synset_dir.iterdir() if p.is_dir()}
        ids |= {p.stem for p in synset_dir.iterdir() if p.is_file() and p.suffix.lower().lstrip(".") in _EXTS}
        for model_id in sorted(ids):
            path = _model_file(root, synset_dir.name, model_id)
            if path is not None:
                entries.append(CadLibraryEntry(synset_dir.name, model_id, path))
    if not entries:
        raise InvalidFileError(root, "CAD library holds no models (expected <synset>/<model id>/models/*.obj or "
                                     f"another of {', '.join(_EXTS)})")
    return entries


def load_cad_mesh(path: str | Path):
    """Load a CAD file as one triangle mesh (trimesh.Trimesh, CAD model frame, no texture needed).

    Returns vertices (V, 3) float64 and faces (F, 3) int64 in `mesh.vertices` / `mesh.faces`.
    """
    import trimesh

    path = Path(path)
    try:
        mesh = trimesh.load(path, force="mesh", process=False, skip_materials=True)
    except Exception as exc:  # trimesh raises many types for bad files; all mean "unreadable"
        raise InvalidFileError(path, f"cannot load CAD mesh: {exc}") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InvalidFileError(path, "CAD file holds no triangles")
    if not np.all(np.isfinite(mesh.vertices)):
        raise InvalidFileError(path, "CAD mesh has non-finite vertices")
    return mesh
