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


def _module_imports() -> dict[str, set[str]]:
    """rigspace module -> the rigspace modules it imports anywhere in its body (lazy ones too)."""
    modules = {}
    for package in ALLOWED:
        for path in (REPO / package).rglob("*.py"):
            name = "rigspace." + ".".join(path.relative_to(REPO).with_suffix("").parts)
            modules[name.removesuffix(".__init__")] = path
    graph = {}
    for name, path in modules.items():
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("rigspace."):
                for alias in node.names:
                    full = f"{node.module}.{alias.name}"
                    found.add(full if full in modules else node.module)
            elif isinstance(node, ast.Import):
                found |= {a.name for a in node.names if a.name.startswith("rigspace.")}
        graph[name] = {m for m in found if m in modules and m != name}
    return graph


def test_no_module_imports_itself_round_a_cycle():
    """No import cycle among rigspace modules, lazy imports counted. There were two: view's
    server took a constant from its command, and shadows.py dispatched to the kernels of
    shadow_pass.py, which reuses its types (now the engine hands PrimShadows the kernels'
    passes: ShadowBackend, CompiledPasses)."""
    graph = _module_imports()
    cycles = []
    for start in graph:
        stack, seen = [(start, [start])], set()
        while stack:
            node, path = stack.pop()
            for nxt in graph[node]:
                if nxt == start:
                    cycles.append(set(path))
                elif nxt not in seen:
                    seen.add(nxt)
                    stack.append((nxt, [*path, nxt]))
    assert not cycles, sorted(sorted(c) for c in cycles)
