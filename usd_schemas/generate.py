"""Regenerate generatedSchema.usda and plugInfo.json from schema.usda.

Run `python -m rigspace.usd_schemas.generate` after editing schema.usda; without
arguments it writes next to schema.usda, `--check` only reports whether the committed
files are in sync (exit 1 when not). Needs jinja2 (the `dev` extra).
"""

from __future__ import annotations

import argparse
import filecmp
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
GENERATED = ("generatedSchema.usda", "plugInfo.json")

# usdGenSchema leaves these for a build system to fill; a codeless plugin is found
# relative to plugInfo.json itself and has no library.
_PLACEHOLDERS = {
    "@PLUG_INFO_ROOT@": ".",
    "@PLUG_INFO_RESOURCE_PATH@": ".",
    "@PLUG_INFO_LIBRARY_PATH@": "",
}


def generate(out_dir: Path, schema: Path = HERE / "schema.usda") -> list[Path]:
    """Run usdGenSchema on `schema` into `out_dir`; return the generated files."""
    out_dir.mkdir(parents=True, exist_ok=True)
    # A subprocess: usdGenSchema builds a schema registry of its own, and this process
    # may already have one with our (older) types registered.
    subprocess.run(
        [sys.executable, "-m", "pxr.Usd.usdGenSchema", "-q", str(schema), str(out_dir)],
        check=True,
        capture_output=True,
        text=True,
    )
    plug_info = out_dir / "plugInfo.json"
    text = plug_info.read_text()
    for placeholder, value in _PLACEHOLDERS.items():
        text = text.replace(placeholder, value)
    plug_info.write_text(text)
    return [out_dir / name for name in GENERATED]


def out_of_sync() -> list[str]:
    """Names of the committed generated files that differ from a fresh generation."""
    with tempfile.TemporaryDirectory() as tmp:
        generate(Path(tmp))
        return [
            name
            for name in GENERATED
            if not (HERE / name).exists()
            or not filecmp.cmp(Path(tmp) / name, HERE / name, shallow=False)
        ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only report; exit 1 when out of sync")
    args = parser.parse_args(argv)
    if args.check:
        stale = out_of_sync()
        for name in stale:
            print(
                f"{name} is out of sync with schema.usda: run python -m rigspace.usd_schemas.generate"
            )
        return 1 if stale else 0
    for path in generate(HERE):
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
