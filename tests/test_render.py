"""Renderer: geometry against the real scene0470 mesh, camera rig, pose sampling constraints, noise statistics."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cadreg.cli.main import main
from cadreg.config import NoiseConfig, RenderConfig
from cadreg.errors import ConfigError
from cadreg.geometry import transform_points
from cadreg.io.frames import RecordedFrames
from cadreg.render import (
    LabelledMesh, MeshRenderer, apply_depth_noise, axial_sigma_m, camera_rig, look_pose, pose_height_pitch_roll,
    render_frames,
)
from cadreg.render.raycast import SCANNET_COLOR


def backproject(depth_m: np.ndarray, K) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n, 3) camera points of the valid pixels of a z-depth image, with their (v, u)."""
    v, u = np.nonzero(np.isfinite(depth_m) & (depth_m > 0))
    z = depth_m[v, u]
    return np.stack([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z], axis=1), v, u


@pytest.fixture(scope="session")
def scene_mesh(scene0470_dir: Path) -> LabelledMesh:
    return LabelledMesh.from_ply(scene0470_dir / "scene0470_00_vh_clean_2.ply",
                                 scene0470_dir / "scene0470_00_vh_clean_2.labels.ply")


@pytest.fixture(scope="session")
def scene_renderer(scene_mesh: LabelledMesh) -> MeshRenderer:
    return MeshRenderer(scene_mesh)


@pytest.fixture(scope="session")
def rendered_rig(scene_mesh: LabelledMesh, tmp_path_factory) -> tuple[Path, list]:
    """6 noiseless frames with a 1296x968 colour camera, >= 2 visible objects each."""
    out = tmp_path_factory.mktemp("rig")
    cfg = RenderConfig(color_width=1296, color_height=968, min_visible_objects=2)
    return out, render_frames(scene_mesh, out, 6, seed=3, config=cfg, noise=None)


def test_mesh_instances(scene_mesh: LabelledMesh) -> None:
    assert scene_mesh.labels is not None and scene_mesh.instances is not None
    # Walls and floor are structure; chairs (5) are split into several connected instances.
    assert np.all(scene_mesh.instances[np.isin(scene_mesh.labels, [0, 1, 2])] == -1)
    chair_instances = np.unique(scene_mesh.instances[scene_mesh.labels == 5])
    assert len(chair_instances) >= 5 and -1 not in chair_instances
    assert abs(scene_mesh.floor_height_m()) < 0.15


@pytest.mark.realdata
def test_backprojected_depth_lands_on_mesh(scene_renderer: MeshRenderer) -> None:
    """Noiseless depth back-projected with its pose lies on the mesh (pixel-centre convention honoured)."""
    depth_intr, color_intr, T_cd = camera_rig(RenderConfig())
    rng = np.random.default_rng(0)
    from cadreg.render import PoseSampler

    sampler = PoseSampler(scene_renderer, RenderConfig())
    dists = []
    for _ in range(3):
        T = sampler.sample(rng)
        frame, dview, _ = scene_renderer.render_frame(T, depth_intr, color_intr, T_cd, noise=None)
        p, _, _ = backproject(frame.depth.astype(float) / frame.depth_scale, depth_intr)
        dists.append(scene_renderer.distance_to_surface(transform_points(T, p)))
    d = np.concatenate(dists)
    assert len(d) > 100_000
    assert np.median(d) < 0.01 and np.percentile(d, 90) < 0.01  # mm quantisation only
    # A half-pixel error in cx would show as a shift: check against an off-by-0.5 camera's points.
    shifted = type(depth_intr)(640, 480, depth_intr.fx, depth_intr.fy, depth_intr.cx + 3.0, depth_intr.cy)
    p_bad, _, _ = backproject(frame.depth.astype(float) / 1000.0, shifted)
    assert np.median(scene_renderer.distance_to_surface(transform_points(T, p_bad))) > np.median(d)


@pytest.mark.realdata
def test_color_camera_size_and_extrinsic(rendered_rig, scene_renderer: MeshRenderer) -> None:
    out, rendered = rendered_rig
    frames = RecordedFrames.open(out)
    assert frames.depth_intrinsics.width == 640 and frames.color_intrinsics == SCANNET_COLOR
    np.testing.assert_allclose(frames.T_color_depth[:3, 3], [-0.025, 0, 0])
    frame, T_map_camera = frames.load(rendered[0].index)
    assert frame.depth.shape == (480, 640) and frame.color.shape == (968, 1296, 3) and frame.labels.shape == (968, 1296)
    np.testing.assert_allclose(T_map_camera, rendered[0].T_map_camera, atol=1e-9)
    # Depth points moved into the colour camera meet the colour camera's own ray-cast depth there.
    p_d, _, _ = backproject(frame.depth.astype(float) / 1000.0, frames.depth_intrinsics)
    q = transform_points(frames.T_color_depth, p_d)
    ci = frames.color_intrinsics
    uc = np.rint(q[:, 0] / q[:, 2] * ci.fx + ci.cx).astype(int)
    vc = np.rint(q[:, 1] / q[:, 2] * ci.fy + ci.cy).astype(int)
    ok = (uc >= 0) & (uc < ci.width) & (vc >= 0) & (vc < ci.height)
    cview = scene_renderer.cast(ci, T_map_camera, with_color=False)
    z_color = cview.depth_m[vc[ok], uc[ok]]
    diff = np.abs(z_color - q[ok, 2])
    assert np.median(diff[np.isfinite(diff)]) < 0.005
    # The wrong extrinsic (identity) disagrees clearly more.
    uc0 = np.rint(p_d[:, 0] / p_d[:, 2] * ci.fx + ci.cx).astype(int)
    vc0 = np.rint(p_d[:, 1] / p_d[:, 2] * ci.fy + ci.cy).astype(int)
    ok0 = (uc0 >= 0) & (uc0 < ci.width) & (vc0 >= 0) & (vc0 < ci.height)
    diff0 = np.abs(cview.depth_m[vc0[ok0], uc0[ok0]] - p_d[ok0, 2])
    assert np.mean(diff0[np.isfinite(diff0)] > 0.02) > np.mean(diff[np.isfinite(diff)] > 0.02)
    # Labels in the colour image are those of the surface the colour camera sees.
    lab = frame.labels[vc[ok], uc[ok]]
    assert set(np.unique(lab)) - {0} <= set(np.unique(scene_renderer.mesh.labels))


@pytest.mark.realdata
def test_pose_sampling_constraints(rendered_rig, scene_renderer: MeshRenderer) -> None:
    _, rendered = rendered_rig
    cfg = RenderConfig()
    floor = scene_renderer.mesh.floor_height_m()
    for r in rendered:
        h, pitch, roll = pose_height_pitch_roll(r.T_map_camera, floor)
        assert cfg.height_min_m - 1e-6 <= h <= cfg.height_max_m + 1e-6
        assert cfg.pitch_min_deg - 1e-6 <= pitch <= cfg.pitch_max_deg + 1e-6
        assert abs(roll) <= cfg.roll_max_deg + 1e-6
        assert scene_renderer.distance_to_surface(r.T_map_camera[None, :3, 3])[0] >= cfg.min_clearance_m
        assert r.visible_objects >= 2 and r.valid_fraction >= cfg.min_valid_fraction
    positions = np.array([r.T_map_camera[:3, 3] for r in rendered])
    assert np.all(positions[:, :2] > -0.1) and np.all(positions[:, 0] < 3.6) and np.all(positions[:, 1] < 3.0)


def test_look_pose_round_trip() -> None:
    T = look_pose(np.array([1.0, 2.0, 1.5]), 30.0, 25.0, -4.0)
    h, pitch, roll = pose_height_pitch_roll(T, 0.2)
    assert (h, pitch, roll) == pytest.approx((1.3, 25.0, -4.0))
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    # The optical axis points along the heading and down.
    f = T[:3, 2]
    assert f[2] < 0 and np.degrees(np.arctan2(f[1], f[0])) == pytest.approx(30.0)


def _plane_mesh(z_m: float, tilt_deg: float = 0.0) -> LabelledMesh:
    """A 40 m square facing the camera at depth z_m, tilted about the camera's y axis."""
    a = np.radians(tilt_deg)
    s = 20.0
    corners = np.array([[-s, -s], [s, -s], [s, s], [-s, s]])
    # Plane in camera axes (x right, y down, z forward), then the camera looks along map +x from the origin.
    pc = np.stack([corners[:, 0] * np.cos(a), corners[:, 1], z_m + corners[:, 0] * np.sin(a)], axis=1)
    return LabelledMesh(pc, np.array([[0, 1, 2], [0, 2, 3]]), np.full((4, 3), 128, np.uint8), labels=None)


def test_noise_statistics() -> None:
    cfg = NoiseConfig()
    depth_intr, color_intr, T_cd = camera_rig(RenderConfig())
    rng = np.random.default_rng(7)
    r = MeshRenderer(_plane_mesh(2.0))
    frame, dview, _ = r.render_frame(np.eye(4), depth_intr, color_intr, T_cd, rng=rng, noise=cfg)
    truth = dview.depth_m
    z = frame.depth.astype(float) / 1000.0
    valid = z > 0
    # Random dropout only (flat, frontal, no edges): ~1 %.
    assert 0.005 < 1 - valid.mean() < 0.02
    resid = (z - truth)[valid]
    sigma = axial_sigma_m(2.0, cfg)
    assert sigma == pytest.approx(0.0012 + 0.0019 * 1.6 ** 2)
    assert np.std(resid) == pytest.approx(sigma, rel=0.15) and abs(np.mean(resid)) < 0.001
    # Quantised to millimetres.
    assert np.allclose(z[valid] * 1000.0, np.rint(z[valid] * 1000.0))
    # Deeper is noisier.
    far, dview_far, _ = MeshRenderer(_plane_mesh(4.0)).render_frame(np.eye(4), depth_intr, color_intr, T_cd, rng=rng,
                                                                    noise=cfg)
    zf = far.depth.astype(float) / 1000.0
    assert np.std((zf - dview_far.depth_m)[zf > 0]) > 2.5 * np.std(resid)
    # Grazing incidence loses everything beyond grazing_full_deg.
    graze = apply_depth_noise(np.full((50, 50), 2.0), np.full((50, 50), np.cos(np.radians(85))), rng, cfg)
    assert np.all(graze == 0)
    # Depth edges lose about edge_dropout_p of their pixels.
    step = np.full((200, 200), 2.0)
    step[:, 100:] = 3.0
    out = apply_depth_noise(step, np.ones_like(step), rng, cfg.model_copy(update={"random_dropout_p": 0.0}))
    edge_loss = np.mean(out[:, 99:101] == 0)
    assert edge_loss == pytest.approx(cfg.edge_dropout_p, abs=0.08) and np.mean(out[:, :90] == 0) == 0
    # Out of range: nothing nearer than min_depth_m.
    near = apply_depth_noise(np.full((10, 10), 0.2), np.ones((10, 10)), rng, cfg)
    assert np.all(near == 0)


def test_render_is_deterministic_and_honours_given_poses(scene_mesh: LabelledMesh, tmp_path: Path) -> None:
    a = render_frames(scene_mesh, tmp_path / "a", 2, seed=11)
    b = render_frames(scene_mesh, tmp_path / "b", 2, seed=11)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.T_map_camera, y.T_map_camera)
        assert (tmp_path / "a" / "depth" / f"{x.index}.png").read_bytes() == \
            (tmp_path / "b" / "depth" / f"{y.index}.png").read_bytes()
    poses = [x.T_map_camera for x in a]
    c = render_frames(scene_mesh, tmp_path / "c", 0, poses=poses, noise=None)
    frames = RecordedFrames.open(tmp_path / "c")
    assert len(frames) == 2 and all(np.allclose(frames.pose(i), T) for i, T in zip(frames.indices, poses))
    assert [x.index for x in c] == [0, 1]
    # the noise model's cut-off is the frames' depth range; noiseless frames measure everything and say nothing
    assert RecordedFrames.open(tmp_path / "a").load(0)[0].depth_range_m == NoiseConfig().max_depth_m
    assert frames.depth_range_m is None and frames.load(0)[0].depth_range_m is None


def test_unlabelled_mesh_needs_zero_visible_objects(tmp_path: Path) -> None:
    mesh = _plane_mesh(2.0)
    with pytest.raises(ConfigError, match="min_visible_objects"):
        render_frames(mesh, tmp_path / "x", 1)


@pytest.mark.realdata
def test_cli_render(scene0470_dir: Path, scene_mesh: LabelledMesh, tmp_path: Path, capsys) -> None:
    mesh_ply = str(scene0470_dir / "scene0470_00_vh_clean_2.ply")
    out = tmp_path / "frames"
    rc = main(["render", "--mesh", mesh_ply, "--labels", str(scene0470_dir / "scene0470_00_vh_clean_2.labels.ply"),
               "--out", str(out), "--n", "3", "--seed", "5", "--color-size", "320", "240", "--height", "1.3", "1.4",
               "--pitch", "20", "30", "--min-visible-objects", "1"])
    assert rc == 0 and '"frames": 3' in capsys.readouterr().out
    frames = RecordedFrames.open(out)
    assert len(frames) == 3 and frames.color_intrinsics.width == 320 and frames.has_labels()
    assert frames.color_intrinsics.fx == pytest.approx(1170.187988 * 320 / 1296)
    for i in frames.indices:
        h, pitch, _ = pose_height_pitch_roll(frames.pose(i), scene_mesh.floor_height_m())
        assert 1.3 - 1e-6 <= h <= 1.4 + 1e-6 and 20 - 1e-6 <= pitch <= 30 + 1e-6
    # Rendering the poses back from the folder reproduces them.
    assert main(["render", "--mesh", mesh_ply, "--out", str(tmp_path / "again"), "--poses", str(out),
                 "--no-noise", "--min-visible-objects", "0"]) == 0
    again = RecordedFrames.open(tmp_path / "again")
    assert all(np.allclose(again.pose(i), frames.pose(i)) for i in frames.indices)
    # No labels but objects required: a config error, exit code 2; so are frames without a folder to write them to.
    assert main(["render", "--mesh", mesh_ply, "--out", str(tmp_path / "bad"), "--n", "1"]) == 2
    capsys.readouterr()
    assert main(["render", "--mesh", mesh_ply, "--n", "1", "--min-visible-objects", "0"]) == 2
    assert "--out is required" in capsys.readouterr().err


@pytest.mark.realdata
def test_a_walk_is_one_camera_carried_through_the_room(scene_mesh: LabelledMesh, scene_renderer: MeshRenderer,
                                                       tmp_path: Path) -> None:
    from cadreg.render.poses import WALK_SPIN_DEG, PoseSampler

    step, n = 0.05, 60
    walked = render_frames(scene_mesh, tmp_path / "walk", n, seed=3, walk_step_m=step, noise=None)
    # its first view is the one a sampled set draws first, with the same seed
    first = render_frames(scene_mesh, tmp_path / "one", 1, seed=3, noise=None)[0]
    np.testing.assert_array_equal(walked[0].T_map_camera, first.T_map_camera)
    sampler, cfg = PoseSampler(scene_renderer), RenderConfig()
    floor = scene_mesh.floor_height_m()
    moves = spins = 0
    for a, b in zip(walked, walked[1:]):
        Ta, Tb = a.T_map_camera, b.T_map_camera
        moved = float(np.linalg.norm(Tb[:3, 3] - Ta[:3, 3]))
        ha, pitch_a, _ = pose_height_pitch_roll(Ta, floor)
        hb, pitch_b, roll_b = pose_height_pitch_roll(Tb, floor)
        heading = lambda T: np.degrees(np.arctan2(T[1, 2], T[0, 2]))  # noqa: E731 (the optical axis seen from above)
        dyaw = abs((heading(Tb) - heading(Ta) + 180.0) % 360.0 - 180.0)
        # a step of step_m the way it looks, or a turn on the spot, never a jump
        if moved > 1e-9:
            moves += 1
            assert moved == pytest.approx(step, abs=1e-9) and dyaw <= 1e-6  # a straight way to the next place
            direction = (Tb[:2, 3] - Ta[:2, 3]) / moved
            assert np.degrees(np.arccos(np.clip(direction @ np.array([np.cos(np.radians(heading(Tb))),
                                                                      np.sin(np.radians(heading(Tb)))]), -1, 1))) < 1e-3
        else:
            spins += 1
            assert dyaw <= WALK_SPIN_DEG + 1e-6
        assert hb == pytest.approx(ha, abs=1e-9)  # carried at one height
        assert cfg.pitch_min_deg - 1e-6 <= pitch_b <= cfg.pitch_max_deg + 1e-6 and abs(roll_b) <= cfg.roll_max_deg + 1e-6
        assert abs(pitch_b - pitch_a) < 3.0
        assert sampler.position_ok(Tb[:3, 3], hb)
    assert moves >= 10 and spins >= 5  # it walks from place to place, turning on the spot between
    # the same seed, the same walk
    again = render_frames(scene_mesh, tmp_path / "again", n, seed=3, walk_step_m=step, noise=None)
    assert all(np.array_equal(x.T_map_camera, y.T_map_camera) for x, y in zip(walked, again))
    for step_m in (0.0, 1e-6, 0.6):  # no step, thousands of placements a way, a step past a way's length
        with pytest.raises(ConfigError, match="walk"):
            render_frames(scene_mesh, tmp_path / "x", 2, walk_step_m=step_m)


@pytest.mark.realdata
def test_a_rendered_walk_is_tracked(scene_mesh: LabelledMesh, scene0470_site_dir: Path, tmp_path: Path) -> None:
    """The stream the tutorial sends (`cadreg render --walk`): after the first frame's search, the session tracks."""
    from cadreg.geometry import pose_errors
    from cadreg.localize.localizer import Localizer
    from cadreg.site.bundle import Site

    out = tmp_path / "walk"
    assert main(["render", "--site", str(scene0470_site_dir), "--out", str(out), "--n", "30", "--seed", "1",
                 "--walk", "0.05"]) == 0
    frames = RecordedFrames.open(out)
    localizer = Localizer.from_site(Site.load(scene0470_site_dir))
    state, modes = None, []
    for k, i in enumerate(frames.indices):
        frame, T_true = frames.load(i)
        tracked = localizer.track(frame, state, t_s=0.1 * k)  # 10 frames a second: 0.5 m/s
        state, result = tracked.state, tracked.result
        modes.append(result.diagnostics.mode)
        assert result.status.value == "ok", (k, result.diagnostics.notes)
        t_err, r_err = pose_errors(result.T_map_camera, T_true)
        assert t_err < 0.05 and r_err < 5.0, (k, t_err, r_err)
    assert modes[0] == "global" and modes.count("tracked") >= 20, modes
    # --walk with given poses is refused
    assert main(["render", "--site", str(scene0470_site_dir), "--out", str(tmp_path / "bad"), "--poses", str(out),
                 "--walk", "0.05"]) == 2
