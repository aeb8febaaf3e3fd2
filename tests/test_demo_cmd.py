"""`cadreg demo` runs the whole pipeline on the bundled demo site and prints its table."""

from __future__ import annotations

import re

from cadreg.cli.main import main


def test_demo_localizes_rendered_frames(tmp_path, capsys) -> None:
    assert main(["demo", "--n", "3", "--seed", "1", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    rows = re.findall(r"^\s*(\d+)\s+(\d+)\s+(\w+)\s+([\d.]+|-)\s+([\d.]+|-)\s+\d+$", out, flags=re.M)
    assert len(rows) == 3, out
    # the demo room is noise-rendered from its own scan: every frame must come back within 5 cm / 5°
    for _, _, status, t_cm, r_deg in rows:
        assert status in ("ok", "ambiguous"), out
        assert float(t_cm) < 5.0 and float(r_deg) < 5.0, out
    assert (tmp_path / "demo" / "site" / "site.json").is_file()
    assert (tmp_path / "frames" / "pose").is_dir()
