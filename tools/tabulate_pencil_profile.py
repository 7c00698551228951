"""Regenerate skinpipe/profile/pencil_profile_table.py by Monte Carlo.

    python tools/tabulate_pencil_profile.py [--keep-rows]   (about 45 minutes on two cores)

``--keep-rows`` keeps the rows of the anisotropies the current table already holds
(their seeds would give them again) and traces only the new ones.

The multiply scattered part of a normal pencil's exit profile, seen from straight above,
of an index-matched half space of Henyey-Greenstein anisotropy g: the share of it that
leaves beyond radius r, for each g the medium inversion tries (those of
pencil_reflectance_table.py), on a grid of van de Hulst's similarity variable
s = sqrt((1 - alpha) / (1 - alpha g)) and of r in mean free paths. The closed-form
shapes the medium inversion also tries (Christensen & Burley 2015 and the diffusion
dipole) are fits and approximations; for skin1 of Jensen et al. 2001 their mean free
paths come out 16-23% long and 14-30% short, and an isotropic half space at the
similarity relation's reduced albedo and length is not an anisotropic one's shape near
the entry point (a traced g = 0.7 medium inverted that way missed its measured edge by
5.6% in blue where its own shape gives 3.7%). The tests' independent light tracer
(tests/physics/light_tracer.py ``trace``, held to Chandrasekhar's closed forms and to
Mitsuba 3's volpath) tallies it; its first collisions, all on the axis for a normal
pencil, are the single scattering the inversion adds exactly, and are taken out.

For the anisotropies beyond adding-doubling's reach (g > 0.7: see
tools/tabulate_pencil_reflectance.py) the tracer's total reflectance of each row is
written beside it (TRACED_REFLECTANCE), so that albedo and shape come from one tracer.
"""

from __future__ import annotations

import math
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from table_literal import rows_literal, wrapped

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from skinpipe.profile.pencil_reflectance_table import (  # noqa: E402
    ANISOTROPIES as ADDING_DOUBLING_ANISOTROPIES,
)
from tests.physics.light_tracer import (  # noqa: E402
    Medium,
    single_scattering_index_matched,
    trace,
)

S_GRID = tuple(float(round(x, 6)) for x in np.concatenate([
    np.geomspace(0.02, 0.2, 10), np.linspace(0.25, 0.95, 8)]))
RADII = tuple(float(round(x, 6)) for x in np.geomspace(0.01, 200.0, 72))
"""Radii in mean free paths at which the share beyond is tabulated."""
TRACED_ONLY = (0.8, 0.9)
"""Anisotropies whose reflectance the tracer gives too: skin's g is 0.8-0.9 (Jacques et
al. 1987), and a capture without an entry spike fits best at the largest g tried."""
ANISOTROPIES = ADDING_DOUBLING_ANISOTROPIES + TRACED_ONLY
PHOTONS = {0.0: 400_000}
"""Photons a row; rows of g > 0 take PHOTONS_ANISOTROPIC (a photon of g = 0.7 scatters
about three times as often before it leaves)."""
PHOTONS_ANISOTROPIC = 200_000
OUT = ROOT / "skinpipe" / "profile" / "pencil_profile_table.py"


def beyond(job: tuple[float, float, int]) -> tuple[list[float], float]:
    """The multiply scattered light's share beyond each of :data:`RADII` (sigma_t = 1)
    for anisotropy g at similarity variable s, and the total reflectance R (pi times
    the exit radiance seen from above per unit power)."""
    g, s, seed = job
    albedo = (1.0 - s * s) / (1.0 - g * s * s)
    medium = Medium(albedo, 1.0 - albedo, g)
    edges = np.asarray(RADII)
    tally = trace(medium, PHOTONS.get(g, PHOTONS_ANISOTROPIC), edges, seed=seed)
    sums = tally.ring_sums.copy() / tally.photons  # ring i: between RADII[i-1] and [i]
    sums[0] -= single_scattering_index_matched(medium)
    multiple = tally.total - single_scattering_index_matched(medium)
    within = np.cumsum(sums)
    return ([float(f"{max(0.0, 1.0 - w / multiple):.5g}") for w in within],
            float(f"{math.pi * tally.total:.6g}"))


def kept_rows() -> dict[float, list[list[float]]]:
    """The current table's rows per anisotropy, where its grids are the ones traced now."""
    from skinpipe.profile import pencil_profile_table as old

    if old.S_GRID != S_GRID or old.RADII != RADII:
        return {}
    return {g: [list(r) for r in rows] for g, rows in zip(old.ANISOTROPIES, old.BEYOND,
                                                          strict=True)}


def main() -> None:
    kept = kept_rows() if "--keep-rows" in sys.argv[1:] else {}
    kept = {g: rows for g, rows in kept.items() if g not in TRACED_ONLY}  # totals: traced
    # the isotropic rows keep their seeds (500 + i): the same table as before g was added
    jobs = [(g, s, 500 + 1000 * k + i) for k, g in enumerate(ANISOTROPIES)
            for i, s in enumerate(S_GRID) if g not in kept]
    with ProcessPoolExecutor(2) as pool:
        traced = dict(zip(jobs, pool.map(beyond, jobs), strict=True))
    for (g, s, _), (row, total) in traced.items():
        print(f"g = {g}, s = {s}: beyond 1 mfp {np.interp(0.0, np.log(RADII), row):.4f}"
              f", R {total:.4f}")
    rows: dict[float, list[list[float]]] = {g: list(kept.get(g, [])) for g in ANISOTROPIES}
    totals: dict[float, list[float]] = {g: [] for g in TRACED_ONLY}
    for (g, _, _), (row, total) in traced.items():
        if g in TRACED_ONLY:
            totals[g].append(total)
        rows[g].append(row)
    blocks = [rows_literal(rows[g]) for g in ANISOTROPIES]
    reflectance = "".join(f"    {g!r}: {wrapped(totals[g])},\n" for g in TRACED_ONLY)
    OUT.write_text(f'''"""Generated by tools/tabulate_pencil_profile.py (the tests' light tracer,
{PHOTONS[0.0]} photons a row at g = 0, {PHOTONS_ANISOTROPIC} beyond): do not edit.

BEYOND[k][i][j]: the share of the multiply scattered light of a normal pencil, seen from
straight above an index-matched half space of Henyey-Greenstein anisotropy
ANISOTROPIES[k] and albedo alpha with sqrt((1 - alpha) / (1 - alpha g)) = S_GRID[i],
that leaves beyond RADII[j] mean free paths of the entry point. TRACED_REFLECTANCE[g][i]:
the same trace's total reflectance (pi times the exit radiance seen from above per unit
power), for the anisotropies adding-doubling does not tabulate.
"""

ANISOTROPIES = {ANISOTROPIES!r}
S_GRID = {wrapped(S_GRID)}
RADII = {wrapped(RADII)}
BEYOND = (
''' + "".join(f"    (\n{b},\n    ),\n" for b in blocks) + f''')
TRACED_REFLECTANCE = {{
{reflectance}}}
''')
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
