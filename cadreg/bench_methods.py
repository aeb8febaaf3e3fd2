"""The names `cadreg bench --method` takes (`bench.py` says what each runs). Kept apart from the benchmark so that
the CLI lists them without importing the localizer and its compiled loops: every command, `cadreg serve` included,
builds the whole parser."""

from __future__ import annotations

from .config import REFINE_METHODS

BASE_METHODS = ("cadreg", "cadreg-nolabels", "fpfh-ransac", "kiss-matcher", "refine-from-gt-perturbed")
METHODS = BASE_METHODS + tuple(f"cadreg:{m}" for m in REFINE_METHODS) + tuple(
    f"refine-from-gt-perturbed:{m}" for m in REFINE_METHODS)
