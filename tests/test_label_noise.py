"""A segmenter's errors in the labels (cadreg/label_noise.py, `cadreg bench --label-noise`), and the labelled path
under them: two basins of one hypothesis are told apart by depth, not by the labels that ranked them."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from cadreg.errors import InvalidArgument
from cadreg.label_noise import LABEL_NOISE_PRESETS, LabelNoise, corrupt_labels

IDS = np.array([5, 7, 39])


def _image() -> np.ndarray:
    """A 60 x 80 label image: wall (1) above floor (2), a chair (5) and a table (7) on them, unlabelled corner."""
    lab = np.ones((60, 80), dtype=np.uint16)
    lab[40:] = 2
    lab[20:45, 10:30] = 5
    lab[30:50, 50:70] = 7
    lab[:5, :5] = 0
    return lab


def test_no_noise_is_the_image_itself_and_the_same_seed_the_same_errors() -> None:
    lab = _image()
    assert np.array_equal(corrupt_labels(lab, LabelNoise(), IDS, np.random.default_rng(0)), lab)
    harsh = LABEL_NOISE_PRESETS["harsh"]
    a = corrupt_labels(lab, harsh, IDS, np.random.default_rng([0, 3, 1]))
    b = corrupt_labels(lab, harsh, IDS, np.random.default_rng([0, 3, 1]))
    assert np.array_equal(a, b) and a.dtype == lab.dtype and not np.array_equal(a, lab)
    assert set(np.unique(a).tolist()) <= {0, 1, 2, 5, 7, 39}  # nothing but the image's own ids and the site's


def test_each_kind_of_error_does_what_it_says() -> None:
    lab, rng = _image(), np.random.default_rng(1)
    shifted = corrupt_labels(lab, LabelNoise(shift_px=4), IDS, rng)
    assert any(np.array_equal(shifted, np.roll(lab, (dy, dx), axis=(0, 1)))
               for dy in range(-4, 5) for dx in range(-4, 5))
    chair = np.where(lab == 5, 5, 0).astype(lab.dtype)
    bled = corrupt_labels(chair, LabelNoise(bleed=1.0, bleed_px=3), IDS, rng)
    assert np.all(bled[chair == 5] == 5) and (bled == 5).sum() > (chair == 5).sum()  # grown over its border
    dropped = corrupt_labels(lab, LabelNoise(drop=1.0), IDS, rng)
    assert np.all(dropped == 0)
    swapped = corrupt_labels(lab, LabelNoise(swap=1.0), IDS, rng)
    # every object class becomes another of the site's, everywhere it was; wall and floor stay
    assert np.all(swapped[lab == 1] == 1) and np.all(swapped[lab == 2] == 2)
    for c in (5, 7):
        new = np.unique(swapped[lab == c])
        assert len(new) == 1 and new[0] != c and new[0] in IDS
    speckled = corrupt_labels(lab, LabelNoise(speckle=0.2), IDS, rng)
    changed = speckled != lab
    assert 0.1 < changed.mean() < 0.2 and np.isin(speckled[changed], IDS).all()
    blobs = [corrupt_labels(lab, LabelNoise(blobs=3), IDS, np.random.default_rng(k)) for k in range(8)]
    assert any((b != lab).any() for b in blobs)
    assert all(np.isin(b[b != lab], IDS).all() for b in blobs)
    # without the site's object ids, swaps, blobs and speckle draw nothing
    assert np.array_equal(corrupt_labels(lab, LabelNoise(swap=1.0, blobs=3, speckle=0.5), IDS[:0], rng), lab)


def test_settings_out_of_range_are_refused() -> None:
    for bad in (dict(swap=1.5), dict(drop=-0.1), dict(shift_px=-1), dict(speckle=2.0)):
        with pytest.raises(InvalidArgument):
            LabelNoise(**bad)


@pytest.fixture(scope="module")
def noisy_renders(scene0470_dir, tmp_path_factory):
    """The first 12 renders of the real mesh with seed 7 (those of the README's scene0470 benchmark)."""
    from conftest import scene0470_mesh

    from cadreg.render.sequence import render_frames

    out = tmp_path_factory.mktemp("noisy") / "scene0470"
    render_frames(scene0470_mesh(scene0470_dir), out, 12, seed=7)
    return out


@pytest.mark.realdata
def test_bench_gives_the_labelled_methods_noisy_labels(scene0470_site_dir, noisy_renders, tmp_path) -> None:
    """`cadreg bench --label-noise harsh`: the labelled method gets labels with errors drawn from the classes the
    site's graph holds, seeded per frame; the report says which noise it ran with."""
    from cadreg import Localizer, Site
    from cadreg.bench import Bench
    from cadreg.cli.main import main
    from cadreg.io.frames import RecordedFrames

    out = tmp_path / "bench.json"
    assert main(["bench", "--site", str(scene0470_site_dir), "--frames", str(noisy_renders), "--limit", "3",
                 "--method", "cadreg", "--label-noise", "harsh", "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["label_noise"] == LABEL_NOISE_PRESETS["harsh"].as_dict()
    assert report["methods"]["cadreg"]["per_frame"][0]["status"] in {"ok", "ambiguous", "uncertain", "low_overlap"}
    site = Site.load(scene0470_site_dir)
    bench = Bench(site, Localizer.from_site(site), label_noise=LABEL_NOISE_PRESETS["harsh"])
    frame, _ = RecordedFrames.open(noisy_renders).load(11)
    noisy = bench.labels_of(11, frame)
    assert np.array_equal(noisy, bench.labels_of(11, frame)) and not np.array_equal(noisy, frame.labels)
    graph_ids = {i for i, c in site.label_maps["nyu40"].items() if c in {n.cls for n in site.graph.nodes}}
    assert set(np.unique(noisy).tolist()) <= set(np.unique(frame.labels).tolist()) | graph_ids | {0}
    assert Bench(site, bench.localizer).labels_of(11, frame) is frame.labels


@pytest.mark.realdata
def test_a_near_basin_the_labels_ranked_first_loses_to_the_pose_the_depth_shows(scene0470_site_dir, noisy_renders,
                                                                                  monkeypatch) -> None:
    """Render 11 looks at a door and a whiteboard. With the harsh preset's errors (seed 0) the whiteboard goes
    unlabelled and the door's label shifts: the labels rank a pose 26 cm along the wall 0.04 above the right one,
    which no distinct-hypothesis rule refines (the two are one hypothesis at 30 cm). Refined as well
    (`_near_contender`) and told apart by depth (0.98 against 0.82 of the view), the right one is the answer;
    without, the wrong one was answered `ok`, confidence 0.93 (now it is put first but `uncertain`: the frame shows no
    floor, and the slide probe finds it fits as well 25 cm along the wall)."""
    import cadreg.localize.refine_stage as refine_stage
    from cadreg import Localizer, Site
    from cadreg.bench import Bench
    from cadreg.geometry import pose_errors
    from cadreg.io.frames import RecordedFrames

    site = Site.load(scene0470_site_dir)
    loc = Localizer.from_site(site)
    frame, T_true = RecordedFrames.open(noisy_renders).load(11)
    noisy = replace(frame, labels=Bench(site, loc, label_noise=LABEL_NOISE_PRESETS["harsh"]).labels_of(11, frame))
    res = loc.localize(noisy)
    assert any("refined 2 close hypotheses" in n for n in res.diagnostics.notes)
    assert res.status.value == "ok" and pose_errors(res.T_map_camera, T_true)[0] < 0.05
    monkeypatch.setattr(refine_stage, "NEAR_REACH_M", 1e9)  # no candidate is beyond a contender's reach
    before = loc.localize(noisy)
    assert before.status.value != "ok" and pose_errors(before.hypotheses[0].T_map_camera, T_true)[0] > 0.2


@pytest.mark.realdata
def test_a_near_contender_is_a_close_candidate_beyond_every_contenders_reach(scene0470_site_dir) -> None:
    """`_near_contender` picks the best candidate within the contender margin that no refined pose's basin holds
    (NEAR_REACH_M / NEAR_REACH_DEG from each) and that is no distinct hypothesis (those are contenders of their own)."""
    from cadreg import Localizer, Site
    from cadreg.localize.refine_stage import NEAR_REACH_M
    from cadreg.localize.stages import Candidate

    loc = Localizer.from_site(Site.load(scene0470_site_dir))

    def at(dx: float, score: float) -> Candidate:
        T = np.eye(4)
        T[0, 3] = dx
        return Candidate(T, score, None, np.zeros(0, dtype=np.int64))

    best, same, slid, far = at(0.0, 0.805), at(0.01, 0.803), at(0.26, 0.763), at(2.0, 0.79)
    assert loc._near_contender([best, same, slid, far], [best]) is slid
    assert loc._near_contender([best, same, at(0.26, 0.6)], [best]) is None  # beyond the contender margin
    assert loc._near_contender([best, same, at(NEAR_REACH_M / 2, 0.8)], [best]) is None  # the best's basin
    assert loc._near_contender([best, far], [best, far]) is None  # distinct: a contender already, or not
