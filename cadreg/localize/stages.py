"""The values that travel between the localizer's stages, its stage timer and its confidence.

    scan (points, clusters, up)  ->  Scan
    hypotheses (graph, prior)    ->  Hypotheses (match.py)
    verify (coarse GICP, fallback) -> [Candidate], best first
    refine (ROI, contenders)     ->  Choice
    result (status, confidence, diagnostics)
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ..result import Hypothesis, Status
from ..site.regions import SearchRegion
from .cluster import ScanCluster
from .field_view import FieldView
from .gravity import Floor
from .match import Hypotheses
from .points import FramePoints
from .refine import RefineOutcome, chroma_spread

# Stages reported to a `progress(done, total)` callback, in order; "fallback" is timed but runs only sometimes.
PROGRESS_STAGES = ("points", "cluster", "gravity", "match", "verify", "refine")
# A refinement settles into the basin it starts in: a candidate farther than this from every refined pose is
# another start (`refine_stage.RefineStage._near_contender`), even when it is no distinct hypothesis
# (MatchConfig.distinct_translation_m); a building's copy of a view within it of a refined pose is that pose's
# basin (`building_views.BuildingViews._twin_views`).
NEAR_REACH_M = 0.1
NEAR_REACH_DEG = 5.0
# A frame whose colours spread in chroma less than this (`refine.chroma_spread`) carries none: a client without a
# colour camera sends a grey or black picture (0). A colour camera's view of a grey room spreads more: Replica
# office0's renders 1.8 or more (median 7), scene0470's 4.5 (median 8), the 3DMatch frames 8, RedKitchen's 11.
COLOURLESS_SPREAD = 0.5


@dataclass
class Scan:
    """What one frame shows, colour-camera frame (OpenCV axes), metres.

    points : every `pixel_stride`-th valid depth pixel with colour and label.
    down : `points` voxel-down-sampled (FrameConfig.voxel_size_m): what is clustered and scored.
    class_index : (len(down),) int64 graph class per down-sampled point, -1 none.
    clusters : class-wise clusters of `down` (the scan graph's nodes).
    floor : up direction (and camera height) from the floor, the client's gravity or the frame's surfaces; None
        when none could be found.
    score_xyz : (≤ score_points, 3) float64 sample of `down` for the distance-field check.
    fit_xyz, fit_lab, fit_cls : a sample of `down` (≤ fit_points): positions, CIE Lab colours, class index, for
        the label and colour agreement that ranks coarse-aligned candidates; fit_cls None for a frame that
        carries no labels (nothing to agree or disagree with the map's classes).
    fit_rgb : (len(fit_xyz), 3) colours of fit_xyz, each the mean of the colour pixels about its own
        (`points.window_colours`): what the colour gate compares with the map's (`Localizer._chroma_at`).
    check_xyz : (≤ check_points, 3) float64 sample of `points` for the final fitness.
    zbuf : coarse z-buffer of `points` (`score.ViewCheck.zbuffer`) for the free-space check; K : the intrinsics it
        was projected with, the depth camera's at the checks' resolution (`score.reference_camera`: no pixel index
        of the depth image). None for scans built without a frame.
    center_camera : (3,) centroid of `points`: the centre of the region of interest (paper §2.5), whose region
    a pose is refined in (`Localizer.maps_at`). search : the client's search region (Frame.search_region).
    unverified : in a building, the best hypotheses of rooms that tied with the best but were not verified (more
    tied than RegionConfig.max_verified): rivals the answer did not rule out.
    view : in a building, the frame's rays and measured depth (`field_view.FieldView`): candidates there are
    ranked by how the map looks along them. None in a one-room site.
    reserve : in a one-room site, the label-free search's next distinct leaves after those it gave as hypotheses
    (LabelFreeConfig.reserve), unpolished: the second look's (`Localizer._second_look`); None when it did not run.
    deeper_below : in a building, the view agreement under which the label-free search's answer has the building
    searched again (`Localizer._deeper_look`): RegionConfig.deeper_view_agreement when the search stopped at its node
    cap with few nodes a room (`fallback_stage.THIN_SEARCH_SHARE`), min_one_object_view_agreement when it covered
    only the graph's candidate rooms (`FallbackStage._label_free`); 0 when the search did not run, was as thorough
    as a room's, or was spent.
    search_cut : in a building, the label-free search covered the whole building (or the client's search region)
    and stopped at its node cap with few nodes a room: what set `deeper_below` to deeper_view_agreement.
    copies_wait : the refine stage left the copies of its answer unrefined for the deeper search that follows
    (`RefineStage._copies_wait`).
    twin_rays : the rays (times poses) the twin check has rendered for this frame so far
    (RegionConfig.twin_check_rays).
    fine : the fine refinements of this frame's contenders so far, by the contender's identity (the contender kept
    beside its outcome): the second and the deeper look run the refine stage again over candidates that hold the
    first run's contenders, whose refinements would come out the same (`RefineStage._fine_pose`).
    """

    points: FramePoints
    down: FramePoints
    class_index: np.ndarray
    clusters: list[ScanCluster]
    floor: Floor | None
    score_xyz: np.ndarray
    fit_xyz: np.ndarray
    fit_lab: np.ndarray
    fit_cls: np.ndarray | None
    fit_rgb: np.ndarray
    check_xyz: np.ndarray
    zbuf: np.ndarray | None = None
    K: object | None = None
    center_camera: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.5]))  # centroid of `points`
    search: SearchRegion | None = None  # the client's search region (Frame.search_region)
    unverified: list[Hypothesis] = field(default_factory=list)  # tied rooms beyond RegionConfig.max_verified
    view: FieldView | None = None
    reserve: Hypotheses | None = None
    deeper_below: float = 0.0
    search_cut: bool = False
    copies_wait: bool = False
    twin_rays: int = 0
    fine: dict[int, tuple[Candidate, RefineOutcome]] = field(default_factory=dict)

    @cached_property
    def in_colour(self) -> bool:
        """fit_rgb's chroma spreads at least COLOURLESS_SPREAD (`refine.chroma_spread`): the camera gives colour, so a
        pose at which the frame is grey where the map is coloured is one at which its colours do not follow the
        map's (`refine.chroma_correlation`)."""
        return chroma_spread(self.fit_rgb) >= COLOURLESS_SPREAD

    @cached_property
    def view_shares(self) -> np.ndarray:
        """(len(clusters),) the share of the frame's view (pixels) each labelled object covers, from its voxel
        points (`down`): each stands for the pixels its voxel covers, about 1/z² at depth z. The repeated-view
        oracle and the view agreement count pixels; the voxel grid keeps far surfaces' points (a door in the next
        room, seen through a gap, held 13 % of a frame's voxel points and 3 % of its pixels)."""
        if not self.clusters:
            return np.zeros(0)
        weight = 1.0 / np.maximum(self.down.xyz[:, 2], 1e-3) ** 2
        return np.array([weight[c.index].sum() for c in self.clusters]) / weight.sum()


@dataclass
class Candidate:
    """A hypothesis after the coarse alignment of the verify stage.

    T_map_camera : (4, 4) float64, colour camera -> map, metres.
    score : geometric fitness weighted by label and colour agreement with the map, in [0, 1]; in a building, the
        share of the frame's rays along which the map shows what the frame measured (`FieldView.agreement`).
    hypothesis : what the result reports of it (its `T_map_camera` is this one).
    assignment : (scan objects,) int64 index into the map graph's nodes per scan object, -1 none; empty for
        hypotheses that did not come from the graph (fallback, prior).
    """

    T_map_camera: np.ndarray
    score: float
    hypothesis: Hypothesis
    assignment: np.ndarray
    rendered: np.ndarray | None = None  # in a building, (rays,) the map's depth along Scan.view's rays at the pose


@dataclass(eq=False)  # one contender is itself only: `list.remove` and `is` find it, not equal fields
class Refined:
    """A contender of the refine stage after its fine refinement, or a copy of the winner's view in another room
    (`Localizer._twin_views`: pulled onto the field, not refined).

    score : what contenders are ranked by: in a building the view agreement along the frame's rays, else the
        agreement score (`Localizer._agreement_score`) weighed by the see-through. outcome : the refinement (its
        `T_map_camera` is the refined pose). candidate : the candidate it started from. see_through : the share of
        the map in view that the frame sees through at the refined pose (0 for a copy).
    """

    score: float
    outcome: RefineOutcome
    candidate: Candidate
    see_through: float = 0.0

    @property
    def T_map_camera(self) -> np.ndarray:
        return self.outcome.T_map_camera


@dataclass
class Choice:
    """The outcome of the refine stage.

    candidate : the candidate that won. outcome : its fine refinement (pose, covariance, iterations).
    margin : how far its score lies above the best distinct rival's (refined scores when several contenders
        were refined, coarse ones otherwise), or its whole score when there is no distinct rival.
    has_rival : a distinct rival exists. fitness, rmse_m : share of `Scan.check_xyz` within the inlier distance
        of the map at the refined pose, and their RMSE in metres.
    center_camera : (3,) centre of the frame's points, colour-camera frame; roi_frame_points : frame points kept
        inside the region of interest. see_through : share of the map in view the frame sees through at the pose;
        depth_agreement : share of the view's cells, among those holding both, where measured depth and map agree
        (`score.ViewCheck.depth_agreement`; 1.0 without a z-buffer); coverage : share of `Scan.check_xyz` whose
        view cell holds some map surface at the pose (`score.ViewCheck.compare_depth`; 1.0 without a z-buffer).
    chroma : the correlation of the frame's chroma with the map's at the pose (`Localizer._chroma_at`), None
        where either is too grey to tell.
    rivals : in a building, the distinct candidates the answer cannot be told from (their view agreement within
        the ambiguity margin of the answer's, or the map showing the same along the frame's rays at both poses:
        `Localizer._view_rivals`); None in a one-room site, whose rivals are the candidates within the margin.
    """

    candidate: Candidate
    outcome: RefineOutcome
    margin: float
    has_rival: bool
    fitness: float
    rmse_m: float
    center_camera: np.ndarray
    roi_frame_points: int
    see_through: float = 0.0
    depth_agreement: float = 1.0
    coverage: float = 1.0
    rivals: list[Candidate] | None = None
    passed_over: bool = False  # taken after every better-ranked contender saw through the map
    chroma: float | None = None
    view_agreement: float | None = None

    @property
    def support(self) -> float:
        """The fitness over the part of the frame the map covers: a frame that looks half past the map (an open
        door, the rest of a kitchen the map never saw) is not for that less likely right, while the points the
        map could have explained and does not still count against it. The low-overlap gate stays on the
        fitness itself."""
        if self.coverage <= 0.0:
            return self.fitness
        return min(1.0, self.fitness / self.coverage)


class StageTimer:
    """Adds each stage's wall time, milliseconds, into `stage_ms[name]` and reports `progress(done, total)` after
    each of `PROGRESS_STAGES`."""

    def __init__(self, stage_ms: dict[str, float], progress: Callable[[int, int], None] | None = None) -> None:
        self.stage_ms = stage_ms
        self.progress = progress

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.stage_ms[name] = self.stage_ms.get(name, 0.0) + (time.perf_counter() - start) * 1000.0
        if self.progress is not None and name in PROGRESS_STAGES:
            self.progress(PROGRESS_STAGES.index(name) + 1, len(PROGRESS_STAGES))


def confidence(fitness: float, rmse_m: float, margin: float, *, inlier_m: float, confident_margin: float,
               see_through: float = 0.0, max_see_through: float = 1.0, pose_std: float = 0.0,
               max_pose_std: float = np.inf) -> float:
    """How much to trust a refined pose, in [0, 1]:

        fitness · exp(−(rmse_m / inlier_m)²) · min(1, ½ + ½ · margin / confident_margin) · max(0, 1 − s / s_max)
                · min(1, σ_max / σ)

    how much of the frame lies on the map (the localizer passes `Choice.support`: the fitness over the part of
    the frame the map covers), how tightly, how clearly the best beat its distinct rival (a tie
    halves the confidence, a margin of `confident_margin` or more leaves it whole), how little of the map in
    view the frame sees through (s = `see_through`, s_max = `max_see_through`), and how firmly the frame's
    geometry pins the pose (σ = `pose_std`, metres, from the refinement's covariance; σ_max = `max_pose_std`).
    """
    value = fitness * np.exp(-(rmse_m / inlier_m) ** 2) * min(1.0, 0.5 + 0.5 * margin / confident_margin)
    value *= max(0.0, 1.0 - see_through / max_see_through)
    if pose_std > 0.0:
        value *= min(1.0, max_pose_std / pose_std)
    return float(np.clip(value, 0.0, 1.0))


def pose_std_m(covariance: np.ndarray | None) -> float:
    """The largest standard deviation, metres, of a pose's translation under its (6, 6) covariance over
    (rx, ry, rz, tx, ty, tz): how far the frame's geometry lets the pose slide. 0 when there is none."""
    if covariance is None:
        return 0.0
    return float(np.sqrt(max(np.linalg.eigvalsh(np.asarray(covariance)[3:, 3:])[-1], 0.0)))


def low_overlap_confidence(fitness: float) -> float:
    """Confidence of a pose too little of the frame supports: half its fitness, always below an `ok` answer's."""
    return float(fitness) * 0.5


def answer_status(fitness: float, margin: float, has_rival: bool, see_through: float, trust: float, *,
                  min_fitness: float, ambiguity_margin: float, max_see_through: float,
                  min_ok_confidence: float, pose_std: float = 0.0, max_pose_std: float = np.inf,
                  depth_agreement: float = 1.0, min_depth_agreement: float = 0.0) -> Status:
    """The status of a refined pose: `low_overlap` when too little of the frame lies on the map; `uncertain` when
    the frame sees through more than max_see_through of the map in view, or when its depth agrees with the map's
    surfaces in less than min_depth_agreement of the view it shares with the map; `ambiguous` when a distinct
    rival scored within the ambiguity margin, `uncertain` instead when the pose may slide by more than
    max_pose_std (it lies nowhere in particular, nor does its rival); `uncertain` when the confidence is below
    min_ok_confidence; else `ok`. Only `ok` claims the pose is right.

    A pose that may slide by more than max_pose_std and would be `ok` stays `ok` here: its confidence falls with
    its spread (`confidence`), and the caller moves it along the directions the frame's geometry pins least to
    see whether it does slide (`Localizer._slides`), a test of what the covariance only estimates."""
    if fitness < min_fitness:
        return Status.LOW_OVERLAP
    if see_through > max_see_through:
        return Status.UNCERTAIN  # whatever its rivals: the frame contradicts the map at this pose
    if depth_agreement < min_depth_agreement:
        return Status.UNCERTAIN  # whatever its rivals: along the rays, the map's surfaces lie elsewhere
    if has_rival and margin < ambiguity_margin:
        return Status.UNCERTAIN if pose_std > max_pose_std else Status.AMBIGUOUS
    if trust < min_ok_confidence:
        return Status.UNCERTAIN
    return Status.OK
