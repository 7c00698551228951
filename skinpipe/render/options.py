"""What a render can be asked for: the options, their allowed values and defaults (no
render machinery imported: the CLI builds its parsers from this module alone)."""

from __future__ import annotations

from dataclasses import dataclass

from ..errors import InputError

AOVS = ("beauty", "diffuse", "specular", "irradiance", "albedo")
"""The default AOVs (colours in the working space)."""
DATA_AOVS = ("region",)
"""AOVs on request: ``region``, the index of the face region the pixel shows (the
largest of its interpolated region weights; -1 off the skin), layer ``region.id``."""
TEXTURE_OUTPUTS = ("irradiance", "radiosity", "stretch", "region")
"""Texture-space maps on request, in ``<name>_uv.exr`` (row 0 is v = 1, as a texture):
irradiance (RGB, before scattering), radiosity (RGB, pi x the diffused exitant
radiance), stretch (mm per texel along u and v), region (index of the largest region
weight, -1 outside the charts), each with the charts' coverage."""
BLURS = ("recursive", "gather")
SHADOW_SAMPLING = ("adaptive", "interleaved", "full")
INTERLEAVE_PERIODS = (2, 4, 8)
"""Periods p of interleaved sampling (p x p classes of texels): p^2 must divide a
scrambled Sobol set's 2^m points for each class's share to be a net itself."""
LIGHT_SEQUENCES = ("stratified", "sobol")
DEFAULT_ROUGHNESS = 0.35
"""Beckmann roughness of the skin's specular lobe (Torrance-Sparrow)."""
DEFAULT_RHO_S = 0.25
"""Specular scale rho_s."""
TASK_SHARES = {"unwrap": 0.05, "bvh": 0.01, "texture_maps": 0.03, "albedo": 0.03,
               "irradiance": 0.35, "diffusion_layout": 0.02, "diffusion": 0.3,
               "bvh_camera": 0.01, "shade": 0.2}
"""Each render task's rough share of a first frame's time (measured on the demo scene
at texture sizes 1024-4096), for the progress bar's share done and time left."""
DEVICE_ENV = "SKINPIPE_OPENCL_DEVICE"
"""Environment variable naming the OpenCL device (same values as ``--device``)."""
DEVICE_HELP = ("OpenCL device: auto (CPU runtimes first: PoCL, then Intel's, then GPUs), "
               "cpu, gpu (a GPU first), a runtime (pocl, intel, nvidia, or its id such as "
               "intel-cpu), or else part of 'platform: device' (e.g. H200); default "
               f"${DEVICE_ENV} or auto")


LAYOUT_CACHE_ENV = "SKINPIPE_LAYOUT_CACHE"
"""Environment variable: the CLI's folder for the seam layout's tiles, or ``off``."""
LAYOUT_CACHE_HELP = (
    "folder that keeps each skin mesh's seam layout (the diffusion's chart tiles, which "
    "depend on geometry, UVs and texture size only) for the next render of the same asset "
    "and texture size: at texture 4096 most of a first render's time, 0.8 GB on disk for "
    "the demo face; least recently used layouts go past $SKINPIPE_LAYOUT_CACHE_GB "
    f"(default 8); 'off': none (default ${LAYOUT_CACHE_ENV}, else "
    "$XDG_CACHE_HOME/skinpipe/layouts or ~/.cache/skinpipe/layouts)")


@dataclass(frozen=True)
class RenderOptions:
    """Everything a render depends on besides the stage."""

    resolution: tuple[int, int] = (1024, 1024)
    texture_size: int = 1024
    aovs: tuple[str, ...] = AOVS
    light_samples: int = 16
    shadow_sampling: str = "interleaved"
    """'interleaved': each texel of a p x p block traces a p^2-th of the light samples
    and borrows the rest from its neighbours within p - 1 texels
    (:attr:`interleave_period`); 'adaptive': the same, then texels whose neighbourhood's
    rays disagree (penumbrae) trace the rest themselves; 'full': every texel traces all
    of them."""
    interleave_period: int = 0
    """The period p of interleaved and adaptive sampling (2, 4 or 8); 0: chosen per skin
    mesh from its texels per image pixel (:func:`~.lighting.interleave_period`: 2 unless
    a pixel holds p x p texels or more)."""
    light_sequence: str = "sobol"
    """Light sample points: 'sobol' (scrambled Sobol, light_samples rounded up to a power
    of two) or 'stratified' (a jittered grid)."""
    roughness: float = DEFAULT_ROUGHNESS
    rho_s: float = DEFAULT_RHO_S
    ior: float = 1.4
    """The skin's refractive index: light crossing its surface loses the Fresnel share of
    a smooth dielectric, relative to normal incidence (:mod:`.light.boundary`); 1:
    index-matched, no loss."""
    transmission: bool = True
    """Light through thin parts (:mod:`.light.thin_parts`): what a back point receives
    leaves the front through the volume."""
    albedo_split: float = 0.5
    """Exponent of the albedo applied before scattering (0.5: sqrt before and after)."""
    variance_grid: int = 12
    """0: every region's own variances (merged where equal); N > 0: all regions
    re-expressed on N shared variances (fewer blurs; the error is reported)."""
    scattering: bool = True
    blur: str = "recursive"
    """'recursive': Deriche IIR on a pyramid (cost independent of width); 'gather': the
    first per-tap kernel (cost grows with width), kept to compare against."""
    single_profile: str | None = None
    """None: each region its own profile; 'mean' or a region name: one for the face."""
    camera: str | None = None
    write_uvs: bool = True
    seed: int = 0
    half_float: bool = False
    """Write the EXR's AOVs as half float (16 bit) instead of float."""
    texture_outputs: tuple[str, ...] = ()
    """Texture-space maps to write (:data:`TEXTURE_OUTPUTS`)."""
    layout_cache: str | None = None
    """Folder where the seam layout's chart tiles are kept between renders
    (:mod:`~.tile_store`; they depend on the geometry, UVs and texture size only); None:
    made in every process. The CLI's default is :data:`LAYOUT_CACHE_HELP`'s."""
    device: str | None = None
    """OpenCL device (:data:`~.opencl.DEVICE_HELP`); None: ``$SKINPIPE_OPENCL_DEVICE``,
    else auto."""

    def __post_init__(self) -> None:
        w, h = self.resolution
        if not (1 <= w <= 16384 and 1 <= h <= 16384):
            raise InputError(f"resolution must be 1-16384 on each side, got {w}x{h}")
        bad = [a for a in self.aovs if a not in AOVS + DATA_AOVS]
        if bad or not self.aovs:
            raise InputError(f"unknown AOV(s) {bad}; choose from "
                             f"{', '.join(AOVS + DATA_AOVS)}")
        bad = [t for t in self.texture_outputs if t not in TEXTURE_OUTPUTS]
        if bad:
            raise InputError(f"unknown texture output(s) {bad}; choose from "
                             f"{', '.join(TEXTURE_OUTPUTS)}")
        if not 1 <= self.light_samples <= 1024:
            raise InputError(f"light samples must be 1-1024, got {self.light_samples}")
        if not 0.0 <= self.albedo_split <= 1.0:
            raise InputError(f"albedo split must be in [0, 1], got {self.albedo_split}")
        if self.shadow_sampling not in SHADOW_SAMPLING:
            raise InputError(f"unknown shadow sampling {self.shadow_sampling!r}; choose from "
                             f"{', '.join(SHADOW_SAMPLING)}")
        if self.interleave_period not in (0, *INTERLEAVE_PERIODS):
            raise InputError(f"interleave period must be 0 (auto) or one of "
                             f"{', '.join(map(str, INTERLEAVE_PERIODS))}, got "
                             f"{self.interleave_period}")
        if self.light_sequence not in LIGHT_SEQUENCES:
            raise InputError(f"unknown light sample sequence {self.light_sequence!r}; choose "
                             f"from {', '.join(LIGHT_SEQUENCES)}")
        if self.blur not in BLURS:
            raise InputError(f"unknown blur {self.blur!r}; choose from {', '.join(BLURS)}")
        if not 0 <= self.variance_grid <= 64:
            raise InputError(f"variance grid must be 0 (each region's own) to 64 variances, "
                             f"got {self.variance_grid}")
        if not 16 <= self.texture_size <= 16384:
            raise InputError(f"texture size must be 16-16384 texels, got {self.texture_size}")
        if self.layout_cache is not None and not str(self.layout_cache).strip():
            raise InputError("the layout cache must be a folder (or None for none), got ''")
        if not (0.01 <= self.roughness <= 1.0 and 0.0 <= self.rho_s <= 1.0):
            raise InputError("roughness must be in [0.01, 1] and rho_s in [0, 1]")
        if not 1.0 <= self.ior <= 3.0:  # NaN too
            raise InputError(f"the skin's refractive index (--ior) must be 1-3, got "
                             f"{self.ior}")
