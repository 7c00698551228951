"""Validation rules for skinpipe assets, registered with OpenUSD's ``pxr.UsdValidation``.

Each rule is a small function over a prim or a stage that returns the problems it finds,
each with the offending site (prim or property path). :func:`register_rules` registers
them with USD's validation registry as named validators with docs (keyword
``skinpipe``), so they run beside USD's built-in validators in one
``UsdValidation.ValidationContext``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape, quoteattr

import numpy as np
from pxr import Sdf, Sdr, Tf, Usd, UsdGeom, UsdShade, UsdValidation

from ..errors import InputError, SkinpipeError
from .io import composed_layer_files, usd_error_message
from .materialx import OPENPBR, is_materialx_id, network_problems
from .schema import (
    PROFILE_TYPE,
    PROFILES_REL,
    REGION_INDEX_PRIMVAR,
    REGION_WEIGHTS_PRIMVAR,
    REGIONS_API,
    SUBSET_FAMILY,
    schema_is_registered,
)

WEIGHT_SUM_TOLERANCE = 1e-4
MAX_VARIANCE_MM2 = 1e4
"""The widest term a profile may hold: the fit's largest plausible radius (100 mm)
squared."""
REGION_WEIGHT_TOLERANCE = 1e-3
KEYWORD = "skinpipe"

# Units (metersPerUnit, upAxis) are USD's own usdGeomValidators:StageMetadataChecker and
# subset partitions its usdGeomValidators:SubsetFamilies; we do not repeat them.
# Every built-in validator runs. One finding can be out of this USD build's reach:
# usd-core has no MaterialX Sdr plugin, so ShaderSdrCompliance cannot resolve MaterialX
# node ids (ND_*). Such findings are reported as "not-applicable", with the reason, and
# fail under --strict; skinpipe:MaterialXNetworkValid makes the same check against the
# MaterialX library's node definitions.
NOT_APPLICABLE = "not-applicable"
SDR_COMPLIANCE = "usdShadeValidators:ShaderSdrCompliance"
NOT_APPLICABLE_REASON = (
    "not applicable in this USD build: it has no MaterialX Sdr plugin (usd-core), so "
    "MaterialX node ids are unknown to its registry; skinpipe:MaterialXNetworkValid checks "
    "this shader against MaterialX's own node definitions instead")


@dataclass(frozen=True)
class Problem:
    """One finding: the rule, a message, the offending sites, error or warning."""

    rule: str
    message: str
    sites: tuple[str, ...]
    severity: str = "error"


@dataclass(frozen=True)
class Rule:
    name: str
    doc: str
    scope: str  # "prim" or "stage"
    check: Callable[[Any], list[tuple[str, str]]]  # -> [(message, site)]


RULES: list[Rule] = []


def rule(name: str, scope: str) -> Callable[[Callable[[Any], list[tuple[str, str]]]],
                                            Callable[[Any], list[tuple[str, str]]]]:
    """Declare a rule; its docstring is the documentation USD's registry shows."""

    def wrap(fn: Callable[[Any], list[tuple[str, str]]]) -> Callable[[Any], list[tuple[str, str]]]:
        RULES.append(Rule(f"{KEYWORD}:{name}", " ".join((fn.__doc__ or "").split()), scope, fn))
        return fn

    return wrap


def _value(prim: Any, name: str) -> Any:
    attr = prim.GetAttribute(name)
    return attr.Get() if attr and attr.HasAuthoredValue() else None


def _array(prim: Any, name: str, width: int = 1) -> np.ndarray | None:
    """An authored numeric attribute as an array; None where it is absent or not numbers
    (USD's AttributeTypeMismatch reports those)."""
    value = _value(prim, name)
    if value is None:
        return None
    try:
        arr = np.asarray(value, dtype=np.float64)
        return arr.reshape(-1, width) if width > 1 else arr.reshape(-1)
    except (TypeError, ValueError):
        return None


def _is_profile(prim: Any) -> bool:
    return bool(prim) and prim.GetTypeName() == PROFILE_TYPE


def _applied_api_names(prim: Any) -> list[str]:
    """API schemas authored on the prim (works without the schema plugin, too)."""
    ops = prim.GetMetadata("apiSchemas")
    return list(ops.GetAddedOrExplicitItems()) if ops is not None else []


# --------------------------------------------------------------------------------- rules


@rule("SchemaPluginRegistered", "stage")
def _schema_plugin(stage: Any) -> list[tuple[str, str]]:
    """skinpipe's schema plugin must be registered: without it SkinDiffusionProfile is an
    unknown type, its fallback values vanish and typed queries silently find nothing."""
    if schema_is_registered():
        return []
    return [("the skinpipe USD schema plugin is not registered (set PXR_PLUGINPATH_NAME, "
             "see 'skinpipe env')", "/")]


@rule("ColorSpaceNamed", "stage")
def _color_space(stage: Any) -> list[tuple[str, str]]:
    """The default prim must name its colour space (UsdColorSpaceAPI colorSpace:name, an
    OCIO interop id such as lin_ap1_scene): profile weights and albedo are colours."""
    prim = stage.GetDefaultPrim()
    if not prim:
        return [("no defaultPrim", "/")]
    api = Usd.ColorSpaceAPI(prim)
    attr = api.GetColorSpaceNameAttr()
    if not prim.HasAPI(Usd.ColorSpaceAPI) or not attr or not attr.HasAuthoredValue():
        return [("the default prim does not name its colour space (colorSpace:name)",
                 str(prim.GetPath()))]
    return []


@rule("MaterialXNetworkValid", "prim")
def _materialx_network(prim: Any) -> list[tuple[str, str]]:
    """A shader whose id is a MaterialX node definition (ND_*) must match it: the
    definition exists in MaterialX's standard libraries and every authored input and
    output is one of its ports, with the USD type of the port's MaterialX type."""
    return network_problems(prim)


@rule("ProfileRegionNamed", "prim")
def _region_named(prim: Any) -> list[tuple[str, str]]:
    """Every SkinDiffusionProfile names its face region (token region, non-empty)."""
    if not _is_profile(prim):
        return []
    region = _value(prim, "region")
    if not region:
        return [("region is empty or not authored", f"{prim.GetPath()}.region")]
    return []


@rule("ProfileArrayLengths", "prim")
def _array_lengths(prim: Any) -> list[tuple[str, str]]:
    """A profile has at least one term, one RGB weight per variance, and measured
    radius, values and stddev arrays of one length."""
    if not _is_profile(prim):
        return []
    v = _array(prim, "variances")
    w = _array(prim, "weights", 3)
    out = []
    if v is None or v.size == 0:
        out.append(("no variances", f"{prim.GetPath()}.variances"))
    elif w is None or w.shape[0] != v.size:
        out.append((f"{0 if w is None else w.shape[0]} weights for {v.size} variances",
                    f"{prim.GetPath()}.weights"))
    r = _array(prim, "measured:radiusMm")
    if r is not None:
        for name in ("measured:values", "measured:stddev"):
            a = _array(prim, name, 3)
            if a is not None and a.shape[0] != r.size:
                out.append((f"{name} has {a.shape[0]} samples, measured:radiusMm {r.size}",
                            f"{prim.GetPath()}.{name}"))
    return out


@rule("ProfileVariancesValid", "prim")
def _variances(prim: Any) -> list[tuple[str, str]]:
    """Variances (mm^2) are finite, > 0, at most 1e4 mm^2 (a 100 mm standard deviation:
    light that spreads wider than a face is no skin profile) and sorted ascending."""
    if not _is_profile(prim):
        return []
    v = _array(prim, "variances")
    if v is None or v.size == 0:
        return []
    site = f"{prim.GetPath()}.variances"
    if not np.all(np.isfinite(v)) or np.any(v <= 0) or np.any(v > MAX_VARIANCE_MM2):
        return [(f"variances must be finite, > 0 and <= {MAX_VARIANCE_MM2:g} mm^2, got "
                 f"[{', '.join(f'{x:.6g}' for x in v)}]", site)]
    if np.any(np.diff(v) < 0):
        return [(f"variances are not sorted ascending: {v.tolist()}", site)]
    return []


@rule("ProfileWeightsNormalized", "prim")
def _weights(prim: Any) -> list[tuple[str, str]]:
    """Weights are finite, >= 0 and sum to 1 per channel (tolerance 1e-4): the profile
    conserves energy and the albedo carries the tint (Park & Oh 2009, eq. 2b)."""
    if not _is_profile(prim):
        return []
    w = _array(prim, "weights", 3)
    if w is None or w.size == 0:
        return []
    site = f"{prim.GetPath()}.weights"
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        return [("weights must be finite and >= 0", site)]
    sums = w.sum(axis=0)
    bad = [f"{c}={s:.6g}" for c, s in zip("RGB", sums, strict=True)
           if abs(s - 1.0) > WEIGHT_SUM_TOLERANCE]
    if bad:
        return [(f"weights must sum to 1 per channel (tolerance {WEIGHT_SUM_TOLERANCE:g}): "
                 f"{', '.join(bad)}", site)]
    return []


@rule("ProfileFitErrorValid", "prim")
def _fit_error(prim: Any) -> list[tuple[str, str]]:
    """fit:error (eq. 2c per channel) and totalReflectance are finite and >= 0."""
    if not _is_profile(prim):
        return []
    out = []
    for name in ("fit:error", "totalReflectance"):
        value = _array(prim, name)
        if value is not None and (not np.all(np.isfinite(value)) or np.any(value < 0)):
            out.append((f"{name} must be finite and >= 0, got {value.tolist()}",
                        f"{prim.GetPath()}.{name}"))
    return out


@rule("MeasuredSamplesFinite", "prim")
def _measured(prim: Any) -> list[tuple[str, str]]:
    """Measured samples are finite and their radii >= 0 mm."""
    if not _is_profile(prim):
        return []
    out = []
    for name in ("measured:radiusMm", "measured:values", "measured:stddev"):
        a = _array(prim, name)
        if a is not None and not np.all(np.isfinite(a)):
            out.append((f"{int((~np.isfinite(a)).sum())} non-finite value(s)",
                        f"{prim.GetPath()}.{name}"))
    r = _array(prim, "measured:radiusMm")
    if r is not None and np.any(r < 0):
        out.append(("negative radius", f"{prim.GetPath()}.measured:radiusMm"))
    return out


MEDIUM_RANGES = {
    "medium:singleScatteringAlbedo": (0.0, 1.0, True),
    "medium:subsurfaceColor": (0.0, 1.0, True),
    "medium:meanFreePathMm": (0.0, math.inf, False),
    "medium:totalReflectance": (0.0, math.inf, False),
    "medium:anisotropy": (-1.0, 1.0, True),
    "medium:error": (0.0, math.inf, True),
    "medium:edgeError": (0.0, math.inf, True),
}
"""Each medium attribute's (low, high, low allowed): what OpenPBR and a volumetric
renderer accept (a mean free path of 0 would be an opaque surface, not this medium)."""


@rule("ProfileMediumValid", "prim")
def _medium(prim: Any) -> list[tuple[str, str]]:
    """The medium on a profile, where authored, is one a renderer can build: albedo and
    subsurfaceColor in [0, 1], meanFreePathMm and totalReflectance finite and > 0,
    anisotropy in [-1, 1], the errors finite and >= 0."""
    if not _is_profile(prim):
        return []
    out = []
    for name, (low, high, closed) in MEDIUM_RANGES.items():
        value = _array(prim, name)
        if value is None:
            continue
        inside = (value >= low) if closed else (value > low)
        if not (np.all(np.isfinite(value)) and np.all(inside) and np.all(value <= high)):
            bound = "[" if closed else "("
            out.append((f"{name} must be finite and in {bound}{low:g}, {high:g}], got "
                        f"{value.tolist()}", f"{prim.GetPath()}.{name}"))
    return out


PROFILE_RULES = ("ProfileArrayLengths", "ProfileVariancesValid", "ProfileWeightsNormalized",
                 "ProfileFitErrorValid", "MeasuredSamplesFinite")


def profile_problems(prim: Any) -> list[Problem]:
    """The findings of the profile rules on one SkinDiffusionProfile prim: what ``render``
    refuses to use is what ``validate`` fails, under the same rule names."""
    wanted = {f"{KEYWORD}:{name}" for name in PROFILE_RULES}
    return [Problem(r.name, message, (site,)) for r in RULES if r.name in wanted
            for message, site in r.check(prim)]


def _is_regions_mesh(prim: Any) -> bool:
    """A Mesh with SkinProfileRegionsAPI (RegionsApiOnMesh reports the API elsewhere)."""
    return prim.GetTypeName() == "Mesh" and REGIONS_API in _applied_api_names(prim)


def _profile_targets(prim: Any) -> list[Any]:
    rel = prim.GetRelationship(PROFILES_REL)
    return list(rel.GetTargets()) if rel else []


@rule("RegionsApiOnMesh", "prim")
def _api_on_mesh(prim: Any) -> list[tuple[str, str]]:
    """SkinProfileRegionsAPI is applied to Mesh prims only."""
    if REGIONS_API in _applied_api_names(prim) and prim.GetTypeName() != "Mesh":
        return [(f"{REGIONS_API} applied to a {prim.GetTypeName() or 'typeless'} prim",
                 str(prim.GetPath()))]
    return []


@rule("RegionProfilesTargetsValid", "prim")
def _targets(prim: Any) -> list[tuple[str, str]]:
    """skin:profiles has at least one target, and every target exists and is a
    SkinDiffusionProfile."""
    if not _is_regions_mesh(prim):
        return []
    site = f"{prim.GetPath()}.{PROFILES_REL}"
    targets = _profile_targets(prim)
    if not targets:
        return [("no profile targets", site)]
    stage = prim.GetStage()
    bad = [str(t) for t in targets if not _is_profile(stage.GetPrimAtPath(t))]
    return [(f"target(s) {bad} missing or not {PROFILE_TYPE}", site)] if bad else []


@rule("RegionIndexValid", "prim")
def _region_index(prim: Any) -> list[tuple[str, str]]:
    """primvars:skin:regionIndex is uniform, has one value per face and every value is a
    valid index into skin:profiles: every face is covered by a profile."""
    if not _is_regions_mesh(prim):
        return []
    site = f"{prim.GetPath()}.primvars:{REGION_INDEX_PRIMVAR}"
    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar(REGION_INDEX_PRIMVAR)
    if not pv or not pv.HasAuthoredValue():
        return [("region index primvar missing", site)]
    if pv.GetInterpolation() != UsdGeom.Tokens.uniform:
        return [(f"interpolation is {pv.GetInterpolation()}, must be uniform", site)]
    idx = np.asarray(pv.Get(), dtype=np.int64)
    n_faces = len(UsdGeom.Mesh(prim).GetFaceVertexCountsAttr().Get() or [])
    n_regions = len(_profile_targets(prim))
    if idx.size != n_faces:
        return [(f"{idx.size} region indices for {n_faces} faces", site)]
    bad = np.flatnonzero((idx < 0) | (idx >= n_regions))
    if bad.size:
        return [(f"{bad.size} face(s) with a region index outside 0..{n_regions - 1} (first: "
                 f"face {int(bad[0])} -> {int(idx[bad[0]])})", site)]
    return []


@rule("RegionWeightsValid", "prim")
def _region_weights(prim: Any) -> list[tuple[str, str]]:
    """Optional primvars:skin:regionWeights: vertex interpolation, elementSize = number of
    regions, one row per point, finite, >= 0, each row summing to 1 (tolerance 1e-3)."""
    if not _is_regions_mesh(prim):
        return []
    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar(REGION_WEIGHTS_PRIMVAR)
    if not pv or not pv.HasAuthoredValue():
        return []
    site = f"{prim.GetPath()}.primvars:{REGION_WEIGHTS_PRIMVAR}"
    n_regions = len(_profile_targets(prim))
    if pv.GetInterpolation() != UsdGeom.Tokens.vertex:
        return [(f"interpolation is {pv.GetInterpolation()}, must be vertex", site)]
    if pv.GetElementSize() != n_regions:
        return [(f"elementSize {pv.GetElementSize()} != {n_regions} regions", site)]
    w = np.asarray(pv.Get(), dtype=np.float64)
    n_points = len(UsdGeom.Mesh(prim).GetPointsAttr().Get() or [])
    if w.size != n_points * n_regions:
        return [(f"{w.size} values for {n_points} points x {n_regions} regions", site)]
    w = w.reshape(n_points, n_regions)
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        return [("weights must be finite and >= 0", site)]
    off = np.abs(w.sum(axis=1) - 1.0) > REGION_WEIGHT_TOLERANCE
    if off.any():
        return [(f"{int(off.sum())} point(s) whose weights do not sum to 1", site)]
    return []


@rule("RegionSubsetsPartition", "prim")
def _subsets(prim: Any) -> list[tuple[str, str]]:
    """The skinRegion GeomSubsets partition the faces, one subset per region, each
    holding exactly the faces whose region index points at it."""
    if not _is_regions_mesh(prim):
        return []
    mesh = UsdGeom.Mesh(prim)
    subsets = UsdGeom.Subset.GetGeomSubsets(mesh, UsdGeom.Tokens.face, SUBSET_FAMILY)
    site = str(prim.GetPath())
    n_regions = len(_profile_targets(prim))
    if len(subsets) != n_regions:
        return [(f"{len(subsets)} {SUBSET_FAMILY} subsets for {n_regions} regions", site)]
    if UsdGeom.Subset.GetFamilyType(mesh, SUBSET_FAMILY) != UsdGeom.Tokens.partition:
        return [(f"family {SUBSET_FAMILY} is not of type partition", site)]
    n_faces = len(mesh.GetFaceVertexCountsAttr().Get() or [])
    valid, reason = UsdGeom.Subset.ValidateSubsets(subsets, n_faces, UsdGeom.Tokens.partition)
    if not valid:
        return [(f"subsets are not a partition of the {n_faces} faces: {reason}", site)]
    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar(REGION_INDEX_PRIMVAR)
    idx = np.asarray(pv.Get(), dtype=np.int64) if pv and pv.HasAuthoredValue() else None
    targets = _profile_targets(prim)
    if idx is None or idx.size != n_faces or idx.min() < 0 or idx.max() >= len(targets):
        return []  # RegionIndexValid reports it
    if not all(_is_profile(prim.GetStage().GetPrimAtPath(t)) for t in targets):
        return []  # RegionProfilesTargetsValid reports it
    for i, target in enumerate(targets):
        name = target.name
        match = [s for s in subsets if s.GetPrim().GetName() == name]
        if not match:
            return [(f"no subset named {name!r} for region {i}", site)]
        faces = np.sort(np.asarray(match[0].GetIndicesAttr().Get(), dtype=np.int64))
        if not np.array_equal(faces, np.flatnonzero(idx == i)):
            return [(f"subset {name!r} does not hold the faces of region index {i}",
                     str(match[0].GetPrim().GetPath()))]
    return []


# --------------------------------------------------------------------------- registration

_REGISTERED = False


def register_rules() -> list[Any]:
    """Register every rule with UsdValidation (once); return our validators."""
    global _REGISTERED
    registry = UsdValidation.ValidationRegistry()
    if not hasattr(registry, "RegisterStageValidator"):  # usd-core 26.3 and older
        raise SkinpipeError(
            f"usd-core {'.'.join(map(str, Usd.GetVersion()[1:]))} cannot register "
            "validation rules from Python; skinpipe needs usd-core 26.5 or newer "
            "(pip install -U usd-core)")
    if not _REGISTERED:
        for r in RULES:
            if registry.HasValidator(r.name):
                continue
            meta = UsdValidation.ValidatorMetadata(name=r.name, doc=r.doc, keywords=[KEYWORD])

            def make(r: Rule) -> Callable[..., list[Any]]:
                def task(obj: Any, time_range: Any = None) -> list[Any]:
                    if r.scope == "prim" and obj.IsPseudoRoot():
                        return []
                    stage = obj if r.scope == "stage" else obj.GetStage()
                    try:
                        found = r.check(obj)
                    except Exception as exc:  # a rule must fail the file, never the run
                        found = [(f"the rule could not check this: {type(exc).__name__}: "
                                  f"{exc}", "/" if r.scope == "stage" else str(obj.GetPath()))]
                    return [UsdValidation.ValidationError(
                        r.name.split(":")[1], UsdValidation.ValidationErrorType.Error,
                        [UsdValidation.ValidationErrorSite(stage, Sdf.Path(site))], message)
                        for message, site in found]
                return task

            if r.scope == "stage":
                registry.RegisterStageValidator(meta, make(r))
            else:
                registry.RegisterPrimValidator(meta, make(r))
        _REGISTERED = True
    return [registry.GetOrLoadValidatorByName(r.name) for r in RULES]


def _validators(include_builtin: bool) -> list[Any]:
    ours = register_rules()
    if not include_builtin:
        return ours
    registry = UsdValidation.ValidationRegistry()
    names = {r.name for r in RULES}
    builtin = [v for v in registry.GetOrLoadAllValidators()
               if v.GetMetadata().name not in names and not v.GetMetadata().isSuite]
    return ours + builtin


# ------------------------------------------------------------------------------ running


@dataclass
class FileReport:
    path: str
    problems: list[Problem] = field(default_factory=list)
    unreadable: str | None = None
    seconds: float = 0.0

    def failed(self, strict: bool) -> bool:
        """Errors fail; warnings and findings out of this USD build's reach fail with
        ``strict``."""
        return self.unreadable is not None or any(
            p.severity == "error" or strict for p in self.problems)


def validate_file(path: str | Path, include_builtin: bool = True,
                  context: Any = None) -> FileReport:
    """Run USD's built-in validators and ours on one file (opened after a safety check)."""
    start = time.perf_counter()
    report = FileReport(str(path))
    try:
        composed_layer_files(path)
        stage = Usd.Stage.Open(str(path))
        if stage is None:
            raise InputError("USD cannot open it", path)
    except (InputError, Tf.ErrorException) as exc:
        report.unreadable = usd_error_message(exc)
        report.seconds = time.perf_counter() - start
        return report
    ctx = context or UsdValidation.ValidationContext(_validators(include_builtin))
    for err in ctx.Validate(stage):
        validator = err.GetValidator()
        name = validator.GetMetadata().name if validator else err.GetName()
        sites = tuple(str(s.GetPrim().GetPath()) if s.IsPrim() else
                      str(s.GetProperty().GetPath()) if s.IsProperty() else "/"
                      for s in err.GetSites())
        severity = {UsdValidation.ValidationErrorType.Warn: "warning",
                    UsdValidation.ValidationErrorType.Info: "info"}.get(err.GetType(), "error")
        message = err.GetMessage()
        if _beyond_this_build(name, err.GetName(), sites, stage):
            severity, message = NOT_APPLICABLE, f"{message} ({NOT_APPLICABLE_REASON})"
        report.problems.append(Problem(name, message, sites, severity))
    report.seconds = time.perf_counter() - start
    return report


@lru_cache(maxsize=1)
def _materialx_in_sdr() -> bool:
    return Sdr.Registry().GetShaderNodeByIdentifier(OPENPBR) is not None


def _beyond_this_build(validator: str, error: str, sites: tuple[str, ...], stage: Any) -> bool:
    """Whether a finding is ShaderSdrCompliance failing to resolve a MaterialX node id
    in a USD build without MaterialX."""
    if validator != SDR_COMPLIANCE or error != "MissingShaderIdInRegistry" or \
            _materialx_in_sdr():
        return False
    for site in sites:
        prim = stage.GetPrimAtPath(Sdf.Path(site).GetPrimPath())
        shader_id = UsdShade.Shader(prim).GetShaderId() if prim else None
        if not shader_id or not is_materialx_id(shader_id):
            return False
    return bool(sites)


def validate_files(paths: Sequence[str | Path], include_builtin: bool = True) -> list[FileReport]:
    """Validate several files with one validation context."""
    context = UsdValidation.ValidationContext(_validators(include_builtin))
    return [validate_file(p, include_builtin, context) for p in paths]


def junit_xml(reports: Sequence[FileReport], strict: bool = False) -> str:
    """JUnit XML: one test suite per file, one test case per rule."""
    lines = ['<?xml version="1.0" encoding="UTF-8"?>', "<testsuites>"]
    for rep in reports:
        cases = []
        if rep.unreadable is not None:
            cases.append(("open", [Problem("open", rep.unreadable, ())]))
        else:
            names = [r.name for r in RULES] + sorted({p.rule for p in rep.problems} -
                                                     {r.name for r in RULES})
            for name in names:
                found = [p for p in rep.problems if p.rule == name
                         and (p.severity == "error" or strict)]
                cases.append((name, found))
        failures = sum(1 for _, f in cases if f)
        lines.append(f"  <testsuite name={quoteattr(rep.path)} tests=\"{len(cases)}\" "
                     f"failures=\"{failures}\" time=\"{rep.seconds:.3f}\">")
        for name, found in cases:
            lines.append(f"    <testcase classname={quoteattr(rep.path)} name={quoteattr(name)}>")
            for p in found:
                lines.append(f"      <failure message={quoteattr(p.message)}>"
                             f"{escape(', '.join(p.sites))}</failure>")
            lines.append("    </testcase>")
        lines.append("  </testsuite>")
    lines.append("</testsuites>")
    return "\n".join(lines) + "\n"
