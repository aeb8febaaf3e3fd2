"""Helpers shared by the tracking tests (no tests here): a small real 7-Scenes RedKitchen site, TSDF-fused from
frames the tracked ones do not include, built once per test session."""

from __future__ import annotations

from pathlib import Path

from cadreg.io.frames import RecordedFrames

# the map: every other frame of 200..249 (fast to fuse); the tracked frames are 250.. (never in the map)
MAP_INDICES = range(200, 250, 2)
SITE_ID = "rk-track"
_BUILT: dict[str, Path] = {}


def redkitchen_site(frames_dir: Path, root: Path) -> Path:
    """The bundle directory `root/rk-track` (built on first call; later calls return the same directory)."""
    if SITE_ID in _BUILT:
        return _BUILT[SITE_ID]
    from cadreg.site.fuse import fuse_site

    site = fuse_site(RecordedFrames.open(frames_dir), list(MAP_INDICES), site_id=SITE_ID)
    out = root / SITE_ID
    site.save(out)
    _BUILT[SITE_ID] = out
    return out
