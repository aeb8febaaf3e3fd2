"""A camera's colour faults in a frame's colour image (cadreg/color_noise.py, `cadreg bench --color-noise`), and the
colour gate under them: right answers stay claimed."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cadreg.color_noise import COLOR_NOISE_PRESETS, ColorNoise, corrupt_colors
from cadreg.errors import InvalidArgument


def _image() -> np.ndarray:
    """A 60 x 80 colour image: white wall above a grey floor, an orange door on the left."""
    img = np.empty((60, 80, 3), dtype=np.uint8)
    img[:] = (215, 215, 208)
    img[40:] = (115, 115, 120)
    img[5:50, 5:25] = (190, 115, 40)
    return img


def test_no_noise_is_the_image_itself_and_the_same_seed_the_same_faults() -> None:
    img = _image()
    assert np.array_equal(corrupt_colors(img, ColorNoise(), np.random.default_rng(0)), img)
    camera = COLOR_NOISE_PRESETS["camera"]
    a = corrupt_colors(img, camera, np.random.default_rng([0, 3, 2]))
    b = corrupt_colors(img, camera, np.random.default_rng([0, 3, 2]))
    assert np.array_equal(a, b) and a.dtype == np.uint8 and a.shape == img.shape and not np.array_equal(a, img)


def test_each_fault_does_what_it_says() -> None:
    img, rng = _image(), np.random.default_rng(1)
    shifted = corrupt_colors(img, ColorNoise(shift_px=4), rng)
    assert any(np.array_equal(shifted, np.roll(img, (dy, dx), axis=(0, 1)))
               for dy in range(-4, 5) for dx in range(-4, 5))
    bright = corrupt_colors(img, ColorNoise(exposure=(1.3, 1.3)), rng).astype(float)
    assert np.allclose(bright[40:, 30:], np.minimum(255, np.array([115, 115, 120]) * 1.3), atol=1)
    tinted = corrupt_colors(img, ColorNoise(white_balance=0.3), rng).astype(float)
    ratios = tinted[0, 40] / img[0, 40]  # the wall's channels scaled each by its own factor within 1 ± 0.3
    assert np.all((ratios > 0.69) & (ratios < 1.31)) and np.ptp(ratios) > 0.01
    curved = corrupt_colors(img, ColorNoise(gamma=(2.0, 2.0)), rng).astype(float)
    assert np.allclose(curved[50, 40], 255 * (np.array([115, 115, 120]) / 255) ** 2, atol=1)
    blurred = corrupt_colors(img, ColorNoise(blur_px=2.0), rng)
    assert np.array_equal(blurred[25, 60], img[25, 60])  # far from any edge
    noisy = corrupt_colors(img, ColorNoise(noise=0.05), rng).astype(float) - img
    assert 8 < noisy[:35, 30:].std() < 16


def test_settings_out_of_range_are_refused() -> None:
    for bad in (dict(gamma=(0.0, 1.0)), dict(exposure=(1.4, 0.6)), dict(white_balance=1.0), dict(noise=-0.1),
                dict(shift_px=-1)):
        with pytest.raises(InvalidArgument):
            ColorNoise(**bad)


@pytest.mark.realdata
def test_bench_gives_every_method_a_cameras_colours(scene0470_site_dir, scene0470_dir, tmp_path) -> None:
    """`cadreg bench --color-noise camera`: every method gets the frame's colour with a camera's faults, seeded per
    frame; the report says which faults it ran with; the colour gate holds back no right answer of these frames."""
    from conftest import scene0470_mesh

    from cadreg.cli.main import main
    from cadreg.render.sequence import render_frames

    frames = tmp_path / "frames"
    render_frames(scene0470_mesh(scene0470_dir), frames, 4, seed=7)
    out = tmp_path / "bench.json"
    assert main(["bench", "--site", str(scene0470_site_dir), "--frames", str(frames), "--method", "cadreg-nolabels",
                 "--color-noise", "camera", "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["color_noise"] == json.loads(json.dumps(COLOR_NOISE_PRESETS["camera"].as_dict()))
    rows = report["methods"]["cadreg-nolabels"]["per_frame"]
    assert sum(r["status"] == "ok" and r["translation_m"] < 0.05 for r in rows) >= 3
