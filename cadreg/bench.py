"""The benchmark: several methods on the same recorded frames, scored against their ground-truth poses.

Methods (`METHODS`):
- `cadreg` — the localizer as configured; `cadreg:<refine method>` with another refinement (REFINE_METHODS).
- `cadreg-nolabels` — the localizer with the frame's labels removed (exercises the fallback on labelled data).
- `fpfh-ransac` — Open3D FPFH + RANSAC + ICP on the whole map, no initial guess (the baseline).
- `kiss-matcher` — KISS-Matcher's global registration + the same ICP (the peer; the optional extra `cadreg[kiss]`).
- `refine-from-gt-perturbed[:<refine method>]` — the refinement alone, started from the ground truth moved by
  20 cm along a random direction and rotated 10° about a random axis (seeded per frame), then brought in by
  the localizer's own path from a hypothesis (coarse GICP at RefineConfig.coarse_voxel_m, then the fine method).

Ground truth is only as good as its source: a map fused from one part of a sequence and poses tracked over the
rest (7-Scenes' KinectFusion) can disagree by centimetres. Per frame the bench therefore also records how many
frame points lie within 1 cm of the map at the ground-truth pose and at the estimate; a failed frame whose
estimate fits the map clearly better than its ground truth is counted in `gt_fits_worse`.

Trust: per method the summary also gives `ok` precision (share of `ok` answers within 5 cm / 5°), the count of
wrong `ok` answers and success by confidence band (`CONFIDENCE_BANDS`, a reliability table: a calibrated
confidence has success rising with the band). The baselines' confidence is their ICP fitness.

Label noise (`label_noise.py`): the labelled methods can be given a segmenter's errors in the frames' labels
(misregistered and bleeding boundaries, swapped, missed and false classes), seeded per frame, to see how the
labelled path fares with labels not its own map's.

Buildings (`cadreg render --layout` writes FRAMES/views.json): per frame the room it was taken in and the rooms
that repeat it (the oracle of cadreg/render/building.py). With it the summary splits the frames: `unique` (views
no other room repeats: success @5cm/5° is what counts) and `repeated` (the right answer is `ambiguous` with the
truth among the reported poses — the answer and its `hypotheses`, by pose; `ok` in the right room is a lucky
guess, `ok` elsewhere is wrong; `ok_twin_room` counts the wrong ones that are the same view in a room that repeats
it). Views taken in a building's corridors are neither: a plain hallway looks the same all along it, at either end
and in every corridor of its size, so they get their own `corridor` figures, where what counts is that no `ok`
answer is wrong (and how often the answer is `ambiguous` with the truth among the reported poses).

This module is a runner: it owns timing. It does no file I/O and prints nothing; the CLI does.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace

import numpy as np
import small_gicp
from scipy.spatial.transform import Rotation

from .bench_methods import METHODS
from .errors import InvalidArgument
from .frame import Frame
from .geometry import invert_T, pose_errors, transform_points
from .color_noise import ColorNoise, corrupt_colors
from .label_noise import LabelNoise, corrupt_labels
from .labels import is_object_class
from .localize.localizer import Localizer
from .localize.points import frame_to_points
from .result import Status

# Lower edges of the confidence bands of the reliability table; the last band includes 1.
CONFIDENCE_BANDS = (0.0, 0.5, 0.7, 0.9)


@dataclass
class FrameOutcome:
    """One method on one frame. errors are inf when no pose came back."""

    index: int
    status: str
    translation_m: float
    rotation_deg: float
    total_ms: float
    stage_ms: dict[str, float] = field(default_factory=dict)
    objects_in_view: int = 0
    gt_overlap: float = float("nan")  # fraction of frame points within 5 cm of the map at the ground truth
    gt_fit_1cm: float = float("nan")  # ... within 1 cm at the ground truth
    est_fit_1cm: float = float("nan")  # ... within 1 cm at the estimate (nan without one)
    confidence: float = float("nan")  # the method's own confidence in its answer, [0, 1]
    truth_in_hypotheses: bool = False  # a reported pose (the answer or a hypothesis) within 5 cm / 5° of the truth
    repeated: bool | None = None  # another room repeats the view (views.json); None = not known
    corridor: bool = False  # the view was taken in one of the building's corridors (views.json)
    twin_answer: bool = False  # the answer is the same view in a room that repeats it (within 5 cm / 5° of it)
    T_answer: np.ndarray | None = field(default=None, repr=False)  # (4, 4) the answered T_map_camera, or None


@dataclass(frozen=True)
class ViewTruth:
    """What a building's views.json says of one frame: the room it was taken in, the rooms that repeat it, and
    T_twins : (4, 4) T_building_camera of the same room-relative view in each of those rooms (same order)."""

    room: str
    repeated_in: tuple[str, ...] = ()
    T_twins: tuple[np.ndarray, ...] = ()
    corridor: bool = False

    @property
    def repeated(self) -> bool:
        return bool(self.repeated_in)


def views_from_doc(doc: dict) -> dict[int, ViewTruth]:
    """Frame index -> ViewTruth from the parsed views.json of `cadreg render --layout` ({"rooms": {name:
    {"T_building_room"}}, "views": [{"index", "room", "repeated_in", "T_room_camera"}]}); InvalidArgument when
    malformed."""
    try:
        T_room = {name: np.asarray(r["T_building_room"], dtype=np.float64) for name, r in doc["rooms"].items()}
        out = {}
        for v in doc["views"]:
            T_room_camera = np.asarray(v["T_room_camera"], dtype=np.float64)
            twins = tuple(str(name) for name in v["repeated_in"])
            corridor = bool(doc["rooms"][str(v["room"])].get("corridor", False))
            out[int(v["index"])] = ViewTruth(str(v["room"]), twins, tuple(T_room[t] @ T_room_camera for t in twins),
                                             corridor)
        return out
    except (KeyError, TypeError, ValueError) as exc:
        raise InvalidArgument(f"not a views.json of `cadreg render --layout`: {exc!r}") from None


def within_5cm_5deg(T_est: np.ndarray, T_true: np.ndarray) -> bool:
    te, re_ = pose_errors(np.asarray(T_est), T_true)
    return te <= 0.05 and re_ <= 5.0


def check_method(name: str) -> str:
    if name not in METHODS:
        raise InvalidArgument(f"unknown bench method {name!r}; choose from {', '.join(METHODS)}")
    return name


def objects_in_view(site, frame: Frame, T_map_camera: np.ndarray, *, occlusion_m: float = 0.5) -> int:
    """Map graph nodes whose centroid projects into the frame and is not hidden behind the depth by > occlusion_m."""
    if not site.graph.nodes:
        return 0
    cent = np.array([np.asarray(n.centroid, float) for n in site.graph.nodes])
    T_depth_map = invert_T(T_map_camera @ frame.T_color_depth)
    p = transform_points(T_depth_map, cent)
    K = frame.depth_intrinsics
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(K.fx * p[:, 0] / z + K.cx)
        v = np.rint(K.fy * p[:, 1] / z + K.cy)
    ok = (z > 0.2) & (u >= 0) & (u < K.width) & (v >= 0) & (v < K.height)
    count = 0
    for i in np.flatnonzero(ok):
        d = frame.depth[int(v[i]), int(u[i])] / frame.depth_scale
        if d == 0 or d >= z[i] - occlusion_m:
            count += 1
    return count


def perturb(T: np.ndarray, rng: np.random.Generator, *, translation_m: float = 0.2, rotation_deg: float = 10.0) -> np.ndarray:
    """T moved by exactly translation_m along a random direction and rotated by rotation_deg about a random axis."""
    d = rng.normal(size=3)
    a = rng.normal(size=3)
    R = Rotation.from_rotvec(np.radians(rotation_deg) * a / np.linalg.norm(a)).as_matrix()
    out = T.copy()
    out[:3, :3] = R @ T[:3, :3]
    out[:3, 3] = T[:3, 3] + translation_m * d / np.linalg.norm(d)
    return out


class Bench:
    """Runs methods on frames; one Localizer serves every cadreg method."""

    def __init__(self, site, localizer: Localizer, *, seed: int = 0, label_noise: LabelNoise | None = None,
                 color_noise: ColorNoise | None = None) -> None:
        self.site = site
        self.localizer = localizer
        self.seed = seed
        self.label_noise = label_noise
        self.color_noise = color_noise
        self._fit_cache: tuple | None = None
        self._kiss = None

    def labels_of(self, index: int, frame: Frame) -> np.ndarray | None:
        """The labels a labelled method is given: the frame's, with `label_noise`'s errors when set (drawn from a
        generator seeded by the bench's seed and the frame's index, from the object classes the site's graph
        holds, in the frame's label set)."""
        if self.label_noise is None or frame.labels is None:
            return frame.labels
        known = {node.cls for node in self.site.graph.nodes}
        ids = np.array(sorted(i for i, c in self.site.label_maps.get(frame.label_set, {}).items()
                              if is_object_class(c) and c in known), dtype=np.int64)
        return corrupt_labels(frame.labels, self.label_noise, ids, np.random.default_rng([self.seed, index, 1]))

    def colors_of(self, index: int, frame: Frame) -> np.ndarray:
        """The colour image every method is given: the frame's, with `color_noise`'s faults when set (drawn from a
        generator seeded by the bench's seed and the frame's index)."""
        if self.color_noise is None:
            return frame.color
        return corrupt_colors(frame.color, self.color_noise, np.random.default_rng([self.seed, index, 2]))

    def kiss(self):
        """The KISS-Matcher peer (InvalidArgument with the install hint when the extra is missing)."""
        if self._kiss is None:
            from .localize.fallback import KissMatcher

            self._kiss = KissMatcher(self.localizer.fpfh())
        return self._kiss

    def run_one(self, method: str, index: int, frame: Frame, T_true: np.ndarray) -> FrameOutcome:
        loc = self.localizer
        rc = loc.config.refine
        # What the method is given, made outside the frame's time: the colour with a camera's faults, the labels
        # with a segmenter's errors (each costs a few image passes, which a client's frame does not).
        if self.color_noise is not None:
            frame = replace(frame, color=self.colors_of(index, frame))
        if method.startswith("cadreg"):
            given = replace(frame, labels=None if method == "cadreg-nolabels" else self.labels_of(index, frame))
        t0 = time.perf_counter()
        stage_ms: dict[str, float] = {}
        trust = float("nan")
        reported: list[np.ndarray] = []  # the answer and every hypothesis, by pose
        if method == "kiss-matcher":
            self.kiss()  # the map side is prepared once, outside the frame's time, as fpfh-ransac's features are
            t0 = time.perf_counter()
        if method.startswith("cadreg"):
            refine = method.split(":", 1)[1] if ":" in method else None
            res = loc.localize(given, method=refine)
            T, status, stage_ms = res.T_map_camera, res.status.value, dict(res.diagnostics.stage_ms)
            trust = float(res.confidence)
            reported = [h.T_map_camera for h in res.hypotheses if h.T_map_camera is not None]
        elif method in ("fpfh-ransac", "kiss-matcher"):
            pts = frame_to_points(frame, pixel_stride=loc.config.frame.pixel_stride)
            T, _ = (loc.fpfh() if method == "fpfh-ransac" else self.kiss()).register(pts.xyz)
            fit, _ = loc.refine_map.fitness(transform_points(T, pts.xyz[:: max(1, len(pts) // 2000)]), inlier_m=rc.inlier_m)
            status = Status.OK.value if fit >= rc.min_fitness else Status.LOW_OVERLAP.value
            T, trust = (T if status == Status.OK.value else None), fit
        elif method.startswith("refine-from-gt-perturbed"):
            refine = method.split(":", 1)[1] if ":" in method else rc.method
            rng = np.random.default_rng([self.seed, index])
            T_init = perturb(T_true, rng)
            t0 = time.perf_counter()
            pts = frame_to_points(frame, pixel_stride=loc.config.frame.pixel_stride)
            # The localizer's own path from a hypothesis: a coarse GICP, then the fine refinement.
            src, _ = small_gicp.preprocess_points(pts.xyz, rc.coarse_voxel_m, num_neighbors=10)
            T_coarse = loc.refine_map.coarse_align(src, T_init, max_correspondence_m=0.5)
            out = loc.refine_map.refine(pts, T_coarse, method=refine, epsilon=rc.epsilon, source_voxel_m=rc.source_voxel_m,
                                        max_correspondence_m=rc.max_correspondence_m, max_iterations=rc.max_iterations,
                                        wide_voxel_m=rc.wide_voxel_m)
            T, status = out.T_map_camera, Status.OK.value
        else:
            raise InvalidArgument(f"unknown bench method {method!r}")
        total_ms = (time.perf_counter() - t0) * 1000.0
        if T is None:
            te, re_ = float("inf"), float("inf")
        else:
            te, re_ = pose_errors(np.asarray(T), T_true)
        if T is not None:
            reported.insert(0, np.asarray(T))
        out = FrameOutcome(index, status, te, re_, total_ms, stage_ms, confidence=trust,
                           truth_in_hypotheses=any(within_5cm_5deg(P, T_true) for P in reported),
                           T_answer=None if T is None else np.asarray(T))
        if T is not None:
            out.est_fit_1cm = self.fit_1cm(frame, np.asarray(T))
        return out

    def fit_1cm(self, frame: Frame, T_map_camera: np.ndarray) -> float:
        """Fraction of (a sample of) the frame's points within 1 cm of the map at a pose."""
        return self._fit(frame, T_map_camera, 0.01)

    def _fit(self, frame: Frame, T_map_camera: np.ndarray, inlier_m: float) -> float:
        if self._fit_cache is None or self._fit_cache[0] is not frame:
            pts = frame_to_points(frame, pixel_stride=4).xyz
            self._fit_cache = (frame, pts[:: max(1, len(pts) // 3000)])
        pts = self._fit_cache[1]
        # The map around the pose (a building's region and its halo): a whole building's map would cost the
        # bench a copy of every room.
        return self.localizer.maps_at(T_map_camera, pts.mean(axis=0)).refine_map.fitness(
            transform_points(T_map_camera, pts), inlier_m=inlier_m)[0]

    def ground_truth_fit(self, frame: Frame, T_true: np.ndarray) -> tuple[float, float]:
        """(overlap within 5 cm, fit within 1 cm) of the frame with the map at its ground-truth pose."""
        return self._fit(frame, T_true, 0.05), self._fit(frame, T_true, 0.01)


def _stat(values: Iterable[float], q: float) -> float | None:
    v = np.asarray(list(values), dtype=float)
    if len(v) == 0:
        return None
    # A missing pose is an infinite error; percentiles of inf warn, so sort it past every finite value instead.
    x = float(np.percentile(np.where(np.isfinite(v), v, 1e300), q))
    return x if x < 1e250 else None


def building_summary(outcomes: list[FrameOutcome], s5: np.ndarray) -> dict:
    """`unique` and `repeated` figures of the frames views.json knows (s5: (n,) bool success @5cm/5° per outcome).

    unique : frames, success_5cm_5deg, ok_precision, ok_wrong.
    repeated : frames, ambiguous (share answered `ambiguous`), ambiguous_with_truth (share answered `ambiguous`
        with a reported pose within 5 cm / 5° of the truth), ok_right_room (ok answers within 5 cm / 5°), ok_wrong
        (the other ok answers), ok_twin_room (of those, the same view in a room that repeats it).
    corridor : frames (views taken in a corridor, in neither bucket above), ok, ok_wrong, ambiguous,
        ambiguous_with_truth.
    A bucket without frames has frames 0 and null shares.
    """
    ok = np.array([o.status == Status.OK.value for o in outcomes], dtype=bool)
    amb = np.array([o.status == Status.AMBIGUOUS.value for o in outcomes], dtype=bool)
    truth = np.array([o.truth_in_hypotheses for o in outcomes], dtype=bool)
    twin = np.array([o.twin_answer for o in outcomes], dtype=bool)
    hall = np.array([o.corridor for o in outcomes], dtype=bool)
    uniq = np.array([o.repeated is False for o in outcomes], dtype=bool) & ~hall
    rep = np.array([o.repeated is True for o in outcomes], dtype=bool) & ~hall

    def share(x: np.ndarray, sel: np.ndarray) -> float | None:
        return float(x[sel].mean()) if sel.any() else None

    return {
        "unique": {"frames": int(uniq.sum()), "success_5cm_5deg": share(s5, uniq),
                   "ok_precision": share(s5, uniq & ok), "ok_wrong": int((uniq & ok & ~s5).sum())},
        "repeated": {"frames": int(rep.sum()), "ambiguous": share(amb, rep),
                     "ambiguous_with_truth": share(amb & truth, rep),
                     "ok_right_room": int((rep & ok & s5).sum()), "ok_wrong": int((rep & ok & ~s5).sum()),
                     "ok_twin_room": int((rep & ok & ~s5 & twin).sum())},
        "corridor": {"frames": int(hall.sum()), "ok": int((hall & ok).sum()), "ok_wrong": int((hall & ok & ~s5).sum()),
                     "ambiguous": share(amb, hall), "ambiguous_with_truth": share(amb & truth, hall)},
    }


def per_frame_record(o: FrameOutcome) -> dict:
    """One frame's outcome as the report's `per_frame` lists it: which frames failed how (status, error,
    confidence), to compare two runs frame by frame or to look at one. Errors, overlap and confidence are null
    where there is none (no pose came back, no map at the truth, a method without a confidence)."""
    def num(x: float, digits: int) -> float | None:
        return round(float(x), digits) if np.isfinite(x) else None

    return {"index": o.index, "status": o.status, "translation_m": num(o.translation_m, 4),
            "rotation_deg": num(o.rotation_deg, 3), "ms": num(o.total_ms, 1), "confidence": num(o.confidence, 3),
            "truth_in_hypotheses": o.truth_in_hypotheses, "repeated": o.repeated, "gt_overlap": num(o.gt_overlap, 3),
            "objects_in_view": o.objects_in_view} | ({"corridor": True} if o.corridor else {})


def summarize(outcomes: list[FrameOutcome]) -> dict:
    """Summary of one method (DESIGN §8 keys, plus breakdowns; `unique` / `repeated` when some outcome knows
    whether another room repeats its view)."""
    n = len(outcomes)
    te = np.array([o.translation_m for o in outcomes])
    re_ = np.array([o.rotation_deg for o in outcomes])
    s5 = (te <= 0.05) & (re_ <= 5.0)
    s10 = (te <= 0.10) & (re_ <= 10.0)
    status_counts: dict[str, int] = {}
    for o in outcomes:
        status_counts[o.status] = status_counts.get(o.status, 0) + 1
    stages = sorted({k for o in outcomes for k in o.stage_ms})
    by_objects: dict[str, dict] = {}
    for key, sel in (("0", lambda k: k == 0), ("1", lambda k: k == 1), ("2", lambda k: k == 2), ("3+", lambda k: k >= 3)):
        idx = [i for i, o in enumerate(outcomes) if sel(o.objects_in_view)]
        if idx:
            by_objects[key] = {"frames": len(idx), "success_5cm_5deg": float(s5[idx].mean()),
                               "success_10cm_10deg": float(s10[idx].mean())}
    by_overlap: dict[str, dict] = {}
    for key, lo, hi in (("<0.5", 0.0, 0.5), ("0.5-0.8", 0.5, 0.8), (">=0.8", 0.8, 1.01)):
        idx = [i for i, o in enumerate(outcomes) if lo <= o.gt_overlap < hi]
        if idx:
            by_overlap[key] = {"frames": len(idx), "success_5cm_5deg": float(s5[idx].mean())}
    # Failed frames whose estimate puts clearly more points within 1 cm of the map than the ground truth does.
    gt_worse = [o.index for o, ok in zip(outcomes, s5)
                if not ok and np.isfinite(o.est_fit_1cm) and o.est_fit_1cm > o.gt_fit_1cm + 0.02]
    ms = [o.total_ms for o in outcomes]
    ok = np.array([o.status == Status.OK.value for o in outcomes], dtype=bool)
    conf = np.array([o.confidence for o in outcomes], dtype=float)
    reliability: dict[str, dict] = {}
    edges = CONFIDENCE_BANDS + (1.0 + 1e-9,)
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (conf >= lo) & (conf < hi)
        if sel.any():
            reliability[f"{lo:.1f}-{min(hi, 1.0):.1f}"] = {"frames": int(sel.sum()), "success_5cm_5deg": float(s5[sel].mean()),
                                                          "ok": int((sel & ok).sum())}
    out = {
        "frames": n,
        "success_5cm_5deg": float(s5.mean()) if n else 0.0,
        "success_10cm_10deg": float(s10.mean()) if n else 0.0,
        # Over all frames, a frame without a pose counting as an infinite error (null when the median is one).
        "median_translation_m": _stat(te, 50),
        "median_rotation_deg": _stat(re_, 50),
        "p90_translation_m": _stat(te, 90),
        "p90_rotation_deg": _stat(re_, 90),
        "median_ms": _stat(ms, 50),
        "p90_ms": _stat(ms, 90),
        "p99_ms": _stat(ms, 99),
        "max_ms": float(max(ms)) if ms else None,
        # Trust: how often `ok` is right, how many `ok` answers are wrong, success by confidence band.
        "ok_precision": float(s5[ok].mean()) if ok.any() else None,
        # DESIGN §8's name, as the unique / repeated / corridor figures name theirs; "wrong_ok" is kept for the
        # scripts that read it since the trust figures came in.
        "ok_wrong": int((ok & ~s5).sum()),
        "wrong_ok": int((ok & ~s5).sum()),
        "reliability": reliability,
        "stage_ms": {s: {"p50": _stat([o.stage_ms.get(s, 0.0) for o in outcomes], 50),
                         "p90": _stat([o.stage_ms.get(s, 0.0) for o in outcomes], 90)} for s in stages},
        "status_counts": status_counts,
        "by_objects_in_view": by_objects,
        "by_ground_truth_overlap": by_overlap,
        "gt_fits_worse": len(gt_worse),
        "gt_fits_worse_frames": gt_worse,
        "failed_frames": [o.index for o, ok in zip(outcomes, s5) if not ok],
        "per_frame": [per_frame_record(o) for o in outcomes],
    }
    if any(o.repeated is not None for o in outcomes):
        out.update(building_summary(outcomes, s5))
    return out


def run_bench(site, frames, methods: list[str], *, localizer: Localizer | None = None, limit: int | None = None,
              seed: int = 0, progress: Callable[[int, int], None] | None = None,
              warn: Callable[[str], None] | None = None, views: dict[int, ViewTruth] | None = None,
              truth: dict[int, np.ndarray] | None = None, label_noise: LabelNoise | None = None,
              color_noise: ColorNoise | None = None) -> dict:
    """Run `methods` on every frame of `frames` (a RecordedFrames) that has a ground-truth pose. `views`: what a
    building's views.json says of the frames (`views_from_doc`), for the unique / repeated figures. `truth`: frame
    index -> T_map_camera to judge by instead of the recorded poses (where the map puts each frame, when a
    dataset's poses drift from the map: `site.fuse.pose_offset_by_window`); frames it lacks are skipped.
    `label_noise`: a segmenter's errors in the labels the labelled methods are given (`Bench.labels_of`).
    `color_noise`: a camera's colour faults in the colour every method is given (`Bench.colors_of`).

    Returns {"frames": N, "skipped": [...], "methods": {name: summary}}, and "label_noise" and "color_noise" (their
    settings) when given.
    """
    for m in methods:
        check_method(m)
    localizer = localizer or Localizer.from_site(site)
    bench = Bench(site, localizer, seed=seed, label_noise=label_noise, color_noise=color_noise)
    if "kiss-matcher" in methods:
        bench.kiss()  # a missing extra fails here, with its install hint, before any frame runs
    indices = list(frames.indices)
    if limit is not None:
        indices = indices[:limit]
    outcomes: dict[str, list[FrameOutcome]] = {m: [] for m in methods}
    skipped: list[int] = []
    for k, i in enumerate(indices):
        frame, T_true = frames.load(i)
        if truth is not None:
            T_true = truth.get(int(i))
        if T_true is None or not np.all(np.isfinite(T_true)):
            skipped.append(int(i))
            if warn and truth is None:  # a given truth leaves out frames by design: the table counts them
                warn(f"frame {i} has no ground-truth pose: skipped")
        else:
            n_obj = objects_in_view(site, frame, T_true)
            overlap, gt_fit = bench.ground_truth_fit(frame, T_true)
            for m in methods:
                o = bench.run_one(m, int(i), frame, T_true)
                o.objects_in_view, o.gt_overlap, o.gt_fit_1cm = n_obj, overlap, gt_fit
                if views is not None and int(i) in views:
                    view = views[int(i)]
                    o.repeated, o.corridor = view.repeated, view.corridor
                    o.twin_answer = o.T_answer is not None and any(within_5cm_5deg(o.T_answer, T) for T in view.T_twins)
                outcomes[m].append(o)
        if progress:
            progress(k + 1, len(indices))
    n = len(indices) - len(skipped)
    report = {"frames": n, "skipped": skipped, "methods": {m: summarize(o) for m, o in outcomes.items()}}
    if label_noise is not None:
        report["label_noise"] = label_noise.as_dict()
    if color_noise is not None:
        report["color_noise"] = color_noise.as_dict()
    return report


def format_table(report: dict) -> str:
    """A plain-text summary table of a `run_bench` report."""
    def f(x, scale=1.0, digits=1):
        return "-" if x is None else f"{x * scale:.{digits}f}"

    lines = [f"frames: {report['frames']}" + (f" (skipped without pose: {len(report['skipped'])})" if report["skipped"] else "")
             + ("" if "label_noise" not in report else "; labels with noise "
                + ", ".join(f"{k} {v}" for k, v in report["label_noise"].items() if v))
             + ("" if "color_noise" not in report else "; colour with a camera's faults "
                + ", ".join(f"{k} {v}" for k, v in report["color_noise"].items() if v))]
    head = (f"{'method':34s} {'@5cm/5°':>8s} {'@10cm/10°':>9s} {'med t cm':>8s} {'p90 t cm':>8s} {'med r °':>7s} "
            f"{'p90 r °':>7s} {'med ms':>7s} {'p90 ms':>7s} {'p99 ms':>7s} {'max ms':>7s} {'ok prec':>7s} {'bad ok':>6s}  statuses")
    lines.append(head)
    for name, s in report["methods"].items():
        st = " ".join(f"{k}={v}" for k, v in sorted(s["status_counts"].items()))
        prec = s.get("ok_precision")
        lines.append(f"{name:34s} {100 * s['success_5cm_5deg']:7.1f}% {100 * s['success_10cm_10deg']:8.1f}% "
                     f"{f(s['median_translation_m'], 100, 2):>8s} {f(s['p90_translation_m'], 100, 2):>8s} "
                     f"{f(s['median_rotation_deg'], 1, 2):>7s} {f(s['p90_rotation_deg'], 1, 2):>7s} "
                     f"{f(s['median_ms'], 1, 0):>7s} {f(s['p90_ms'], 1, 0):>7s} {f(s.get('p99_ms'), 1, 0):>7s} "
                     f"{f(s.get('max_ms'), 1, 0):>7s} {'-' if prec is None else f'{100 * prec:.1f}%':>7s} "
                     f"{s.get('ok_wrong', 0):>6d}  {st}")
    for name, s in report["methods"].items():
        if s["stage_ms"]:
            parts = " ".join(f"{k}={f(v['p50'], 1, 0)}/{f(v['p90'], 1, 0)}" for k, v in s["stage_ms"].items())
            lines.append(f"  {name} stage ms p50/p90: {parts}")
        if s["by_objects_in_view"]:
            parts = " ".join(f"{k}: {100 * v['success_5cm_5deg']:.0f}% of {v['frames']}" for k, v in s["by_objects_in_view"].items())
            lines.append(f"  {name} @5cm/5° by map objects in view: {parts}")
        if s.get("by_ground_truth_overlap"):
            parts = " ".join(f"{k}: {100 * v['success_5cm_5deg']:.0f}% of {v['frames']}"
                             for k, v in s["by_ground_truth_overlap"].items())
            lines.append(f"  {name} @5cm/5° by frame overlap with the map at ground truth: {parts}")
        if s.get("reliability"):
            parts = " ".join(f"[{k}] {100 * v['success_5cm_5deg']:.0f}% of {v['frames']} ({v['ok']} ok)"
                             for k, v in s["reliability"].items())
            lines.append(f"  {name} @5cm/5° by confidence: {parts}")
        if s.get("unique") is not None:
            u, r = s["unique"], s["repeated"]
            lines.append(f"  {name} unique views: {u['frames']}, @5cm/5° {f(u['success_5cm_5deg'], 100)}%, ok precision "
                         f"{f(u['ok_precision'], 100)}%, wrong ok {u['ok_wrong']}; repeated views: {r['frames']}, "
                         f"ambiguous {f(r['ambiguous'], 100)}%, ambiguous with the truth among hypotheses "
                         f"{f(r['ambiguous_with_truth'], 100)}%, ok right room {r['ok_right_room']}, ok wrong "
                         f"{r['ok_wrong']} (same view in a twin room {r['ok_twin_room']})")
            c = s["corridor"]
            if c["frames"]:
                lines.append(f"  {name} corridor views: {c['frames']}, ok {c['ok']}, ok wrong {c['ok_wrong']}, "
                             f"ambiguous {f(c['ambiguous'], 100)}%, ambiguous with the truth among hypotheses "
                             f"{f(c['ambiguous_with_truth'], 100)}%")
        if s.get("gt_fits_worse"):
            lines.append(f"  {name}: {s['gt_fits_worse']} failed frames fit the map better at the estimate than "
                         f"at their ground truth (1 cm inliers)")
    return "\n".join(lines)
