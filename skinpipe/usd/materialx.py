"""The skin material as MaterialX: an OpenPBR network in USD's ``mtlx`` render context
and the same network as a ``.mtlx`` document, both checked against the node definitions
of the ``materialx`` package (MaterialX 1.39's standard libraries).

usd-core has no MaterialX plugin, so USD's Sdr registry does not know ``ND_*`` node ids;
:func:`network_problems` is the check USD's ShaderSdrCompliance validator would make
(every node id defined, every input and output of the definition's type), made with
MaterialX's own definitions instead.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import MaterialX as mx
import numpy as np
from pxr import Gf, Sdf, UsdShade

from ..errors import SkinpipeError
from ..fileio import atomic_write_text

MTLX_COLORSPACE = "acescg"
"""MaterialX's name of the working space (OCIO interop id ``lin_ap1_scene``)."""
MX_TO_SDF = {"color3": "color3f", "color4": "color4f", "float": "float", "vector2": "float2",
             "vector3": "float3", "vector4": "float4", "filename": "asset", "string": "string",
             "integer": "int", "boolean": "bool", "surfaceshader": "token",
             "material": "token"}
"""USD's value type for each MaterialX type (as usdMtlx maps them)."""
OPENPBR = "ND_open_pbr_surface_surfaceshader"
IMAGE = "ND_image_color3"
TEXCOORD = "ND_texcoord_vector2"
MULTIPLY = "ND_multiply_color3"


@lru_cache(maxsize=1)
def library() -> Any:
    """MaterialX's standard data libraries (node definitions), loaded once."""
    lib = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), lib)
    return lib


def is_materialx_id(shader_id: str) -> bool:
    """Whether ``shader_id`` names a node definition of MaterialX's libraries."""
    return library().getNodeDef(shader_id) is not None


def network_problems(prim: Any) -> list[tuple[str, str]]:
    """(message, site) for a UsdShade shader whose id is a MaterialX node definition
    (``ND_*``): the definition must exist and every authored input and output must be
    one of its ports, of its type."""
    shader = UsdShade.Shader(prim)
    if not shader:
        return []
    shader_id = shader.GetShaderId() or ""
    if not shader_id.startswith("ND_"):
        return []
    nodedef = library().getNodeDef(shader_id)
    if nodedef is None:
        return [(f"{shader_id} is not a MaterialX node definition", f"{prim.GetPath()}.info:id")]
    out = []
    ports = [(p.GetBaseName(), p.GetTypeName(), p.GetAttr().GetPath(), nodedef.getActiveInput)
             for p in shader.GetInputs(False)]
    ports += [(p.GetBaseName(), p.GetTypeName(), p.GetAttr().GetPath(), nodedef.getActiveOutput)
              for p in shader.GetOutputs(False)]
    for name, type_name, site, lookup in ports:
        port = lookup(str(name))
        if port is None:
            out.append((f"{shader_id} has no port {name!r}", str(site)))
            continue
        want = MX_TO_SDF.get(port.getType())
        if want is not None and str(type_name) != want:
            out.append((f"{site} is {type_name}, {shader_id}.{name} is "
                        f"{port.getType()} ({want} in USD)", str(site)))
    return out


def _sdf(mx_type: str) -> Any:
    """USD's value type for a MaterialX type."""
    return Sdf.ValueTypeNames.Find(MX_TO_SDF[mx_type])


def author_usd_network(stage: Any, material_path: str, values: Mapping[str, Any]) -> Any:
    """The OpenPBR shader (``values``: input name -> float or RGB) under the material,
    wired to its ``outputs:mtlx:surface``; returns the shader."""
    nodedef = library().getNodeDef(OPENPBR)
    shader = UsdShade.Shader.Define(stage, f"{material_path}/OpenPBR")
    shader.CreateIdAttr(OPENPBR)
    for name, value in values.items():
        kind = nodedef.getActiveInput(name).getType()
        v = Gf.Vec3f(*(float(x) for x in value)) if kind == "color3" else float(value)
        shader.CreateInput(name, _sdf(kind)).Set(v)
    material = UsdShade.Material(stage.GetPrimAtPath(material_path))
    material.CreateSurfaceOutput("mtlx").ConnectToSource(
        shader.CreateOutput("out", _sdf("surfaceshader")))
    return shader


def usd_network_values(shader: Any) -> dict[str, Any]:
    """The OpenPBR input values authored on ``shader`` (as :func:`author_usd_network`
    takes them)."""
    out: dict[str, Any] = {}
    for port in shader.GetInputs(False):
        value = port.GetAttr().Get()
        if value is not None:
            out[str(port.GetBaseName())] = tuple(value) if hasattr(value, "__len__") \
                else float(value)
    return out


def subsurface_factor(values: Mapping[str, Any]) -> tuple[float, float, float]:
    """subsurface_color / base_color of a material's values: what turns an albedo
    texture (which replaces base_color) into the subsurface colour about the albedo the
    medium was inverted at, so that painted detail reaches the subsurface too."""
    base = np.maximum(np.asarray(values["base_color"], dtype=np.float64), 1e-6)
    ratio = np.asarray(values["subsurface_color"], dtype=np.float64) / base
    return (float(ratio[0]), float(ratio[1]), float(ratio[2]))


@dataclass(frozen=True)
class SubsurfaceMaps:
    """Painted subsurface inputs: ``colour`` (ACEScg) and ``radius_scale`` (data) texture
    paths, and the ``radius`` (scene units) the scale multiplies."""

    colour: str
    radius_scale: str
    radius: float


def _usd_image(stage: Any, path: str, texture: str, colorspace: str | None,
               coords: Any) -> Any:
    """A MaterialX image (color3) shader reading ``texture`` at ``coords``; its output."""
    image = UsdShade.Shader.Define(stage, path)
    image.CreateIdAttr(IMAGE)
    file_input = image.CreateInput("file", _sdf("filename"))
    file_input.Set(Sdf.AssetPath(texture))
    if colorspace is not None:
        file_input.GetAttr().SetColorSpace(colorspace)
    image.CreateInput("texcoord", _sdf("vector2")).ConnectToSource(coords)
    return image.CreateOutput("out", _sdf("color3"))


def author_usd_texture(stage: Any, material_path: str, texture: str, colorspace: str,
                       maps: SubsurfaceMaps | None = None) -> None:
    """A MaterialX image (color3) reading ``texture`` by the default texture coordinates,
    feeding OpenPBR's base colour, and through a multiply by :func:`subsurface_factor`
    its subsurface colour; with ``maps``, the subsurface colour and radius scale read
    those instead."""
    coords = UsdShade.Shader.Define(stage, f"{material_path}/MtlxTexcoord")
    coords.CreateIdAttr(TEXCOORD)
    uv = coords.CreateOutput("out", _sdf("vector2"))
    color = _usd_image(stage, f"{material_path}/MtlxAlbedo", texture, colorspace, uv)
    openpbr = UsdShade.Shader(stage.GetPrimAtPath(f"{material_path}/OpenPBR"))
    openpbr.GetInput("base_color").ConnectToSource(color)
    if maps is not None:
        openpbr.GetInput("subsurface_color").ConnectToSource(_usd_image(
            stage, f"{material_path}/MtlxSubsurfaceColorMap", maps.colour, colorspace, uv))
        openpbr.GetInput("subsurface_radius_scale").ConnectToSource(_usd_image(
            stage, f"{material_path}/MtlxSubsurfaceRadiusScaleMap", maps.radius_scale, None,
            uv))
        openpbr.GetInput("subsurface_radius").Set(float(maps.radius))
        return
    factor = subsurface_factor(usd_network_values(openpbr))
    scale = UsdShade.Shader.Define(stage, f"{material_path}/MtlxSubsurfaceColor")
    scale.CreateIdAttr(MULTIPLY)
    scale.CreateInput("in1", _sdf("color3")).ConnectToSource(color)
    scale.CreateInput("in2", _sdf("color3")).Set(Gf.Vec3f(*factor))
    openpbr.GetInput("subsurface_color").ConnectToSource(
        scale.CreateOutput("out", _sdf("color3")))


def mtlx_document(materials: Mapping[str, Mapping[str, Any]], texture: str | None = None,
                  maps: Mapping[str, SubsurfaceMaps] | None = None) -> Any:
    """The materials as a MaterialX document: per name a surfacematerial over an
    open_pbr_surface (``values`` as in :func:`author_usd_network`; the shader of
    ``SkinMaterial`` is named ``OpenPBR``, others ``OpenPBR_<name>``), with one image node
    for ``texture`` feeding each base colour and, scaled, each subsurface colour (or, for
    a material in ``maps``, its painted subsurface maps); raises :class:`SkinpipeError`
    unless MaterialX's ``validate()`` accepts each element."""
    doc = mx.createDocument()
    doc.importLibrary(library())
    doc.setColorSpace(MTLX_COLORSPACE)
    nodedef = library().getNodeDef(OPENPBR)
    image = None
    if texture is not None:
        coords = doc.addNode("texcoord", "MtlxTexcoord", "vector2")
        image = doc.addNode("image", "MtlxAlbedo", "color3")
        file_input = image.addInput("file", "filename")
        file_input.setValueString(texture)
        file_input.setColorSpace(MTLX_COLORSPACE)
        image.addInput("texcoord", "vector2").setConnectedNode(coords)
    for name, values in materials.items():
        shader_name = "OpenPBR" if name == "SkinMaterial" else f"OpenPBR_{name}"
        shader = doc.addNode("open_pbr_surface", shader_name, "surfaceshader")
        for key, value in values.items():
            kind = nodedef.getActiveInput(key).getType()
            port = shader.addInput(key, kind)
            if kind == "color3":
                port.setValue(mx.Color3(*(float(x) for x in value)))
            else:
                port.setValue(float(value))
        painted = (maps or {}).get(name)
        if image is not None:
            shader.getInput("base_color").setConnectedNode(image)
        if image is not None and painted is not None:
            for key, file, node, space in (
                    ("subsurface_color", painted.colour, "SubsurfaceColorMap", MTLX_COLORSPACE),
                    ("subsurface_radius_scale", painted.radius_scale,
                     "SubsurfaceRadiusScaleMap", None)):
                reader = doc.addNode("image", f"{node}_{name}", "color3")
                reader_file = reader.addInput("file", "filename")
                reader_file.setValueString(file)
                if space is not None:
                    reader_file.setColorSpace(space)
                reader.addInput("texcoord", "vector2").setConnectedNode(coords)
                shader.getInput(key).setConnectedNode(reader)
            shader.getInput("subsurface_radius").setValue(float(painted.radius))
        elif image is not None:
            scale = doc.addNode("multiply", f"SubsurfaceColor_{name}", "color3")
            scale.addInput("in1", "color3").setConnectedNode(image)
            scale.addInput("in2", "color3").setValue(mx.Color3(*subsurface_factor(values)))
            shader.getInput("subsurface_color").setConnectedNode(scale)
        material = doc.addMaterialNode(name, shader)
        assert material is not None
    problems = document_problems(doc)
    if problems:
        raise SkinpipeError(f"the MaterialX document is not valid: {' '.join(problems)}")
    return doc


def document_problems(doc: Any) -> list[str]:
    """MaterialX's ``validate()`` messages for the elements of ``doc`` that are not from an
    imported library (nodes against their nodedefs, the types of connections). The
    document's own ``validate()`` walks the whole library as well, 0.14-0.33 s a call,
    and gives the same verdict on what is ours."""
    return [message.strip() for element in doc.getChildren() if not element.hasSourceUri()
            for ok, message in [element.validate()] if not ok]


def write_mtlx(path: Path, materials: Mapping[str, Mapping[str, Any]],
               texture: str | None = None) -> Path:
    """Write :func:`mtlx_document` to ``path`` (atomically), without the libraries."""
    return write_mtlx_document(path, mtlx_document(materials, texture))


def write_mtlx_document(path: Path, doc: Any) -> Path:
    """Write a document of :func:`mtlx_document` to ``path`` (atomically), without the
    libraries it imports."""
    options = mx.XmlWriteOptions()
    options.writeXIncludeEnable = False
    options.elementPredicate = lambda elem: not elem.hasSourceUri()
    atomic_write_text(path, mx.writeToXmlString(doc, options))
    return path


def read_openpbr_inputs(path: Path, shader_name: str = "OpenPBR") -> dict[str, Any]:
    """The OpenPBR inputs of a ``.mtlx`` file written by :func:`write_mtlx` (values as
    floats or RGB arrays; connected inputs by the name of their node)."""
    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(path))
    shader = doc.getNode(shader_name)
    out: dict[str, Any] = {}
    for port in shader.getInputs():
        if port.getNodeName():
            out[port.getName()] = port.getNodeName()
        else:
            value = port.getValue()
            out[port.getName()] = np.array(value.asTuple()) if hasattr(value, "asTuple") \
                else float(value)
    return out
