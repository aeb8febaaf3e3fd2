"""The refine stage: the best candidates refined inside their region of interest and ranked again (DESIGN §1).

`RefineStage._refine` reads as its steps: the contenders and the frame points they share (`RefineRun`), each
contender refined and scored (`_refine_contender`, with the slide check `_unslid`), more candidates when every
contender sees through the map (`_refine_past_see_through`), the ranking (in one room by score, `_rank_room`; in a
building by view agreement along the frame's rays, with the copies of the view in the rooms that repeat it,
`_rank_building` and `building_views.py`), and the winner with its fit (`_choice`).

`RefineStage` is a part of `Localizer` (one of its base classes), kept in a module of its own: its methods read the
localizer's `config`, `maps` (`RegionMaps`) and `maps_at`, the building steps of `BuildingViews`, and its
`_distinct` and `_agreement_score`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np

from ..camera import axial_noise_sigma_m
from ..geometry import transform_points
from ..result import Diagnostics
from .building_views import Renders
from .match import distinct_pairs
from .points import FramePoints, noise_octaves, voxel_budget
from .refine import RefineMap, RefineOutcome, crop_to_roi
from .stages import NEAR_REACH_DEG, NEAR_REACH_M, Candidate, Choice, Refined, Scan

# Distinct candidates refined beyond the contenders when every contender sees through the map: two, since a
# frame of a place the map lacks sees through it at every pose, and each costs a refinement.
EXTRA_CONTENDERS = 2
# A rival (any contender but the best) seeing through the map this many times MatchConfig.max_see_through at its
# coarse pose is not refined: of about 800 refinements of 7-Scenes frames, none that started above 1.5 times it
# ended at or below it (the largest start of one that did: 1.1 times), and such rivals were most of the cost of
# frames looking past the map's edge.
HOPELESS_SEE_THROUGH = 1.5
# A refinement whose whole-frame fitness fell by more than this from its start slid (`_unslid`).
SLIDE_TOLERANCE = 0.01
# In a building, so did one whose view agreement (the share of the frame's rays along which the map shows what the
# frame measured, the building's ranking) fell by more than this from its start's.
VIEW_SLIDE_TOLERANCE = 0.05
# A frame whose refinement points are at least this share noisy (depth noise over RefineConfig.noise_reference_m) is
# refined a second time on them weighed by their noise (`_noise_weighed`); the scene0470 renders (depth to 4.5 m)
# and real Kinect frames (to 4 m) mostly are not.
NOISY_SHARE = 0.1


@dataclass(eq=False)
class RefineRun:
    """What the refinements of one frame's contenders share (`RefineStage._refine`).

    contenders : the candidates refined first, the best first. near : in one room, the contender `_near_contender`
    added (then every score is weighed by depth agreement), else None. source : the frame points the refinement
    draws on (`_refine_source`); roi_points : those within γ of the frame's centre, within the point budget;
    roi_frame_points : how many lay within γ before the budget. center_camera : the centre of the ROI, camera
    frame. renders : a building's refined poses' renders. roi_weighed : roi_points with each point's voxel grown by
    its depth noise (`_noise_weighed`), or None. whole : the whole frame within the budget, made when a refinement
    slid (`_unslid`)."""

    scan: Scan
    method: str
    diag: Diagnostics
    contenders: list[Candidate]
    near: Candidate | None
    source: FramePoints
    roi_points: FramePoints
    roi_frame_points: int
    center_camera: np.ndarray
    renders: Renders
    roi_weighed: FramePoints | None = None
    whole: FramePoints | None = None


class RefineStage:
    """The refine stage's steps (a base class of `Localizer`; see the module's text)."""

    def _refine(self, scan: Scan, candidates: list[Candidate], method: str, diag: Diagnostics) -> Choice:
        """Candidates -> Choice: fine refinement of the best inside the region of interest, and of its distinct
        rivals within the ambiguity margin (up to MatchConfig.refine_contenders), re-ranked after refinement."""
        run = self._refine_run(scan, candidates, method, diag)
        refine = partial(self._refine_contender, run)
        refined = [refine(c) for c in run.contenders]
        taken_next = self._refine_past_see_through(run, refined, candidates, refine)
        if scan.view is not None:
            has_rival, margin, rivals = self._rank_building(run, refined, candidates, refine)
        else:
            rivals = None
            has_rival, margin = self._rank_room(refined, candidates, diag)
        if scan.unverified:
            diag.notes.append(f"{len(scan.unverified)} more regions tied with the best and were not verified")
            has_rival, margin = True, 0.0
        return self._choice(run, refined, taken_next, has_rival, margin, rivals)

    def _refine_run(self, scan: Scan, candidates: list[Candidate], method: str, diag: Diagnostics) -> RefineRun:
        """What the contenders' refinements share: the contenders (in one room the best, its distinct rivals within
        the ambiguity margin and the near contender; in a building `_view_contenders`) and the frame points of the
        region of interest."""
        mc, rc = self.config.match, self.config.refine
        best = candidates[0]
        if scan.view is None:
            contenders = [best] + [c for c in candidates[1:mc.refine_contenders] if best.score - c.score < mc.ambiguity_margin
                                   and self._distinct(c.T_map_camera, best.T_map_camera)]
            near = self._near_contender(candidates, contenders)
            if near is not None:
                contenders.append(near)
        else:
            near = None
            contenders = self._view_contenders(candidates, scan.center_camera)
        # Region of interest (paper §2.5, radius γ about the frame's centre under the hypothesis). The map's search
        # structures are built once per site rather than cropped per frame; leaving out the frame points farther
        # than γ from their centroid has the same effect, since correspondences are sought only a few centimetres
        # from each frame point.
        source = self._refine_source(scan, method)
        roi_points, center_camera = crop_to_roi(source, rc.roi_radius_m, scan.center_camera)
        # The cost of a refinement is bounded by its inputs: at most MatchConfig.refine_points frame points
        # (`_budget`), for at most refine_contenders hypotheses, each at most twice (the slide check in
        # `_refine_contender`).
        return RefineRun(scan, method, diag, contenders, near, source, self._budget(roi_points, method), len(roi_points),
                         center_camera, Renders(), roi_weighed=self._noise_weighed(roi_points, method))

    def _refine_contender(self, run: RefineRun, c: Candidate) -> Refined:
        """One contender refined and scored: in a building by its view agreement along the frame's rays, in one
        room by its agreement score, both lowered by how far the frame sees through the map there."""
        scan, mc = run.scan, self.config.match
        maps = self.maps_at(c.T_map_camera, run.center_camera)
        if c is not run.contenders[0] and scan.zbuf is not None:
            see = maps.view_check.see_through(c.T_map_camera, scan.zbuf, scan.K)
            if see > HOPELESS_SEE_THROUGH * mc.max_see_through:
                # A rival the frame sees through this far at its coarse pose never refined into a credible
                # one: it keeps that pose and a score of 0, as its refinement would have earned.
                return Refined(0.0, RefineOutcome(c.T_map_camera, None, 0, False, run.method), c, see)
        out = self._fine_pose(run, maps.refine_map, c)
        see = 0.0 if scan.zbuf is None else self.maps_at(out.T_map_camera, run.center_camera).view_check.see_through(
            out.T_map_camera, scan.zbuf, scan.K)
        if scan.view is not None:
            # Along the frame's rays the map in front of the measured depth already counts against the pose.
            return Refined(self._view_agreement(run, out), out, c, see)
        # A pose at which the frame sees through the map ranks below one at which it does not, whatever its
        # fit: the same factor as in the confidence.
        score = self._agreement_score(out.T_map_camera, scan) * max(0.0, 1.0 - see / mc.max_see_through)
        if run.near is not None and scan.zbuf is not None:
            # Two basins of one hypothesis are told apart as the sensor sees them: the labels that ranked them
            # are what put them side by side (`_near_contender`).
            score *= maps.view_check.depth_agreement(out.T_map_camera, scan.zbuf, scan.K)
        return Refined(score, out, c, see)

    def _fine_pose(self, run: RefineRun, refine_map: RefineMap, c: Candidate) -> RefineOutcome:
        """A contender's fine refinement, or the one this frame's refine stage made of it before (`Scan.fine`: the
        region of interest, the points and the map it is refined on are the frame's and the contender's own, so a
        second run of the stage, after the second or the deeper look, would redo the same GICP passes)."""
        known = run.scan.fine.get(id(c))
        if known is not None and known[0] is c:
            return known[1]
        out = self._refine_one(refine_map, run.roi_points, c.T_map_camera, run.method)
        if run.roi_weighed is not None:
            # GICP pairs each point with its nearest map point, and where two surfaces lie a few centimetres apart
            # along a noisy point's ray (a room's wall and the corridor wall behind it, 12-18 cm apart, seen 5 m away
            # at σ 5 cm) the noisy points pair across and pull the pose, 7-8 cm off from the true pose itself: the
            # weighed points fit the frame better there. Where the far points hold what the near ones cannot (a far
            # wall the only one in view), the points alike do (the demo room's view 4.4 m deep: 2.6 cm alike, 6.4
            # weighed).
            out = self._fits_better(run, refine_map, out, self._refine_one(refine_map, run.roi_weighed,
                                                                           c.T_map_camera, run.method))
        if run.roi_frame_points < len(run.source):
            out = self._unslid(run, refine_map, c, out)
        run.scan.fine[id(c)] = (c, out)
        return out

    def _unslid(self, run: RefineRun, refine_map: RefineMap, c: Candidate, out: RefineOutcome) -> RefineOutcome:
        """The ROI leaves out the frame's far points; when those were what held the pose along some direction (a
        corner whose far wall lies beyond γ), the refinement slides and the whole frame fits worse than at its
        start. Then the whole frame (within the same point budget) refines it, and the better fit is kept.

        In a building the refinement has slid too when it shows the frame worse along its rays than its start did
        (by VIEW_SLIDE_TOLERANCE): a view from one room over a low wall into the next, whose ROI held the near
        room's chair and wall but little of what lay beyond, was pulled 3.5 cm off by the ROI's points from the
        true pose itself (view agreement 0.75 -> 0.56; the whole frame's refinement 1.3 cm, 0.78), and the answer
        went to a copy 9 m away that showed the frame 0.65 (a 12-room building with moved furniture, with and
        without labels). Its check points lay within 5 cm of the map at all three poses: the view agreement, whose
        depth tolerance is 4 cm plus 2 %, chooses then."""
        fit = lambda T: self._whole_fit(run, refine_map, T)  # noqa: E731
        seen = self._view_agreement(run, out) if run.scan.view is not None else None
        in_view = seen is not None and seen < c.score - VIEW_SLIDE_TOLERANCE
        if fit(out.T_map_camera) >= fit(c.T_map_camera) - SLIDE_TOLERANCE and not in_view:
            return out
        if run.whole is None:
            run.whole = self._budget(run.source, run.method)
        again = self._refine_one(refine_map, run.whole, c.T_map_camera, run.method)
        if in_view:
            better = again if self._view_agreement(run, again) > seen else out
        else:
            better = self._fits_better(run, refine_map, out, again)
        if better is again:
            run.diag.notes.append("the ROI refinement slid: refined with the whole frame")
        return better

    def _view_agreement(self, run: RefineRun, out: RefineOutcome) -> float:
        """In a building: the share of the frame's rays along which the map at a refinement's pose shows what the
        frame measured (`FieldView.agreement`; its render is kept for the refine stage)."""
        return float(run.scan.view.agreement(self._render_of(run.scan, run.renders, out))[0])

    def _fits_better(self, run: RefineRun, refine_map: RefineMap, first: RefineOutcome,
                     second: RefineOutcome) -> RefineOutcome:
        """Of two refinements of one contender (on other points: the noise-weighed ones, the whole frame), the one
        at which more of the whole frame lies on the map (`_whole_fit`); the first on a tie."""
        if self._whole_fit(run, refine_map, second.T_map_camera) > self._whole_fit(run, refine_map, first.T_map_camera):
            return second
        return first

    def _whole_fit(self, run: RefineRun, refine_map: RefineMap, T_map_camera: np.ndarray) -> float:
        """The share of the frame's check points within RefineConfig.inlier_m of the map at T_map_camera."""
        return refine_map.fitness(transform_points(T_map_camera, run.scan.check_xyz),
                                  inlier_m=self.config.refine.inlier_m)[0]

    def _refine_past_see_through(self, run: RefineRun, refined: list[Refined], candidates: list[Candidate],
                                 refine: Callable[[Candidate], Refined]) -> Candidate | None:
        """When every contender puts the map in front of what the frame measured, the next distinct candidates (at
        most EXTRA_CONTENDERS more) are refined into `refined` until one does not. Returns the candidate so taken,
        else None."""
        if not all(r.see_through > self.config.match.max_see_through for r in refined):
            return None
        tried = [r.T_map_camera for r in refined]
        limit = len(refined) + EXTRA_CONTENDERS
        for c in candidates[1:]:
            if len(refined) >= limit:
                break
            if any(c is k for k in run.contenders) or not all(self._distinct(c.T_map_camera, T) for T in tried):
                continue
            refined.append(refine(c))
            tried.append(refined[-1].T_map_camera)
            if refined[-1].see_through <= self.config.match.max_see_through:
                run.diag.notes.append(f"the best {len(refined) - 1} poses saw through the map: took the next")
                return c
        return None

    def _rank_building(self, run: RefineRun, refined: list[Refined], candidates: list[Candidate],
                       refine: Callable[[Candidate], Refined]) -> tuple[bool, float, list[Candidate]]:
        """In a building: the refined contenders ranked by view agreement, the copies of the best's view looked at
        (and promoted when they show the frame better), the rivals that look the same along the frame's rays found
        and, when there are some, told apart by the frame's objects or depth, else ordered by its fit
        (`building_views.py`). Returns (has a distinct rival, margin, rivals)."""
        scan, diag, renders, center_camera = run.scan, run.diag, run.renders, run.center_camera
        mc = self.config.match
        refined.sort(key=lambda r: -r.score)
        self._deepest_at_the_winners_place_first(scan, refined, renders)
        self._report_refined(refined, candidates)
        twins = self._twin_views(scan, refined[0].T_map_camera, center_camera, candidates, renders, len(refined),
                                 refined[0].score)
        unlooked = []
        for r in refined[1:]:
            # A contender the answer cannot be told from: the copies of its view are looked at too. The truth's
            # room may be a copy of the runner-up's room-relative view, not of the answer's (a room lacking
            # a chair the frame sees shows the right view a little worse than another room a wrong one).
            if refined[0].score - r.score >= self._view_margin(refined[0].score) or not self._distinct(
                    r.T_map_camera, refined[0].T_map_camera):
                continue
            if scan.twin_rays >= self.config.regions.twin_check_rays:
                unlooked.append(r)
                continue
            more = self._twin_views(scan, r.T_map_camera, center_camera, candidates, renders, len(refined),
                                    refined[0].score)
            twins += self._apart_from(more, [u.T_map_camera for u in twins])
        if unlooked:
            diag.notes.append(f"the twin check rendered {scan.twin_rays} rays: the copies of {len(unlooked)} tied "
                              f"runner-ups' views were not looked at")
        if self._copies_wait(scan, refined, twins):
            scan.copies_wait = True
        else:
            twins = self._promote_twins(scan, refined, twins, refine, candidates, renders, center_camera)
        candidates.extend(t.candidate for t in twins)
        has_rival, margin, rivals = self._view_rivals(refined + twins, renders, candidates, scan)
        diag.notes.append(f"refined {len(refined)} of the best poses, view agreement "
                          + ", ".join(f"{r.score:.3f}" for r in refined)
                          + (f"; {len(rivals)} distinct poses look the same along the frame's rays" if rivals else ""))
        if rivals:
            before = refined[0].candidate
            compared = [refined[0].T_map_camera] + [c.T_map_camera for c in rivals]
            told = ((bool(scan.clusters) and self._told_by_objects(scan, refined, rivals, refine, candidates, diag))
                    or self._told_by_depth(scan, refined, rivals, refine, candidates, renders, refined + twins, diag))
            if told and refined[0].candidate is not before:
                # The objects (or the depth) put a rival first, and told it only from the poses that looked like
                # the answer it replaced. A pose that looks like the new answer, but not like the old (within the
                # new answer's lower view margin), was never told from it; nor were the copies of its view (the twin
                # check ran from the pose it replaced). Either stands as its rival. (A 100-room view repeated in
                # four rooms was answered `ok` in one of its copies; a real RedKitchen frame in a building holding
                # two copies of the fused kitchen was answered `ok` in the copy it was not taken in, its true room's
                # pose 0.013 behind, its depth agreement lowered by the next rooms seen through the map's holes.)
                # (The copies of the twin check still stand, but for one the tie-break refined and put first.)
                looked = refined + [t for t in twins if all(t.candidate is not r.candidate for r in refined)]
                unexamined = self._unexamined_rivals(scan, looked, renders, candidates, compared)
                copies = self._promoted_twins(scan, refined, center_camera, candidates, renders)
                # a copy looked at again from the new answer replaces the same copy seen from the pose it replaced
                unexamined = self._apart_from(unexamined, [c.T_map_camera for c in copies])
                if unexamined or copies:
                    told = False
                    # the pose put first is the answer now, no rival of its own
                    rivals = self._apart_from(rivals, [refined[0].T_map_camera]) + unexamined + copies
                    diag.notes.append(f"poses that look like the pose put first and were not told from it: "
                                      f"{len(unexamined)}, and copies of its view that show the frame as well: "
                                      f"{len(copies)}")
            if told:
                # The frame's objects, or its depth, rule the other poses out: no rival stands, whatever the view
                # margin.
                has_rival, margin, rivals = False, mc.confident_margin, []
        if any(self._distinct(r.T_map_camera, refined[0].T_map_camera) for r in unlooked):
            # A copy of a runner-up's view nobody looked at may show the frame as well as the answer: what the frame's
            # objects or depth told the answer from, it was not told from. (A runner-up they put first has had its
            # copies looked at, `_promoted_twins`; whatever the order below, the answer now has a rival.)
            has_rival, margin = True, 0.0
        if rivals:
            self._closest_fit_first(scan, refined, rivals, refine, candidates, diag)
        return has_rival, margin, rivals

    def _copies_wait(self, scan: Scan, refined: list[Refined], twins: list[Refined]) -> bool:
        """In a building: whether the copies of the view are left unrefined (`_promote_twins`) for the deeper search
        that follows (`Localizer._deeper_look`, which runs whenever they are): the label-free search was cut short
        over the whole building (`Scan.search_cut`), and neither the best refined pose nor any copy shows the frame
        along its rays as well as the lower of RegionConfig.min_view_agreement and `Scan.deeper_below` asks. The refine
        stage after the deeper search refines the copies of its own winner. In a 135-room building with corridors,
        views repeated in 70-80 rooms refined three copies of a first answer that showed them 0.55, at 120 ms each (a
        room map built, the refinement redone on the whole frame and on its noise-weighed points), before the deeper
        search found poses that showed them 0.91-0.97: 1.3-1.5 s a frame.
        An answer, or a copy of its view, between min_view_agreement and the deeper look's bar
        (RegionConfig.deeper_view_agreement) is mostly right (that bar's comment), and the copies are refined first:
        left waiting, they were never refined when the deeper search found no new pose (a 9-room view was answered
        8 m off, showing the frame 0.55, with a copy beside the truth that showed it 0.68 listed behind it)."""
        bar = min(scan.deeper_below, self.config.regions.min_view_agreement)
        return scan.search_cut and max(r.score for r in refined + twins) < bar

    def _rank_room(self, refined: list[Refined], candidates: list[Candidate], diag: Diagnostics) -> tuple[bool, float]:
        """In one room: the refined contenders ranked by score; (has a distinct rival, margin), with a rival standing
        whenever a distinct candidate as close as the contenders was left unrefined."""
        mc = self.config.match
        best = candidates[0]
        if len(refined) > 1:
            refined.sort(key=lambda r: -r.score)
            diag.notes.append(f"refined {len(refined)} close hypotheses, scores " + ", ".join(f"{r.score:.3f}" for r in refined))
            has_rival, margin = self._rival_margin([r.score for r in refined], [r.T_map_camera for r in refined])
        else:
            has_rival, margin = self._rival_margin([c.score for c in candidates], [c.T_map_camera for c in candidates])
        # A distinct candidate as close to the best as the contenders, but beyond the refine_contenders refined,
        # was never ruled out: the answer cannot claim to be the one.
        unexamined = self._apart_from([c for c in candidates[1:] if best.score - c.score < mc.ambiguity_margin
                                       and not any(c is r.candidate for r in refined)],
                                      [r.T_map_camera for r in refined])
        if unexamined:
            diag.notes.append(f"{len(unexamined)} more distinct hypotheses as close as the refined ones were not refined")
            has_rival, margin = True, 0.0
        return has_rival, margin

    def _choice(self, run: RefineRun, refined: list[Refined], taken_next: Candidate | None, has_rival: bool,
                margin: float, rivals: list[Candidate] | None) -> Choice:
        """The winner, refined[0], with its fit to the map and its agreement with the frame's depth and colours."""
        scan, rc, center_camera = run.scan, self.config.refine, run.center_camera
        out, winner, see = refined[0].outcome, refined[0].candidate, refined[0].see_through
        fitness, rmse = self.maps_at(out.T_map_camera, center_camera).refine_map.fitness(
            transform_points(out.T_map_camera, scan.check_xyz), inlier_m=rc.inlier_m)
        if scan.view is not None:
            # In a building, along the frame's rays through the whole map: a region's map holds its neighbours
            # only 3 m out, and a view over the low walls of a composed building reaches farther.
            agreement, coverage = scan.view.shared(self._render_of(scan, run.renders, out))
        elif scan.zbuf is None:
            agreement, coverage = 1.0, 1.0
        else:
            agreement, coverage = self.maps_at(out.T_map_camera, center_camera).view_check.compare_depth(
                out.T_map_camera, scan.zbuf, scan.K, scan.check_xyz)
        passed_over = winner is taken_next
        return Choice(winner, out, margin, has_rival, fitness, rmse, center_camera, run.roi_frame_points, see, agreement,
                      coverage, rivals, passed_over, self._chroma_at(scan, out.T_map_camera, center_camera),
                      view_agreement=refined[0].score if scan.view is not None else None)

    def _near_contender(self, candidates: list[Candidate], contenders: list[Candidate]) -> Candidate | None:
        """In one room: the best candidate within RegionConfig.contender_margin of the best's score that lies beyond
        the refinement's reach of every contender (NEAR_REACH_M, NEAR_REACH_DEG) though not distinct from the best
        (MatchConfig.distinct_translation_m): to the graph one hypothesis, to the refinement another basin, and it
        is refined too, so that the geometry picks between them. A segmenter's labels shift a door's or a
        whiteboard's centroid along its wall: a scene0470 view of a door, its whiteboard left unlabelled, ranked a
        pose 26 cm along the wall 0.04 above the right one (depth agreement 0.82 against 0.98), which was never
        refined, and was answered `ok`, confidence 0.93."""
        best, margin = candidates[0], self.config.regions.contender_margin
        starts = np.array([k.T_map_camera for k in contenders])
        for c in candidates[1:]:
            if best.score - c.score >= margin:
                break  # (sorted best first)
            if any(c is k for k in contenders) or self._distinct(c.T_map_camera, best.T_map_camera):
                continue
            beyond = distinct_pairs(c.T_map_camera[None], starts, min_translation_m=NEAR_REACH_M,
                                    min_rotation_deg=NEAR_REACH_DEG)
            if beyond.all():
                return c
        return None

    def _rival_margin(self, scores: list[float], poses: list[np.ndarray]) -> tuple[bool, float]:
        """(has a distinct rival, margin) of poses sorted best first (refined contenders, or the candidates when
        only the best was refined): the rival is the best pose distinct from the winner, wherever it ranks. A
        runner-up that converged onto the winner is the winner again, not a rival, and must not hide a distinct
        pose behind it (two twin rooms refined to 0.962 and 0.947 with a copy of the first between them were
        answered `ok` with the whole score as margin)."""
        for score, T in zip(scores[1:], poses[1:]):
            if self._distinct(T, poses[0]):
                return True, scores[0] - score
        return False, scores[0]

    def _refine_source(self, scan: Scan, method: str) -> FramePoints:
        """The frame points the refinement draws on: the scan's voxel grid (FrameConfig.voxel_size_m) when it is no
        coarser than small_gicp's own (RefineConfig.source_voxel_m), else every point. Its point budget then grids
        a ninth of the points: on 7-Scenes frames gridding all of them took 18 ms of a 100 ms frame."""
        if method == "small_gicp" and self.config.frame.voxel_size_m <= self.config.refine.source_voxel_m:
            return scan.down
        return scan.points

    def _budget(self, points: FramePoints, method: str) -> FramePoints:
        """The refinement's input: at its own resolution or, when that leaves more than MatchConfig.refine_points,
        at a coarser one that does not (a voxel grid, not a random sample: thin structure such as a door frame
        keeps its points). The others sample their own scales (down to 2 cm) and get the points as they are."""
        if method != "small_gicp":
            return points
        return voxel_budget(points, self.config.refine.source_voxel_m, self.config.match.refine_points)

    def _noise_weighed(self, points: FramePoints, method: str) -> FramePoints | None:
        """The refinement's input as `_budget`, each point's voxel grown with its depth noise (`points.noise_octaves`,
        RefineConfig.noise_reference_m): the input of a second refinement (`_fits_better` keeps the better), or None
        when fewer than NOISY_SHARE of the points are noisy enough to weigh less (the same input, near enough).
        The reference is absolute: measured against the noise of the frame's nearest points instead, the two walls
        `_refine_contender` tells of still pulled the weighed refinement 6 cm off; at 0.5 cm rather than 2, weighing
        alone cost real Kinect frames (depth to 4 m), whose far points hold the turn, a centimetre of median accuracy."""
        rc, fc = self.config.refine, self.config.frame
        if method != "small_gicp" or rc.noise_reference_m <= 0 or not len(points):
            return None
        sigma = axial_noise_sigma_m(points.xyz[:, 2], fc.axial_noise_a_m, fc.axial_noise_b_per_m, fc.axial_noise_z0_m)
        octaves = noise_octaves(sigma, rc.noise_reference_m)
        if np.count_nonzero(octaves) < NOISY_SHARE * len(points):
            return None
        return voxel_budget(points, rc.source_voxel_m, self.config.match.refine_points, octaves=octaves)

    def _refine_one(self, refine_map: RefineMap, points: FramePoints, T_start: np.ndarray, method: str):
        rc = self.config.refine
        return refine_map.refine(points, T_start, method=method, epsilon=rc.epsilon, source_voxel_m=rc.source_voxel_m,
                                 max_correspondence_m=rc.max_correspondence_m, max_iterations=rc.max_iterations,
                                 grid_max_iterations=rc.grid_max_iterations, wide_voxel_m=rc.wide_voxel_m)
