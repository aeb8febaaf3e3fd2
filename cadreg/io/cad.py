"""CAD models from a ShapeNet-style library: `<cad_root>/<synset>/<model id>/models/model_normalized.obj`.

Other trimesh-readable files (`.ply`, `.stl`, `.glb`, `.off`) are found at `<cad_root>/<synset>/<model id>.<ext>`
or `<cad_root>/<synset>/<model id>/model.<ext>`.
"""

from __future__ import annotations

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
