"""The bench's trust figures (ok precision, wrong ok answers, reliability by confidence band) and the KISS-Matcher
peer: its install hint when the extra is missing, and a real registration of a rendered scene0470 frame."""

from __future__ import annotations

import builtins
import json
import math

import numpy as np
import pytest

from cadreg.bench import Bench, FrameOutcome, format_table, summarize
from cadreg.errors import CadregError, InvalidArgument


def test_trust_figures_count_wrong_ok_answers_and_band_success() -> None:
    outs = [FrameOutcome(0, "ok", 0.01, 0.5, 10.0, confidence=0.95),
            FrameOutcome(1, "ok", 0.40, 30.0, 10.0, confidence=0.75),  # confidently wrong
            FrameOutcome(2, "uncertain", 0.02, 1.0, 10.0, confidence=0.6),  # right, but not claimed
            FrameOutcome(3, "ok", 0.02, 1.0, 10.0, confidence=0.92),
            FrameOutcome(4, "no_match", math.inf, math.inf, 10.0, confidence=0.0)]
    s = summarize(outs)
    assert s["ok_precision"] == pytest.approx(2 / 3) and s["ok_wrong"] == s["wrong_ok"] == 1
    assert s["reliability"] == {"0.0-0.5": {"frames": 1, "success_5cm_5deg": 0.0, "ok": 0},
                                "0.5-0.7": {"frames": 1, "success_5cm_5deg": 1.0, "ok": 0},
                                "0.7-0.9": {"frames": 1, "success_5cm_5deg": 0.0, "ok": 1},
                                "0.9-1.0": {"frames": 2, "success_5cm_5deg": 1.0, "ok": 2}}
    table = format_table({"frames": 5, "skipped": [], "methods": {"m": s}})
    assert "ok prec" in table and "66.7%" in table and "by confidence: [0.0-0.5] 0% of 1" in table
    json.dumps(s)
    # No ok answer at all: precision is undefined, not 0 or 1.
    assert summarize([FrameOutcome(0, "low_overlap", math.inf, math.inf, 1.0)])["ok_precision"] is None


def test_kiss_matcher_missing_gives_the_install_hint(monkeypatch) -> None:
    real_import = builtins.__import__

    def no_kiss(name, *args, **kwargs):
        if name == "kiss_matcher" or name.startswith("kiss_matcher."):
            raise ImportError("No module named 'kiss_matcher'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_kiss)
    from cadreg.localize.fallback import KissMatcher

    with pytest.raises(InvalidArgument) as info:
        KissMatcher(fpfh=None)
    assert isinstance(info.value, CadregError)
    assert 'pip install "cadreg[kiss]"' in str(info.value)


@pytest.mark.realdata
def test_kiss_matcher_peer_registers_a_real_render(scene0470_site_dir, scene0470_dir, tmp_path) -> None:
    pytest.importorskip("kiss_matcher")
    from cadreg.io.frames import RecordedFrames
    from cadreg.localize.localizer import Localizer
    from cadreg.render.mesh import LabelledMesh
    from cadreg.render.sequence import render_frames
    from cadreg.site.bundle import Site

    mesh = LabelledMesh.from_ply(scene0470_dir / "scene0470_00_vh_clean_2.ply",
                                 scene0470_dir / "scene0470_00_vh_clean_2.labels.ply")
    render_frames(mesh, tmp_path / "f", 1, seed=7)
    frame, T_true = RecordedFrames.open(tmp_path / "f").load(0)
    site = Site.load(scene0470_site_dir)
    bench = Bench(site, Localizer.from_site(site))
    o = bench.run_one("kiss-matcher", 0, frame, T_true)
    assert o.status in ("ok", "low_overlap") and 0.0 <= o.confidence <= 1.0
    if o.status == "ok":
        assert np.isfinite(o.translation_m)
