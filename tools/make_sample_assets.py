"""Regenerate skinpipe/samples/captures: the bundled six-region capture set.

    python tools/make_sample_assets.py

Deterministic (fixed seed). The simulator's realistic preset (every capture effect
on: coarse pixels, a Gaussian projector footprint, a black level, a field the red tail
leaves, a P3 camera; docs/ingest.md). The forehead follows the seed paper's fitted
table; the other regions are dipoles from Jensen et al. 2001's measured skin
coefficients, varied per region (see skinpipe.capture.simulate.sample_subject_truths).
Lips and chin have hair strands across the spot; nose and cheek carry their exposure
times in EXIF only.
"""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

from skinpipe.capture.simulate import PRESETS, sample_subject_truths, simulate_capture_set

ROOT = Path(__file__).resolve().parents[1] / "skinpipe" / "samples" / "captures"


def main() -> None:
    base = PRESETS["realistic"]
    settings = {
        "default": base,
        "lips": replace(base, hair_strands=2),
        "chin": replace(base, hair_strands=3),
        "nose": replace(base, exposure_in_manifest=False),
        "cheek": replace(base, exposure_in_manifest=False),
    }
    staging = ROOT.with_name("captures.tmp")
    shutil.rmtree(staging, ignore_errors=True)
    simulate_capture_set(sample_subject_truths(), staging, settings, subject="sample_subject_01",
                         seed=2009, progress=print)
    shutil.rmtree(ROOT, ignore_errors=True)
    staging.rename(ROOT)
    print(f"wrote {ROOT}")


if __name__ == "__main__":
    main()
