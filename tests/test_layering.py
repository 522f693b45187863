"""Dependencies point one way (DESIGN.md): usd_schemas <- sdk <- {capture, train, runtime}."""

from __future__ import annotations

import ast

import pytest

from tests.conftest import REPO

# What each package may import from rigspace (train reads datasets through capture).
ALLOWED = {
    "usd_schemas": set(),
    "sdk": {"usd_schemas", "sdk"},
    "capture": {"usd_schemas", "sdk", "capture"},
    "train": {"usd_schemas", "sdk", "capture", "train"},
    "runtime": {"usd_schemas", "sdk", "runtime"},
    # The bench measures everything side by side, so it alone may import every package.
    "bench": {"usd_schemas", "sdk", "capture", "train", "runtime", "bench"},
}


def rigspace_imports(path) -> set[str]:
    tree = ast.parse(path.read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("rigspace."):
            names.add(node.module.split(".")[1])
        elif isinstance(node, ast.Import):
            names |= {a.name.split(".")[1] for a in node.names if a.name.startswith("rigspace.")}
    return names


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_package_imports_only_what_it_may(package):
    for path in sorted((REPO / package).rglob("*.py")):
        extra = rigspace_imports(path) - ALLOWED[package]
        assert not extra, (
            f"{path.relative_to(REPO)} imports rigspace.{', rigspace.'.join(sorted(extra))}"
        )


def test_runtime_never_imports_torch():
    for path in sorted((REPO / "runtime").rglob("*.py")):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else ([node.module] if isinstance(node, ast.ImportFrom) and node.module else [])
            )
            assert not any(n == "torch" or n.startswith("torch.") for n in names), path
