"""Regenerate skinpipe/schemas/generatedSchema.usda and plugInfo.json from schema.usda.

    python tools/gen_schema.py

Runs OpenUSD's usdGenSchema (codeless: skipCodeGeneration), then repairs what it does
not carry over for a codeless, Python-registered plugin: the @PLUG_INFO_*@ placeholders
in plugInfo.json become paths relative to the plugInfo file, and every class and
property ``doc`` string of schema.usda is copied into the generated schema (the
generator keeps only a first-sentence ``userDocBrief``), so that usdview's metadata view
explains each property in full. The outputs are committed.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from pxr import Sdf

SCHEMAS = Path(__file__).resolve().parents[1] / "skinpipe" / "schemas"


def main() -> None:
    subprocess.run([sys.executable, "-m", "pxr.Usd.usdGenSchema", "schema.usda", "."],
                   cwd=SCHEMAS, check=True)
    info_path = SCHEMAS / "plugInfo.json"
    text = info_path.read_text()
    header = "".join(line for line in text.splitlines(keepends=True) if line.startswith("#"))
    info = json.loads("".join(line for line in text.splitlines(keepends=True)
                              if not line.startswith("#")))
    for plugin in info["Plugins"]:
        plugin["LibraryPath"] = ""
        plugin["ResourcePath"] = "."
        plugin["Root"] = "."
    info_path.write_text(header + json.dumps(info, indent=4, sort_keys=True) + "\n")

    source = Sdf.Layer.FindOrOpen(str(SCHEMAS / "schema.usda"))
    generated = Sdf.Layer.FindOrOpen(str(SCHEMAS / "generatedSchema.usda"))
    copied = 0
    for prim in generated.rootPrims:
        src = source.GetPrimAtPath(prim.path)
        if src is None:
            continue
        prim.documentation = " ".join(src.documentation.split())
        copied += 1
        for prop in prim.properties:
            src_prop = src.properties.get(prop.name)
            if src_prop is not None and src_prop.documentation:
                prop.documentation = src_prop.documentation
                copied += 1
    generated.Save()
    print(f"wrote {info_path} and {SCHEMAS / 'generatedSchema.usda'} ({copied} docs kept)")


if __name__ == "__main__":
    main()
