"""Inspect fitted profiles in a USD asset: text summary and measured-vs-fitted plots.

The usdview plugin (skinpipe/usdview_plugin) calls :func:`plot_profile` for the selected
prim, so the command line and usdview draw the same figure.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..fileio import atomic_path
from ..profile.edge import edge_report
from ..profile.models import sum_of_gaussians
from ..profile.types import FitResult, MeasuredProfile
from .author import read_profiles

CHANNEL_COLOURS = ("tab:red", "tab:green", "tab:blue")


def describe_profile(path: str, fit: FitResult, measured: MeasuredProfile | None) -> str:
    """Terms per channel, errors and solver facts of one profile, as text."""
    lines = [f"{path}  region={fit.name}"]
    lines.append(f"  {'variance mm^2':>14} {'w_R':>8} {'w_G':>8} {'w_B':>8}")
    for v, w in zip(fit.variances_mm2, fit.weights, strict=True):
        lines.append(f"  {v:>14.6g} {w[0]:>8.4f} {w[1]:>8.4f} {w[2]:>8.4f}")
    sums = fit.weights.sum(axis=0)
    lines.append(f"  {'sum':>14} {sums[0]:>8.4f} {sums[1]:>8.4f} {sums[2]:>8.4f}")
    err = " ".join(f"{c}={e:.3e}" for c, e in zip("RGB", fit.error, strict=True))
    lines.append(f"  eq. 2c error: {err}")
    lines.append(f"  solver: {fit.solver or '?'}  status: {fit.status or '?'}"
                 + (f"  seconds: {fit.seconds:.3f}" if fit.seconds > 0 else ""))
    if fit.total_reflectance is not None:
        lines.append("  total reflectance: " + " ".join(f"{x:.4f}" for x in fit.total_reflectance))
    if measured is not None:
        lines.append(f"  measured: {measured.radius_mm.size} samples, "
                     f"{measured.radius_mm.min():.3f}-{measured.radius_mm.max():.3f} mm")
        edge = edge_report(measured.radius_mm, measured.values, fit.variances_mm2,
                           fit.weights)
        lines.append("  shadow edge: spread error " + " ".join(
            f"{c}={e:.2%}" for c, e in zip("RGB", edge["edge_error"], strict=True)))
        lines.append("  10-90% edge width mm (fit/measured): " + " ".join(
            f"{c}={a:.3g}/{b:.3g}" for c, a, b in zip(
                "RGB", edge["edge_width_mm"], edge["edge_width_measured_mm"], strict=True)))
        lines.append("  light in the shadow (fit/measured): " + " ".join(
            f"{c}={x:.3f}" for c, x in zip("RGB", edge["shadow_light_ratio"], strict=True)))
    return "\n".join(lines)


def describe_medium(prim: Any) -> str:
    """The medium other renderers get for this profile (its medium:* attributes: see
    docs/usd.md), as text; empty where none is authored."""
    def rgb(name: str) -> Any:
        attr = prim.GetAttribute(f"medium:{name}") if prim else None
        return None if not attr or attr.Get() is None else np.asarray(attr.Get(), float)

    mfp, albedo, colour, edge = (rgb(n) for n in (
        "meanFreePathMm", "singleScatteringAlbedo", "subsurfaceColor", "edgeError"))
    if mfp is None or albedo is None or colour is None:
        return ""
    g = prim.GetAttribute("medium:anisotropy").Get() or 0.0
    model = prim.GetAttribute("medium:model").Get() or "?"

    def three(values: Any, fmt: str) -> str:
        return " ".join(f"{c}={format(float(x), fmt)}" for c, x in zip("RGB", values,
                                                                      strict=True))

    lines = [f"  medium (OpenPBR subsurface): g={float(g):.1f}  model={model}",
             f"    mean free path mm: {three(mfp, '.4g')}",
             f"    single-scattering albedo: {three(albedo, '.5f')}",
             f"    subsurface colour: {three(colour, '.4f')}"]
    if edge is not None:
        lines.append(f"    model's edge-spread error: {three(edge, '.2%')}")
    return "\n".join(lines)


def plot_profile(fit: FitResult, measured: MeasuredProfile | None, out_png: str | Path,
                 log_radius: bool = False, title: str | None = None) -> Path:
    """Measured (points) and fitted (lines) profiles per channel, with residuals below."""
    import matplotlib  # lazy: 0.18 s to import

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: 0.56 s to import

    if measured is not None:
        r = measured.radius_mm
    else:
        r = np.linspace(0.0, 3.0 * float(np.sqrt(fit.variances_mm2.max())), 300)
    r_plot = np.geomspace(max(r[r > 0].min(), 1e-4), r.max(), 400) if log_radius else \
        np.linspace(r.min(), r.max(), 400)
    scale = 1.0 if fit.total_reflectance is None else fit.total_reflectance
    curve = sum_of_gaussians(fit.variances_mm2, fit.weights, r_plot) * scale
    rows = 2 if measured is not None else 1
    fig, axes = plt.subplots(rows, 1, figsize=(7, 6 if rows == 2 else 4), dpi=110,
                             sharex=True, squeeze=False,
                             gridspec_kw={"height_ratios": [3, 1][:rows]})
    ax = axes[0, 0]
    for c in range(3):
        ax.plot(r_plot, curve[:, c], color=CHANNEL_COLOURS[c], label=f"fit {'RGB'[c]}")
        if measured is not None:
            ax.plot(measured.radius_mm, measured.values[:, c], ".", ms=2.5,
                    color=CHANNEL_COLOURS[c], alpha=0.6, label=f"measured {'RGB'[c]}")
    ax.set_yscale("log")
    ax.set_ylabel("R(r)  [mm^-2]")
    heading = f"{fit.name}: eq. 2c error " + " ".join(f"{e:.2e}" for e in fit.error)
    if measured is not None:
        edge = edge_report(measured.radius_mm, measured.values, fit.variances_mm2,
                           fit.weights)
        heading += "\nshadow edge: spread error " + " ".join(
            f"{e:.2%}" for e in edge["edge_error"]) + "; 10-90% width fit/measured\n" + \
            " ".join(f"{a:.3g}/{b:.3g}" for a, b in zip(
                edge["edge_width_mm"], edge["edge_width_measured_mm"], strict=True)) + " mm"
    ax.set_title(title or heading, fontsize=9)
    ax.legend(fontsize=7, ncol=2)
    ax.grid(True, which="both", alpha=0.3)
    if measured is not None:
        fitted = sum_of_gaussians(fit.variances_mm2, fit.weights, measured.radius_mm) * scale
        rel = (measured.values - fitted) / np.maximum(np.abs(fitted), 1e-30)
        res_ax = axes[1, 0]
        for c in range(3):
            res_ax.plot(measured.radius_mm, rel[:, c], ".", ms=2, color=CHANNEL_COLOURS[c])
        res_ax.axhline(0.0, color="k", lw=0.6)
        res_ax.set_ylabel("(measured - fit) / fit")
        res_ax.set_ylim(-0.2, 0.2)
        res_ax.grid(True, alpha=0.3)
    axes[-1, 0].set_xlabel("radius from the entry point [mm]")
    if log_radius:
        axes[-1, 0].set_xscale("log")
    fig.tight_layout()
    out = Path(out_png)
    with atomic_path(out) as tmp:
        fig.savefig(tmp)
    plt.close(fig)
    return out


def profiles_on_stage(stage: Any, prim_path: str | None = None) -> dict[str, tuple]:
    """The stage's profiles (all, or the one at / bound under ``prim_path``)."""
    found = read_profiles(stage)
    if prim_path is None:
        return found
    if prim_path in found:
        return {prim_path: found[prim_path]}
    # a Mesh with the regions API: its targets
    prim = stage.GetPrimAtPath(prim_path)
    rel = prim.GetRelationship("skin:profiles") if prim else None
    if rel:
        return {str(t): found[str(t)] for t in rel.GetTargets() if str(t) in found}
    return {}
