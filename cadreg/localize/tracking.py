"""Tracking a session's frames: the next frame of a stream is a small correction of the last pose, not a search.

A session (a stream device, or an HTTP client sending `session_id`) holds a `TrackState`: the hypotheses it follows
(one once it is sure; several after an `ambiguous` answer, at most TrackConfig.max_hypotheses), each with its last
accepted pose and a constant-velocity motion, and the time of its last accepted frame. `track_frame` reads as its
stages:

    predict     each hypothesis's pose moved by its velocity over the time since the last accepted frame
    points      the frame's points at the tracking stride, inside the region of interest (radius γ)
    track       point-to-plane ICP from each prediction (coarse GICP first when the prediction may be further
                off than the fine step reaches; the site's small_gicp maps, built once in
                `Localizer.from_site`); accepted when the correction stays within what the camera can move in
                the time since the state (`correction_limits`: the motion agrees) and the fitness holds;
                hypotheses that fall behind the best are pruned; one left, where the frame lies on the map, is
                polished by the search's own refinement (`_polished`)
    result      `tracked`: ok once a single hypothesis remains, the frame pins it (its ICP covariance lets it slide
                at most the search's MatchConfig.max_pose_std_m) and its confidence reaches the search's
                MatchConfig.min_ok_confidence (uncertain otherwise, the session follows it), ambiguous while several
                remain, uncertain after tracking alone dropped the others until a search agrees
                (`TrackState.unsure_s`); low_overlap (no pose, the session follows on) while the camera looks past
                the map's edge (TrackConfig.coast_fitness)
    global      nothing accepted, no live state or a gap longer than TrackConfig.max_gap_s: the whole localizer,
                with the best prediction as a prior (`relocalized`), or from nothing (`global`); after a search
                that found nothing, the next waits TrackConfig.search_interval_s (no_match at once meanwhile);
                a runner with several frames of a session in flight lets one search at a time (`may_search`)

The object clustering and graph matching of a global localization never run on a tracked frame.

Never a silent jump: a relocalized pose that disagrees with where the session's motion put the camera is answered
`ambiguous` (the tracked prediction is its rival) until the next frame tracks from it, unless the frame refuted the
prediction (tracked from it, less than TrackConfig.min_fitness of the frame lay on the map) and the global answer is
`ok` by the localizer's own rules, rivals included (a kidnapped robot is placed on the jump frame; mode
`relocalized` and a note say it jumped); an ambiguous session answers `ok` only when one hypothesis is left.

The core has no clock: `t_s` (seconds, any monotonic clock, the same for a session's frames) comes from the runner.
`TrackState.to_dict` / `from_dict` give the plain form a runner stores between frames.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import small_gicp
from scipy.spatial.transform import Rotation

from ..config import TrackConfig
from ..errors import InvalidArgument, InvalidFrame
from ..frame import Frame
from ..geometry import rotation_angle_deg, transform_points
from ..result import Diagnostics, Hypothesis, LocalizationResult, Refinement, Roi, Status
from .points import FramePoints, sampled_points
from .refine import GICP_NEIGHBORS, MIN_ROI_POINTS, RefineMap, covariance_from_hessian, crop_to_roi
from .stages import StageTimer, confidence, low_overlap_confidence, pose_std_m

if TYPE_CHECKING:
    from .localizer import Localizer

MODES = ("tracked", "relocalized", "global")


@dataclass(frozen=True)
class Track:
    """One hypothesis a session follows.

    T_map_camera : (4, 4) float64, colour camera -> map, metres: the last accepted pose.
    velocity : (6,) float64, rotation vector (rad/s) then translation (m/s), both in the map frame: the constant
        motion that predicts the next pose.
    fitness : share of the last frame's points on the map at that pose, in [0, 1].
    """

    T_map_camera: np.ndarray
    velocity: np.ndarray
    fitness: float

    def predict(self, dt_s: float) -> np.ndarray:
        """(4, 4) T_map_camera `dt_s` seconds after the last accepted frame (dt_s < 0 is taken as 0)."""
        dt = max(0.0, float(dt_s))
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(self.velocity[:3] * dt).as_matrix() @ self.T_map_camera[:3, :3]
        T[:3, 3] = self.T_map_camera[:3, 3] + self.velocity[3:] * dt
        return T


@dataclass(frozen=True)
class TrackState:
    """What a session keeps between frames: hypotheses best first, the time of the last accepted frame (t_s,
    seconds, the runner's clock), and `confirmed` = the poses were accepted by tracking (False right after a
    relocalization that jumped: the next tracked frame confirms it). A session whose global search found nothing
    keeps its tracks (or none) and the time of that search, `searched_s`. `unsure_s`: the time of the last search
    that found nothing after a frame the tracks it keeps could not track, while the session tracks on from them, or of
    the frame whose tracking alone dropped all but one of the places the session held (None: no such doubt): they
    may be stale (the camera carried off) or a copy of the room, and what is tracked from them is not `ok` until a
    search, TrackConfig.search_interval_s later, agrees (`track_frame`)."""

    tracks: tuple[Track, ...]
    t_s: float
    confirmed: bool = True
    searched_s: float | None = None  # time of the last global search that found no pose (None: none since)
    unsure_s: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able form (lists of floats): what a runner stores and hands back."""
        return {"t_s": float(self.t_s), "confirmed": bool(self.confirmed),
                "searched_s": None if self.searched_s is None else float(self.searched_s),
                "unsure_s": None if self.unsure_s is None else float(self.unsure_s),
                "tracks": [{"T_map_camera": np.asarray(t.T_map_camera, dtype=float).tolist(),
                            "velocity": np.asarray(t.velocity, dtype=float).tolist(), "fitness": float(t.fitness)}
                           for t in self.tracks]}

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> "TrackState":
        """The state `to_dict` wrote; InvalidArgument for anything else."""
        try:
            tracks = tuple(Track(np.asarray(t["T_map_camera"], dtype=np.float64).reshape(4, 4),
                                 np.asarray(t["velocity"], dtype=np.float64).reshape(6), float(t["fitness"]))
                           for t in doc["tracks"])
            searched, unsure = doc.get("searched_s"), doc.get("unsure_s")
            return cls(tracks, float(doc["t_s"]), bool(doc.get("confirmed", True)),
                       None if searched is None else float(searched), None if unsure is None else float(unsure))
        except (KeyError, TypeError, ValueError) as exc:
            raise InvalidArgument(f"not a tracking state: {exc}") from None


@dataclass
class Tracked:
    """The answer to a session frame and the state for its next one (None: nothing worth keeping)."""

    result: LocalizationResult
    state: TrackState | None


@dataclass
class _Outcome:
    """One hypothesis refined on this frame."""

    prior: Track
    predicted: np.ndarray
    T_map_camera: np.ndarray
    fitness: float
    rmse_m: float
    correction_m: float
    correction_deg: float
    iterations: int
    converged: bool
    covariance: np.ndarray | None
    method: str = "small_gicp"  # what refined it last: small_gicp's point-to-plane ICP, or the search's refinement
    accepted: bool = False  # the motion agrees and the fitness is at least coast_fitness
    on_map: bool = False  # ... and at least min_fitness: a pose to answer


def velocity_between(T_prev: np.ndarray, T_next: np.ndarray, dt_s: float) -> np.ndarray:
    """(6,) map-frame rotation vector rate (rad/s) and translation rate (m/s) that move T_prev to T_next in dt_s."""
    if dt_s <= 1e-6:
        return np.zeros(6)
    w = Rotation.from_matrix(T_next[:3, :3] @ T_prev[:3, :3].T).as_rotvec()
    return np.concatenate([w, T_next[:3, 3] - T_prev[:3, 3]]) / dt_s


def track_frame(localizer: "Localizer", frame: Frame, state: TrackState | None, *, t_s: float,
                top_k: int | None = None, may_search: bool = True) -> Tracked:
    """One session frame: tracked from `state` when it is live, else localized globally (see the module docstring).

    state : the session's state after its previous frame, None for a new session. t_s : this frame's time, seconds,
    on the clock of `state.t_s`. may_search : False when another frame of the session is being searched (the
    runner's lease): a frame that does not track is answered `no_match` at once, its state kept. Raises
    InvalidFrame for a frame that cannot be registered.
    """
    search = _global if may_search else _search_elsewhere
    cfg = localizer.config.track
    if not isinstance(frame, Frame):
        raise InvalidFrame(f"expected a Frame, got {type(frame).__name__}")
    if not np.isfinite(t_s):
        raise InvalidArgument(f"t_s must be a finite time in seconds, got {t_s}")
    if state is None or not state.tracks:
        return search(localizer, frame, state, None, t_s, top_k, "global", [])
    dt_s = t_s - state.t_s
    predictions = [tr.predict(dt_s) for tr in state.tracks]
    if not cfg.enabled:
        return search(localizer, frame, state, predictions[0], t_s, top_k, "relocalized", ["tracking is off"])
    if dt_s > cfg.max_gap_s:
        return search(localizer, frame, state, predictions[0], t_s, top_k, "relocalized",
                       [f"{dt_s:.2f} s since the last accepted frame (more than {cfg.max_gap_s:g} s): not tracked"])
    if state.unsure_s is not None and t_s - state.unsure_s >= cfg.search_interval_s:
        return search(localizer, frame, state, predictions[0], t_s, top_k, "relocalized",
                      ["the poses tracked since a frame no search could place are checked by a search"])
    frame.validate()
    diag = Diagnostics(site_id=localizer.site.site_id, bundle_version=localizer.site.version, mode="tracked")
    timer = StageTimer(diag.stage_ms)
    with timer("points"):
        points, center_camera, check_xyz = _track_points(localizer, frame)
        diag.frame_points = len(points)
    with timer("track"):
        limits = correction_limits(cfg, dt_s)
        outcomes = [_refine(localizer, points, check_xyz, tr, T, limits) for tr, T in zip(state.tracks, predictions)]
        accepted = [o for o in outcomes if o.accepted]
        kept = _prune(localizer, accepted, cfg.clear_margin, cfg.max_hypotheses)
        if len(kept) == 1 and kept[0].on_map:
            # (an ambiguous answer is not claimed: its hypotheses are told apart by the ICP's fitness alone)
            kept[0] = _polished(localizer, points, center_camera, check_xyz, kept[0], limits)
    if not accepted:
        best = max(outcomes, key=lambda o: o.fitness)
        why = (f"tracking failed: fitness {best.fitness:.2f} (min {cfg.coast_fitness:g}), correction "
               f"{best.correction_m * 100:.1f} cm / {best.correction_deg:.1f}° (max {limits[0] * 100:.3g} cm / "
               f"{limits[1]:.3g}°)")
        # A frame that lies on the map nowhere near any prediction refutes them: a confident global answer may
        # then stand at once (the robot was carried off), instead of waiting for the next frame to confirm it.
        refuted = best.fitness < cfg.min_fitness
        tracked = search(localizer, frame, state, predictions[0], t_s, top_k, "relocalized", [why], refuted=refuted)
        # the failed attempt's cost belongs to this frame's answer too
        for k in ("points", "track"):
            tracked.result.diagnostics.stage_ms[f"{k}_tried"] = diag.stage_ms[k]
        return tracked
    return _tracked_result(localizer, frame, state, outcomes, kept, dt_s, t_s, center_camera, len(points), diag,
                           top_k)


# --- stages -----------------------------------------------------------------------------------------------------


def _track_points(localizer: "Localizer", frame: Frame) -> tuple[FramePoints, np.ndarray, np.ndarray]:
    """The frame's points at the tracking stride inside the ROI (radius γ about their centre, as in the localizer's
    refine stage), that centre (colour-camera frame) and a fixed sample for the fitness."""
    fc, cfg = localizer.config.frame, localizer.config.track
    points = sampled_points(frame, cfg.pixel_stride, reference_pixels=fc.stride_reference_pixels,
                            min_depth_m=fc.min_depth_m, max_depth_m=fc.max_depth_m, min_points=fc.min_points)
    points, center = crop_to_roi(points, localizer.config.refine.roi_radius_m)
    check = np.random.default_rng(0).choice(len(points), min(cfg.check_points, len(points)), replace=False)
    return points, center, points.xyz[check]


def correction_limits(cfg: TrackConfig, dt_s: float) -> tuple[float, float]:
    """(metres, degrees) a tracked frame dt_s after its state may correct the prediction by: the fixed bounds at a
    stream's rate, and what the camera can move in dt_s beyond them (TrackConfig.max_speed_m_s, max_turn_deg_s),
    within the coarse GICP's reach. A state's prediction is only as good as the time since it: right after a
    relocalization (motion unknown) the next frame comes a search's time later, several frames at 30 fps, and
    the fixed 5 cm sent it back to a search, again and again."""
    dt = max(0.0, float(dt_s))
    metres = min(cfg.coarse_correspondence_m, max(cfg.max_correction_m, cfg.max_speed_m_s * dt))
    return metres, max(cfg.max_correction_deg, cfg.max_turn_deg_s * dt)


def _refine(localizer: "Localizer", points: FramePoints, check_xyz: np.ndarray, prior: Track,
            predicted: np.ndarray, limits: tuple[float, float]) -> _Outcome:
    """The prediction refined against the site's small_gicp maps; accepted when the fitness holds and the
    refinement moved the prediction by no more than `limits` (metres, degrees: the motion agrees).

    A prediction the fine step can reach (`limits` within TrackConfig.fine_correspondence_m: consecutive frames of a
    stream) goes straight to the fine step; coarse then fine when it is not accepted, or when the prediction may
    be further off (after a relocalization or dropped frames). Skipping the coarse step halves a tracked frame."""
    cfg = localizer.config.track
    rm = localizer.maps_at(predicted, points.xyz.mean(axis=0)).refine_map
    xyz = _near_the_map(localizer, points.xyz, predicted)
    # point-to-plane needs no covariances of the frame's points (a third of a tracked frame's time for GICP's)
    fine = small_gicp.voxelgrid_sampling(xyz, cfg.fine_voxel_m)
    if limits[0] <= cfg.fine_correspondence_m:
        out = _fine(localizer, rm, fine, check_xyz, prior, predicted, predicted, limits)
        if out.accepted:
            return out
    coarse, _ = small_gicp.preprocess_points(xyz, localizer.config.refine.coarse_voxel_m, num_neighbors=GICP_NEIGHBORS)
    T = rm.coarse_align(coarse, predicted, max_correspondence_m=cfg.coarse_correspondence_m,
                        max_iterations=cfg.coarse_iterations)
    return _fine(localizer, rm, fine, check_xyz, prior, predicted, T, limits)


def _near_the_map(localizer: "Localizer", xyz: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """The frame points (colour-camera frame) that the prediction puts within the distance field's truncation
    (0.5 m) of the map. Farther ones cannot pair with a map point within the correspondence distances (0.1, 0.2 m)
    at any accepted correction, but small_gicp's nearest-neighbour search has no distance bound, and a frame that
    looks past the map's edge spent 25-40 ms of ICP on them. Read in the field: a lookup a point."""
    near = localizer.near_map(xyz, predicted)
    # too few left to register: the frame as it is (it will not track, and the fitness will say so)
    return xyz[near] if np.count_nonzero(near) >= MIN_ROI_POINTS else xyz


def _fine(localizer: "Localizer", rm: RefineMap, fine: small_gicp.PointCloud, check_xyz: np.ndarray, prior: Track,
          predicted: np.ndarray, T_start: np.ndarray, limits: tuple[float, float]) -> _Outcome:
    """Point-to-plane ICP from T_start against the map's fine target (its normals come with it): the tracking
    stage of KinectFusion and its kin. On 7-Scenes it tracked as often as GICP and slid less along walls seen
    at an angle (3.0 against 4.0 cm on the same frames)."""
    cfg, rc = localizer.config.track, localizer.config.refine
    target, tree = rm.fine_target()
    res = small_gicp.align(target, fine, tree, init_T_target_source=T_start, registration_type="PLANE_ICP",
                           max_correspondence_distance=cfg.fine_correspondence_m, num_threads=1,
                           max_iterations=cfg.fine_iterations, translation_epsilon=rc.epsilon,
                           rotation_epsilon=rc.epsilon)
    covariance = covariance_from_hessian(np.asarray(res.H), 2.0 * float(res.error), int(res.num_inliers),
                                         residuals_per_inlier=1)
    return _judged(localizer, rm, check_xyz, prior, predicted, np.asarray(res.T_target_source), int(res.iterations),
                   bool(res.converged), covariance, limits)


def _polished(localizer: "Localizer", points: FramePoints, center_camera: np.ndarray, check_xyz: np.ndarray,
              out: _Outcome, limits: tuple[float, float]) -> _Outcome:
    """The tracked pose refined as a search refines its answer (`RefineStage._refine_one`: GICP on the map of the
    pose's region), when the motion still agrees and the frame still lies on the map there; else `out` as it is.

    The point-to-plane ICP tracks (cheap, and on real frames it keeps hold of a stream where GICP from the
    prediction lost it: RedKitchen at 30 Hz, 6 -> 31 relocalizations), but it settles where the frame's points lie
    closest to the map's planes, which is not where the map's edges and furniture say: on four walks through the
    10-room building (`cadreg render --walk 0.05`) 16 of 281 tracked `ok` answers were 5-9 cm and up to 3.6° off,
    confidence 0.7-0.93, where the search's refinement from the same pose came back within 0.6-3.2 cm. Polished
    (and with `_tracked_result`'s rule for copies told apart): none of 316; the tracked `ok` poses of eight
    scene0470 walks 0.3-1.9 -> 0.1-0.5 cm at the 90th percentile; real RedKitchen frames against the map fused from
    250-499, 2.5 -> 2.0 cm at the median.
    The ICP's covariance stays the pose's: the slide rule of `_tracked_result` was set on it, and GICP's
    plane-shaped covariances make it certain along planes (`Localizer._slides`). No fitness guard as the search's
    `_unslid` has: the ICP's pose is where most of the frame lies within the inlier distance, and the right pose can
    fit less (walk frame 42 above: 0.985 at the ICP's pose 5.9 cm off, 0.963 at the truth); the motion's bounds hold
    the polish to where the camera can be."""
    rm = localizer.maps_at(out.T_map_camera, center_camera).refine_map
    ref = localizer._refine_one(rm, points, out.T_map_camera, "small_gicp")
    polished = _judged(localizer, rm, check_xyz, out.prior, out.predicted, ref.T_map_camera,
                       out.iterations + ref.iterations, ref.converged, out.covariance, limits)
    polished.method = ref.method
    return polished if polished.on_map else out


def _judged(localizer: "Localizer", rm: RefineMap, check_xyz: np.ndarray, prior: Track, predicted: np.ndarray,
            T: np.ndarray, iterations: int, converged: bool, covariance: np.ndarray | None,
            limits: tuple[float, float]) -> _Outcome:
    """The outcome of refining `predicted` to T: its fitness on the map, the correction it made, and whether that
    is accepted (the motion agrees and at least TrackConfig.coast_fitness of the frame lies on the map) and on the
    map (at least min_fitness)."""
    cfg, rc = localizer.config.track, localizer.config.refine
    fitness, rmse = rm.fitness(transform_points(T, check_xyz), inlier_m=rc.inlier_m)
    delta = np.linalg.inv(predicted) @ T
    out = _Outcome(prior, predicted, T, fitness, rmse, float(np.linalg.norm(T[:3, 3] - predicted[:3, 3])),
                   rotation_angle_deg(delta[:3, :3]), iterations, converged, covariance)
    out.accepted = fitness >= cfg.coast_fitness and out.correction_m <= limits[0] and out.correction_deg <= limits[1]
    out.on_map = out.accepted and fitness >= cfg.min_fitness
    return out


def _prune(localizer: "Localizer", accepted: list[_Outcome], margin: float, count: int) -> list[_Outcome]:
    """Best first; hypotheses that converged onto a better one are merged into it, those more than `margin`
    behind the best are dropped while the best lies on the map (`_Outcome.on_map`), at most `count` kept.

    Off the map's edge nothing is told apart: a real RedKitchen stream in a building of four copies of its room,
    looking past the map (fitness 0.15-0.21), dropped three copies whose fitness fell 0.05 behind the fourth's, where
    a few of the frame's points beyond the map landed on the neighbouring copy's walls, and the session then
    answered `ok` in that copy, 1.2-1.3 m from the truth."""
    ranked = sorted(accepted, key=lambda o: -o.fitness)
    kept: list[_Outcome] = []
    for o in ranked:
        if ranked[0].on_map and o.fitness < ranked[0].fitness - margin:
            break
        if all(localizer._distinct(o.T_map_camera, k.T_map_camera) for k in kept):
            kept.append(o)
        if len(kept) == count:
            break
    return kept


def _tracked_result(localizer: "Localizer", frame: Frame, state: TrackState, outcomes: list[_Outcome],
                    kept: list[_Outcome], dt_s: float, t_s: float, center_camera: np.ndarray, frame_points: int,
                    diag: Diagnostics, top_k: int | None) -> Tracked:
    cfg, mc, rc = localizer.config.track, localizer.config.match, localizer.config.refine
    best = kept[0]
    # Tracking alone told the session's places apart: the poses it held are now one, a rival the frame did not refute
    # dropped (fell behind, or its correction went past the motion's bounds), not merged into it. A few hundredths
    # of fitness is thin evidence between the copies of a room: on a walk through the 10-room building (`cadreg
    # render --walk 0.05 --seed 1`) the session held two copies 4.6 and 13.9 m from the truth, dropped one, and
    # answered the other `ok` 13.9 m off at 0.84. Like poses tracked on after a fruitless search: not `ok` until a
    # search agrees (`TrackState.unsure_s`).
    told_apart = len(state.tracks) > 1 and len(kept) == 1 and _dropped_rivals(localizer, outcomes, best)
    unsure_s = t_s if told_apart and state.unsure_s is None else state.unsure_s
    rival = kept[1].fitness if len(kept) > 1 else 0.0
    diag.method = "track"
    diag.refinement = Refinement(method=best.method, iterations=best.iterations, fitness=best.fitness,
                                 inlier_rmse_m=best.rmse_m, converged=best.converged)
    center = transform_points(best.T_map_camera, center_camera[None])[0]
    diag.roi = Roi(center.tolist(), rc.roi_radius_m, localizer.maps_at(best.T_map_camera, center_camera).refine_map.roi_count(
        center, rc.roi_radius_m),
                   frame_points)
    diag.notes.append(f"tracked {len(state.tracks)} hypothes{'i' if len(state.tracks) == 1 else 'e'}s, "
                      f"{len(kept)} kept; correction {best.correction_m * 100:.1f} cm / {best.correction_deg:.1f}°")
    tracks = tuple(Track(o.T_map_camera, velocity_between(o.prior.T_map_camera, o.T_map_camera, dt_s), o.fitness)
                   for o in kept)
    k = mc.top_k if top_k is None else int(top_k)
    hypotheses = [Hypothesis(o.T_map_camera, 0.0, 0.0, 0.0, o.fitness, source="track",
                             region=localizer.region_of(o.T_map_camera)) for o in kept[:k]]
    if not best.on_map:
        # the camera looks past the map's edge: too little to answer with, enough to follow (the correction is
        # small), so the session goes on from here instead of paying for a global search every frame
        diag.notes.append(f"fitness {best.fitness:.2f} below {cfg.min_fitness:g}: following the motion, no pose answered")
        result = LocalizationResult(Status.LOW_OVERLAP, None, confidence=low_overlap_confidence(best.fitness),
                                    hypotheses=hypotheses, diagnostics=diag, frame_id=frame.frame_id)
        return Tracked(result, TrackState(tracks, t_s, confirmed=state.confirmed, unsure_s=unsure_s))
    status = Status.OK if len(kept) == 1 else Status.AMBIGUOUS
    if len(kept) > 1:
        diag.notes.append(f"{len(kept)} hypotheses still fit (fitness " + ", ".join(f"{o.fitness:.3f}" for o in kept)
                          + "): ambiguous until the following frames tell them apart")
    slide = pose_std_m(best.covariance)
    trust = confidence(best.fitness, best.rmse_m, best.fitness - rival, inlier_m=rc.inlier_m,
                       confident_margin=mc.confident_margin, pose_std=slide, max_pose_std=mc.max_pose_std_m)
    if status == Status.OK and slide > mc.max_pose_std_m:
        # A search's rule too (MatchConfig.max_pose_std_m): a close view of a bare wall, or of a wall and the floor,
        # pins the tracked ICP along few directions, and a session slides along it frame after frame (on a walk
        # through scene0470, `cadreg render --walk`, ten frames in a row answered `ok` 6-9 cm and up to 13 degrees
        # off, confidence 0.95; their covariance let them slide 6.9-23 mm). Right tracked poses slide 1.5 mm at the
        # median, at most 3.4 mm on the real RedKitchen frames; on eight walks, 11 of 800 frames 6-12 mm.
        status = Status.UNCERTAIN
        diag.notes.append(f"the frame lets the tracked pose slide {slide * 1000:.1f} mm (more than "
                          f"{mc.max_pose_std_m * 1000:g} mm): uncertain, the session follows it")
    elif status == Status.OK and unsure_s is not None:
        # Tracked on from the poses the session held before a frame that could not be tracked, and that a search
        # could not place either: the camera may have been carried off (a kidnap on a clock that ran on), and the
        # poses be stale. RedKitchen frames 250-299 then 400-459 at 30 Hz: frame 400 failed (a correction of 11 cm
        # / 9.5°), its search found nothing, frame 405 tracked from frame 299's pose onto a fit 1 m from the truth,
        # and the session followed it, `ok` at 0.50-0.55 on seven frames 0.7-1 m off. Or one of several places
        # the session held, the others dropped by tracking alone (`told_apart`). Not `ok` until a search agrees.
        status = Status.UNCERTAIN
        diag.notes.append("the session's pose is unsure (tracked on past a frame no search could place, or told "
                          "from its rivals by tracking alone): uncertain until a search agrees")
    elif status == Status.OK and trust < mc.min_ok_confidence:
        # a search's rule too (`stages.answer_status`): on 7-Scenes the tracked poses below it (0.35-0.47, with
        # 0.40-0.52 of the frame on the map) were 5-10 cm off where the session tracked back in from the map's edge
        status = Status.UNCERTAIN
        diag.notes.append(f"confidence {trust:.2f} below {mc.min_ok_confidence:g}: uncertain, the session follows it")
    result = LocalizationResult(status, best.T_map_camera, confidence=trust, covariance=best.covariance,
                                hypotheses=hypotheses, diagnostics=diag, frame_id=frame.frame_id)
    return Tracked(result, TrackState(tracks, t_s, confirmed=True, unsure_s=unsure_s))


def _dropped_rivals(localizer: "Localizer", outcomes: list[_Outcome], kept: _Outcome) -> bool:
    """Whether a hypothesis the session followed ended this frame elsewhere than `kept` (distinct from it: dropped
    rather than converged onto it) and was not refuted: refuted is a place where less than TrackConfig.min_fitness
    of the frame lies on the map while at least that lies on it at `kept` (as a prediction is when the session
    jumps, `_global`)."""
    cfg = localizer.config.track
    refuted = lambda o: o.fitness < cfg.min_fitness <= kept.fitness  # noqa: E731  (on the map at kept, not at o)
    return any(not refuted(o) and localizer._distinct(o.T_map_camera, kept.T_map_camera)
               for o in outcomes if o.prior is not kept.prior)  # (kept may be its own outcome polished)


def _deferred(localizer: "Localizer", frame: Frame, state: TrackState, t_s: float, mode: str,
              notes: list[str]) -> Tracked:
    """No pose, at once: the last global search found nothing less than TrackConfig.search_interval_s ago."""
    wait_s = localizer.config.track.search_interval_s - (t_s - (state.searched_s or t_s))
    return _no_pose(localizer, frame, state, mode, [*notes, f"no global search for another {wait_s:.2f} s: the last "
                                                            "one found no pose"])


def _search_elsewhere(localizer: "Localizer", frame: Frame, state: TrackState | None, predicted: np.ndarray | None,
                      t_s: float, top_k: int | None, mode: str, notes: list[str], *, refuted: bool = False) -> Tracked:
    """No pose, at once, the state kept: another frame of this session holds the search (`track_frame`; the
    signature is `_global`'s, for which it stands in)."""
    return _no_pose(localizer, frame, state, mode, [*notes, "not searched: another frame of this session is being "
                                                            "searched"])


def _no_pose(localizer: "Localizer", frame: Frame, state: TrackState | None, mode: str, notes: list[str]) -> Tracked:
    """`no_match` without a search, the session's state handed back as it came."""
    diag = Diagnostics(site_id=localizer.site.site_id, bundle_version=localizer.site.version, mode=mode, notes=notes)
    return Tracked(LocalizationResult(Status.NO_MATCH, diagnostics=diag, frame_id=frame.frame_id), state)


def _global(localizer: "Localizer", frame: Frame, state: TrackState | None, predicted: np.ndarray | None, t_s: float,
            top_k: int | None, mode: str, notes: list[str], *, refuted: bool = False) -> Tracked:
    """The whole localizer, with the session's prediction as a prior (the client's own prior wins); then the state
    its answer leaves. A relocalized pose far from the prediction is a jump: answered `ambiguous` until confirmed,
    unless the frame `refuted` the prediction (tracked from it, too little of the frame lay on the map: fitness
    below TrackConfig.min_fitness) and the global answer is `ok` on its own: then the prediction is no rival."""
    cfg = localizer.config.track
    if state is not None and state.searched_s is not None and 0 <= t_s - state.searched_s < cfg.search_interval_s:
        return _deferred(localizer, frame, state, t_s, mode, notes)
    if predicted is not None and frame.T_map_camera_prior is None:
        frame = dataclasses.replace(frame, T_map_camera_prior=predicted)
    result = localizer.localize(frame, top_k=top_k)
    diag = result.diagnostics
    diag.mode = mode
    diag.notes[:0] = notes
    if result.status not in (Status.OK, Status.AMBIGUOUS) or result.T_map_camera is None:
        # nothing learnt: the session keeps what it had (its gap grows) and waits before it searches again; what
        # it tracks on from them is unsure (`TrackState.unsure_s`)
        kept = state.tracks if state is not None else ()
        t_kept = state.t_s if state is not None else t_s
        return Tracked(result, TrackState(kept, t_kept, confirmed=False, searched_s=t_s,
                                          unsure_s=t_s if kept else None))
    T = np.asarray(result.T_map_camera)
    tracks = [Track(T, np.zeros(6), result.diagnostics.refinement.fitness if result.diagnostics.refinement else 0.0)]
    if result.status == Status.AMBIGUOUS:
        best_score = max((h.geometric_score for h in result.hypotheses), default=0.0)
        for h in result.hypotheses:
            if len(tracks) == cfg.max_hypotheses:
                break
            if h.geometric_score >= best_score - cfg.hypothesis_margin and all(
                    localizer._distinct(h.T_map_camera, t.T_map_camera) for t in tracks):
                tracks.append(Track(np.asarray(h.T_map_camera, dtype=np.float64), np.zeros(6), h.geometric_score))
        if len(tracks) > 1:
            diag.notes.append(f"the session tracks {len(tracks)} hypotheses until one remains")
    confirmed = True
    if predicted is not None and localizer._distinct(T, predicted):
        jump = float(np.linalg.norm(T[:3, 3] - predicted[:3, 3]))
        diag.notes.append(f"relocalized {jump:.2f} m from where the session's motion put the camera")
        if result.status == Status.OK and refuted:
            diag.notes.append("the frame does not fit the map where the motion put it: the new pose stands")
            return Tracked(result, TrackState(tuple(tracks), t_s, confirmed=True))
        if result.status == Status.OK:
            # not silently: the pose waits for the next frame to track from it
            result.status = Status.AMBIGUOUS
            result.hypotheses.append(Hypothesis(predicted, 0.0, 0.0, 0.0, 0.0, source="track"))
            diag.notes.append("answered ambiguous until the next frame tracks from the new pose")
        confirmed = False
    return Tracked(result, TrackState(tuple(tracks), t_s, confirmed=confirmed))
