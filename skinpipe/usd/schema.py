"""Registration of skinpipe's codeless USD schema, and typed access to its prims.

USD reads schema plugins once, when the schema registry is first queried; a plugin
registered later stays unknown without a warning. ``import skinpipe`` therefore calls
:func:`register_schema_plugin` before anything else touches USD.
"""

from __future__ import annotations

import os
from pathlib import Path

from pxr import Plug, Usd

from ..errors import SkinpipeError
from ..package_data import package_folder

PROFILE_TYPE = "SkinDiffusionProfile"
PROFILE_TFTYPE = "SkinpipeSkinDiffusionProfile"
REGIONS_API = "SkinProfileRegionsAPI"
REGIONS_API_TFTYPE = "SkinpipeSkinProfileRegionsAPI"
REGION_INDEX_PRIMVAR = "skin:regionIndex"
REGION_WEIGHTS_PRIMVAR = "skin:regionWeights"
PROFILES_REL = "skin:profiles"
SUBSET_FAMILY = "skinRegion"
WORKING_COLORSPACE = "lin_ap1_scene"
CAMERA_VISIBILITY_PRIMVAR = "skinpipe:cameraVisibility"
"""Constant bool primvar: false on an occluder skinpipe's camera must not see (it still
casts shadows). USD has no renderer-neutral attribute for it; other renderers read their
own (RenderMan ``ri:attributes:visibility:camera``, Arnold ``arnold:visibility:camera``,
Karma ``karma:object:rendervisibility``)."""


def schema_dir() -> Path:
    """Folder of plugInfo.json + generatedSchema.usda (``SKINPIPE_SCHEMA_DIR`` overrides)."""
    override = os.environ.get("SKINPIPE_SCHEMA_DIR")
    return Path(override) if override else package_folder("schemas")


def usdview_plugin_dir() -> Path:
    """Folder of the usdview plugin's plugInfo.json."""
    return package_folder("usdview_plugin")


def register_schema_plugin() -> bool:
    """Register the schema plugin with USD's plugin registry (idempotent).

    A missing plugin is not an import error: ``skinpipe validate`` must still run and
    report it (rule skinpipe:SchemaPluginRegistered), and :func:`require_schema` stops
    the verbs that author typed prims.
    """
    folder = schema_dir()
    if not (folder / "plugInfo.json").is_file():
        return False
    Plug.Registry().RegisterPlugins(str(folder))
    return True


def require_schema() -> None:
    """Raise a clear error when the schema plugin is not registered."""
    if not schema_is_registered():
        raise SkinpipeError(f"skinpipe's USD schema plugin is not registered (no plugInfo.json "
                            f"in {schema_dir()}?): refusing to author untyped profiles")


def schema_is_registered() -> bool:
    """True when USD knows SkinDiffusionProfile (with its fallbacks) and the regions API."""
    reg = Usd.SchemaRegistry()
    return (reg.FindConcretePrimDefinition(PROFILE_TYPE) is not None
            and reg.FindAppliedAPIPrimDefinition(REGIONS_API) is not None)


def pxr_plugin_path_line() -> str:
    """The environment line a usdview or DCC user adds to see the schema and plugin."""
    return f"export PXR_PLUGINPATH_NAME={schema_dir()}{os.pathsep}{usdview_plugin_dir()}" \
           f"${{PXR_PLUGINPATH_NAME:+{os.pathsep}$PXR_PLUGINPATH_NAME}}"


def plugin_path_note() -> str | None:
    """A note for users of plain USD tools when ``PXR_PLUGINPATH_NAME`` does not list
    the schema (skinpipe registers it for itself, usdview and DCCs do not), else None."""
    listed = [Path(p).resolve() for p in os.environ.get("PXR_PLUGINPATH_NAME", "").split(
        os.pathsep) if p]
    if schema_dir().resolve() in listed:
        return None
    return ("note: outside skinpipe, USD tools (usdview, DCCs) see SkinDiffusionProfile and "
            "SkinProfileRegionsAPI as unknown types and drop their fallbacks unless "
            "PXR_PLUGINPATH_NAME lists the schema; 'skinpipe env' prints the line")
