"""The localizer's stage values: the confidence formula, the stage timer, the synthetic scene's real Site, and
the stages run one by one giving what `localize` gives."""

from __future__ import annotations

import time

import numpy as np
import pytest

from cadreg.camera import CameraIntrinsics
from cadreg.config import LocalizeConfig, MatchConfig
from cadreg.errors import InvalidArgument, InvalidFrame
from cadreg.localize import Localizer
from cadreg.localize.stages import (PROGRESS_STAGES, Choice, StageTimer, answer_status, confidence,
                                   low_overlap_confidence, pose_std_m)
from cadreg.result import Status
from cadreg.localize.synthetic import look_pose, make_scene, render_frame
from cadreg.result import Diagnostics
from cadreg.site.bundle import Site

K = CameraIntrinsics(240, 180, 216.0, 216.0, 119.5, 89.5)


@pytest.fixture(scope="module")
def scene():
    return make_scene(5, n_objects=7)


def test_confidence_formula() -> None:
    # perfect fit, clear winner: whole confidence
    assert confidence(1.0, 0.0, 0.5, inlier_m=0.05, confident_margin=0.1) == 1.0
    # a tie halves it; half the confident margin gives three quarters
    assert confidence(1.0, 0.0, 0.0, inlier_m=0.05, confident_margin=0.1) == pytest.approx(0.5)
    assert confidence(1.0, 0.0, 0.05, inlier_m=0.05, confident_margin=0.1) == pytest.approx(0.75)
    # an RMSE of one inlier distance costs a factor e⁻¹; fitness scales linearly
    assert confidence(0.8, 0.05, 1.0, inlier_m=0.05, confident_margin=0.1) == pytest.approx(0.8 / np.e)
    assert 0.0 <= confidence(2.0, 0.0, 9.0, inlier_m=0.05, confident_margin=0.1) <= 1.0
    assert low_overlap_confidence(0.4) == pytest.approx(0.2)
    # a pose the geometry lets slide twice the allowed spread keeps half its confidence; within it, all
    assert confidence(1.0, 0.0, 0.5, inlier_m=0.05, confident_margin=0.1, pose_std=0.008,
                      max_pose_std=0.004) == pytest.approx(0.5)
    assert confidence(1.0, 0.0, 0.5, inlier_m=0.05, confident_margin=0.1, pose_std=0.002, max_pose_std=0.004) == 1.0


def test_a_pose_the_geometry_lets_slide_is_uncertain() -> None:
    """The largest translation standard deviation of the refined pose's covariance decides: a frame of one wall
    pins the pose along the wall's normal only."""
    cov = np.diag([1e-6, 1e-6, 1e-6, 0.001 ** 2, 0.013 ** 2, 0.0005 ** 2])
    R = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))[0]
    cov[3:, 3:] = R @ cov[3:, 3:] @ R.T  # in any axes
    assert pose_std_m(cov) == pytest.approx(0.013)
    assert pose_std_m(None) == 0.0
    rules = dict(min_fitness=0.5, ambiguity_margin=0.03, max_see_through=0.1, min_ok_confidence=0.5)
    # with a close rival: not ambiguous between two rooms, since the pose itself is not pinned
    assert answer_status(0.9, 0.0, True, 0.0, 0.8, **rules, pose_std=0.013, max_pose_std=0.004) == Status.UNCERTAIN
    assert answer_status(0.9, 0.0, True, 0.0, 0.8, **rules, pose_std=0.002, max_pose_std=0.004) == Status.AMBIGUOUS
    # alone, its confidence falls with the spread (the caller's slide probe tests the rest)
    trust = confidence(0.9, 0.0, 0.5, inlier_m=0.05, confident_margin=0.1, pose_std=0.013, max_pose_std=0.004)
    assert answer_status(0.9, 0.5, False, 0.0, trust, **rules, pose_std=0.013, max_pose_std=0.004) == Status.UNCERTAIN
    trust = confidence(0.9, 0.0, 0.5, inlier_m=0.05, confident_margin=0.1, pose_std=0.0045, max_pose_std=0.004)
    assert answer_status(0.9, 0.5, False, 0.0, trust, **rules, pose_std=0.0045, max_pose_std=0.004) == Status.OK
    assert answer_status(0.9, 0.5, False, 0.0, 0.8, **rules, pose_std=0.002, max_pose_std=0.004) == Status.OK


def test_a_pose_whose_depth_disagrees_with_the_map_is_uncertain() -> None:
    rules = dict(min_fitness=0.5, ambiguity_margin=0.03, max_see_through=0.1, min_ok_confidence=0.5,
                 min_depth_agreement=0.6)
    assert answer_status(0.9, 0.5, False, 0.0, 0.8, **rules, depth_agreement=0.42) == Status.UNCERTAIN
    assert answer_status(0.9, 0.0, True, 0.0, 0.8, **rules, depth_agreement=0.42) == Status.UNCERTAIN  # rival or not
    assert answer_status(0.9, 0.5, False, 0.0, 0.8, **rules, depth_agreement=0.9) == Status.OK
    assert answer_status(0.3, 0.5, False, 0.0, 0.8, **rules, depth_agreement=0.42) == Status.LOW_OVERLAP


def test_support_is_the_fitness_over_the_part_of_the_frame_the_map_covers() -> None:
    def choice(fitness: float, coverage: float) -> Choice:
        return Choice(None, None, 0.5, False, fitness, 0.015, np.zeros(3), 1000, coverage=coverage)

    assert choice(0.55, 0.6).support == pytest.approx(0.55 / 0.6)  # looks partly past the map: not held against it
    assert choice(0.55, 1.0).support == pytest.approx(0.55)  # the map covers all of it: the fitness itself
    assert choice(0.8, 0.7).support == 1.0  # inliers in cells the map's surface sample left empty: at most 1
    assert choice(0.55, 0.0).support == pytest.approx(0.55)  # nothing rendered to compare with: the fitness


def test_stage_timer_adds_up_and_reports_progress() -> None:
    stage_ms: dict[str, float] = {}
    calls: list[tuple[int, int]] = []
    timer = StageTimer(stage_ms, lambda done, total: calls.append((done, total)))
    with timer("points"):
        time.sleep(0.02)
    with timer("fallback"):  # timed, but no progress step of its own
        pass
    with timer("points"):
        time.sleep(0.01)
    assert stage_ms["points"] >= 30.0 and "fallback" in stage_ms
    assert calls == [(1, len(PROGRESS_STAGES)), (1, len(PROGRESS_STAGES))]
    with pytest.raises(RuntimeError):
        with timer("refine"):
            raise RuntimeError("a failing stage is still timed")
    assert "refine" in stage_ms


def test_synthetic_scene_is_a_real_site(scene, tmp_path) -> None:
    site = scene.site
    assert isinstance(site, Site) and len(site.version) == 12
    assert len(site.graph.nodes) == 7 and all(n.points > 0 for n in site.graph.nodes)
    # every object's points carry its instance and class
    for i, node in enumerate(site.graph.nodes):
        assert set(site.classes[c] for c in np.unique(site.map.class_index[site.map.instance == i])) == {node.cls}
    site.save(tmp_path / "s")
    again = Site.load(tmp_path / "s")
    assert again.version == site.version and len(again.map) == len(site.map)


def test_stages_one_by_one_match_localize(scene) -> None:
    loc = Localizer.from_site(scene.site)
    T = look_pose(np.array([2.5, 2.0, 1.5]), 0.6, np.radians(30))
    frame = render_frame(scene, T, intrinsics=K, depth_noise_m=0.0015)
    whole = loc.localize(frame)
    diag = Diagnostics()
    timer = StageTimer(diag.stage_ms)
    scan = loc._scan(frame, diag, timer)
    assert len(scan.score_xyz) == loc.config.frame.score_points and len(scan.fit_xyz) == loc.config.frame.fit_points
    hyp = loc._hypotheses(scan)
    assert 0 < len(hyp) <= loc.config.match.candidates
    candidates = loc._verify(scan, hyp, None, diag, timer)
    assert [c.score for c in candidates] == sorted((c.score for c in candidates), reverse=True)
    choice = loc._refine(scan, candidates, "small_gicp", diag)
    np.testing.assert_allclose(choice.outcome.T_map_camera, whole.T_map_camera)
    assert set(whole.diagnostics.stage_ms) >= {"points", "cluster", "gravity", "match", "verify", "refine"}


def test_top_k_default_and_request_checks(scene) -> None:
    loc = Localizer.from_site(scene.site, LocalizeConfig(match=MatchConfig(top_k=2)))
    T = look_pose(np.array([2.5, 2.0, 1.5]), 0.6, np.radians(30))
    frame = render_frame(scene, T, intrinsics=K)
    assert len(loc.localize(frame).hypotheses) == 2
    assert len(Localizer.from_site(scene.site).localize(frame).hypotheses) > 2  # the default, 5
    with pytest.raises(InvalidArgument, match="unknown refinement method"):
        loc.localize(frame, method="nope")
    with pytest.raises(ValueError):  # InvalidArgument is a ValueError too
        loc.localize(frame, method="nope")
    with pytest.raises(InvalidFrame):
        loc.localize("not a frame")  # type: ignore[arg-type]


def test_an_objects_share_of_the_view_counts_pixels_not_voxel_points() -> None:
    """Two square patches that cover the same pixels, one 0.5 m wide at 1 m and one 1.5 m wide at 3 m: the voxel
    grid keeps nine times the points of the far one, the view shows both alike."""
    from cadreg.localize.cluster import ScanCluster
    from cadreg.localize.points import FramePoints
    from cadreg.localize.stages import Scan

    def patch(width_m: float, depth_m: float) -> np.ndarray:
        g = np.arange(-width_m / 2, width_m / 2, 0.02)
        x, y = np.meshgrid(g, g)
        return np.stack([x.ravel(), y.ravel(), np.full(x.size, depth_m)], axis=1)

    near, far = patch(0.5, 1.0), patch(1.5, 3.0)
    xyz = np.vstack([near, far])
    down = FramePoints(xyz, np.zeros_like(xyz), np.full(len(xyz), -1))
    index = [np.arange(len(near)), len(near) + np.arange(len(far))]
    clusters = [ScanCluster(0, xyz[i].mean(axis=0), xyz[i].mean(axis=0), np.ptp(xyz[i], axis=0), i) for i in index]
    scan = Scan(down, down, np.zeros(len(xyz), dtype=np.int64), clusters, None, score_xyz=xyz, fit_xyz=xyz,
                fit_lab=np.zeros_like(xyz), fit_cls=np.zeros(len(xyz), dtype=np.int64), fit_rgb=np.zeros_like(xyz),
                check_xyz=xyz)
    assert len(far) > 8 * len(near)
    np.testing.assert_allclose(scan.view_shares, [0.5, 0.5], atol=0.01)
