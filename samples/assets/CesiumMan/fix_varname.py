"""Re-author CesiumMan's `inputs:varname` as a string (USD's type) and re-package the usdz.

The usd-wg conversion authors UsdPrimvarReader_float2 `inputs:varname` as a token;
UsdPreviewSurface declares it a string, so USD's ShaderSdrCompliance validator reports
an error (and a stronger layer cannot change an attribute's type). This rewrites the
package's root layer with the attribute as a string, same value, and packages it again
with the texture it names. How the shipped copy was made (see NOTICE.md):

    .venv/bin/python samples/assets/CesiumMan/fix_varname.py ORIGINAL.usdz CesiumMan.usdz
"""

from __future__ import annotations

import argparse
import tempfile
import zipfile
from pathlib import Path

from pxr import Sdf, UsdUtils

ATTRIBUTE = "inputs:varname"


def fix_layer(layer: Sdf.Layer) -> list[str]:
    """Make every token-typed inputs:varname of `layer` a string; return their paths."""
    paths: list[Sdf.Path] = []
    layer.Traverse(
        Sdf.Path.absoluteRootPath,
        lambda p: paths.append(p) if p.IsPropertyPath() and p.name == ATTRIBUTE else None,
    )
    fixed = []
    for path in paths:
        spec = layer.GetAttributeAtPath(path)
        if spec.typeName != Sdf.ValueTypeNames.Token:
            continue
        value, variability = spec.default, spec.variability
        owner = spec.owner
        owner.RemoveProperty(spec)
        replacement = Sdf.AttributeSpec(owner, ATTRIBUTE, Sdf.ValueTypeNames.String, variability)
        replacement.default = str(value)
        fixed.append(str(path))
    return fixed


def fix_package(source: Path, target: Path) -> list[str]:
    """Unpack `source`, fix its root layer, and write the package `target`."""
    with tempfile.TemporaryDirectory() as tmp, zipfile.ZipFile(source) as archive:
        archive.extractall(tmp)
        root = Path(tmp) / archive.namelist()[0]  # a usdz's first file is its root layer
        layer = Sdf.Layer.FindOrOpen(str(root))
        fixed = fix_layer(layer)
        if not layer.Save():
            raise RuntimeError(f"could not save {root}")
        if not UsdUtils.CreateNewUsdzPackage(str(root), str(target)):
            raise RuntimeError(f"could not package {target}")
    return fixed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", type=Path, help="the original CesiumMan.usdz")
    parser.add_argument("target", type=Path, help="the corrected package to write")
    args = parser.parse_args()
    for path in fix_package(args.source, args.target):
        print(f"{path}: token -> string")


if __name__ == "__main__":
    main()
