"""Automatic CAD alignment (issue 13): fit the models of a CAD library to the furniture of a labelled scan, for
sites with no Scan2CAD annotation.

    load_library(cad_root) -> CadLibrary                    models by class, with their rotational symmetry
    AlignJob(instance, cls, points, support_z, models, config)   one per clustered instance of a class the library
                                                            covers (made by cadreg.site.build.auto_cad_placements
                                                            from the build's class-wise clustering)
    align_instances(jobs, workers) -> [InstanceResult]      best model per instance, on `workers` processes
    prefer_common_models(results, configs)                  one model for a class's instances where the fits allow
    scan2cad_record(id_scan, placements) -> dict            the alignments as a Scan2CAD record (identity scan trs)

Furniture stands upright on the floor (maps are z up), so a fit has 7 parameters, not 10: yaw, translation and an
anisotropic scale. Per instance and model:
1. yaw hypotheses: the 4 axes of the instance's minimum-area footprint rectangle and a coarse sweep, taken modulo
   the model's rotational symmetry about its up axis (found from the model's own geometry);
2. per yaw, scale and translation from the instance's extents along the rotated axes, the bottom on the surface
   the instance stands on and the top at its top (a table's legs are rarely labelled: its top alone would make it
   a slab);
3. a truncated two-way Chamfer score ranks the hypotheses; the best few (with distinct yaws) are refined by ICP
   restricted to yaw, horizontal translation and horizontal scales (nearest neighbours both ways from scipy's
   cKDTree, each step a robust scipy least_squares). Score and ICP see only the parts above the base (the lowest
   `base_fraction` of the height, scan and model): legs and swivel bases differ most between models of a class and
   turn apart from the seat. The box is then grown over the instance's points the CAD explains;
4. the fit of each model is measured against the instance both ways (median distance, coverage), with exact
   point-to-mesh distances (Open3D RaycastingScene), and the best model is kept when it passes `AutoCadConfig`'s
   thresholds; else the instance stays a cluster node;
5. the instances of a class take the class's common model where it fits within `same_model_margin` of their best
   (`prefer_common_models`): a room's chairs are mostly of one kind.
Open3D's ICP estimates rigid or similarity transforms only (full rotation, one scale): an upright pose with three
scales is no estimator of it, hence the small hand-written ICP loop around least_squares.
"""

from __future__ import annotations

import logging
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from ..config import AutoCadConfig
from ..errors import InvalidFileError
from ..io.cad import list_cad_library, load_cad_mesh
from ..labels import SHAPENET_SYNSETS, synset_class
from ..pointset import PointSet

log = logging.getLogger("cadreg.autocad")

# ShapeNet models are y-up, maps z-up: this rotation takes CAD coordinates to "upright" ones (CAD y -> z).
R_UPRIGHT_CAD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

SYM_NONE, SYM_2, SYM_4, SYM_INF = "__SYM_NONE", "__SYM_ROTATE_UP_2", "__SYM_ROTATE_UP_4", "__SYM_ROTATE_UP_INF"
# Yaw period searched per symmetry. A round model (INF) still has a yaw once its two horizontal scales differ
# (an oval table); 90° with the scales taken from the box along each axis covers it, as for SYM_4.
_YAW_PERIOD_DEG = {SYM_NONE: 360.0, SYM_2: 180.0, SYM_4: 90.0, SYM_INF: 90.0}
# Scan2CAD's symmetry names -> the yaw period (degrees) within which two alignments are the same; 0 = any yaw.
SYM_PERIOD_DEG = {SYM_NONE: 360.0, SYM_2: 180.0, SYM_4: 90.0, SYM_INF: 0.0}

_SYMMETRY_SAMPLES = 3000
_MODEL_SAMPLES = 6000       # surface samples per model kept for the search (a random fit_points of them per job)
_FIT_SAMPLES = 20000        # CAD samples of the final CAD -> scan distances
_SCALE_RANGE = 1.6          # the ICP may change each scale by at most this factor from its box-derived start
_MIN_FIT_POINTS = 30        # fewer points above the base than this: fit the whole instance (or model) instead


# --- the library ------------------------------------------------------------------------------------------------


@dataclass
class LibraryModel:
    """One CAD model prepared for fitting.

    mesh : trimesh.Trimesh in the CAD frame (ShapeNet: y up). lo, hi : (3,) its vertex bounds, CAD frame.
    bottom_up : (3,) the centre of the bottom face of its box in upright coordinates (R_UPRIGHT_CAD @ p_cad).
    extent_up : (3,) box extents in upright coordinates (x, y horizontal, z up).
    samples_up : (m, 3) float64 surface samples, upright coordinates relative to `bottom_up`.
    sym : Scan2CAD symmetry name found from the geometry.
    """

    cad_id: str
    synset: str
    cls: str
    path: str
    mesh: Any
    lo: np.ndarray
    hi: np.ndarray
    bottom_up: np.ndarray
    extent_up: np.ndarray
    samples_up: np.ndarray
    sym: str


@dataclass
class CadLibrary:
    root: str
    models: list[LibraryModel]
    notes: list[str] = field(default_factory=list)  # models skipped, and why

    def classes(self) -> set[str]:
        return {m.cls for m in self.models}

    def of_class(self, cls: str) -> list[LibraryModel]:
        return [m for m in self.models if m.cls == cls]

    def model(self, cad_id: str) -> LibraryModel:
        return next(m for m in self.models if m.cad_id == cad_id)


def _rotate_z(points: np.ndarray, yaw_rad: float, center_xy: np.ndarray) -> np.ndarray:
    """points (m, 3) turned by yaw_rad about the vertical axis through center_xy."""
    center = np.array([center_xy[0], center_xy[1], 0.0])
    return (points - center) @ _Rz(yaw_rad).T + center


def rotational_symmetry(samples_up: np.ndarray, seed: int = 0) -> str:
    """Symmetry of a model about its vertical axis (through its box centre), in Scan2CAD's names.

    samples_up : (m, 3) surface samples, upright coordinates. A rotation is a symmetry when the rotated samples lie
    as close to the unrotated ones as a second, independent sample of the same surface does (the sampling noise).
    """
    rng = np.random.default_rng(seed)
    n = len(samples_up)
    perm = rng.permutation(n)
    a, b = samples_up[perm[: n // 2]], samples_up[perm[n // 2:]]
    center_xy = (samples_up[:, :2].min(axis=0) + samples_up[:, :2].max(axis=0)) / 2.0
    tree = cKDTree(b)
    base = float(np.mean(tree.query(a)[0]))

    def symmetric(angle_deg: float) -> bool:
        d = tree.query(_rotate_z(a, np.radians(angle_deg), center_xy))[0]
        return float(np.mean(d)) <= 1.5 * base

    if not symmetric(180.0):
        return SYM_NONE
    if not symmetric(90.0):
        return SYM_2
    if symmetric(30.0) and symmetric(360.0 / 7.0):
        return SYM_INF
    return SYM_4


def prepare_model(mesh, *, synset: str, model_id: str, path: str, seed: int = 0) -> LibraryModel:
    """A loaded CAD mesh (CAD frame) ready for fitting: upright box, surface samples, symmetry."""
    import trimesh

    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    corners_up = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    corners_up = corners_up @ R_UPRIGHT_CAD.T
    lo_up, hi_up = corners_up.min(axis=0), corners_up.max(axis=0)
    bottom_up = np.array([(lo_up[0] + hi_up[0]) / 2, (lo_up[1] + hi_up[1]) / 2, lo_up[2]])
    pts, _ = trimesh.sample.sample_surface(mesh, _MODEL_SAMPLES, seed=seed)
    samples_up = np.asarray(pts, np.float64) @ R_UPRIGHT_CAD.T - bottom_up
    sym = rotational_symmetry(samples_up[:_SYMMETRY_SAMPLES * 2], seed)
    return LibraryModel(cad_id=f"{synset}/{model_id}", synset=synset, cls=synset_class(synset), path=str(path),
                        mesh=mesh, lo=lo, hi=hi, bottom_up=bottom_up, extent_up=hi_up - lo_up,
                        samples_up=samples_up, sym=sym)


def load_library(cad_root: str | Path, seed: int = 0) -> CadLibrary:
    """Load every model of a ShapeNet-style library (`cadreg.io.cad.list_cad_library`).

    Folders that are no ShapeNet synset and files trimesh cannot read are skipped with a warning (in `notes`).
    Raises InvalidFileError naming the folder when it is missing or empty, or when no model could be loaded.
    """
    entries = list_cad_library(cad_root)
    models: list[LibraryModel] = []
    notes: list[str] = []
    for synset in sorted({e.synset for e in entries} - set(SHAPENET_SYNSETS)):
        notes.append(f"skipped CAD folder {Path(cad_root) / synset}: {synset!r} is no ShapeNet synset, so its "
                     "models have no class")
    for e in entries:
        if e.synset not in SHAPENET_SYNSETS:
            continue
        try:
            mesh = load_cad_mesh(e.path)
        except InvalidFileError as exc:
            notes.append(f"skipped unreadable CAD model {exc.message}")
            continue
        models.append(prepare_model(mesh, synset=e.synset, model_id=e.model_id, path=str(e.path), seed=seed))
    for note in notes:
        log.warning("%s", note)
    if not models:
        raise InvalidFileError(cad_root, f"CAD library has no usable model ({len(entries)} found, none readable "
                                         "with a ShapeNet synset folder)")
    return CadLibrary(str(cad_root), models, notes)


# --- instances --------------------------------------------------------------------------------------------------


@dataclass
class ModelData:
    """What a worker needs of a model (picklable arrays): upright samples, box, mesh, symmetry."""

    cad_id: str
    samples_up: np.ndarray
    extent_up: np.ndarray
    vertices_up: np.ndarray  # (V, 3) mesh vertices, upright coordinates relative to the model's bottom centre
    faces: np.ndarray
    sym: str
    bottom_up: np.ndarray


@dataclass
class AlignJob:
    """One instance to fit. points : (n, 3) float64, map frame; support_z : height of the surface it stands on."""

    instance: int
    cls: str
    points: np.ndarray
    support_z: float
    models: list[ModelData]
    config: AutoCadConfig


@dataclass
class Fit:
    """How well an aligned CAD explains its instance (metres, shares in [0, 1])."""

    median_scan_to_cad_m: float
    scan_coverage: float
    median_cad_to_scan_m: float
    cad_coverage: float
    score: float

    def passes(self, c: AutoCadConfig) -> bool:
        return (self.median_scan_to_cad_m <= c.max_median_scan_to_cad_m and self.scan_coverage >= c.min_scan_coverage
                and self.median_cad_to_scan_m <= c.max_median_cad_to_scan_m and self.cad_coverage >= c.min_cad_coverage)

    def to_dict(self) -> dict[str, float]:
        return {"median_scan_to_cad_m": round(self.median_scan_to_cad_m, 4),
                "scan_coverage": round(self.scan_coverage, 3),
                "median_cad_to_scan_m": round(self.median_cad_to_scan_m, 4),
                "cad_coverage": round(self.cad_coverage, 3), "score": round(self.score, 4)}


@dataclass
class ModelFit:
    """One model fitted to one instance. A_map_cad : (4, 4) affine CAD frame -> map frame; vertices_map : (V, 3)
    the model's mesh vertices in the map frame; score : the truncated Chamfer distance the search minimised;
    fit : measured afterwards (`measure_fit`)."""

    cad_id: str
    A_map_cad: np.ndarray
    vertices_map: np.ndarray
    yaw_deg: float
    scale_up: np.ndarray
    sym: str
    score: float
    fit: Fit | None = None


@dataclass
class InstanceResult:
    """The fit of every model of the instance's class, best first; `accepted` is the best if it passes."""

    instance: int
    cls: str
    points: int
    center: np.ndarray
    fits: list[ModelFit]
    accepted: ModelFit | None

    def to_dict(self) -> dict[str, Any]:
        best = self.fits[0] if self.fits else None
        return {"instance": self.instance, "class": self.cls, "points": self.points,
                "center": [round(float(x), 4) for x in self.center],
                "accepted": self.accepted is not None,
                "chosen": None if self.accepted is None else self.accepted.cad_id,
                "best": None if best is None else {"cad_id": best.cad_id, **best.fit.to_dict()},
                "models": {f.cad_id: f.fit.to_dict() for f in self.fits}}


def support_height(raw: PointSet, structure: np.ndarray, points: np.ndarray, search_m: float) -> float:
    """Height (map z, metres) of the surface an instance stands on: upward-facing points that belong to no object
    (floor, or unlabelled) under its footprint grown by search_m, below its lowest point. The instance's lowest
    point when there are none (an object the scan saw from below, or a map without floor)."""
    lo_xy, hi_xy = points[:, :2].min(axis=0) - search_m, points[:, :2].max(axis=0) + search_m
    z_min = float(points[:, 2].min())
    near = np.all((raw.points[:, :2] >= lo_xy) & (raw.points[:, :2] <= hi_xy), axis=1)
    no_object = (raw.class_index < 0) | structure
    cand = near & no_object & (np.abs(raw.normals[:, 2]) > 0.9) & (raw.points[:, 2] <= z_min + 0.02)
    z = np.sort(raw.points[cand, 2].astype(np.float64))
    if len(z) < 20:
        return z_min
    # The lowest dense layer (the floor), not the mean of everything below (a footrest, a box under a table).
    layer = z[z <= z[len(z) // 10] + 0.03]
    return float(np.median(layer))


def model_data(m: LibraryModel) -> ModelData:
    return ModelData(m.cad_id, m.samples_up, m.extent_up,
                     np.asarray(m.mesh.vertices, np.float64) @ R_UPRIGHT_CAD.T - m.bottom_up,
                     np.asarray(m.mesh.faces, np.int64), m.sym, m.bottom_up)


# --- fitting one instance ---------------------------------------------------------------------------------------


def _Rz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _apply(x: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Upright model points q (m, 3) -> map frame under x = (yaw, tx, ty, tz, ln sx, ln sy, ln sz)."""
    return (q * np.exp(x[4:7])) @ _Rz(x[0]).T + x[1:4]


def _yaw_hypotheses(points: np.ndarray, sym: str, sweep_deg: float) -> list[float]:
    """Yaws (radians): the footprint rectangle's 4 axes and a sweep, modulo the symmetry period, de-duplicated."""
    import trimesh

    period = _YAW_PERIOD_DEG[sym]
    try:
        T2, _ = trimesh.bounds.oriented_bounds_2D(points[:, :2])
        # T2 rotates the points by -yaw onto the axes: its first row is (cos yaw, sin yaw)
        rect = np.degrees(np.arctan2(T2[0, 1], T2[0, 0]))
    except Exception:  # degenerate footprint (qhull): the sweep alone
        rect = 0.0
    cands = [rect + 90.0 * k for k in range(4)] + list(np.arange(0.0, 360.0, sweep_deg))
    out: list[float] = []
    for a in (c % period for c in cands):
        if all(min(abs(a - b), period - abs(a - b)) > 1.0 for b in out):
            out.append(a)
    return [float(np.radians(a)) for a in out]


def _initial_params(points: np.ndarray, yaw: float, support_z: float, m: ModelData) -> np.ndarray:
    """Scale and translation for one yaw from the instance's extents along the rotated axes (robust percentiles:
    a few points of label bleed should not stretch a chair)."""
    local = points[:, :2] @ _Rz(yaw)[:2, :2]
    lo, hi = np.percentile(local, 0.5, axis=0), np.percentile(local, 99.5, axis=0)
    center = _Rz(yaw)[:2, :2] @ ((lo + hi) / 2.0)
    top = float(np.percentile(points[:, 2], 99.5))
    extent = np.array([hi[0] - lo[0], hi[1] - lo[1], max(top - support_z, 0.05)])
    scale = np.maximum(extent, 0.05) / np.maximum(m.extent_up, 1e-6)
    return np.array([yaw, center[0], center[1], support_z, *np.log(scale)])


def _chamfer(x: np.ndarray, q: np.ndarray, p: np.ndarray, p_tree: cKDTree, tau: float) -> float:
    """Truncated two-way Chamfer distance (metres) between model samples q under x and instance points p."""
    mq = _apply(x, q)
    d_pm = cKDTree(mq).query(p)[0]
    d_mp = p_tree.query(mq)[0]
    return float(np.mean(np.minimum(d_pm, tau)) + np.mean(np.minimum(d_mp, tau)))


# Free parameters of the ICP: yaw, tx, ty, ln sx, ln sy (indices into x). The bottom stays on the support surface
# and the top at the instance's top (both seen reliably: floors, seat backs and table tops face the sensor), so
# height and vertical scale are fixed by the hypothesis; a wrong yaw cannot buy a better fit by stretching.
_FREE = np.array([0, 1, 2, 4, 5])


def _icp(x0: np.ndarray, q: np.ndarray, p: np.ndarray, p_tree: cKDTree, c: AutoCadConfig) -> np.ndarray:
    """ICP over yaw, horizontal translation and horizontal scales: pairs both ways within a shrinking distance,
    then a robust least-squares step (soft L1) with each scale within _SCALE_RANGE of x0's and a prior that
    keeps the model's horizontal proportions within about `anisotropy_sigma` (log ratio) of its own."""
    x = x0.copy()
    v = x0[_FREE].copy()
    lo = np.full(5, -np.inf)
    hi = np.full(5, np.inf)
    lo[3:], hi[3:] = v[3:] - np.log(_SCALE_RANGE), v[3:] + np.log(_SCALE_RANGE)
    n_it = c.icp_iterations
    for it in range(n_it):
        tau = c.icp_max_correspondence_m * (1.0 - (2.0 / 3.0) * it / max(n_it - 1, 1))
        mq = _apply(x, q)
        d1, j1 = cKDTree(mq).query(p, distance_upper_bound=tau)
        d2, j2 = p_tree.query(mq, distance_upper_bound=tau)
        ok1, ok2 = np.isfinite(d1), np.isfinite(d2)
        qa = np.vstack([q[j1[ok1]], q[ok2]])
        pa = np.vstack([p[ok1], p[j2[ok2]]])
        if len(qa) < 10:
            break
        # the prior weighs like every pair being 1 cm off when the proportions are off by one sigma
        w_prior = np.sqrt(3 * len(qa)) * 0.01 / c.anisotropy_sigma

        def full(u: np.ndarray) -> np.ndarray:
            y = x.copy()
            y[_FREE] = u
            return y

        def residual(u: np.ndarray) -> np.ndarray:
            r = (_apply(full(u), qa) - pa).ravel()
            return np.append(r, w_prior * (u[3] - u[4]))

        def jacobian(u: np.ndarray) -> np.ndarray:
            y = full(u)
            sq = qa * np.exp(y[4:7])
            R = _Rz(y[0])
            dR = np.array([[-R[1, 0], -R[0, 0], 0.0], [R[0, 0], -R[1, 0], 0.0], [0.0, 0.0, 0.0]])
            J = np.zeros((len(qa), 3, 5))
            J[:, :, 0] = sq @ dR.T
            J[:, :2, 1:3] = np.eye(3)[:2, :2]
            J[:, :, 3:5] = R[None, :, :2] * sq[:, None, :2]
            Jf = np.zeros((3 * len(qa) + 1, 5))
            Jf[:-1] = J.reshape(-1, 5)
            Jf[-1, 3], Jf[-1, 4] = w_prior, -w_prior
            return Jf

        res = least_squares(residual, np.clip(v, lo + 1e-9, hi - 1e-9), jac=jacobian, bounds=(lo, hi),
                            loss="soft_l1", f_scale=tau / 3.0, max_nfev=8, method="trf", tr_solver="lsmr")
        step = np.abs(res.x - v)
        v = res.x
        x = full(v)
        if step[0] < np.radians(0.05) and step[1:3].max() < 5e-4 and step[3:].max() < 1e-3:
            break
    return x


def _A_map_cad(x: np.ndarray, bottom_up: np.ndarray) -> np.ndarray:
    """The affine CAD frame -> map of upright parameters x (model relative to its bottom centre b, see ModelData).

    p = Rz · diag(s_up) · (R_up · q_cad − b) + t = (Rz · R_up) · diag(s_cad) · q_cad + (t − Rz · diag(s_up) · b):
    the CAD axes are x, y (up), z, so s_cad = (s_up_x, s_up_z, s_up_y).
    """
    s_up = np.exp(x[4:7])
    A = np.eye(4)
    A[:3, :3] = _Rz(x[0]) @ R_UPRIGHT_CAD @ np.diag([s_up[0], s_up[2], s_up[1]])
    A[:3, 3] = x[1:4] - _Rz(x[0]) @ (s_up * bottom_up)
    return A


def measure_fit(points: np.ndarray, vertices_map: np.ndarray, faces: np.ndarray, c: AutoCadConfig,
                score: float, seed: int = 0) -> Fit:
    """Fit of a CAD mesh (already in the map frame) to instance points (n, 3): exact point-to-mesh distances of
    the points (Open3D RaycastingScene) and distances of CAD surface samples to the points."""
    import open3d as o3d
    import trimesh

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices_map.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    d_scan = scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()
    mesh = trimesh.Trimesh(vertices_map, faces, process=False)
    samples = trimesh.sample.sample_surface(mesh, _FIT_SAMPLES, seed=seed)[0]
    d_cad = cKDTree(points).query(samples)[0]
    return Fit(float(np.median(d_scan)), float(np.mean(d_scan <= c.inlier_m)), float(np.median(d_cad)),
               float(np.mean(d_cad <= c.inlier_m)), score)


def _cover_footprint(x: np.ndarray, points: np.ndarray, m: ModelData, explained_m: float) -> np.ndarray:
    """Grow the horizontal scales (and shift the centre) so the CAD's box covers the footprint of the instance's
    points that the fitted CAD explains (within explained_m of its surface samples; robust 0.5–99.5 % along the
    fitted axes): a library model is rarely the scanned object, and a model that fits part of it snugly leaves the
    rest outside its box, while the box is what the object node and the enhancement use. Points farther from the
    CAD are left out, not trimmed by a fixed share: the labels bleed onto walls and floors by more than a few per
    cent of an instance's points, while a swivel chair's star legs, sparse but real, are a few per cent too."""
    d = cKDTree(_apply(x, m.samples_up)).query(points, distance_upper_bound=explained_m)[0]
    explained = points[np.isfinite(d)]
    if len(explained) < _MIN_FIT_POINTS:
        return x
    R2 = _Rz(x[0])[:2, :2]
    local = (explained[:, :2] - x[1:3]) @ R2
    half = m.extent_up[:2] * np.exp(x[4:6]) / 2.0
    lo = np.minimum(-half, np.percentile(local, 0.5, axis=0))
    hi = np.maximum(half, np.percentile(local, 99.5, axis=0))
    y = x.copy()
    y[1:3] = x[1:3] + R2 @ ((lo + hi) / 2.0)
    y[4:6] = np.log((hi - lo) / m.extent_up[:2])
    return y


def _distinct_best(hyps: list[np.ndarray], scores: list[float], k: int, period_deg: float) -> list[int]:
    """Indices of the k best-scoring hypotheses whose yaws are ≥ 20° apart (modulo the period): neighbours of one
    minimum would converge to the same pose and leave the other basins untried."""
    picked: list[int] = []
    for i in np.argsort(scores):
        yaw = np.degrees(hyps[i][0])
        if all(min((yaw - np.degrees(hyps[j][0])) % period_deg, (np.degrees(hyps[j][0]) - yaw) % period_deg) >= 20.0
               for j in picked):
            picked.append(int(i))
        if len(picked) == k:
            break
    return picked


def _above_base(points: np.ndarray, bottom_z: float, height_m: float, fraction: float) -> np.ndarray:
    """The points (m, 3) higher than `fraction` of height_m above bottom_z; all of them when fewer than
    _MIN_FIT_POINTS would be left (a flat object: nothing above its base but its top)."""
    upper = points[points[:, 2] > bottom_z + fraction * height_m]
    return upper if len(upper) >= _MIN_FIT_POINTS else points


def fit_model(points: np.ndarray, support_z: float, m: ModelData, c: AutoCadConfig) -> ModelFit:
    """Best upright alignment of one model to one instance (points (n, 3) float64, map frame); `fit` unset.

    The footprint and height of the hypotheses come from all the instance's points; the yaw, scale and translation
    are then searched and refined on the parts above the base (`AutoCadConfig.base_fraction`) of both sides."""
    rng = np.random.default_rng(c.seed)
    p = points if len(points) <= c.fit_points else points[rng.choice(len(points), c.fit_points, replace=False)]
    q = m.samples_up[rng.choice(len(m.samples_up), min(c.fit_points, len(m.samples_up)), replace=False)]
    top_z = float(np.percentile(points[:, 2], 99.5))
    p_up = _above_base(p, support_z, top_z - support_z, c.base_fraction)
    q_up = _above_base(q, 0.0, float(m.extent_up[2]), c.base_fraction)
    p_tree = cKDTree(p_up)
    tau = c.score_truncation_m
    hyps = [_initial_params(p, yaw, support_z, m) for yaw in _yaw_hypotheses(p, m.sym, c.yaw_sweep_deg)]
    scores = [_chamfer(x, q_up, p_up, p_tree, tau) for x in hyps]
    best_x, best_score = None, np.inf
    for k in _distinct_best(hyps, scores, c.refine_hypotheses, _YAW_PERIOD_DEG[m.sym]):
        x = _icp(hyps[k], q_up, p_up, p_tree, c)
        s = _chamfer(x, q_up, p_up, p_tree, tau)
        if s < best_score:
            best_x, best_score = x, s
    if c.cover_footprint:
        best_x = _cover_footprint(best_x, points, m, c.cover_explained_m)
    return ModelFit(m.cad_id, _A_map_cad(best_x, m.bottom_up), _apply(best_x, m.vertices_up),
                    float(np.degrees(best_x[0])), np.exp(best_x[4:7]), m.sym, best_score)


def search_instance(job: AlignJob) -> list[ModelFit]:
    """fit_model for every model of the job's class (numpy and scipy only: safe in a forked worker)."""
    return [fit_model(job.points, job.support_z, m, job.config) for m in job.models]


def _judge(job: AlignJob, fits: list[ModelFit]) -> InstanceResult:
    """Measure each model's fit; the lowest-score model whose fit passes is accepted."""
    for f, m in zip(fits, job.models):
        f.fit = measure_fit(job.points, f.vertices_map, m.faces, job.config, f.score, job.config.seed)
    fits = sorted(fits, key=lambda f: f.score)
    passing = [f for f in fits if f.fit.passes(job.config)]
    center = (job.points.min(axis=0) + job.points.max(axis=0)) / 2.0
    return InstanceResult(job.instance, job.cls, len(job.points), center, fits, passing[0] if passing else None)


def align_instances(jobs: list[AlignJob], workers: int) -> list[InstanceResult]:
    """The best model per instance, searched on `workers` processes (largest jobs first); results in job order.

    Processes, not threads: the search is many small numpy/scipy calls that hold the GIL. They are forked (no
    `__main__` guard needed in callers' scripts, unlike spawn) and run numpy/scipy only; the Open3D distances of
    `measure_fit` run here, since a fork of a process whose OpenMP pool has started may hang inside OpenMP.
    Inside a daemonic process (a service worker) no children may start, so the search runs here too.
    """
    parallel = (workers > 1 and len(jobs) > 1 and not multiprocessing.current_process().daemon
                and "fork" in multiprocessing.get_all_start_methods())
    if not parallel:
        results = [_judge(j, search_instance(j)) for j in jobs]
    else:
        order = sorted(range(len(jobs)), key=lambda i: -len(jobs[i].points) * len(jobs[i].models))
        with ProcessPoolExecutor(max_workers=min(workers, len(jobs)),
                                 mp_context=multiprocessing.get_context("fork")) as pool:
            found = dict(zip(order, pool.map(search_instance, [jobs[i] for i in order])))
        results = [_judge(jobs[i], found[i]) for i in range(len(jobs))]
    prefer_common_models(results, [j.config for j in jobs])
    return results


def prefer_common_models(results: list[InstanceResult], configs: list[AutoCadConfig]) -> None:
    """Give the instances of a class one model where the evidence allows (in place; `configs` per result).

    The common model of a class is the one whose truncated Chamfer scores, each relative to its instance's accepted
    fit, sum lowest over the class's accepted instances; an instance takes it when it passes there and scores within
    `same_model_margin` of the instance's accepted fit. A room's chairs are mostly of one kind, and one partly seen
    chair is weak evidence between similar models: a few per cent of score is noise of the subsets and the unseen
    parts, not a different chair. A clearly better fit (another kind of chair) keeps its own model.
    """
    by_cls: dict[str, list[int]] = {}
    for i, r in enumerate(results):
        if r.accepted is not None:
            by_cls.setdefault(r.cls, []).append(i)
    for idx in by_cls.values():
        if len(idx) < 2:
            continue
        relative: dict[str, float] = {}
        for i in idx:
            for f in results[i].fits:
                relative[f.cad_id] = relative.get(f.cad_id, 0.0) + f.score / max(results[i].accepted.score, 1e-9)
        common = min(sorted(relative), key=relative.get)  # sorted: ties go the same way in every build
        for i in idx:
            r, c = results[i], configs[i]
            f = next((f for f in r.fits if f.cad_id == common), None)
            if f is not None and f.fit.passes(c) and f.score <= (1.0 + c.same_model_margin) * r.accepted.score:
                r.accepted = f


# --- Scan2CAD output --------------------------------------------------------------------------------------------


def aligned_model_record(cad_id: str, trs, lo: np.ndarray, hi: np.ndarray, sym: str | None,
                         **extra: Any) -> dict[str, Any]:
    """One `aligned_models` entry of a Scan2CAD record: `trs` (cadreg.io.scan2cad.TRS) takes the CAD into the map
    frame (the record's scan trs is the identity).

    `bbox` are the half extents of the CAD's box and `center` its centre, in the CAD frame, as in Scan2CAD.
    """
    synset, model_id = cad_id.split("/", 1)
    return {"catid_cad": synset, "id_cad": model_id, "trs": trs.to_json(),
            "bbox": [float(x) for x in (hi - lo) / 2.0], "center": [float(x) for x in (hi + lo) / 2.0],
            "sym": sym or SYM_NONE, **extra}


def scan2cad_record(id_scan: str, models: list[dict[str, Any]]) -> dict[str, Any]:
    """A Scan2CAD scan record with an identity scan trs (the map frame is the scan frame)."""
    identity = {"translation": [0.0, 0.0, 0.0], "rotation": [1.0, 0.0, 0.0, 0.0], "scale": [1.0, 1.0, 1.0]}
    return {"id_scan": id_scan, "trs": identity, "n_aligned_models": len(models), "aligned_models": models}
