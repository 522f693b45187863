"""The installed package: pyproject.toml lists every package and data file, and the wheel built
from it installs into a fresh virtualenv, imports every module from there and renders a frame
through the installed `rigspace` command (docs/scale.md tells cluster nodes to `pip install`)."""

from __future__ import annotations

import ast
import fnmatch
import json
import os
import shutil
import site
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path, PurePosixPath

import pytest

from tests.conftest import REPO

SETUPTOOLS = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
ROOTS = {package: REPO / folder for package, folder in SETUPTOOLS["package-dir"].items()}
"""Import name -> the repository folder installed under it (rigspace.sdk -> sdk/, ...)."""
SITE = ("lib", f"python{sys.version_info.major}.{sys.version_info.minor}", "site-packages")
"""Where a virtualenv made by this interpreter keeps its packages."""


def tracked_files() -> list[Path]:
    """The files under the package roots that a clone has (git's list where there is one, so
    that build outputs and scratch files do not count), caches left out."""
    folders = [str(root.relative_to(REPO)) for root in ROOTS.values()]
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--", *folders], cwd=REPO, capture_output=True, check=False
    )
    if listed.returncode == 0 and listed.stdout:
        files = [REPO / name for name in listed.stdout.decode().split("\0") if name]
    else:  # not a git checkout (an unpacked sdist): every file
        files = [p for root in ROOTS.values() for p in root.rglob("*") if p.is_file()]
    return sorted(p for p in files if "__pycache__" not in p.parts and p.suffix != ".pyc")


def package_of(path: Path) -> tuple[str, PurePosixPath]:
    """(package, path relative to its folder) of a file under the roots: the deepest folder
    with an __init__.py above it."""
    for package, root in ROOTS.items():
        if root in path.parents:
            inner = path.parent
            while inner != root and not (inner / "__init__.py").is_file():
                inner = inner.parent
            name = ".".join([package, *inner.relative_to(root).parts])
            return name, PurePosixPath(path.relative_to(inner).as_posix())
    raise AssertionError(f"{path} is under none of {sorted(ROOTS)}")


def wheel_path(path: Path) -> str:
    """Where a file of the source tree lies in the wheel (rigspace/runtime/engine.py)."""
    for package, root in ROOTS.items():
        if root in path.parents:
            return "/".join([*package.split("."), *path.relative_to(root).parts])
    raise AssertionError(f"{path} is under none of {sorted(ROOTS)}")


def test_every_package_folder_is_listed():
    """setuptools installs only the listed packages: a folder with an __init__.py left off the
    list is missing from every install but the editable one (rigspace.runtime.shadows was)."""
    found = {
        ".".join([package, *init.parent.relative_to(root).parts])
        for package, root in ROOTS.items()
        for init in root.rglob("__init__.py")
    }
    listed = set(SETUPTOOLS["packages"])
    assert not found - listed, f"add to [tool.setuptools] packages: {sorted(found - listed)}"
    assert not listed - found, f"listed without an __init__.py: {sorted(listed - found)}"


def test_every_data_file_is_package_data():
    """Every file under the roots that is not Python source (the schema, the view's page) is
    matched by a [tool.setuptools.package-data] pattern of its package."""
    patterns = SETUPTOOLS.get("package-data", {})
    missing = []
    for path in tracked_files():
        if path.suffix == ".py":
            continue
        package, inside = package_of(path)
        if not any(fnmatch.fnmatch(str(inside), p) for p in patterns.get(package, [])):
            missing.append(f"{package}: {inside}")
    assert not missing, f"add to [tool.setuptools.package-data]: {missing}"


def _module_paths(path: Path) -> dict[str, Path]:
    """The module-level names of `path` bound to a path built from Path(__file__) (through
    .resolve(), .parent, .parents[N] and / "name"), evaluated for the file where it lies."""
    found: dict[str, Path] = {}

    def value(node: ast.expr) -> Path | None:
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
            arg = node.args[0] if len(node.args) == 1 else None
            if node.func.id == "Path" and isinstance(arg, ast.Name) and arg.id == "__file__":
                return path
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            if node.func.attr == "resolve" and not node.args:
                inner = value(node.func.value)
                return inner.resolve() if inner else None
        if isinstance(node, ast.Attribute) and node.attr == "parent":
            inner = value(node.value)
            return inner.parent if inner else None
        if (
            isinstance(node, ast.Subscript)
            and isinstance(node.value, ast.Attribute)
            and node.value.attr == "parents"
            and isinstance(node.slice, ast.Constant)
        ):
            inner = value(node.value.value)
            return inner.parents[node.slice.value] if inner else None
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div):
            inner = value(node.left)
            if inner is not None and isinstance(node.right, ast.Constant):
                return inner / node.right.value
        if isinstance(node, ast.Name):
            return found.get(node.id)
        return None

    for statement in ast.parse(path.read_text()).body:
        if isinstance(statement, ast.Assign) and len(statement.targets) == 1:
            target = statement.targets[0]
            if isinstance(target, ast.Name) and (v := value(statement.value)) is not None:
                found[target.id] = v
    return found


def test_paths_built_from_a_modules_own_file_exist():
    """A module's constants like `Path(__file__).resolve().parents[1] / "samples"` point at
    what they name in this checkout: a module moved into a package (shadows/timing.py) or out
    of one (apps/shadow_timing.py) keeps the right depth. Those inside the package are package data (the test above); those
    outside (samples/) exist only in a source checkout."""
    wrong = [
        f"{source.relative_to(REPO)}: {name} = {target}"
        for source in tracked_files()
        if source.suffix == ".py"
        for name, target in _module_paths(source).items()
        if target != source and not target.exists()
    ]
    assert not wrong, wrong


# --- the wheel, installed -----------------------------------------------------------------------


def _requirement_closure(python: Path) -> list[str]:
    """The distributions a plain `pip install rigspace` brings (no extras), read in the
    environment of `python` from the installed wheel's metadata and its requirements'."""
    script = """
import json
from importlib import metadata
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
seen, todo = {}, [("rigspace", ("",))]
while todo:
    name, extras = todo.pop()
    key = canonicalize_name(name)
    if key in seen and set(extras) <= seen[key]:
        continue
    seen.setdefault(key, set()).update(extras)
    for text in metadata.distribution(name).requires or []:
        req = Requirement(text)
        if req.marker is None or any(req.marker.evaluate({"extra": e}) for e in extras):
            todo.append((req.name, ("", *req.extras)))
print(json.dumps(sorted(set(seen) - {"rigspace"})))
"""
    return json.loads(_run([python, "-I", "-c", script], cwd=python.parent, env=_venv_env()).stdout)


def _link_distributions(names: list[str], folder: Path) -> None:
    """Symlink into `folder` every top-level file and folder of the distributions `names`
    (as this .venv has them) and their .dist-info: the packages a fresh virtualenv would get
    from pip, without installing them again (about a minute and 950 MB)."""
    from importlib import metadata

    folder.mkdir()
    for name in names:
        dist = metadata.distribution(name)
        base = Path(str(dist.locate_file("")))
        tops = {PurePosixPath(f).parts[0] for f in dist.files or []}
        for top in sorted(t for t in tops if t not in ("..", "__pycache__")):
            link = folder / top
            if not link.exists():
                link.symlink_to(base / top)


def _run(command: list, **kwargs) -> subprocess.CompletedProcess:
    """Run `command`; on failure, its stderr's end in the assertion."""
    done = subprocess.run(command, capture_output=True, text=True, check=False, **kwargs)
    assert done.returncode == 0, f"{command[:3]}...: {done.stderr[-3000:]}"
    return done


def _venv_env() -> dict[str, str]:
    """A plain environment: system PATH, no PYTHONPATH or other Python variables."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "VIRTUAL_ENV"))}
    env["PATH"] = "/usr/bin:/bin"
    return env


IMPORT_ALL = """
import importlib, json, sys
from importlib import metadata
modules = json.loads(sys.argv[1])
files = {}
for name in modules:
    files[name] = importlib.import_module(name).__file__
import rigspace
from rigspace.sdk.plugins import discover
from rigspace.sdk.cli import COMMANDS
from rigspace.sdk.plugins import SOURCES
from rigspace.sdk.predictors import PREDICTORS
from rigspace.sdk.render import RENDERERS
from rigspace.sdk.validation import VALIDATORS
mine = metadata.distribution("rigspace")
groups = {
    group: [
        [ep.name, str(ep.dist._path)]
        for ep in metadata.entry_points(group=group)
        if group != "console_scripts" or ep.name == "rigspace"
    ]
    for group in sorted({ep.group for ep in mine.entry_points})
}
kinds = [COMMANDS, SOURCES, PREDICTORS, RENDERERS, VALIDATORS]
print(json.dumps({
    "plugins": {k.group: [sorted(discover(k).specs), discover(k).failed] for k in kinds},
    "files": files,
    "namespace": list(rigspace.__path__),
    "dist": str(mine._path),
    "entry_points": groups,
    "sys_path": sys.path,
    "editable": [m for m in sys.modules if "editable" in m],
}))
"""


def _build_wheel(files: list[Path], tmp_path: Path) -> Path:
    """`pip wheel` of a copy of `files` (with pyproject.toml and README.md) in TMP/src,
    written to TMP/dist."""
    source = tmp_path / "src"  # setuptools writes build/ and *.egg-info beside the sources
    for path in [*files, REPO / "pyproject.toml", REPO / "README.md"]:
        copy = source / path.relative_to(REPO)
        copy.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(path, copy)
    _run([sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "--no-build-isolation",
          "--no-index", "-q", "-w", str(tmp_path / "dist")])  # fmt: skip
    (wheel,) = (tmp_path / "dist").glob("rigspace-*.whl")
    return wheel


def _install_in_venv(wheel: Path, venv: Path) -> Path:
    """The wheel alone (no dependencies) installed into a fresh virtualenv; its python."""
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)])
    python = venv / "bin" / "python"
    _run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps",
          "--no-index", "-q", str(wheel)])  # fmt: skip
    return python


def _copy_compiled_kernels(packages: Path) -> None:
    """numba caches compiled kernels by the source's content: the checkout's (.ci/setup
    compiles them) serve the identical installed modules, where compiling again takes a
    minute or two."""
    for package, root in ROOTS.items():
        for cached in root.rglob("__pycache__/*.nb[ic]"):
            target = packages.joinpath(*package.split("."), cached.relative_to(root))
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(cached, target)


def _import_every_module(python: Path, packages: Path, names: set[str], cwd: Path) -> dict:
    """IMPORT_ALL's findings for every module of the wheel (`names`: its files) in the
    virtualenv of `python`, with every extra's packages reachable (torch for train, ...): a
    .pth line puts this .venv's site-packages on the path, but its .pth files (the editable
    install's finder) are not run, and the wheel's own rigspace comes first."""
    (packages / "dependencies.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    modules = sorted(
        n.removesuffix(".py").removesuffix("/__init__").replace("/", ".")
        for n in names
        if n.startswith("rigspace/") and n.endswith(".py") and not n.endswith("__main__.py")
    )
    imported = _run([python, "-I", "-c", IMPORT_ALL, json.dumps(modules)], cwd=cwd, env=_venv_env())
    return json.loads(imported.stdout)


@pytest.mark.slow
def test_the_wheel_installs_imports_every_module_and_renders(tmp_path):
    """`pip wheel .` from a copy of the tracked files, installed into a fresh virtualenv with
    nothing of the source tree on its path: the wheel holds every tracked file of the
    packages, every module imports from the virtualenv (the other packages of this .venv
    reachable through a .pth line), the entry points resolve to the wheel alone, and with
    only rigspace's own requirements beside it `rigspace render` draws a frame of the previs
    scene from a copy of samples/."""
    files = tracked_files()
    wheel = _build_wheel(files, tmp_path)
    names = set(zipfile.ZipFile(wheel).namelist())
    missing = sorted(wheel_path(p) for p in files if wheel_path(p) not in names)
    assert not missing, f"the wheel lacks {missing}"

    venv = tmp_path / "venv"
    python = _install_in_venv(wheel, venv)
    packages = venv.joinpath(*SITE)
    installed = packages / "rigspace"
    _copy_compiled_kernels(packages)

    found = _import_every_module(python, packages, names, tmp_path)
    assert not found["editable"], found["editable"]
    assert str(REPO) not in found["sys_path"]
    for name, file in found["files"].items():
        assert Path(file).is_relative_to(installed), f"{name} imported from {file}"
    assert [Path(p) for p in found["namespace"]] == [installed]
    assert Path(found["dist"]).parent == packages
    assert found["entry_points"], "no rigspace entry points"
    for group, points in found["entry_points"].items():
        plugins = [name for name, _ in points]
        assert len(plugins) == len(set(plugins)), f"{group}: a plugin found twice: {plugins}"
        assert all(Path(dist).parent == packages for _, dist in points), (group, points)
    assert set(found["plugins"]) == set(found["entry_points"]) - {"console_scripts"}
    for group, (loaded, failed) in found["plugins"].items():  # the SDK's own discovery
        assert loaded and not failed, (group, failed)

    # The render, with only what `pip install rigspace` brings beside the wheel.
    closure = _requirement_closure(python)
    assert {"usd-core", "numpy", "onnxruntime", "numba"} <= set(closure)
    _link_distributions(closure, tmp_path / "requirements")
    (packages / "dependencies.pth").write_text(f"{tmp_path / 'requirements'}\n")
    shutil.copytree(
        REPO / "samples", tmp_path / "samples",
        ignore=shutil.ignore_patterns("__pycache__", "training"),
    )  # fmt: skip
    rendered = _run(
        [venv / "bin" / "rigspace", "render", "samples/scenes/previs.usda", "--out", "out",
         "--frames", "300:300", "--resolution", "160x90"],
        cwd=tmp_path, env=_venv_env(),
    )  # fmt: skip
    assert "rendered 1 frames at 160x90" in rendered.stdout
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["frames"][0]["counts"]["evaluated"] == 1, report["frames"][0]["counts"]
    assert (tmp_path / "out" / "frame_000300.0.png").is_file()
