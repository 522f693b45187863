"""Dependencies point one way (DESIGN.md): usd_schemas <- sdk <- {capture, train, runtime} <- bench,
and the apps (the `rigspace` subcommands and the `python -m` tools) above all of them."""

from __future__ import annotations

import ast
import re

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
    # The apps: commands and tools over the library, which imports none of them.
    "apps": {"usd_schemas", "sdk", "capture", "train", "runtime", "bench", "apps"},
}
LIBRARY = sorted(set(ALLOWED) - {"apps"})
APP_MODULE = re.compile(r"rigspace\.apps(\.\w+)*")
"""A string naming an app module: what `python -m`, importlib or runpy would load."""
LIBRARY_MAINS = {
    "sdk/__main__.py": "`python -m rigspace.sdk` is the `rigspace` front door (rigspace.sdk.cli)",
    "usd_schemas/generate.py": "the schema package's build step: writes the files beside it",
}
"""The library modules that may still run as programs, and why."""


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


def _names_an_app(path) -> list[str]:
    """The places in `path` that load an app: imports of rigspace.apps, and strings that are an
    app's module name (`[sys.executable, "-m", "rigspace.apps.x"]`, import_module)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            names = [node.value] if APP_MODULE.fullmatch(node.value) else []
        else:
            continue
        found += [
            f"line {node.lineno}: {n}"
            for n in names
            if n == "rigspace.apps" or n.startswith("rigspace.apps.")
        ][:1]
    return found


@pytest.mark.parametrize("package", LIBRARY)
def test_no_library_module_imports_an_app(package):
    """The apps sit above the library: a library module that needs something of an app's
    needs library code, which moves down (runtime.reference from render, sdk.posing's
    centre_joint from init); a process started by name counts as an import."""
    found = {
        str(path.relative_to(REPO)): hits
        for path in sorted((REPO / package).rglob("*.py"))
        if (hits := _names_an_app(path))
    }
    assert not found, f"library modules that load rigspace.apps: {found}"


def _runs_as_a_program(path) -> bool:
    """Whether a module is a `python -m` program: a __main__.py, or an `if __name__ ==
    "__main__"` block."""
    if path.name == "__main__.py":
        return True
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Compare) and isinstance(node.left, ast.Name):
            if node.left.id == "__name__" and any(
                isinstance(c, ast.Constant) and c.value == "__main__" for c in node.comparators
            ):
                return True
    return False


def test_the_commands_and_tools_are_apps():
    """Every `rigspace` subcommand's module and every `python -m` tool lives in apps/; the
    library holds none but LIBRARY_MAINS."""
    import tomllib

    programs = {
        str(path.relative_to(REPO))
        for package in LIBRARY
        for path in (REPO / package).rglob("*.py")
        if _runs_as_a_program(path)
    }
    assert programs == set(LIBRARY_MAINS), f"move to apps/: {sorted(programs - set(LIBRARY_MAINS))}"
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    commands = project["entry-points"]["rigspace.commands"]
    outside = {n: v for n, v in commands.items() if not v.startswith("rigspace.apps.")}
    assert not outside, f"subcommands outside rigspace.apps: {outside}"
