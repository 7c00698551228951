"""Benchmark: one 2D Gaussian blur of an RGBA float32 texture, ours vs OpenCV and scipy.

    python benchmarks/bench_blur.py [--size 1024] [--sigmas 1,4,16,64]

Same input, same run: skinpipe's OpenCL kernel (PoCL on the CPU; per-texel sigma and
coverage, so it does more work per tap than a fixed-sigma blur), cv2.GaussianBlur and
scipy.ndimage.gaussian_filter (both fixed sigma, truncated at 3 sigma). Reports
seconds, speed ratios, effective GB/s (two passes, each reading and writing the
texture) against a measured numpy copy bandwidth, and the error against scipy.
Also the recursive (Deriche IIR) blur of pipeline/recursive_blur.py, with a per-texel
sigma map and with one sigma, and its peak error against the exact Gaussian.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np


def best_of(fn: Callable[[], object], repeats: int = 3) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    import cv2
    from scipy.ndimage import gaussian_filter

    from pipeline.diffusion import OpenCLBlur
    from pipeline.recursive_blur import RecursiveBlur

    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--sigmas", default="1,4,16,64")
    parser.add_argument("-o", "--output", type=Path, default=Path("benchmarks/results/blur.json"))
    args = parser.parse_args()
    n = args.size
    tex = np.random.default_rng(0).random((n, n, 4), dtype=np.float32)
    nbytes = tex.nbytes
    copy_s = best_of(lambda: tex.copy())
    bandwidth = 2 * nbytes / copy_s  # a copy reads and writes
    floor_s = 4 * nbytes / bandwidth  # two passes, each reads and writes the texture
    blur = OpenCLBlur(np.ones((n, n), np.float32))
    iir = RecursiveBlur(n, n)
    rows = []
    for sigma in (float(s) for s in args.sigmas.split(",")):
        sig = np.full((n, n), sigma, np.float32)
        blur.upload(tex)
        blur.blur_in_place(sig, sig)  # warm-up: the first enqueue JIT-compiles
        ours_s = best_of(lambda sig=sig: blur.blur_in_place(sig, sig))
        ours = OpenCLBlur(np.ones((n, n), np.float32)).blur(tex, sig, sig)
        k = int(2 * np.ceil(3 * sigma) + 1)
        cv_s = best_of(lambda sigma=sigma, k=k: cv2.GaussianBlur(
            tex, (k, k), sigma, borderType=cv2.BORDER_REPLICATE))
        ref = gaussian_filter(tex.astype(np.float64), (sigma, sigma, 0), truncate=3.0,
                              mode="nearest")
        sp_s = best_of(lambda sigma=sigma: gaussian_filter(
            tex, (sigma, sigma, 0), truncate=3.0, mode="nearest"), repeats=1)
        m = int(3 * sigma) + 1
        err = float(np.max(np.abs(ours[m:-m, m:-m] - ref[m:-m, m:-m])) / np.abs(ref).max())
        # the recursive blur: per-texel sigma map, as the diffusion would run it; its
        # error against the exact Gaussian (not truncated at 3 sigma), on an impulse
        iir.upload(tex)
        iir.blur_in_place(sig, sig)
        iir_s = best_of(lambda sig=sig: iir.blur_in_place(sig, sig))
        iir_uniform_s = best_of(lambda sigma=sigma: iir.blur_in_place(sigma, sigma))
        half = int(8 * sigma) + 8
        impulse = np.zeros((2 * half + 1, 2 * half + 1, 4), np.float32)
        impulse[half, half] = 1.0
        got = RecursiveBlur(2 * half + 1, 2 * half + 1).blur(impulse, sigma, sigma)[..., 0]
        k1 = np.arange(-half, half + 1)
        g1 = np.exp(-k1 * k1 / (2 * sigma * sigma))
        g2 = np.outer(g1 / g1.sum(), g1 / g1.sum())
        iir_err = float(np.abs(got - g2).max() / g2.max())
        rows.append({"sigma": sigma, "ours_s": ours_s, "cv2_s": cv_s, "scipy_s": sp_s,
                     "recursive_s": iir_s, "recursive_uniform_s": iir_uniform_s,
                     "recursive_vs_cv2": iir_s / cv_s, "recursive_vs_floor": iir_s / floor_s,
                     "recursive_uniform_vs_floor": iir_uniform_s / floor_s,
                     "recursive_peak_error_vs_exact": iir_err,
                     "ours_vs_cv2": ours_s / cv_s, "ours_vs_scipy": ours_s / sp_s,
                     "ours_gbps": 4 * nbytes / ours_s / 1e9, "ours_vs_floor": ours_s / floor_s,
                     "max_rel_error_vs_scipy": err})
        print(f"sigma {sigma:>5g}: ours {ours_s * 1e3:8.1f} ms  cv2 {cv_s * 1e3:8.1f} ms  "
              f"scipy {sp_s * 1e3:8.1f} ms  ours/cv2 {ours_s / cv_s:6.2f}  "
              f"ours/floor {ours_s / floor_s:7.1f}  err {err:.1e}", flush=True)
        print(f"{'':>12} recursive: per-texel {iir_s * 1e3:7.1f} ms, uniform "
              f"{iir_uniform_s * 1e3:7.1f} ms  /cv2 {iir_s / cv_s:6.2f}  /floor "
              f"{iir_uniform_s / floor_s:5.1f} (uniform)  peak err vs exact {iir_err:.1e}",
              flush=True)
    doc = {"benchmark": "blur", "size": n, "channels": 4, "dtype": "float32",
           "copy_bandwidth_gbps": bandwidth / 1e9, "floor_s": floor_s, "rows": rows}
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"copy bandwidth {bandwidth / 1e9:.1f} GB/s, floor {floor_s * 1e3:.1f} ms; "
          f"wrote {args.output}")


if __name__ == "__main__":
    main()
