"""Regenerate sample_assets/captures: the bundled six-region capture set.

    python tools/make_sample_assets.py

Deterministic (fixed seed). The forehead follows the seed paper's fitted table; the
other regions are dipoles from Jensen et al. 2001's measured skin coefficients, varied
per region (see pipeline.capture.simulate.sample_subject_truths). Lips and chin have hair strands
across the spot; nose and cheek carry their exposure times in EXIF only.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from pipeline.capture.simulate import CaptureSettings, sample_subject_truths, simulate_capture_set

ROOT = Path(__file__).resolve().parents[1] / "sample_assets" / "captures"


def main() -> None:
    base = CaptureSettings()
    settings = {
        "default": base,
        "lips": CaptureSettings(hair_strands=2),
        "chin": CaptureSettings(hair_strands=3),
        "nose": CaptureSettings(exposure_in_manifest=False),
        "cheek": CaptureSettings(exposure_in_manifest=False),
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
