"""The localizer end to end: known poses recovered on seeded synthetic scenes and on renders of the real
scene0470 mesh; fallback when labels are missing; failures reported by status; bad frames raise InvalidFrame."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from cadreg.camera import CameraIntrinsics
from cadreg.config import FallbackConfig, LabelFreeConfig, LocalizeConfig, MatchConfig, RefineConfig
from cadreg.errors import InvalidFrame
from cadreg.frame import Frame
from cadreg.geometry import R_to_quat_wxyz, make_T, pose_errors, quat_wxyz_to_R
from cadreg.localize import Localizer
from cadreg.localize.picture import render_localization_png
from cadreg.localize.synthetic import look_pose, make_scene, render_frame
from cadreg.result import Status

K = CameraIntrinsics(240, 180, 216.0, 216.0, 119.5, 89.5)


@pytest.fixture(scope="module")
def scene():
    return make_scene(11, n_objects=8)


@pytest.fixture(scope="module")
def localizer(scene):
    return Localizer.from_site(scene.site)


def _views(scene, n: int, seed: int, min_objects: int = 2):
    """Poses inside the room seeing at least `min_objects` labelled objects (counted on the rendered labels)."""
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        T = look_pose(np.array([rng.uniform(0.8, 4.2), rng.uniform(0.8, 3.2), rng.uniform(1.2, 1.75)]),
                      rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(15, 45)))
        f = render_frame(scene, T, intrinsics=K, depth_noise_m=0.0015, seed=len(out))
        seen = {int(v) for v in np.unique(f.labels) if v not in (0, 1, 2)}
        if (f.depth > 0).mean() > 0.8 and len(seen) >= 1 and _objects_seen(scene, f) >= min_objects:
            out.append((f, T))
    return out


def _objects_seen(scene, f) -> int:
    from cadreg.localize.cluster import cluster_objects
    from cadreg.localize.points import frame_to_points, voxel_downsample

    p = voxel_downsample(frame_to_points(f), 0.03)
    cls = scene.site.classes_for_labels("nyu40", np.maximum(p.labels, 0))
    return len(cluster_objects(p.xyz, cls, tolerance_m=0.07, min_points=25))


def test_known_poses_are_recovered(scene, localizer) -> None:
    # The box room is harder than a real room: large bare planes give GICP local minima (one of these four
    # views ends 10 cm off, flagged ambiguous or uncertain, its pose then first among the hypotheses), so three
    # of four must be exact.
    exact = 0
    for f, T in _views(scene, 4, seed=1):
        r = localizer.localize(f)
        assert r.status in (Status.OK, Status.AMBIGUOUS, Status.UNCERTAIN), r.diagnostics.notes
        T_est = r.T_map_camera if r.status != Status.UNCERTAIN else r.hypotheses[0].T_map_camera
        te, re_ = pose_errors(T_est, T)
        assert r.status != Status.OK or te < 0.05
        exact += te < 0.02 and re_ < 1.0
        assert te < 0.2 and re_ < 10.0, (te, re_, r.diagnostics.method)
        if r.status == Status.UNCERTAIN:
            continue  # not claimed: no covariance, and whichever hypothesis it was
        assert 0.0 < r.confidence <= 1.0 and r.covariance.shape == (6, 6)
        d = r.diagnostics
        assert d.method == "cadreg" and len(d.scan_objects) >= 2 and d.matches
        assert set(d.stage_ms) >= {"points", "cluster", "gravity", "match", "verify", "refine"}
        assert d.refinement.fitness > 0.9 and d.roi.radius_m == 3.0 and d.roi.points > 0
        assert 100 <= d.roi.frame_points <= d.frame_points
        wire = json.loads(json.dumps(r.to_dict()))  # JSON-able
        q = np.array(wire["pose"]["quaternion_wxyz"])  # the answer's rotation, w >= 0 of q and -q
        assert q[0] >= 0.0 and np.allclose(quat_wxyz_to_R(q), r.T_map_camera[:3, :3], atol=1e-9)
    assert exact >= 3


def test_an_answers_quaternion_is_the_one_with_w_not_negative() -> None:
    # turns about z past a half turn, where the quaternion's w would come out negative, and some tilted ones
    rng = np.random.default_rng(0)
    turns = [make_T(np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]), np.zeros(3))[:3, :3]
             for a in np.radians([200.0, 270.0, 359.0])]
    for R in turns + [quat_wxyz_to_R(q) for q in rng.normal(size=(20, 4))]:
        q = R_to_quat_wxyz(R)
        assert q[0] >= 0.0 and np.isclose(np.linalg.norm(q), 1.0) and np.allclose(quat_wxyz_to_R(q), R, atol=1e-12)


def test_the_region_of_interest_bounds_the_refinement(scene) -> None:
    (f, T), = _views(scene, 1, seed=3)
    narrow = Localizer.from_site(scene.site, LocalizeConfig(refine=RefineConfig(roi_radius_m=0.6)))
    r = narrow.localize(f)
    d = r.diagnostics
    assert d.roi.radius_m == 0.6 and 100 <= d.roi.frame_points < 0.9 * d.frame_points
    # the map side: only map points within γ of the centre count, far fewer than in the whole room
    assert 0 < d.roi.points < len(scene.site.map.points) / 4
    te, re_ = pose_errors(r.T_map_camera, T)
    assert te < 0.05 and re_ < 2.0


def test_without_labels_the_fallback_answers(scene, localizer) -> None:
    (f, T), = _views(scene, 1, seed=5, min_objects=3)
    r = localizer.localize(replace(f, labels=None))
    assert r.diagnostics.method.startswith("fallback:") and not r.diagnostics.scan_objects
    assert r.diagnostics.method == "fallback:bbs"  # the label-free search (bbs.py)
    te, re_ = pose_errors(r.T_map_camera, T)
    assert te < 0.02 and re_ < 1.0


def test_a_frame_without_labels_is_not_scored_against_the_maps_classes(scene, localizer) -> None:
    """The candidates' label agreement (`RefineMap.agreement`): a frame without labels says nothing of classes, so
    its true pose scores as well as the labelled frame's does (which loses a little at the objects' borders);
    counted as points of no class, the frame's points on the map's objects halved it, and poses that laid them on
    walls ranked first."""
    from cadreg.localize.stages import StageTimer
    from cadreg.result import Diagnostics

    (f, T), = _views(scene, 1, seed=5, min_objects=3)
    diag = Diagnostics()
    bare = localizer._scan(replace(f, labels=None), diag, StageTimer(diag.stage_ms))
    labelled = localizer._scan(f, diag, StageTimer(diag.stage_ms))
    assert bare.fit_cls is None and (labelled.fit_cls >= 0).any()
    score = localizer._agreement_score(T, labelled)
    assert score > 0.8 and localizer._agreement_score(T, bare) >= score


def test_refinement_methods_and_top_k(scene, localizer) -> None:
    (f, T), = _views(scene, 1, seed=9)
    for method in ("small_gicp", "color_gicp"):
        r = localizer.localize(f, method=method, top_k=2)
        assert r.diagnostics.refinement.method == method
        assert len(r.hypotheses) <= 2
        te, re_ = pose_errors(r.T_map_camera, T)
        assert te < 0.02 and re_ < 1.0, (method, te, re_)
    with pytest.raises(ValueError):
        localizer.localize(f, method="nope")


def test_pose_prior_is_used_as_a_hypothesis(scene, localizer) -> None:
    (f, T), = _views(scene, 1, seed=5, min_objects=3)
    near = T.copy()
    near[:3, 3] += [0.05, -0.04, 0.02]
    r = localizer.localize(replace(f, labels=None, T_map_camera_prior=near))
    assert r.diagnostics.method == "prior"
    te, re_ = pose_errors(r.T_map_camera, T)
    assert te < 0.02 and re_ < 1.0


def test_frame_of_another_place_is_not_ok(localizer) -> None:
    other = make_scene(99, size_m=(9.0, 7.0, 3.0), n_objects=3)
    T = look_pose(np.array([1.0, 1.0, 1.5]), 0.7, np.radians(30.0))
    f = render_frame(other, T, intrinsics=K)
    r = localizer.localize(f)
    if r.status in (Status.OK, Status.AMBIGUOUS):
        # whatever pose came back must not claim a near-perfect overlap
        assert r.diagnostics.refinement.fitness < 0.95
    else:
        assert r.T_map_camera is None


def test_invalid_frames_raise(localizer) -> None:
    with pytest.raises(InvalidFrame):
        localizer.localize("not a frame")  # type: ignore[arg-type]
    far = Frame(depth=np.full((180, 240), 9000, np.uint16), color=np.zeros((180, 240, 3), np.uint8),
                depth_intrinsics=K, color_intrinsics=K)
    with pytest.raises(InvalidFrame):
        localizer.localize(far)  # every depth beyond max_depth_m


def test_unknown_label_set_is_refused_naming_the_known_ones(scene, localizer) -> None:
    (f, T), = _views(scene, 1, seed=3)
    with pytest.raises(InvalidFrame, match=r"no label map 'ade20k'; known label sets: \['nyu40'\]"):
        localizer.localize(replace(f, label_set="ade20k"))
    # a frame without labels names no label set worth checking: its label_set is not looked up
    assert localizer.localize(replace(f, labels=None, label_set="ade20k")).T_map_camera is not None


def test_real_scene0470_renders(scene0470_site_dir, scene0470_dir, tmp_path) -> None:
    """Real map, real labels, real CAD: frames rendered from the real mesh are localized to < 2 cm / 1°."""
    from cadreg.io.frames import RecordedFrames
    from cadreg.render.mesh import LabelledMesh
    from cadreg.render.sequence import render_frames
    from cadreg.site.bundle import Site

    site = Site.load(scene0470_site_dir)
    mesh = LabelledMesh.from_ply(scene0470_dir / "scene0470_00_vh_clean_2.ply",
                                 scene0470_dir / "scene0470_00_vh_clean_2.labels.ply")
    render_frames(mesh, tmp_path / "frames", 5, seed=123)
    frames = RecordedFrames.open(tmp_path / "frames")
    loc = Localizer.from_site(site)
    ok = 0
    for i in frames.indices:
        f, T = frames.load(i)
        r = loc.localize(f)
        if r.T_map_camera is not None:
            te, re_ = pose_errors(r.T_map_camera, T)
            ok += te < 0.02 and re_ < 1.0
    assert ok >= 4
    png = render_localization_png(site, f, r, T_true=T)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_pose_whose_depth_disagrees_with_the_map_is_not_ok(scene0470_site_dir, scene0470_dir, tmp_path) -> None:
    """Frame 25 of `cadreg render --seed 7` without its labels: the search's best pose is more than a metre off, yet
    most of the frame lies near some surface of the map there (fitness 0.79-0.86). Along the rays the map's
    surfaces lie elsewhere: measured depth and map agree in 38-63 % of the cells they share, where every right pose
    on 7-Scenes and the scene0470 renders agreed in 78 % or more. (Which wrong pose the search ends on differs
    between installs of the same pinned requirements: on 2 December's it was 2.97 m off and nothing but this gate
    kept it from `ok`; on 3 December's the frame also sees through the map there.)"""
    from cadreg.io.frames import RecordedFrames
    from cadreg.localize.points import frame_to_points, voxel_downsample
    from cadreg.localize.score import ViewCheck
    from cadreg.render.mesh import LabelledMesh
    from cadreg.render.sequence import render_frames
    from cadreg.site.bundle import Site

    site = Site.load(scene0470_site_dir)
    mesh = LabelledMesh.from_ply(scene0470_dir / "scene0470_00_vh_clean_2.ply",
                                 scene0470_dir / "scene0470_00_vh_clean_2.labels.ply")
    render_frames(mesh, tmp_path / "frames", 26, seed=7)
    frame, T_true = RecordedFrames.open(tmp_path / "frames").load(25)
    frame = replace(frame, labels=None)
    # That pose's colours are not the map's either, and the second look now finds the right one (an `ok` answer
    # 1 mm off), as do the search's leaves the exact field ranks first, verified at once when no reserve is kept;
    # without both, the depth gate holds the wrong one back.
    r = Localizer.from_site(site).localize(frame)
    assert r.status == Status.OK and pose_errors(r.T_map_camera, T_true)[0] < 0.05, r.diagnostics.notes
    first = Localizer.from_site(site, LocalizeConfig(label_free=LabelFreeConfig(reserve=0))).localize(frame)
    assert first.status == Status.OK and pose_errors(first.T_map_camera, T_true)[0] < 0.05, first.diagnostics.notes
    loc = Localizer.from_site(site, LocalizeConfig(label_free=LabelFreeConfig(reserve=0, exact_leaves=0)))
    r = loc.localize(frame)
    assert r.status == Status.UNCERTAIN and r.T_map_camera is None
    T_wrong = r.hypotheses[0].T_map_camera
    assert pose_errors(T_wrong, T_true)[0] > 1.0  # the pose it did not claim is wrong
    assert any("depth agreement" in n for n in r.diagnostics.notes if n.startswith("uncertain"))
    # The gate tells that pose from the true one on this frame.
    K = frame.depth_intrinsics
    zbuf = ViewCheck.zbuffer(voxel_downsample(frame_to_points(frame), 0.03).xyz, K)
    gate = loc.config.match.min_depth_agreement
    assert loc.view_check.depth_agreement(T_wrong, zbuf, K) < gate <= loc.view_check.depth_agreement(T_true, zbuf, K)


def test_an_answer_taken_after_every_better_pose_saw_through_the_map_agrees_on_its_own(
        scene0470_site_dir, scene0470_dir, tmp_path) -> None:
    """The 32nd render of seed 7: the poses the graph ranked first saw through the map once refined, the next one
    that did not was answered `ok` 0.86 m and 34 degrees off with a margin of 0.52 over their scores of 0 (depth
    agreement 0.79). Taken so, an answer must agree with the map's depth on its own
    (MatchConfig.min_depth_agreement_passed_over)."""
    from cadreg.io.frames import RecordedFrames
    from cadreg.render.mesh import LabelledMesh
    from cadreg.render.sequence import render_frames
    from cadreg.site.bundle import Site

    site = Site.load(scene0470_site_dir)
    mesh = LabelledMesh.from_ply(scene0470_dir / "scene0470_00_vh_clean_2.ply",
                                 scene0470_dir / "scene0470_00_vh_clean_2.labels.ply")
    render_frames(mesh, tmp_path / "frames", 32, seed=7)
    frame, T_true = RecordedFrames.open(tmp_path / "frames").load(31)
    r = Localizer.from_site(site).localize(frame)
    assert any("saw through the map: took the next" in n for n in r.diagnostics.notes)
    assert r.status == Status.UNCERTAIN and r.T_map_camera is None
    assert pose_errors(r.hypotheses[0].T_map_camera, T_true)[0] > 0.5  # the pose it did not claim is wrong
    # Without the gate it is claimed (the colour gate off as well: the frame's chroma correlates 0.12 with the
    # map's there, and that holds it back on its own).
    loose = LocalizeConfig(match=MatchConfig(min_depth_agreement_passed_over=0.0, min_chroma_correlation=-1.0))
    assert Localizer.from_site(site, loose).localize(frame).status == Status.OK


def test_warm_builds_the_fallback_features_up_front(scene) -> None:
    loc = Localizer.from_site(scene.site)
    assert loc._fpfh is None  # built on first use ...
    assert loc.warm() is loc and loc._fpfh is not None  # ... or up front, as the service's workers do
    off = Localizer.from_site(scene.site, LocalizeConfig(fallback=FallbackConfig(enabled=False))).warm()
    assert off._fpfh is None


def test_config_is_validated() -> None:
    with pytest.raises(Exception):
        LocalizeConfig(refine=RefineConfig(method="bogus"))  # type: ignore[arg-type]


@pytest.mark.parametrize("tilt_deg", [0.0, 30.0])
def test_a_bare_wall_is_never_answered_ok(scene0470_site_dir, tilt_deg: float) -> None:
    """Issue 14, item 5: a frame of one flat textureless wall (plausible camera, no labels) fits anywhere along any
    wall of the map; it was answered `ok` with confidence 0.64. Whatever pose comes back, it is not claimed."""
    from cadreg.site.bundle import Site

    cam = CameraIntrinsics(640, 480, 577.87, 577.87, 319.5, 239.5)
    v, u = np.mgrid[0:480, 0:640].astype(np.float64)
    # a plane 1.5 m in front of the camera, turned by tilt_deg about the camera's vertical axis
    slope = np.tan(np.radians(tilt_deg)) * (u - cam.cx) / cam.fx
    depth_m = 1.5 / np.maximum(1.0 + slope, 0.2)
    depth = np.where(depth_m < 4.0, depth_m * 1000.0, 0).astype(np.uint16)
    rng = np.random.default_rng(0)
    color = np.clip(200 + rng.normal(0, 2, (480, 640, 3)), 0, 255).astype(np.uint8)
    frame = Frame(depth=depth, color=color, depth_intrinsics=cam, color_intrinsics=cam)
    result = Localizer.from_site(Site.load(scene0470_site_dir)).localize(frame)
    assert result.status != Status.OK, (result.status, result.confidence)


def test_a_close_view_of_a_door_without_the_floor_is_not_pinned_by_the_door(scene0470_site_dir, scene0470_dir,
                                                                           tmp_path) -> None:
    """A robot's camera 0.75 m up, 0.6 m from scene0470's door and looking at it: the door and a strip of the wall
    beside it fill the frame, flush, and no floor is seen. The graph matched the door, whose visible part's centroid
    lies lower than the whole door's, and the refinement, free to slide up and down the wall, left the camera 9 cm
    too low: answered `ok`, confidence 0.95. Without the floor the door does not pin the camera's height: the slide
    probe tests the pose, and it is not claimed."""
    from conftest import scene0470_mesh

    from cadreg.io.frames import RecordedFrames
    from cadreg.render.sequence import render_frames
    from cadreg.site.bundle import Site

    T_door = np.array([[0.586541310172, 0.065209200776, 0.807289942707, 2.857502905138],
                       [-0.809816309107, 0.031322157615, 0.585846795628, 2.223546095393],
                       [0.012916538494, -0.997379908849, 0.071179213657, 0.750674864960],
                       [0.0, 0.0, 0.0, 1.0]])
    render_frames(scene0470_mesh(scene0470_dir), tmp_path / "frames", 1, seed=5, poses=[T_door])
    frame, T_true = RecordedFrames.open(tmp_path / "frames").load(0)
    assert frame.labels is not None and set(np.unique(frame.labels)) <= {1, 8}  # wall and door only
    r = Localizer.from_site(Site.load(scene0470_site_dir)).localize(frame)
    assert not any(n.startswith("up from floor") for n in r.diagnostics.notes)
    if r.status == Status.OK:  # claimed only where it is right
        assert pose_errors(r.T_map_camera, T_true)[0] < 0.05, r.diagnostics.notes
    else:
        assert r.status == Status.UNCERTAIN and any("fits as well" in n for n in r.diagnostics.notes)


def _chroma_reversed(frame: Frame) -> Frame:
    """The frame with every colour's chroma turned to its opposite about its own grey (orange becomes blue, white
    stays white): the same shapes, the colours of another place."""
    rgb = frame.color.astype(np.float64)
    grey = rgb.mean(axis=2, keepdims=True)
    return replace(frame, color=np.clip(np.rint(2 * grey - rgb), 0, 255).astype(np.uint8))


def _door_view(scene0470_dir, tmp_path) -> tuple[Frame, np.ndarray]:
    """Frame 6 of `cadreg render --seed 7` (the orange door, the whiteboard, the floor), without its labels, and its
    true pose."""
    from conftest import scene0470_mesh

    from cadreg.io.frames import RecordedFrames
    from cadreg.render.sequence import render_frames

    T_view = np.array([[0.151856002985, -0.444472487241, 0.882827255154, 0.705756650069],
                       [-0.985587089875, -0.000724100586, 0.169167266192, 1.699125599499],
                       [-0.074550939831, -0.895792210149, -0.43817630425, 1.697019826155],
                       [0.0, 0.0, 0.0, 1.0]])
    render_frames(scene0470_mesh(scene0470_dir), tmp_path / "frames", 1, seed=7, poses=[T_view])
    frame, T_true = RecordedFrames.open(tmp_path / "frames").load(0)
    return replace(frame, labels=None), T_true


def _not_claimed_for_its_colours(r, T_true: np.ndarray) -> None:
    """The right pose, `uncertain` because the frame's colours are not the map's there."""
    assert r.status == Status.UNCERTAIN and r.T_map_camera is None, r.diagnostics.notes
    assert pose_errors(r.hypotheses[0].T_map_camera, T_true)[0] < 0.05  # the same pose, not claimed
    assert any(n.startswith("uncertain") and "colours are not the map's" in n for n in r.diagnostics.notes)


def test_a_pose_whose_colours_are_not_the_maps_is_not_ok(scene0470_site_dir, scene0470_dir, tmp_path) -> None:
    """Frame 6 of `cadreg render --seed 7` without its labels (the door, the whiteboard, the floor): answered `ok`
    and right. The same depth with each colour's chroma reversed is the same shape in other colours, as a view of
    another place of that shape would be: along a* and b* the frame's colours now run against the map's (the
    correlation turns negative), and the pose, however well it fits, is not claimed."""
    from cadreg.site.bundle import Site

    frame, T_true = _door_view(scene0470_dir, tmp_path)
    loc = Localizer.from_site(Site.load(scene0470_site_dir))
    r = loc.localize(frame)
    assert r.status == Status.OK and pose_errors(r.T_map_camera, T_true)[0] < 0.05
    correlation = [n for n in r.diagnostics.notes if n.startswith("colour: ")]
    assert correlation and float(correlation[0].split("correlates ")[1].split()[0]) > 0.5
    r = loc.localize(_chroma_reversed(frame))
    _not_claimed_for_its_colours(r, T_true)


def test_a_colour_cameras_grey_view_where_the_map_is_coloured_is_not_ok(scene0470_site_dir, scene0470_dir,
                                                                         tmp_path) -> None:
    """Frame 6 of `cadreg render --seed 7` (the orange door, the whiteboard, the floor) without its labels, its
    colours turned grey: with a colour camera's chroma noise left in them, it is a view of a grey place of that shape,
    and where the map has the orange door the colours do not follow the map's (a render of Replica office0 was
    answered `ok` so in the 7-Scenes kitchen, 3.3 m off, confidence 0.90). Without any colour at all (a client
    without a colour camera) the picture says nothing, and the pose is claimed on its shape as before."""
    from cadreg.site.bundle import Site

    frame, T_true = _door_view(scene0470_dir, tmp_path)
    grey = np.repeat(frame.color.astype(np.float64).mean(axis=2, keepdims=True), 3, axis=2)
    colourless = replace(frame, color=np.rint(grey).astype(np.uint8))
    # The sensor's chroma noise: patches of a few pixels, each channel off by about a level.
    rng = np.random.default_rng(0)
    h, w = grey.shape[:2]
    patches = rng.normal(0, 1.2, ((h + 7) // 8, (w + 7) // 8, 3)).repeat(8, axis=0).repeat(8, axis=1)[:h, :w]
    noisy = replace(colourless, color=np.clip(np.rint(grey + patches), 0, 255).astype(np.uint8))
    loc = Localizer.from_site(Site.load(scene0470_site_dir))
    r = loc.localize(colourless)
    assert r.status == Status.OK and pose_errors(r.T_map_camera, T_true)[0] < 0.05, r.diagnostics.notes
    assert not any(n.startswith("colour: ") for n in r.diagnostics.notes)  # nothing to compare
    r = loc.localize(noisy)
    _not_claimed_for_its_colours(r, T_true)


def _found_by_the_second_look(scene0470_dir, scene0470_site_dir, tmp_path, T_map_camera: np.ndarray, *, seed: int):
    """scene0470's mesh rendered at T_map_camera with the noise of `seed`, without labels, is answered `ok` within
    5 cm after the second look (`Localizer._second_look`). Returns (site, frame, its true pose)."""
    from conftest import scene0470_mesh

    from cadreg.io.frames import RecordedFrames
    from cadreg.render.sequence import render_frames
    from cadreg.site.bundle import Site

    render_frames(scene0470_mesh(scene0470_dir), tmp_path / "frames", 1, seed=seed, poses=[T_map_camera])
    frame, T_true = RecordedFrames.open(tmp_path / "frames").load(0)
    frame = replace(frame, labels=None)
    site = Site.load(scene0470_site_dir)
    r = Localizer.from_site(site).localize(frame)
    assert r.status == Status.OK and pose_errors(r.T_map_camera, T_true)[0] < 0.05, r.diagnostics.notes
    assert any("more leaves of the label-free search" in n for n in r.diagnostics.notes)
    return site, frame, T_true


def test_a_close_view_of_a_door_in_a_corner_is_found_in_its_own_corner_by_its_colours(
        scene0470_site_dir, scene0470_dir, tmp_path) -> None:
    """A robot's camera 0.5 m up, looking into the corner of scene0470's orange door, the white wall and the floor
    (frame 79 of `cadreg render --height 0.3 0.8 --pitch -5 20 --n 150 --seed 5`). Without labels the search's best
    leaves lie in other corners of the room, where walls and floor fit as well: the first answer, 2.1 m off and
    turned 87 degrees (fitness 0.87, depth agreement 0.79), was claimed `ok` with confidence 0.83. The map's colours
    there are white wall where the frame shows the door: that answer is ruled out, and the second look refines the
    search's further leaves whose colours do follow the map's, among them the true corner's (17th). Without that
    reserve of leaves, the ruled-out answer is only held back."""
    T_corner = np.array([[0.66020416264, -0.186963546966, 0.727444221737, 2.588325742854],
                         [-0.749164580354, -0.233156767784, 0.619992220257, 2.124116647567],
                         [0.053692598893, -0.954296889727, -0.293997535843, 0.512223554859],
                         [0.0, 0.0, 0.0, 1.0]])
    site, frame, T_true = _found_by_the_second_look(scene0470_dir, scene0470_site_dir, tmp_path, T_corner, seed=5)
    no_reserve = LocalizeConfig(label_free=LabelFreeConfig(reserve=0))
    r = Localizer.from_site(site, no_reserve).localize(frame)
    assert r.status == Status.UNCERTAIN and pose_errors(r.hypotheses[0].T_map_camera, T_true)[0] > 1.0
    assert any(n.startswith("uncertain") and "colours are not the map's" in n for n in r.diagnostics.notes)
    # An answer that does not lie on the map is `low_overlap` whatever its colours: no second look is paid for.
    r = Localizer.from_site(site, LocalizeConfig(refine=RefineConfig(min_fitness=1.0))).localize(frame)
    assert r.status == Status.LOW_OVERLAP
    assert not any("more leaves of the label-free search" in n for n in r.diagnostics.notes)


def test_an_answer_whose_colours_follow_the_map_weakly_takes_the_second_look(scene0470_site_dir, scene0470_dir,
                                                                              tmp_path) -> None:
    """MatchConfig.second_look_chroma: a robot's camera 0.38 m up at a bare wall of scene0470 (the pose of frame 30
    of `cadreg render --height 0.3 0.9 --n 100 --seed 23`, rendered with seed 1). Without labels the search's first
    answer fits another wall 1.2 m away, turned 90 degrees, and its chroma correlates 0.46 with the map's: above
    the 0.25 that rules an answer out, so it was claimed `ok`. Below the bar (0.5 then, 0.7 now) the search's further
    leaves whose colours do follow the map's are refined too, and the true pose, its chroma at 0.95, wins."""
    T_wall = np.array([[-0.790797868658, -0.356760937728, 0.497353359532, 2.816386617975],
                       [-0.609477119377, 0.384153342886, -0.693515573081, 1.791930198000],
                       [0.056359310521, -0.851556129953, -0.521225273425, 0.382012800030],
                       [0.0, 0.0, 0.0, 1.0]])
    site, frame, T_true = _found_by_the_second_look(scene0470_dir, scene0470_site_dir, tmp_path, T_wall, seed=1)
    # With the look only below the bar that rules an answer out, the first answer stands, and is wrong.
    bar = LocalizeConfig().match.min_chroma_correlation
    r = Localizer.from_site(site, LocalizeConfig(match=MatchConfig(second_look_chroma=bar))).localize(frame)
    assert r.status == Status.OK and pose_errors(r.T_map_camera, T_true)[0] > 1.0


def test_two_chairs_before_a_wall_are_found_in_their_own_place_by_the_second_look(scene0470_site_dir, scene0470_dir,
                                                                                  tmp_path) -> None:
    """A robot's camera 0.49 m up at two of scene0470's chairs before the white wall (frame 43 of `cadreg render
    --height 0.3 0.8 --pitch -5 20 --n 150 --seed 23`). Without labels the search's first answer puts them before
    another wall, 1.4 m off and turned 85 degrees, with a margin over rivals the frame sees through (`ok`,
    confidence 0.93); its colours correlate 0.61-0.63 with the map's there, the true pose's 0.95. Rendered with
    seed 1, the second look (below MatchConfig.second_look_chroma, 0.7) finds the truth among the search's further
    leaves; below the former 0.5 it was not taken. Rendered with seed 0, the further leaf 5 cm from the truth is
    the place of a candidate 22 cm off that was never refined (the frame sees through it there,
    `refine_stage.HOPELESS_SEE_THROUGH`), and is refined as a place of its own (`Localizer._new_places`)."""
    T_chairs = np.array([[-0.071317816324, 0.260173927616, -0.962924346179, 1.045287652193],
                         [0.996106342957, -0.031582253852, -0.08230865545, 1.484719455104],
                         [-0.051825887307, -0.965045122588, -0.256908522191, 0.488631882296],
                         [0.0, 0.0, 0.0, 1.0]])
    site, frame, T_true = _found_by_the_second_look(scene0470_dir, scene0470_site_dir, tmp_path / "s1", T_chairs,
                                                    seed=1)
    r = Localizer.from_site(site, LocalizeConfig(match=MatchConfig(second_look_chroma=0.5))).localize(frame)
    assert r.status == Status.OK and pose_errors(r.T_map_camera, T_true)[0] > 1.0
    _found_by_the_second_look(scene0470_dir, scene0470_site_dir, tmp_path / "s0", T_chairs, seed=0)


def _candidate(T_map_camera: np.ndarray, score: float):
    """A candidate of the refine stage at a pose, as the verify stage hands it over (no graph assignment)."""
    from cadreg.localize.stages import Candidate
    from cadreg.result import Hypothesis

    return Candidate(T_map_camera, score, Hypothesis(T_map_camera, 0.0, 0.0, 0.0, score), np.zeros(0, np.int64))


def _refinement_starts(monkeypatch) -> list[np.ndarray]:
    """The start of every fine refinement (`Localizer._refine_one`) from here on, in order."""
    starts = []
    real_refine_one = Localizer._refine_one

    def counting(self, refine_map, points, T_start, method):
        starts.append(T_start)
        return real_refine_one(self, refine_map, points, T_start, method)

    monkeypatch.setattr(Localizer, "_refine_one", counting)
    return starts


def test_the_second_look_brings_places_the_candidates_do_not(localizer) -> None:
    """`Localizer._new_places`: a further leaf distinct from every candidate is new; one at a candidate's place is
    new only when it scores higher there (a closer start), and replaces that candidate; one at the answer's refined
    pose is not, wherever the answer started."""
    start, refined = make_T(t=np.array([0.0, 0.0, 0.0])), make_T(t=np.array([0.0, -1.0, 0.0]))
    answer, passed = _candidate(start, 0.85), _candidate(make_T(t=np.array([2.0, 0.0, 0.0])), 0.84)
    elsewhere = _candidate(make_T(t=np.array([0.0, 3.0, 0.0])), 0.5)
    closer = _candidate(make_T(t=np.array([2.05, 0.0, 0.0])), 0.9)
    farther = _candidate(make_T(t=np.array([2.05, 0.0, 0.0])), 0.8)
    at_the_answer = _candidate(make_T(t=np.array([0.0, -1.05, 0.0])), 0.5)  # distinct from every candidate
    new, kept = localizer._new_places([elsewhere, closer, farther, at_the_answer], [answer, passed], refined)
    assert len(new) == 2 and new[0] is elsewhere and new[1] is closer
    assert len(kept) == 1 and kept[0] is answer  # `passed` is replaced by `closer`
    new, kept = localizer._new_places([at_the_answer], [answer, passed], refined)
    assert new == [] and len(kept) == 2


def test_the_margin_is_to_the_best_distinct_refined_rival(localizer) -> None:
    """Refined contenders best first: a runner-up that converged onto the winner is no rival and must not hide a
    distinct one behind it (twin rooms at 0.962 and 0.947 with a copy of the first between them were answered
    `ok` with the whole score as margin)."""
    here = np.eye(4)
    same = make_T(t=np.array([0.01, 0.0, 0.0]))  # within the distinct-pose tolerance of `here`
    there = make_T(t=np.array([4.0, 0.0, 0.0]))
    has_rival, margin = localizer._rival_margin([0.962, 0.961, 0.947], [here, same, there])
    assert has_rival and margin == pytest.approx(0.015)
    assert localizer._rival_margin([0.9, 0.8], [here, same]) == (False, 0.9)
    has_rival, margin = localizer._rival_margin([0.9, 0.85], [here, there])
    assert has_rival and margin == pytest.approx(0.05)


def test_a_second_run_of_the_refine_stage_refines_no_contender_again(scene, localizer, monkeypatch) -> None:
    """The second and the deeper look run the refine stage again over candidates that hold the first run's
    contenders: their refinements are the frame's own (`Scan.fine`), the same GICP passes from the same start, and are
    not redone; a new contender is refined, and the answer is what one run over them all gives."""
    import cadreg.localize.refine_stage as refine_stage
    from cadreg.localize.stages import StageTimer
    from cadreg.result import Diagnostics

    frame, T = _views(scene, 1, seed=5)[0]
    diag = Diagnostics(site_id="s", bundle_version="v")
    scan = localizer._scan(frame, diag, StageTimer(diag.stage_ms))

    starts = _refinement_starts(monkeypatch)
    near = T @ make_T(t=np.array([0.03, -0.02, 0.02]))
    first = [_candidate(near, 0.9)]
    choice = localizer._refine(scan, first, "small_gicp", diag)
    assert starts and pose_errors(choice.outcome.T_map_camera, T)[0] < 0.02
    refined_once = len(starts)
    again = localizer._refine(scan, first, "small_gicp", diag)
    assert len(starts) == refined_once  # nothing refined again
    assert np.array_equal(again.outcome.T_map_camera, choice.outcome.T_map_camera)
    # A contender the first run did not have (a distinct rival, refined whatever the frame sees through at its
    # start) is refined; one run over both from a fresh scan answers the same.
    monkeypatch.setattr(refine_stage, "HOPELESS_SEE_THROUGH", 1e9)
    more = first + [_candidate(T @ make_T(t=np.array([0.6, 0.0, 0.0])), 0.89)]
    both = localizer._refine(scan, more, "small_gicp", diag)
    assert len(starts) > refined_once
    fresh = localizer._scan(frame, diag, StageTimer(diag.stage_ms))
    once = localizer._refine(fresh, more, "small_gicp", diag)
    assert np.array_equal(both.outcome.T_map_camera, once.outcome.T_map_camera)
    assert both.margin == once.margin and both.fitness == once.fitness


def test_a_rival_the_frame_sees_through_at_its_coarse_pose_is_not_refined(scene, localizer, monkeypatch) -> None:
    """A contender other than the best at which the frame sees through the map far beyond max_see_through keeps its
    coarse pose and a score of 0 without a refinement (each costs a GICP, and such a one never became credible);
    it still counts as the distinct rival it is."""
    import cadreg.localize.refine_stage as refine_stage
    from cadreg.localize.stages import StageTimer
    from cadreg.result import Diagnostics

    frame, T = _views(scene, 1, seed=5)[0]
    diag = Diagnostics(site_id="s", bundle_version="v")
    scan = localizer._scan(frame, diag, StageTimer(diag.stage_ms))
    ahead = T @ make_T(t=np.array([0.0, 0.0, 0.7]))  # 70 cm forward: the map stands in front of what was measured
    assert localizer.view_check.see_through(ahead, scan.zbuf, scan.K) > 0.5

    starts = _refinement_starts(monkeypatch)
    best, rival = _candidate(T, 0.9), _candidate(ahead, 0.89)
    choice = localizer._refine(scan, [best, rival], "small_gicp", diag)
    assert all(np.allclose(s, T) for s in starts)  # only the best was refined (and maybe its slide check)
    assert choice.candidate is best and choice.has_rival and choice.margin > 0.5
    monkeypatch.setattr(refine_stage, "HOPELESS_SEE_THROUGH", 1e9)  # the rule off: the rival is refined too
    starts.clear()
    localizer._refine(scan, [best, rival], "small_gicp", diag)
    assert any(np.allclose(s, ahead) for s in starts)


def test_only_a_pose_the_geometry_alone_found_is_held_to_the_slide_limit(scene) -> None:
    """`MatchConfig.max_pose_std_m`: the graph's object matches pin a pose along the directions the refinement
    leaves free, so a graph answer is not held to it; the label-free search's answer has only the geometry."""
    from cadreg.config import MatchConfig

    strict = Localizer.from_site(scene.site, LocalizeConfig(match=MatchConfig(max_pose_std_m=1e-6)))
    loose = Localizer.from_site(scene.site)
    for frame, T in _views(scene, 6, seed=21, min_objects=3):
        graph = strict.localize(frame)
        if graph.status != Status.OK or graph.diagnostics.method != "cadreg":
            continue
        assert loose.localize(frame).status == Status.OK
        geometric = strict.localize(replace(frame, labels=None))
        if geometric.diagnostics.method.startswith("fallback") and loose.localize(
                replace(frame, labels=None)).status == Status.OK:
            assert geometric.status == Status.UNCERTAIN
            assert any("pose std" in n for n in geometric.diagnostics.notes)
            return
    pytest.fail("no view gave an ok graph answer and an ok label-free one")


def test_a_label_free_pose_over_the_slide_limit_is_ok_when_the_probe_finds_it_pinned(scene, localizer) -> None:
    """Beyond `MatchConfig.max_pose_std_m` the covariance no longer holds a pose that would be `ok` back on its own
    word: its confidence falls by limit / σ, and the slide probe decides. Just over the limit a pinned view stays
    `ok`; at a third of its spread its confidence falls below `min_ok_confidence`."""
    from cadreg.config import MatchConfig
    from cadreg.localize.stages import pose_std_m

    for frame, T in _views(scene, 6, seed=23, min_objects=3):
        result = localizer.localize(replace(frame, labels=None))
        if result.status != Status.OK or not result.diagnostics.method.startswith("fallback"):
            continue
        std = pose_std_m(np.asarray(result.covariance))
        just_under = Localizer.from_site(scene.site, LocalizeConfig(match=MatchConfig(max_pose_std_m=0.95 * std)))
        held = just_under.localize(replace(frame, labels=None))
        assert held.status == Status.OK
        assert held.confidence == pytest.approx(0.95 * result.confidence, rel=0.02)
        far_under = Localizer.from_site(scene.site, LocalizeConfig(match=MatchConfig(max_pose_std_m=std / 3)))
        assert far_under.localize(replace(frame, labels=None)).status == Status.UNCERTAIN
        return
    pytest.fail("no view gave an ok label-free answer")


def test_a_close_view_of_a_bare_wall_slides_and_a_view_of_the_room_does_not(scene, localizer) -> None:
    """`Localizer._slides`: 60 cm from a wall, the frame sees one plane, which fits as well 25 cm along it (its
    fitness and depth agreement kept): such a pose is not claimed. A view of the floor, walls and objects loses
    its fit when moved so far."""
    from cadreg.localize.stages import StageTimer
    from cadreg.result import Diagnostics

    def scan_of(frame):
        diag = Diagnostics(site_id="s", bundle_version="v")
        return localizer._scan(frame, diag, StageTimer(diag.stage_ms))

    # the wall at y = 0 (x 0-5 m, z 0-2.6 m), looked at level from 0.6 m at mid-height
    T_wall = look_pose(np.array([2.5, 0.6, 1.3]), -np.pi / 2, 0.0)
    wall = render_frame(scene, T_wall, intrinsics=K, depth_noise_m=0.0015, seed=1)
    seen = wall.depth > 0
    assert seen.mean() > 0.9 and set(np.unique(wall.labels[seen]).tolist()) == {1}  # the wall alone
    def slides(scan, T):
        return localizer._slides(scan, T, scan.center_camera, localizer._depth_agreement(T, scan, scan.center_camera))

    assert slides(scan_of(wall), T_wall)
    frame, T = _views(scene, 1, seed=3, min_objects=3)[0]
    assert not slides(scan_of(frame), T)


@pytest.mark.realdata
def test_an_answer_from_behind_the_maps_surfaces_is_not_claimed(scene0470_site_dir, scene0470_dir, tmp_path) -> None:
    """`Localizer._seen_from_behind`: a close view of scene0470's door, rendered as a phone's 256 x 192 depth camera
    sees it, fits the door's flat face as well from outside the room, turned 180° and 1.1 m off (the pose the
    label-free search answered `ok`, confidence 0.94, before this check). From there nearly every point lies on
    surfaces seen from behind; from the true pose, none: only the first is held back. A building has no such check
    (its composed rooms are seen from behind across their unscanned sides)."""
    from cadreg import Site
    from cadreg.config import RenderConfig
    from cadreg.io.frames import RecordedFrames
    from cadreg.localize.stages import StageTimer
    from cadreg.render import LabelledMesh, render_frames
    from cadreg.result import Diagnostics

    T_true = np.array([[-0.107801, -0.564027, 0.818689, 2.696788], [-0.992321, 0.111285, -0.053996, 2.297449],
                       [-0.060652, -0.818223, -0.571692, 1.375697], [0.0, 0.0, 0.0, 1.0]])
    T_outside = np.array([[0.117486, 0.610837, -0.782991, 3.841899], [0.949979, -0.298876, -0.090621, 2.345214],
                          [-0.289372, -0.733178, -0.615397, 1.38804], [0.0, 0.0, 0.0, 1.0]])
    phone = RenderConfig(depth_width=256, depth_height=192, depth_fx=231.148, depth_fy=231.148, depth_cx=127.5,
                         depth_cy=95.5, color_width=960, color_height=720, baseline_m=0.01, min_visible_objects=0)
    mesh = LabelledMesh.from_ply(scene0470_dir / "scene0470_00_vh_clean_2.ply",
                                 scene0470_dir / "scene0470_00_vh_clean_2.labels.ply")
    render_frames(mesh, tmp_path / "door", 0, poses=[T_true], seed=7, config=phone)
    frame, _ = RecordedFrames.open(tmp_path / "door").load(0)
    loc = Localizer.from_site(Site.load(scene0470_site_dir))
    diag = Diagnostics(site_id="s", bundle_version="v")
    scan = loc._scan(frame, diag, StageTimer(diag.stage_ms))
    assert not loc._seen_from_behind(scan, T_true, scan.center_camera)
    assert loc._seen_from_behind(scan, T_outside, scan.center_camera)
