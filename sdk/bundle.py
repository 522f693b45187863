"""The model bundle's manifest: the one versioned artefact that crosses from train to runtime.

A bundle is a folder with `manifest.json` and the ONNX graphs it names. This module
reads and checks the manifest; `rigspace.train` writes it and `rigspace.runtime` loads
the graphs. Reading never executes anything from the bundle.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rigspace.sdk.errors import RigspaceError
from rigspace.sdk.fields import BUNDLE_MANIFEST, problems

FORMAT = "rigspace.bundle"
FORMAT_VERSION = 2
"""Written by this rigspace for the paper's rotations-only input. Version 2 added the albedo
graphs' `alpha` (coverage) output."""
CONDITIONED_VERSION = 3
"""Written for a pose-conditioned model (manifest `conditioning`): its graphs also read
`joints2d`, so a rigspace that reads only versions 1-2 refuses it by name instead of failing
inside onnxruntime on a missing input."""
READABLE_VERSIONS = (1, 2, 3)
ENCODINGS = ("rot6d", "quaternion")


class BundleError(RigspaceError):
    """A model bundle that cannot be used: missing, unreadable, or of another format."""


@dataclass(frozen=True)
class ModelManifest:
    """What a model bundle's manifest.json declares (format versions 1 to 3)."""

    path: Path
    """The manifest file."""
    joints: tuple[str, ...]
    """Skeleton joint names the model reads, in input order."""
    rotation_encoding: str
    maps: tuple[str, ...] = ()
    look_at_joint: str = ""
    training_distance: float = 0.0
    training_focal_length: float = 0.0
    training_aperture: float = 0.0
    format_version: int = FORMAT_VERSION
    raw: dict[str, Any] = field(default_factory=dict, repr=False)
    """The whole manifest, for the fields the train and runtime packages own."""

    @property
    def folder(self) -> Path:
        return self.path.parent


def manifest_path(path: str | Path) -> Path:
    path = Path(path)
    return path / "manifest.json" if path.is_dir() else path


def read_manifest(path: str | Path) -> ModelManifest:
    """Read and check a bundle's manifest (a bundle folder or its manifest.json)."""
    file = manifest_path(path)
    if not file.is_file():
        raise BundleError(
            f"Model bundle {path}: there is no manifest.json at {file}.",
            "point rigspace:model at a folder written by `rigspace train` (or its manifest.json).",
        )
    try:
        data = json.loads(file.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BundleError(
            f"Model bundle manifest {file} is not readable JSON ({exc}).",
            "re-export the bundle with `rigspace train`; the file is damaged.",
        ) from exc
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise BundleError(
            f"{file} is not a rigspace model bundle manifest (format is "
            f"{data.get('format') if isinstance(data, dict) else type(data).__name__!r}, "
            f"expected {FORMAT!r}).",
            "point rigspace:model at a folder written by `rigspace train`.",
        )
    version = data.get("format_version")
    if version not in READABLE_VERSIONS:
        raise BundleError(
            f"{file} has bundle format version {version!r}; this rigspace reads versions "
            f"{', '.join(map(str, READABLE_VERSIONS))}.",
            "re-export the bundle with this version of rigspace, or install the rigspace "
            "version that wrote it.",
        )
    joints = data.get("joints")
    if not isinstance(joints, list) or not joints or not all(isinstance(j, str) for j in joints):
        raise BundleError(
            f"{file}: 'joints' must be a non-empty list of joint names.",
            "re-export the bundle; the manifest is incomplete.",
        )
    encoding = data.get("rotation_encoding")
    if encoding not in ENCODINGS:
        raise BundleError(
            f"{file}: rotation_encoding is {encoding!r}, expected one of {ENCODINGS}.",
            "re-export the bundle; the manifest is incomplete.",
        )
    wrong = problems(data, BUNDLE_MANIFEST)
    if wrong:
        raise BundleError(
            f"Model bundle manifest {file}: {'; '.join(wrong)}.",
            "re-export the bundle with `rigspace train` (or restore the file).",
        )
    camera = data.get("training_camera", {})
    return ModelManifest(
        path=file,
        joints=tuple(joints),
        rotation_encoding=encoding,
        maps=tuple(data.get("maps", ())),
        look_at_joint=str(data.get("look_at_joint", "")),
        training_distance=float(camera.get("distance", 0.0)),
        training_focal_length=float(camera.get("focal_length", 0.0)),
        training_aperture=float(camera.get("horizontal_aperture", 0.0)),
        format_version=int(version),
        raw=data,
    )
