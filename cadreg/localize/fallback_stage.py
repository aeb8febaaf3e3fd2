"""The fallbacks of the verify stage: what finds hypotheses when the graph's best is weak (no labels, no objects,
no match). The label-free search first (branch-and-bound over x, y, z and yaw on the site's grid pyramid,
`bbs.py`), over the client's search region, else the rooms of the graph's weak candidates, else the whole site;
FPFH + RANSAC (`fallback.py`) only where the frame gives no up direction, and in a building against one room.

`FallbackStage` is a part of `Localizer` (one of its base classes), kept in a module of its own: its methods read
the localizer's `config`, `field`, `maps` (`RegionMaps`), `up`, `region_floor_m`, `pyramid()`, `fpfh()` and
`_one_object_view_bar()`, and the hypotheses stage's `_region_candidates` and `_unverified_hypothesis`.
"""

from __future__ import annotations

import numpy as np

from ..geometry import make_Ts, rotation_between
from ..site.regions import CAMERA_MARGIN_M, Region
from .bbs import YawPlaces, all_yaws, frame_direction_histogram, polish, yaws_allowed
from .fallback import FpfhRansac
from .gravity import planar_normals
from .match import Hypotheses, distinct_pairs
from .score import score_poses
from .stages import NEAR_REACH_DEG, NEAR_REACH_M, Candidate, Scan

# A building's FPFH + RANSAC registers against one room's box grown by this (walls scanned a little outside it).
ROOM_MARGIN_M = 0.3
# Flat-surface normals sampled for the yaw candidates of the label-free search when the up estimate gave none.
YAW_NORMAL_POINTS = 1000
# The label-free search's leaves are polished (`bbs.polish`) twice, the second round only for those its first left
# within RegionConfig.tie_margin and this of the best: the second round's half steps raised a leaf's score by at
# most 0.12 (the 100-room frames without labels: 245 leaves a frame, 52 within 0.16 after the first round), and
# only leaves that end within the tie margin are ranked by room. 100 rooms without labels: median -3 %, p90 -8 %,
# every answer the same. One room takes the same cut (its five leaves; every answer the same on its sets too).
POLISH_LATER_GAIN = 0.14
# A frame whose best leaf has fewer than this share of its points near a map surface sees what the map lacks (a real
# frame beside a map fused from other frames): in a building its leaves' same-place alternates are verified too
# (`_same_place_alternates`). Real RedKitchen frames in a 3-room building: best leaf 0.67 / 0.79 (5th percentile,
# median); renders of the building sets 0.85-0.93 / 0.93-0.96 (robot height, 10 and 100 rooms, corridor, mixed: a
# tenth of the 100-room frames lie under it, and no answer of theirs changed).
SEES_PAST_THE_MAP_LEAF = 0.88
# A building's answer that shows the frame poorly along its rays, after a label-free search kept to the graph's
# candidate rooms, or cut at its node cap where that gave the rooms it covered less than THIN_SEARCH_SHARE of a
# one-room search's nodes each, has the search run again over the building with DEEPER_SEARCH_NODES times the nodes
# (`Localizer._deeper_look`). A search of a few rooms at about a room's nodes each is as thorough as a one-room
# site's, which searches no deeper: real RedKitchen frames in a 3-room building (1000 nodes a room), their poses
# where the fused kitchen lacks what they see, showed the frame 0.31-0.60 at the answers, and the deeper search
# found no better pose for any of them (median 83 -> 134 ms).
DEEPER_SEARCH_NODES = 4
THIN_SEARCH_SHARE = 0.5
# A building's regions whose main wall directions lie further apart than this face their own ways
# (`rooms_face_their_own_ways`): the spread of the yaws kept about each peak of the frame's directions
# (`bbs.yaws_allowed`).
OWN_DIRECTIONS_DEG = 6.0
# The source of the hypotheses of rooms the label-free search found tied with its best and did not verify.
BBS_UNVERIFIED = "fallback:bbs:unverified"


class FallbackStage:
    """The verify stage's fallbacks (a base class of `Localizer`; see the module's text)."""

    def _candidate_regions(self, candidates: list[Candidate]) -> list[Region]:
        """In a building, the regions of the graph's candidates (at most RegionConfig.max_verified, best first):
        where the label-free search looks when the graph found something but nothing strong (a search over the
        whole building costs as many rooms as it has). [] for a one-room site or when the graph found nothing."""
        if len(self.maps) == 1:
            return []
        rooms: list[Region] = []
        for c in sorted(candidates, key=lambda c: -c.score):
            region = self.maps.region_at(c.T_map_camera[:3, 3])
            if region not in rooms:
                rooms.append(region)
        return rooms[: self.config.regions.max_verified]

    def _fallback(self, name: str, scan: Scan, notes: list[str], rooms: list[Region]) -> Hypotheses | None:
        """Hypotheses of one fallback method, or None when it cannot run (the label-free search needs up) or
        found nothing the frame's up direction allows."""
        fb, floor = self.config.fallback, scan.floor
        if name == "bbs":
            return self._label_free(scan, notes, rooms)
        registrar = self._fpfh_in_reach(scan, rooms, notes)
        if registrar is None:
            return None
        T, _ = registrar.register(scan.down.xyz, max_points=fb.fpfh_max_points)
        if floor is not None:
            # FPFH + RANSAC knows nothing of gravity: on a bare wall it happily returns the camera upside down.
            tilt = np.degrees(np.arccos(np.clip((T[:3, :3] @ floor.up_camera) @ self.up, -1.0, 1.0)))
            if tilt > fb.max_up_disagreement_deg:
                notes.append(f"fallback fpfh-ransac refused: its pose tilts up by {tilt:.0f}° from the {floor.source}'s")
                return None
        hyp = Hypotheses.of_pose(T)
        hyp.geometric = score_poses(self.field, scan.score_xyz, hyp.R, hyp.t, tau_m=self.config.match.score_tau_m)
        return hyp

    def _fpfh_in_reach(self, scan: Scan, rooms: list[Region], notes: list[str]) -> FpfhRansac | None:
        """The FPFH + RANSAC registrar this frame may use: the whole map's in a one-room site; in a building the one
        of a single room (its region map, features computed on first use and kept with it): the room the client's
        search region names or centres on, else the graph's best candidate room. None, with a note, when neither
        exists: the whole building's features would cost seconds a room and a copy of the building per worker, for
        a pose a building could not trust anyway (any other room may repeat the view)."""
        if len(self.maps) == 1:
            return self.fpfh()
        room = None
        if scan.search is not None:
            named = scan.search.resolve(self.maps.regions)
            room = named[0] if len(named) == 1 else (self.maps.region_at(scan.search.center) if not named else None)
        elif rooms:
            room = rooms[0]
        if room is None:
            notes.append("fallback fpfh-ransac skipped: in a building it searches one room (name one in search_region)")
            return None
        index = self.maps.index(room)
        if index.fpfh is None:
            # The room's own box, not its refinement map: that holds a halo of the neighbours' points (3 m), and
            # their features and RANSAC over them took 18 s for one frame of a 100-room site.
            xyz = index.refine_map.xyz
            lo, hi = room.bounds[0] - ROOM_MARGIN_M, room.bounds[1] + ROOM_MARGIN_M
            index.fpfh = FpfhRansac(xyz[np.all((xyz >= lo) & (xyz <= hi), axis=1)],
                                    voxel_m=self.config.fallback.voxel_size_m)
        return index.fpfh

    def _label_free(self, scan: Scan, notes: list[str], rooms: list[Region], *,
                    deeper: bool = False, own_yaws: bool = False) -> Hypotheses | None:
        """The label-free search (bbs.py): level the frame by its up, pick the yaws its walls allow, branch and
        bound over (x, y, z, yaw) — over the client's search region, else over `rooms` (a building's candidate
        regions), else over the whole site; the distinct best leaves as hypotheses. None without an up direction.
        In a building a search stopped at its node cap with fewer than THIN_SEARCH_SHARE of a room's nodes a room
        sets `Scan.deeper_below` to RegionConfig.deeper_view_agreement, and one kept to the candidates' rooms to
        min_one_object_view_agreement: the graph's best fell short of its bar, so the rooms it names are a guess,
        and an answer found only there has no more to say for its room than one object would. `deeper` searches
        with DEEPER_SEARCH_NODES times the nodes (`Localizer._deeper_look`); `own_yaws` tries each region's own yaws
        that the site's leave out, instead of the site's (`_yaws`; None when there are none)."""
        lf, floor = self.config.label_free, scan.floor
        if not lf.enabled or floor is None:
            return None
        pyr, map_hist, region_hists = self.pyramid()
        R_up = rotation_between(floor.up_camera, np.array([0.0, 0.0, 1.0]))
        rng = np.random.default_rng(1)
        pick = rng.choice(len(scan.down), min(lf.points, len(scan.down)), replace=False)
        normals = floor.normals if floor.normals is not None else planar_normals(scan.down.xyz, max_points=YAW_NORMAL_POINTS)[1]
        yaws, places = self._yaws(frame_direction_histogram(normals @ R_up.T), map_hist,
                                  region_hists if own_yaws else None, pyr.R_level_map)
        if not len(yaws):
            return None
        labelled_floor = floor.source == "floor" and floor.height_m is not None
        points_level = scan.down.xyz[pick] @ R_up.T
        rc = self.config.regions
        found, thin = [], False
        for box, floor_m, covered in self._search_boxes(scan, pyr.R_level_map, rooms):
            # The budget grows with the rooms the box covers: their coarse levels tie (`bbs.highest`). A box of one
            # room (a candidate's, a region the client names) keeps a room's: at the building's minimum, the
            # graph's weak candidates' rooms searched one by one cost ten times the whole building (a 100-room
            # frame's 48 rooms: 3.3 M nodes, 430 ms); at a room's, every answer of the labelled building sets
            # (10, 16, 100 rooms, mixed; clean and with harsh label noise) stayed, means 3-11 % lower.
            max_nodes = lf.max_nodes if len(self.maps) == 1 or covered == 1 else max(
                rc.search_max_nodes, rc.search_nodes_per_region * covered)
            thin |= max_nodes < THIN_SEARCH_SHARE * lf.max_nodes * covered
            if deeper:
                max_nodes *= DEEPER_SEARCH_NODES
            z_range = None
            if labelled_floor and floor_m is not None:
                # A labelled floor gives the camera's height: only a band about it is searched.
                z_level = floor_m + floor.height_m  # heights along up are the level frame's z
                z_range = (z_level - 2 * lf.voxel_m, z_level + 2 * lf.voxel_m)
            found.append(pyr.search(points_level, yaws, z_range_level=z_range, box_level=box,
                                    keep_ratio=lf.keep_ratio, max_nodes=max_nodes, places=places))
        poses = np.concatenate([f[0] for f in found])
        scores = np.concatenate([f[1] for f in found])
        order = np.argsort(-scores, kind="stable")
        poses, scores = poses[order], scores[order]
        stats = found[0][2]
        for f in found[1:]:
            stats.nodes += f[2].nodes
            stats.capped |= f[2].capped
            stats.best = max(stats.best, f[2].best)
        if len(self.maps) > 1 and not deeper:
            kept_to_rooms = bool(rooms) and scan.search is None
            scan.search_cut = stats.capped and thin and not kept_to_rooms
            scan.deeper_below = max(rc.deeper_view_agreement if stats.capped and thin else 0.0,
                                    self._one_object_view_bar() if kept_to_rooms else 0.0)
        mc = self.config.match
        # In a building the same view may fit in many rooms: more distinct leaves are kept (a room's own leaves
        # would otherwise crowd its twins out), then ranked by room.
        count = lf.candidates if len(self.maps) == 1 else lf.candidates * (1 + self.config.regions.max_verified)
        reserve = lf.reserve if len(self.maps) == 1 else 0
        hyp = pyr.hypotheses(poses, scores, R_up, count=count + reserve, min_translation_m=mc.distinct_translation_m,
                             min_rotation_deg=mc.distinct_rotation_deg, extra=lf.exact_leaves,
                             exact=lambda R, t: score_poses(self.field, scan.score_xyz, R, t, tau_m=mc.score_tau_m))
        if reserve:
            # The leaves after the first `count` are kept for the second look (`Localizer._second_look`): the
            # choice is greedy in score order, so the first `count` are those a search of `count` gives.
            scan.reserve = hyp.take(np.arange(min(count, len(hyp)), len(hyp)))
            hyp = hyp.take(np.arange(min(count, len(hyp))))
        hyp = polish(self.field, scan.score_xyz, hyp, self.up, step_m=lf.voxel_m / 2, step_deg=lf.yaw_step_deg / 2,
                     later_within=self.config.regions.tie_margin + POLISH_LATER_GAIN)
        if len(self.maps) > 1 and len(hyp):
            keep, unverified = self._region_candidates(hyp, hyp.geometric, self.maps.indices_at(hyp.t),
                                                       count=lf.candidates)
            scan.unverified += [self._unverified_hypothesis(hyp, i, BBS_UNVERIFIED) for i in unverified]
            if stats.best < SEES_PAST_THE_MAP_LEAF:
                keep += self._same_place_alternates(hyp, keep)
            hyp = hyp.take(np.array(keep, dtype=np.int64))
        notes.append(f"label-free search: {len(yaws)} yaws, {stats.nodes} nodes, best leaf {stats.best:.2f}"
                     + (" (node cap reached)" if stats.capped else ""))
        return hyp if len(hyp) else None

    def rooms_face_their_own_ways(self) -> bool:
        """In a building, whether its regions' main wall directions (each one's histogram's peak, modulo a quarter
        turn) lie further apart than OWN_DIRECTIONS_DEG: rooms turned by odd angles. Then the deeper search tries
        each region's own yaws too (`_yaws`). The quarter-turned benchmark's rooms and corridors peak 4° apart (the
        scan's walls are not quite square to its frame), and the yaws the site's directions allow hold theirs."""
        hists = [h for h in (self.pyramid()[2] or []) if h is not None]
        if len(hists) < 2:
            return False
        quarter = len(hists[0]) // 2
        peaks = np.array([int(np.argmax(h)) % quarter for h in hists])
        apart = np.abs(peaks[:, None] - peaks[None, :])
        apart = np.minimum(apart, quarter - apart) * (180.0 / len(hists[0]))
        return bool(apart.max() > OWN_DIRECTIONS_DEG)

    def _yaws(self, frame_hist: np.ndarray | None, map_hist: np.ndarray | None,
              region_hists: list[np.ndarray | None] | None,
              R_level_map: np.ndarray) -> tuple[np.ndarray, YawPlaces | None]:
        """The yaws the label-free search tries, and where it tries each (None: everywhere).

        Without `region_hists`: the yaws the site's wall directions allow for the frame's, everywhere. With them
        (the deeper look's second search in a building whose rooms face their own ways, `Localizer._deeper_look`):
        each region's own yaws that the site's leave out, from the roots whose cube meets its box. A building's
        directions are the mean of its kinds of region's, and a corridor's one axis rules that mean: in a 30-room
        building on three storeys whose rooms are turned by odd angles, the yaws it allowed held none within 21°
        of the true one for 11 of the 19 unique views the search lost without labels; each view's own room's held
        it for 98.6 % of the views. But a room may face so many directions (scene0470's: low walls, chairs, a round
        table) that it allows most yaws (86-90 of 120): a first search trying every room's own lost views it had
        found (the coarse levels' ties cut their branches at the node cap) and answered four in other rooms, `ok`
        (`docs/buildings-history.md`, thirty-second session). Only a weak answer's deeper look tries them, beside
        the site's."""
        step = self.config.label_free.yaw_step_deg
        whole = yaws_allowed(frame_hist, map_hist, step_deg=step)
        if region_hists is None:
            return all_yaws(step)[whole], None
        allowed = np.array([np.zeros_like(whole) if h is None else yaws_allowed(frame_hist, h, step_deg=step) & ~whole
                            for h in region_hists])
        tried = allowed.any(axis=0)
        boxes = [_level_box(r.bounds[0], r.bounds[1], R_level_map) for r in self.maps.regions]
        return all_yaws(step)[tried], YawPlaces(np.array(boxes), allowed[:, tried])

    def _same_place_alternates(self, hyp: Hypotheses, keep: list[int]) -> list[int]:
        """For each kept leaf (indices into the polished leaves `hyp`), the best other leaf at its place: within the
        distinct-pose radius of it, beyond the refinement's reach (NEAR_REACH_M, NEAR_REACH_DEG). Polishing brings
        leaves of one place together, and the region ranking keeps the one that fits the field best; a real
        frame's points on surfaces the map lacks pull that fit toward a pose turned onto the mapped part, which the
        verify stage, pulling each leaf in from its own cell's reach only, cannot bring back (real RedKitchen frames
        in a 3-room building: leaves 3-6 cm from the kitchen alone's answer dropped for ones 20-28 cm off). Both are
        verified, and `Localizer._one_per_place` chooses between them by the depth along the frame's rays."""
        if not keep or len(hyp) <= len(keep):
            return []
        mc = self.config.match
        T = make_Ts(hyp.R, hyp.t)
        kept = np.array(keep, dtype=np.int64)
        rest = np.setdiff1d(np.arange(len(hyp)), kept)
        beyond_reach = distinct_pairs(T[rest], T[kept], min_translation_m=NEAR_REACH_M, min_rotation_deg=NEAR_REACH_DEG)
        elsewhere = distinct_pairs(T[rest], T[kept], min_translation_m=mc.distinct_translation_m,
                                   min_rotation_deg=mc.distinct_rotation_deg)
        out: list[int] = []
        for j in range(len(kept)):
            here = rest[beyond_reach[:, j] & ~elsewhere[:, j]]
            if len(here):
                best = int(here[np.argmax(hyp.geometric[here])])
                if best not in out:
                    out.append(best)
        return out

    def _leaves_in_the_frames_colours(self, scan: Scan) -> Hypotheses | None:
        """The label-free search's reserve leaves (`Scan.reserve`) at which the frame's colours follow the map's
        (`Localizer._chroma_at` not `_chroma_rules_out`: measured at a leaf, up to half a cell and a yaw step off, a
        right pose's chroma is lower than refined, and at the doubt's bar the true corner of a view at a robot's
        height was left out; a leaf where the map's colours are too flat to tell is left out: a frame in colour was
        doubted for colours the map's did not follow, and one grey where the map is coloured has its true place, if
        grey, left out too, and its answer then stays doubted), polished as the first leaves were; None when none is.
        The reserve is spent."""
        reserve, scan.reserve = scan.reserve, None
        if reserve is None or not len(reserve):
            return None
        lf = self.config.label_free
        chroma = [self._chroma_at(scan, reserve.T(i), scan.center_camera) for i in range(len(reserve))]
        keep = np.array([c is not None and not self._chroma_rules_out(c) for c in chroma])
        if not keep.any():
            return None
        return polish(self.field, scan.score_xyz, reserve.take(np.flatnonzero(keep)), self.up, step_m=lf.voxel_m / 2,
                      step_deg=lf.yaw_step_deg / 2)

    def _search_boxes(self, scan: Scan, R_level_map: np.ndarray,
                      rooms: list[Region]) -> list[tuple[np.ndarray | None, float | None, int]]:
        """(box, floor, regions) of each part of the site the label-free search covers: the box (level frame,
        (2, 3) corners) of camera positions, or None for the whole site; the floor height along up under it, None
        where the regions under it do not share one; and how many regions' boxes it meets. One per region the client
        named, or the client's ball; without a search region one per room of `rooms`, or the whole site when there
        are none."""
        if scan.search is None and not rooms:
            return [(None, self._shared_floor(self.maps.regions), len(self.maps))]
        if scan.search is None or scan.search.region_ids:
            chosen = rooms if scan.search is None else scan.search.resolve(self.maps.regions)
            boxes = [(np.stack([r.bounds[0] - CAMERA_MARGIN_M, r.bounds[1] + CAMERA_MARGIN_M]), self._shared_floor([r]), 1)
                     for r in chosen]
        else:
            lo, hi = scan.search.center - scan.search.radius_m, scan.search.center + scan.search.radius_m
            met = sum(bool(np.all(r.bounds[0][:2] <= hi[:2]) and np.all(lo[:2] <= r.bounds[1][:2]))
                      for r in self.maps.regions)
            boxes = [(np.stack([lo, hi]), self._shared_floor(self.maps.regions), max(met, 1))]
        return [(_level_box(lo, hi, R_level_map), floor_m, covered) for (lo, hi), floor_m, covered in boxes]

    def _shared_floor(self, regions: list[Region]) -> float | None:
        """The floor height along up those regions share (within the label-free search's voxel), else None."""
        floors = np.array([self.region_floor_m[r.id] for r in regions])
        return float(np.median(floors)) if np.ptp(floors) <= self.config.label_free.voxel_m else None


def _level_box(lo: np.ndarray, hi: np.ndarray, R_level_map: np.ndarray) -> np.ndarray:
    """(2, 3) min and max corners, level frame, of the box of the map-frame box [lo, hi] turned into it."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    level = corners @ R_level_map.T
    return np.stack([level.min(axis=0), level.max(axis=0)])
