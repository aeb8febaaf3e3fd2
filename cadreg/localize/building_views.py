"""A building's look at the views its rooms repeat: the refine stage's steps that only a site of many regions takes.

Copies of a room show a view the same, or nearly, from the same room-relative pose, and differ in the furniture
one of them lacks or the neighbour seen over a wall. After the best contenders are refined, the winner's pose is
moved into each room that repeats its room (`twins.py`) and looked at there along the frame's rays
(`field_view.py`): a copy that shows the frame better is refined and may win, one that shows it as well stands as
a rival (the answer is then `ambiguous`), and when poses look the same along the rays the frame's labelled
objects, or the depth on the rays both the frame and the map show a surface on, may tell one from the rest, else
how closely its points lie on the map orders them (`refine_stage.RefineStage._rank_building` calls these in turn).

`BuildingViews` is a part of `Localizer` (one of its base classes), kept in a module of its own: its methods read the
localizer's `config`, `field` (the site's distance field), `maps` (`RegionMaps`), `twins` (`RoomTwins`), `graph`
(`MapGraph`) and its `_distinct`, `_distinct_from_all`, `_apart_from` and `region_of`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..geometry import make_Ts, pose_errors
from ..result import Diagnostics, Hypothesis
from .field_view import align_on_field
from .match import distinct_pairs
from .refine import RefineOutcome
from .score import score_poses
from .stages import NEAR_REACH_DEG, NEAR_REACH_M, Candidate, Refined, Scan

# A view moved into a room that repeats it starts within the copies' misfit (centimetres): a short alignment.
TWIN_ALIGN_ITERATIONS = 6
TWIN_ALIGN_REACH_M = (0.15, 0.06)
# A copy's pose goes on to the alignment and the render when the frame's points fit the field there at most this
# much worse than at the answer (MatchConfig.score_tau_m's soft inlier share). 0.3, was 0.15: a copy lacking an
# object in view fits the field worse than its view agreement shows (a repeated 100-room view's twin fit 0.152
# worse at its exact pose and agreed along the rays within 0.007, and the view was answered `ok`); the renders
# that judge the copies cost a fifth of what they did (`field_kernels.trace`). On the 100-room benchmark repeated
# views with the truth reported 93.5 -> 97.8 % labelled, 91.3 -> 93.5 % without; no wrong `ok`.
TWIN_SCREEN_MARGIN = 0.3
# The twin check's first look at every copy takes every TWIN_THIN_STEP-th ray of every TWIN_THIN_STEP-th row; a
# copy is rendered in full when that look puts it within the ambiguity margin plus this slack of the answer (432
# rays: a few hundredths of sampling noise).
TWIN_THIN_STEP = 2
TWIN_THIN_SLACK = 0.1
# Copies that show the frame better than the answer are refined, best first, at most this many a frame.
TWIN_PROMOTIONS = 3
# A promoted copy that wins and whose refinement moved it less than this from where the twin check put it has the
# same copies, at the same poses, as that check looked at already: they are not looked at again. (100-room
# benchmark: the winners' refinement moved them 1.2 mm and 0.03° at the median, 6.4 mm and 0.37° at the 90th
# percentile; a render's depth tolerance is 4 cm.)
TWIN_SAME_POSE_M = 0.005
TWIN_SAME_POSE_DEG = 0.2
# An object one pose places (its centroid within MatchConfig.match_radius_m of a node of its class) counts as missing
# at another pose only when that pose puts it this much farther from a node of its class than the first does, and
# beyond the radius: a partly seen whiteboard's centroid lies about the radius from its node, and copies of one
# view, millimetres apart, fell on both sides of it (a 100-room view repeated in 9 rooms was told by its
# whiteboard, 52 % of the view, to be in one of them: 0.598 m against 0.601).
OBJECT_SLACK_M = 0.1
# A frame's object whose centroid lies inside the box of a node of its class, grown by this, is where that node is
# (distance 0), however far from the node's centre: a large object seen in part (a whiteboard 2.4 m wide, half in
# view) has its centroid a metre from its node's, and a scan clustered the same board into a large node and a
# 0.3 m sliver in one copy of a room only; that copy alone then "placed" the frame's board, and four views repeated
# in ten rooms turned by odd angles were answered `ok` in it (confidence 0.92-0.96). Grown by the depth noise of the
# frame's points and the thickness a box of a scanned surface lacks.
OBJECT_BOX_MARGIN_M = 0.1
# A refined contender at the winner's place (not distinct from it) whose depth agrees with the frame's on the rays
# both show a surface on by this much more than the winner's is put first (`_deepest_at_the_winners_place_first`).
SAME_PLACE_DEPTH_MARGIN = 0.05
# Among distinct poses within the ambiguity margin of one another's view agreement, one whose depth agrees with the
# frame's on the rays both show a surface on by this much more than every other's is the answer, and the others are no
# rivals (`_told_by_depth`). Real 7-Scenes RedKitchen frames in a 3-room building (the kitchen fused from other
# frames of the sequence, no labels): the right pose and one 0.4-0.5 m off in the same kitchen tied along the rays
# (0.007-0.024 apart: the frame sees what the map lacks, which counts against both) while their depths agreed
# 0.79-0.87 against 0.57-0.65, the right pose ahead by 0.17-0.25 each time (11 frames, the wrong pose ranked first in
# 5; 10 told at this margin: 111 -> 121 `ok` answers, all at the kitchen alone's). In the `ambiguous` answers of the
# 10- and 100-room, corridor, mixed and robot-height buildings (renders, with and without labels), the best depth
# agreement led the others by at most 0.1 (0.098 at one frame, neither pose right).
DEPTH_TIEBREAK_MARGIN = 0.2
# ... on at least this many rays where both the frame and the map show a surface (fewer: `FieldView.shared` finds
# no evidence against a pose, and says 1.0).
SHARED_MIN_RAYS = 20
# The ambiguity margin (MatchConfig.ambiguity_margin) between two poses' view agreements holds at this agreement and
# above, and grows below it as a share's spread does, √(p(1 − p)) (`BuildingViews._view_margin`).
MARGIN_AGREEMENT = 0.8
# Among poses that look the same along the frame's rays, one whose frame points lie within TIE_FIT_TAU_M of the map
# (`score_poses`' soft share) by this much more than the answer's is put first (`_closest_fit_first`).
TIE_FIT_TAU_M = 0.02
TIE_FIT_MARGIN = 0.02


class Renders:
    """The map's depth along the frame's rays ((r,), `FieldView.render`) at the poses of one frame's refine stage,
    by the outcome (RefineOutcome) each belongs to. Each outcome is held with its render: keyed by a bare `id`, an
    outcome the stage discards (a copy the twin check replaces) freed its id for a new one, which could then read
    the old one's render as its own."""

    def __init__(self) -> None:
        self._by_id: dict[int, tuple[object, np.ndarray]] = {}

    def __setitem__(self, outcome: object, depth: np.ndarray) -> None:
        self._by_id[id(outcome)] = (outcome, depth)

    def __getitem__(self, outcome: object) -> np.ndarray:
        held, depth = self._by_id[id(outcome)]
        if held is not outcome:
            raise KeyError(outcome)
        return depth

    def __contains__(self, outcome: object) -> bool:
        entry = self._by_id.get(id(outcome))
        return entry is not None and entry[0] is outcome


class BuildingViews:
    """The refine stage's steps of a building (module docstring): a base class of `Localizer`."""

    def _promote_twins(self, scan: Scan, refined: list[Refined], twins: list[Refined], refine,
                       candidates: list[Candidate], renders: Renders, center_camera: np.ndarray) -> list[Refined]:
        """The copies of the winner's view (`_twin_views`) that `_twin_to_refine` picks, refined (`refine`, the
        refine stage's) into `refined` (kept sorted, best first), at most TWIN_PROMOTIONS a frame; a copy that wins
        has its own copies looked at in turn. Returns the copies left unrefined."""
        looked_below = False
        for _ in range(TWIN_PROMOTIONS):
            promoted = self._twin_to_refine(twins, refined[0].score, below=not looked_below)
            if promoted is None:
                break
            # A copy of the winner's room shows the frame better, or nearly as well with no other copy as close:
            # it is refined too, and may win (when its refinement leaves it below the winner, the next copy that
            # shows the frame better is tried); a new winner's own copies are then looked at as well.
            looked_below |= promoted.score <= refined[0].score
            twins.remove(promoted)
            refined.append(refine(promoted.candidate))
            refined.sort(key=lambda r: -r.score)
            self._deepest_at_the_winners_place_first(scan, refined, renders)
            self._report_refined(refined, candidates)
            if refined[0].candidate is promoted.candidate:
                moved_m, turned_deg = pose_errors(refined[0].T_map_camera, promoted.T_map_camera)
                if moved_m < TWIN_SAME_POSE_M and turned_deg < TWIN_SAME_POSE_DEG:
                    # The copy refined in its room stayed where the twin check put it: its copies are the rooms
                    # that check looked at (the new winner's view moved into them is the earlier pose moved there),
                    # and their renders stand.
                    continue
                candidates.extend(t.candidate for t in twins)
                # Only the rooms whose copies stood from the earlier pose are looked at again: the new winner is
                # that pose's copy refined (a few centimetres off it) and shows the frame better, so a room whose
                # copy fell short of the earlier, lower bar falls short of this one too.
                # So are the rooms of the poses it beat, whose copies of the new winner were never looked at: a
                # refinement in the true room that slid 9 cm (view agreement 0.83) lost to a copy refined in
                # another room (0.84), whose view moved back into the true room showed the frame 0.91 (10-room
                # corridor building; the truth was not among the `ambiguous` answer's hypotheses).
                more = self._twin_views(scan, refined[0].T_map_camera, center_camera, candidates, renders,
                                        len(refined), refined[0].score,
                                        among={self._roi_region(t.T_map_camera, center_camera) for t in twins}
                                        | {self._roi_region(r.T_map_camera, center_camera) for r in refined[1:]})
                # a copy seen from the new winner replaces the same copy seen from an earlier pose
                twins = self._apart_from(twins, [u.T_map_camera for u in more]) + more
                candidates[len(refined):] = [c for c in candidates[len(refined):]
                                             if all(c is not t.candidate for t in twins)]
        return twins

    def _deepest_at_the_winners_place_first(self, scan: Scan, refined: list[Refined], renders: Renders) -> None:
        """Refined contenders at the winner's place (within the distinct-pose radius of refined[0], which is then
        no rival of it), ranked by view agreement: the one whose depth agrees with the frame's clearly best on the
        rays where both show a surface (`FieldView.shared`, by SAME_PLACE_DEPTH_MARGIN) is put first, in place.

        Two refinements of one place can end in two basins, 20-40 cm apart. The view agreement counts against a
        pose every ray on which the frame sees a surface the map lacks, and a real map lacks what no mapping frame
        saw: a pose turned or shifted toward the mapped part shows fewer such rays, and more on which the map stands
        in front of what the frame measured. Real 7-Scenes RedKitchen frames in a 3-room building, the kitchen fused
        from other frames of the sequence: the right pose (1 cm from the kitchen alone's answer) showed the frame
        0.548 along the rays, its depth agreeing on 84 % of the rays both see; one 26 cm off showed 0.556, 72 %.
        Renders of the map itself show nothing it lacks: on the building sets no answer changed."""
        if len(refined) < 2:
            return
        here = [k for k in range(1, len(refined)) if not self._distinct(refined[k].T_map_camera,
                                                                         refined[0].T_map_camera)]
        if not here:
            return
        depth = {k: scan.view.shared(self._render_of(scan, renders, refined[k].outcome))[0] for k in [0] + here}
        best = max(here, key=lambda k: depth[k])
        if depth[best] > depth[0] + SAME_PLACE_DEPTH_MARGIN:
            refined.insert(0, refined.pop(best))

    def _twin_to_refine(self, twins: list[Refined], score: float, *, below: bool) -> Refined | None:
        """The copy of the winner's view (`_twin_views`) to refine next, or None: the one that shows the frame best
        when it shows it better than the winner (view agreement `score`); or, when `below` (once a frame: on the
        100-room benchmark a fifth of the frames had such a copy, and a second or third one refined never changed
        an answer), when it lies below, within RegionConfig.contender_margin, and no copy stands within the
        ambiguity margin. A copy's pose is the winner's refined pose moved into its room, and that refinement
        fitted the winner's room, not the copy's: in a 10-room building the right room's copy of a view answered
        `ok` in its neighbour landed 2.3 cm off and showed the frame 0.767 to the winner's 0.811, where the truth
        showed it 0.815. Refined, it is judged as the winner was. A copy already within the ambiguity margin makes
        the answer ambiguous as it stands."""
        if not twins:
            return None
        best = max(twins, key=lambda t: t.score)
        if best.score > score:
            return best
        behind = score - best.score
        mc = self.config.match
        return best if below and mc.ambiguity_margin <= behind < self.config.regions.contender_margin else None

    def _view_contenders(self, candidates: list[Candidate], center_camera: np.ndarray) -> list[Candidate]:
        """In a building: the best candidate and, up to MatchConfig.refine_contenders, its distinct rivals within
        RegionConfig.contender_margin of its view agreement, to be refined: a rival room's pose the field
        alignment left a few centimetres off looks worse along the rays than it is, and only refined poses can be
        told apart, or found to be the same view, fairly. A candidate at the best's view moved into a room that
        repeats the best's is left to the twin check, which looks at it from the refined winner
        (`_twin_views`): each refinement in a building builds a room's map (0.3 s at 100 rooms)."""
        best, margin = candidates[0], self.config.regions.contender_margin
        copies = dict(self.twins.of(self._roi_region(best.T_map_camera, center_camera)))
        out = [best]
        for c in candidates[1:]:
            if len(out) >= self.config.match.refine_contenders:
                break
            b = self._roi_region(c.T_map_camera, center_camera)
            if b in copies and not self._distinct(copies[b] @ best.T_map_camera, c.T_map_camera):
                continue
            if best.score - c.score < margin and all(
                    self._distinct(c.T_map_camera, k.T_map_camera) for k in out):
                out.append(c)
        return out

    def _twin_views(self, scan: Scan, T_map_camera: np.ndarray, center_camera: np.ndarray,
                    candidates: list[Candidate], renders: Renders, refined: int,
                    view_score: float, among: set[int] | None = None) -> list[Refined]:
        """In a building: the winner's pose moved into each room that repeats the room its view looks into, or
        the room its camera stands in (`_copies_of_view`, `twins.py`), where no refined contender stands, pulled
        onto the field and rendered: each as a `Refined` (its view agreement, an outcome with no refinement, its
        candidate), each render put in `renders` under its outcome's id.
        view_score : the winner's view agreement. among : the rooms to look at (every copy when None).
        candidates : the refined contenders first (`refined` of them), then the others; an unrefined candidate at a
        copy's pose is dropped from it (the copy's pose comes from the refined answer). A refined one stands, and
        the copy is dropped, when the copy lies at it (TWIN_SAME_POSE_M, TWIN_SAME_POSE_DEG: judged already) or
        within its refinement's reach showing the frame no clearly better (`_stands_beside_contenders`).
        The graph match misses a copy whose objects rank it lower (a chair missing out of view, another
        neighbour), and a view that copy repeats must not be answered `ok`, nor one it shows better."""
        copies = [(b, T_ba) for b, T_ba in self._copies_of_view(T_map_camera, center_camera)
                  if (among is None or b in among) and (
                  scan.search is None or scan.search.allows((T_ba @ T_map_camera)[None, :3, 3], self.maps.regions)[0])]
        moved = [T_ba @ T_map_camera for _, T_ba in copies]
        keep = distinct_pairs(np.array(moved).reshape(-1, 4, 4), self._refined_poses(candidates, refined),
                              min_translation_m=TWIN_SAME_POSE_M, min_rotation_deg=TWIN_SAME_POSE_DEG).all(axis=1)
        if moved and scan.clusters:
            keep &= self._shows_objects(scan, T_map_camera, moved)
        copies, moved = [c for c, k in zip(copies, keep) if k], [T for T, k in zip(moved, keep) if k]
        if len(moved):
            # The view's pose in each copy, where the frame's points fit the map about as well as at the answer:
            # a cheap screen on the field before the alignment and the render (a 100-room building has 99 copies).
            mc = self.config.match
            Ms = np.array(moved)
            fit = score_poses(self.field, scan.score_xyz, Ms[:, :3, :3], Ms[:, :3, 3], tau_m=mc.score_tau_m)
            here = score_poses(self.field, scan.score_xyz, T_map_camera[None, :3, :3], T_map_camera[None, :3, 3],
                               tau_m=mc.score_tau_m)[0]
            copies = [c for c, f in zip(copies, fit) if f >= here - TWIN_SCREEN_MARGIN]
            moved = [T for T, f in zip(moved, fit) if f >= here - TWIN_SCREEN_MARGIN]
        if not moved:
            return []
        # The objects the winner matched, carried into each copy: what pins the copy's pose as they pin the winner's.
        assignment = candidates[0].assignment
        candidates[refined:] = self._apart_from(candidates[refined:], moved)
        T = np.array(moved)
        # Each copy is first looked at along a quarter of the rays (a 100-room building has 99 copies, and a full
        # render costs 2 ms a pose): only the copies that may show the frame about as well as the answer are
        # rendered in full. Those that cannot are no rival (two views alike enough to be twins agree with the
        # frame within a few hundredths of each other) and are not listed.
        coarse = scan.view.thinned(TWIN_THIN_STEP)
        thin = coarse.render(self.field, T)
        scan.twin_rays += thin.size
        score = coarse.agreement(thin)
        # A moved pose that shows the frame less well than the answer may only be a little off (real copies are
        # never placed exactly): it is pulled onto the field, and kept there when that shows the frame better.
        # The copies of a composed building are exact, and the field's alignment, good to a centimetre or two,
        # would only blur the others.
        low = np.flatnonzero(score < view_score - self.config.match.ambiguity_margin)
        if len(low):
            R, t = align_on_field(self.field, scan.score_xyz, T[low, :3, :3], T[low, :3, 3],
                                  up=None if scan.floor is None else self.up,
                                  iterations=TWIN_ALIGN_ITERATIONS, reach_m=TWIN_ALIGN_REACH_M)
            aligned = make_Ts(R, t)
            thin_again = coarse.render(self.field, aligned)
            scan.twin_rays += thin_again.size
            again = coarse.agreement(thin_again)
            better = again > score[low]
            T[low[better]], score[low[better]] = aligned[better], again[better]
            thin[low[better]] = thin_again[better]
        near = np.flatnonzero(score >= view_score - self.config.match.ambiguity_margin - TWIN_THIN_SLACK)
        if not len(near):
            return []
        copies, T = [copies[k] for k in near], T[near]
        # in full: the rays of the first look are traced already
        rendered = scan.view.render_completing(self.field, T, scan.view.thinned_rays(TWIN_THIN_STEP), thin[near])
        scan.twin_rays += len(T) * (len(scan.view) - len(coarse))
        score = scan.view.agreement(rendered)
        stands = self._stands_beside_contenders(T, score, candidates, refined)
        copies, T, rendered, score = [c for c, k in zip(copies, stands) if k], T[stands], rendered[stands], score[stands]
        out = []
        carried_all = self.twins.carry_all(assignment, copies)
        regions = self.maps.indices_at(T[:, :3, 3])
        for k, T_k in enumerate(T.copy()):  # one array per pose, shared by its outcome and its candidate
            carried = carried_all[k]
            h = Hypothesis(T_k, 0.0, 0.0, 0.0, float(score[k]), source="twin", region=self.maps.regions[regions[k]].id,
                           matches=[(int(i), self.graph.ids[n]) for i, n in enumerate(carried) if n >= 0])
            outcome = RefineOutcome(T_k, None, 0, False, "field")
            renders[outcome] = rendered[k]
            out.append(Refined(float(score[k]), outcome, Candidate(T_k, float(score[k]), h, carried, rendered[k])))
        return out

    def _copies_of_view(self, T_map_camera: np.ndarray, center_camera: np.ndarray) -> list[tuple[int, np.ndarray]]:
        """[(b, T_ba)]: the rooms that repeat the room a pose's view looks into (the region of its ROI's centre) and,
        when the camera stands in another, those that repeat the camera's room, each with the transform that moves
        the view there (`RoomTwins.of`); a copy of the second kind only where it moves the pose elsewhere than one
        of the first. A view from a room through its door into the corridor looks into the corridor, whose
        segments need not repeat as the rooms along them do: in the 10-room corridor building such a view, repeated
        in three rooms, was answered `ambiguous` in one of them without the truth's room among its hypotheses."""
        looked_into = self._roi_region(T_map_camera, center_camera)
        copies = list(self.twins.of(looked_into))
        stood_in = int(self.maps.indices_at(T_map_camera[None, :3, 3])[0])
        if stood_in == looked_into or not self.twins.of(stood_in):
            return copies
        more = self.twins.of(stood_in)
        elsewhere = self._distinct_from_all([T_ba @ T_map_camera for _, T_ba in more],
                                            [T_ba @ T_map_camera for _, T_ba in copies])
        return copies + [c for c, k in zip(more, elsewhere) if k]

    @staticmethod
    def _refined_poses(candidates: list[Candidate], refined: int) -> np.ndarray:
        """(refined, 4, 4): the poses of the refined contenders, first in `candidates` (`_report_refined`)."""
        return np.array([c.T_map_camera for c in candidates[:refined]]).reshape(-1, 4, 4)

    def _stands_beside_contenders(self, poses: np.ndarray, scores: np.ndarray, candidates: list[Candidate],
                                  refined: int) -> np.ndarray:
        """(len(poses),) bool: whether each copy (poses (h, 4, 4), view agreements `scores`) stands beside the
        refined contenders (the first `refined` of `candidates`, scores their view agreement): it lies beyond the
        refinement's reach of each (NEAR_REACH_M, NEAR_REACH_DEG), or shows the frame clearly better than every
        one within it (by the ambiguity margin). A copy in a contender's basin that shows the frame about as well
        is that contender again; one that shows it clearly better found what the contender's refinement missed (it
        slid, or stopped short: the 9 cm of `_promote_twins`), and it is looked at as any copy is. (Left in, the
        copies about as good as a contender made a unique 100-room view `ambiguous`, a copy 1 cm from a rival's
        refined pose looking the same along the rays where the rival itself had not; and the same room's pose was
        listed twice among an answer's hypotheses, a few millimetres apart.)"""
        within = ~distinct_pairs(poses, self._refined_poses(candidates, refined), min_translation_m=NEAR_REACH_M,
                                 min_rotation_deg=NEAR_REACH_DEG)
        bar = np.array([c.score for c in candidates[:refined]]) + self.config.match.ambiguity_margin
        return ~np.any(within & (bar[None, :] >= scores[:, None]), axis=1)

    def _shows_objects(self, scan: Scan, T_map_camera: np.ndarray, poses: list[np.ndarray]) -> np.ndarray:
        """(len(poses),) bool: whether each pose (a copy of T_map_camera in a room that repeats its room) has the
        frame's large objects where it places them: each labelled object of the frame covering at least
        RegionConfig.object_tiebreak_share of its view (`Scan.view_shares`) that T_map_camera places
        (`_objects_placed`) must be placed by the pose too, about as near (`_near_as`). A copy that lacks such an
        object (a building's copies each miss some furniture) shows the frame differently by at least that share of
        the view, more than the repeated-view oracle's 3 % of the pixels: it repeats no view of it and shows it no
        better, and is not rendered (at 100 rooms, most of the twin check's 99 copies a frame)."""
        large = scan.view_shares >= self.config.regions.object_tiebreak_share
        mine = self._object_distances(scan, T_map_camera)[0]
        pins = large & (mine < self.config.match.match_radius_m)
        return self._near_as(self._object_distances(scan, np.asarray(poses)), mine)[:, pins].all(axis=1)

    def _roi_region(self, T_map_camera: np.ndarray, center_camera: np.ndarray) -> int:
        """Index of the region holding the centre of a pose's region of interest (what `maps_at` builds)."""
        return int(self.maps.indices_at(T_map_camera[:3, :3] @ center_camera + T_map_camera[:3, 3])[0])

    def _report_refined(self, refined: list[Refined], candidates: list[Candidate]) -> None:
        """In a building: the refined contenders' candidates are replaced, in `candidates` and in the refined
        order (the winner first), by their refined poses and view agreements, so that the result reports the poses
        the answer was judged by (the field alignment leaves a few centimetres)."""
        first = []
        for r in refined:
            T, c = r.T_map_camera, r.candidate
            first.append(replace(c, T_map_camera=T, score=r.score, hypothesis=replace(
                c.hypothesis, T_map_camera=T, geometric_score=r.score, region=self.region_of(T))))
        done = [r.candidate for r in refined] + first
        candidates[:] = first + [c for c in candidates if not any(c is d or c.T_map_camera is d.T_map_camera for d in done)]

    def _told_by_objects(self, scan: Scan, refined: list[Refined], rivals: list[Candidate], refine,
                         candidates: list[Candidate], diag: Diagnostics) -> bool:
        """In a building, when distinct poses look the same along the frame's rays: whether the frame's labelled
        objects tell one of them from the rest. Each pose is credited with the frame's view in objects that have
        a map node of their class within match_radius_m where it places them (`_objects_placed`); when one pose
        explains clearly more than every other, each of them credited with the objects it places about as near
        as that pose does (`_near_as`), it is the answer (refined first, and put first in `refined`, when it was a
        rival).

        Rooms that copy one another differ in the furniture one of them lacks; the depth along the rays barely
        shows a chair, its label does: in the 100-room building, a labelled unique view was answered in a copy
        (the view agreement tied among 61 rooms) where the true room's pose alone explained all three of the
        frame's objects (8 % of its points more than any copy). A pose must explain
        RegionConfig.object_tiebreak_share more of the frame's view than every other: the repeated-view oracle
        calls views that differ by less than about one small object (3 % of the pixels) the same, and a sliver of
        a chair at the frame's border, or a partly seen table whose centroid lands 0.6 m from its node, told
        copies apart by 0.3-4 % (one of them wrongly)."""
        poses = np.array([refined[0].T_map_camera] + [c.T_map_camera for c in rivals])
        distances = self._object_distances(scan, poses)
        explained = scan.view_shares @ (distances < self.config.match.match_radius_m).T
        k = int(np.argmax(explained))
        # the others credited with what they place about as near as pose k does
        second = float(np.max(scan.view_shares @ self._near_as(np.delete(distances, k, axis=0), distances[k]).T))
        if explained[k] - second < self.config.regions.object_tiebreak_share:
            return False
        return self._told(k, rivals, refined, refine, candidates, diag,
                          f"the frame's objects: {100 * explained[k]:.1f} % of its view lies in objects whose map "
                          f"node is where the answer places them, at most {100 * second:.1f} % at the "
                          f"{len(poses) - 1} other poses that look the same")

    def _told_by_depth(self, scan: Scan, refined: list[Refined], rivals: list[Candidate], refine,
                       candidates: list[Candidate], renders: Renders, looked: list[Refined], diag: Diagnostics) -> bool:
        """In a building, when distinct poses look the same along the frame's rays (`_view_rivals`): whether the
        depth along the rays tells one of them from the rest. The view agreement counts every ray on which the frame
        sees a surface the map lacks against a pose, so a real frame (it sees what no mapping frame saw) can tie a
        right pose with a wrong one turned toward the mapped part; on the rays where both the frame and the map show
        a surface (`FieldView.shared`), the wrong pose's depths disagree. One whose depth agreement beats every
        other's by DEPTH_TIEBREAK_MARGIN, on at least SHARED_MIN_RAYS such rays, is the answer (refined first, and
        put first in `refined`, when it was a rival). looked : the refined contenders and the copies of the view,
        whose renders are in `renders` (a rival's own `rendered` is that of its candidate's pose)."""
        by_pose = {id(r.T_map_camera): r.outcome for r in looked}
        views = [self._render_of(scan, renders, refined[0].outcome)] + [
            self._render_of(scan, renders, by_pose[id(c.T_map_camera)]) if id(c.T_map_camera) in by_pose
            else c.rendered for c in rivals]
        if any(v is None for v in views):  # a pose never rendered: nothing to tell it by
            return False
        depth, coverage = np.array([scan.view.shared(v, min_rays=SHARED_MIN_RAYS) for v in views]).T
        shared_rays = np.rint(coverage * np.isfinite(scan.view.measured).sum())  # coverage: shared / measured rays
        k = int(np.argmax(depth))
        second = float(np.max(np.delete(depth, k)))
        if shared_rays[k] < SHARED_MIN_RAYS or depth[k] - second < DEPTH_TIEBREAK_MARGIN:
            return False
        return self._told(k, rivals, refined, refine, candidates, diag,
                          f"the depth along the frame's rays: it agrees with the map's on {100 * depth[k]:.0f} % of "
                          f"the rays both show a surface on at the answer, at most {100 * second:.0f} % at the "
                          f"{len(rivals)} other poses that look the same")

    def _told(self, k: int, rivals: list[Candidate], refined: list[Refined], refine, candidates: list[Candidate],
              diag: Diagnostics, note: str) -> bool:
        """A tie-break told pose k of [the answer] + `rivals` from the rest: a rival is put first (`_put_first`),
        and the note says why. Returns True (told)."""
        if k > 0:
            self._put_first(rivals[k - 1], refined, refine, candidates)
        diag.notes.append(note)
        return True

    def _put_first(self, rival: Candidate, refined: list[Refined], refine, candidates: list[Candidate]) -> None:
        """A rival a tie-break chose becomes the answer: its refined entry moved to the front of `refined`, or, when
        it was not refined, refined now (`refine`, the refine stage's) and put there; `candidates` reordered to
        match (`_report_refined`)."""
        promoted = next((r for r in refined if r.T_map_camera is rival.T_map_camera), None)
        if promoted is None:
            promoted = refine(rival)
        else:
            refined.remove(promoted)
        refined.insert(0, promoted)
        self._report_refined(refined, candidates)

    def _closest_fit_first(self, scan: Scan, refined: list[Refined], rivals: list[Candidate], refine,
                           candidates: list[Candidate], diag: Diagnostics) -> None:
        """In a building, when distinct poses look the same along the frame's rays (the answer will be
        `ambiguous`): the one whose frame points lie closest to the map's surfaces, by TIE_FIT_MARGIN or more over
        the answer, is put first (refined first when it was a rival). Its rivals stay: this orders them, it claims
        nothing.

        The rays (48 × 36, 4 cm + 2 % of the depth) see a surface at about the right depth as agreeing, and a
        view over a low wall into the next room shows another chair there at about the same depth in each copy of
        the room; the frame's points, one per 3 cm voxel (so a far surface counts by its area, not its pixels),
        against the field at 2 cm see it. On the 100-room benchmark three unique views were answered `ambiguous`
        with the truth second, 0.001-0.004 of view agreement behind and 0.06-0.09 ahead in this fit; over every
        `ambiguous` answer of the 10- and 100-room and mixed buildings, it put the truth first 16 times (9 of them
        repeated views, the truth's own room first among its copies) and never put a wrong pose before a right one."""
        poses = np.stack([refined[0].T_map_camera] + [c.T_map_camera for c in rivals])
        fit = score_poses(self.field, scan.down.xyz, poses[:, :3, :3], poses[:, :3, 3], tau_m=TIE_FIT_TAU_M)
        k = int(np.argmax(fit))
        if k == 0 or fit[k] < fit[0] + TIE_FIT_MARGIN:
            return
        self._put_first(rivals[k - 1], refined, refine, candidates)
        diag.notes.append(f"of {len(poses)} poses that look the same, the frame's points lie closest to the map at "
                          f"the one put first ({fit[k]:.3f} within {100 * TIE_FIT_TAU_M:.0f} cm, the answer before it "
                          f"{fit[0]:.3f})")

    def _promoted_twins(self, scan: Scan, refined: list[Refined], center_camera: np.ndarray,
                        candidates: list[Candidate], renders: Renders) -> list[Candidate]:
        """The copies of the winner's view (`_twin_views`, from refined[0]) that stand as its rivals: within the
        ambiguity margin of its view agreement, or showing the same along the frame's rays
        (RegionConfig.twin_agreement): `_look_alike`, as `_view_rivals` has them. Each is added to `candidates`."""
        score, out = refined[0].score, refined[0].outcome
        twins = self._twin_views(scan, out.T_map_camera, center_camera, candidates, renders, len(refined), score)
        if not twins:
            return []
        alike = self._look_alike(scan, score, np.array([t.score for t in twins]),
                                 np.stack([renders[t.outcome] for t in twins]), self._render_of(scan, renders, out))
        standing = [t.candidate for t, a in zip(twins, alike) if a]
        candidates.extend(standing)
        return standing

    def _unexamined_rivals(self, scan: Scan, looked: list[Refined], renders: Renders, candidates: list[Candidate],
                           compared: list[np.ndarray]) -> list[Candidate]:
        """The rivals of the answer (looked[0], which a tie-break has just put first; `_view_rivals` over `looked`,
        the refined contenders and the copies of the view) distinct from every pose of `compared` (the poses the
        tie-break told apart)."""
        _, _, alike = self._view_rivals(looked, renders, candidates, scan)
        return self._apart_from(alike, compared)

    def _render_of(self, scan: Scan, renders: Renders, outcome: RefineOutcome) -> np.ndarray:
        """The map's depth along the frame's rays at an outcome's pose, rendered and kept when it has none yet: an
        outcome `refine` left as it was (a pose the frame sees through) has none, whether it stays a rival or a
        tie-break puts it first."""
        if outcome not in renders:
            renders[outcome] = scan.view.render(self.field, outcome.T_map_camera)[0]
        return renders[outcome]

    def _view_margin(self, agreement: float) -> float:
        """The ambiguity margin between the answer's view agreement (`agreement`) and a rival's: MatchConfig's, grown
        below MARGIN_AGREEMENT by the spread of a share at the answer's agreement over the spread at MARGIN_AGREEMENT,
        √(p(1 − p) / (0.8 · 0.2)); never smaller.

        A view agreement is a share of the frame's rays, and the difference between two poses' is noisier the nearer
        they lie to one half. The margin was set where the building sets' right answers lie (view agreement 0.81 at
        the median, 0.72 at the 10th percentile). Lower down it let chance decide: a unique view of a 30-room
        building with corridors, seen without labels and without its floor, was answered `ok` in a room turned
        about, 3.4 m off, at 0.635, its true room's pose 0.032 behind (the oracle has the two rooms' views agree at
        0.962); and a robot-height view two rooms of a 10-room building repeat was answered `ok` in the wrong copy
        at 0.491, 0.030 ahead. Both are now `ambiguous` (their margins 0.036 and 0.037), the first with its true
        pose first; so are 3 right `ok` answers of 1045 over the building sets (at 0.66-0.80, 0.030-0.032 ahead)."""
        p = min(max(float(agreement), 0.0), 1.0)
        spread = np.sqrt(p * (1.0 - p) / (MARGIN_AGREEMENT * (1.0 - MARGIN_AGREEMENT)))
        return self.config.match.ambiguity_margin * max(1.0, float(spread))

    def _look_alike(self, scan: Scan, score: float, scores: np.ndarray, rendered: np.ndarray,
                    mine: np.ndarray) -> np.ndarray:
        """(h,) bool: which of h poses the answer cannot be told from — their view agreement `scores` within the
        ambiguity margin of the answer's `score` (`_view_margin`), or their renders `rendered` ((h, r)) showing what
        the answer's render `mine` ((r,)) shows along RegionConfig.twin_agreement of the frame's rays."""
        return ((score - scores < self._view_margin(score))
                | (scan.view.agreement(rendered, mine) >= self.config.regions.twin_agreement))

    def _objects_placed(self, scan: Scan, poses: np.ndarray) -> np.ndarray:
        """(p, objects) bool: whether each pose (poses (p, 4, 4) or (4, 4)) puts each of the frame's labelled
        objects (`Scan.clusters`) with its centroid within match_radius_m of a map node of its class."""
        return self._object_distances(scan, poses) < self.config.match.match_radius_m

    def _near_as(self, distances: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """(p, objects) bool: whether poses that put the frame's labelled objects `distances` ((p, objects),
        `_object_distances`) from their nodes place each as a pose at `reference` ((objects,)) does: within
        match_radius_m, or, for an object that pose places, at most OBJECT_SLACK_M farther than it."""
        radius = self.config.match.match_radius_m
        return distances < np.where(reference < radius, np.maximum(radius, reference + OBJECT_SLACK_M), radius)

    def _object_distances(self, scan: Scan, poses: np.ndarray) -> np.ndarray:
        """(p, objects) float: how far each pose (poses (p, 4, 4) or (4, 4)) puts each of the frame's labelled
        objects' centroids (`Scan.clusters`) from the nearest map node of its class; 0 inside the box of one
        (OBJECT_BOX_MARGIN_M); inf beyond match_radius_m plus OBJECT_SLACK_M (what no rule here tells apart,
        `_near_as`)."""
        P = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        distances = np.full((len(P), len(scan.clusters)), np.inf)
        if not len(scan.clusters):
            return distances
        centroids = np.array([c.centroid for c in scan.clusters])
        xyz = centroids @ P[:, :3, :3].transpose(0, 2, 1) + P[:, None, :3, 3]  # (p, objects, 3), as transform_points
        reach = self.config.match.match_radius_m + OBJECT_SLACK_M
        for k, c in enumerate(scan.clusters):
            node = self.graph.nearest_of_class(xyz[:, k], c.cls, reach)
            found = node >= 0
            distances[found, k] = np.linalg.norm(self.graph.centroid[node[found]] - xyz[found, k], axis=1)
            distances[self.graph.in_box_of_class(xyz[:, k], c.cls, OBJECT_BOX_MARGIN_M), k] = 0.0
        return distances

    def _view_rivals(self, refined: list[Refined], renders: Renders, candidates: list[Candidate],
                     scan: Scan) -> tuple[bool, float, list[Candidate]]:
        """In a building: (has a distinct rival, margin, the rivals the answer cannot be told from) of the winner,
        refined[0] (the refined contenders and the copies of the winner's view, best first). A
        pose distinct from the winner's is a rival when its view agreement lies within the ambiguity margin of the
        winner's, or when the map along the frame's rays shows the same at both (RegionConfig.twin_agreement): a
        room that repeats the view, which the frame's noise may rank either way. Refined contenders are compared
        with the refined winner, the other candidates with the winner's candidate as the field alignment left both
        (a refined pose would beat an unrefined one by the refinement alone). The margin is to the best distinct
        pose, 0 when a twin stands."""
        score, winner = refined[0].score, refined[0].candidate
        T, mine = refined[0].T_map_camera, self._render_of(scan, renders, refined[0].outcome)
        rivals, margin, has_rival = [], score, False
        others = refined[1:]
        others = self._apart_from(others, [T])
        if others:
            # all at once: a 100-room frame's refined contenders and copies of the view are some thirty poses
            has_rival, margin = True, min(margin, score - max(r.score for r in others))
            alike = self._look_alike(scan, score, np.array([r.score for r in others]),
                                     np.stack([self._render_of(scan, renders, r.outcome) for r in others]), mine)
            # (by the pose array's identity: each refined pose's candidate holds the same array, `_report_refined`)
            by_pose = {id(c.T_map_camera): c for c in reversed(candidates)}
            rivals += [by_pose[id(r.T_map_camera)] for r, a in zip(others, alike) if a]
        done = [r.T_map_camera for r in refined] + [r.candidate.T_map_camera for r in refined]
        rest = self._apart_from(candidates, done)
        if rest:
            has_rival = True
            alike = self._look_alike(scan, winner.score, np.array([c.score for c in rest]),
                                     np.stack([c.rendered for c in rest]), winner.rendered)
            margin = min(margin, winner.score - max(c.score for c in rest))
            rivals += [c for c, a in zip(rest, alike) if a]
        if any(r.score < score - self._view_margin(score) for r in rivals):
            margin = 0.0  # a twin: the same view, however the noise ranked it
        return has_rival, margin, rivals
