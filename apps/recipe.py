"""The GPU recipe: retrain the shipped sample model on a lent GPU machine, one command a side.

    python -m rigspace.apps.recipe prepare                  # here: gathers what the GPU lacks
    python3 apps/recipe.py run --out "$OUT"                 # there: <= 9 minutes, no registry
    python -m rigspace.apps.recipe unpack FILES             # here: the bundle and the GPU table
    python -m rigspace.apps.recipe run --smoke --out DIR    # anywhere: the whole recipe on the
                                                            # CPU at 32x32 in about a minute (CI)
    python3 apps/recipe.py test --out "$OUT" -- TESTS       # there: part of the suite on CUDA

A lent GPU machine (docs/gpu.md) has torch with CUDA, numpy, numba, onnx, onnxruntime and
OpenCV, Python 3.12, no package registry, about 15 minutes at a stretch and 10 minutes a
command; at most 64 MiB of the working tree and carried files travel to it, and 8 files of at
most 16 MiB come back. So:

- `prepare` (a machine that reaches PyPI and Debian's archive) downloads the cp312 wheels of
  what rigspace needs there and the machine lacks (PAYLOAD_PACKAGES, pinned to the versions
  installed here), unpacks them, strips their shared libraries' symbol tables, packs them as
  one xz tarball, downloads Debian's EGL loader packages (EGL_DEBS: with them the NVIDIA driver
  serves EGL, so the gl renderer draws on the GPU), and checks that the tree and the payload
  fit what travels. It writes the ignored folder .gpu/ (carry it).
- `run` installs the payload (a script until then: it needs nothing but Python's standard
  library), captures the sample dataset with the gl renderer on the GPU, trains the sample
  recipe (RECIPE_FLAGS, on CUDA) for what the time budget leaves, exports, evaluates (held-out
  views, the held-out clip, at display size), runs the GPU check (apps/gpu_check.py), and
  packs the bundle and every number into at most MAX_FILES files under --out, after each
  stage: a run stopped at its limit still returns what it finished.
- `test` installs the payload the same way and runs part of the suite with the machine's own
  pytest (a test running past HANG_SECONDS has its threads' stacks written), so code that
  trains, evaluates and renders is checked on CUDA and the NVIDIA EGL, not only on the CPU.
- `unpack` joins what came back, checks it, puts the bundle in samples/models/sample (or
  --bundle-into) and writes the GPU table to docs/bench/gpu.md and gpu.json.
"""

from __future__ import annotations

import os
import sys

if __name__ == "__main__" and sys.path:  # run as a script (`python3 apps/recipe.py`): apps/'s
    # modules must not shadow anything, as apps/inspect.py would the standard library's inspect
    # (dataclasses imports it below).
    if os.path.realpath(sys.path[0]) == os.path.dirname(os.path.realpath(__file__)):
        sys.path.pop(0)

import argparse
import hashlib
import io
import json
import lzma
import re
import shutil
import subprocess
import tarfile
import tempfile
import time
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

# Standard library only at module level: `run` starts on a machine where rigspace's
# dependencies are not installed yet (it installs them).

PAYLOAD = Path(".gpu")
"""The ignored folder `prepare` writes and a device call carries."""
SITE_ARCHIVE = "site.tar.xz"
PAYLOAD_FILE = "payload.json"
PAYLOAD_PACKAGES = (
    "usd-core",
    "openimageio",
    "moderngl",
    "glcontext",
    "flip-evaluator",
    "pyserial",
    "python-osc",
)
"""What capture, training, evaluation and the GPU check import that the GPU machine's image
lacks (its package list: torch, numpy, numba, onnx, onnxruntime, opencv-python-headless, tqdm
are there). embreex, PyAV and the view's server are not needed there."""
EGL_DEBS = ("libegl1", "libglvnd0", "libopengl0", "libgl1", "libglx0", "libgles2")
"""Debian's GL vendor-neutral loaders: the NVIDIA driver on the GPU machine provides the rest."""
NVIDIA_EGL_VENDOR = "/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json"
DROP_FROM_SITE = ("OpenImageIO/bin",)
"""Parts of the wheels nothing here runs (oiiotool and friends)."""
TRAVEL_LIMIT = 64 * 2**20
"""What travels to the GPU machine: the working tree and the carried files together."""
TRAVEL_MARGIN = 1 * 2**20
"""Kept free under TRAVEL_LIMIT for what a session adds to the tree before its call."""
MAX_FILES = 8
MAX_FILE_BYTES = 16 * 2**20
PART_BYTES = 15 * 2**20
"""The packed results are split into parts of at most this size (under MAX_FILE_BYTES)."""
PYTHON = "3.12"
"""The GPU machine's Python (its torch lives in /opt/torch/.venv)."""
PLATFORMS = (
    "manylinux_2_28_x86_64",
    "manylinux_2_27_x86_64",
    "manylinux_2_17_x86_64",
    "manylinux2014_x86_64",
    "manylinux1_x86_64",
)

SCENE = Path("samples/scenes/previs.usda")
BUNDLE_HOME = Path("samples/models/sample")
RECIPE_FLAGS = tuple(
    "--preset small --conditioning bones2d --conditioning-mode add --conditioning-top 32 "
    "--mask-loss bce --depth-weight 2 --batch 256 --lr 0.004 --eval-every 1000 "
    "--checkpoint-every 1000".split()
)
"""The committed sample model's recipe (docs/training.md) at the batch a GPU runs well (256:
6,015 images/s fp32 on an H200 against 832 at 16; the learning rate scaled by sqrt(256/16)).
fp32: a bf16 head cannot place a coordinate within a texel of a 1,024-texel chart (8 bits of
mantissa), and tf32 convolutions are nearly as fast on Hopper."""
CAPACITY_FLAGS = ("--base-width", "128", "--min-width", "32", "--texture-branch", "texture")
"""The recipe's hypothesis for capacity (docs/training.md, "Capacity"): 32 channels at 64x64
and 128x128 instead of 16, and the texture head on its own branch. Its cost is measured on
2 CPU cores (2.5x the network's); what it buys at 128x128 is the first GPU run's question."""


@dataclass(frozen=True)
class Plan:
    """What one `run` does and how much time each stage may take (seconds)."""

    smoke: bool
    minutes: float
    capture_flags: tuple[str, ...]
    display_flags: tuple[str, ...]
    train_flags: tuple[str, ...]
    eval_limit: int
    gpu_check_flags: tuple[str, ...]
    reserve: dict[str, float] = field(default_factory=dict)
    """Seconds kept for the stages after training (export is inside training's command)."""

    @classmethod
    def gpu(cls, minutes: float, extra: tuple[str, ...] = ()) -> Plan:
        return cls(
            smoke=False,
            minutes=minutes,
            capture_flags=("--renderer", "gl", "--workers", str(os.cpu_count() or 1)),
            display_flags=("--renderer", "gl", "--resolution", "512", "--every", "30"),
            train_flags=(*RECIPE_FLAGS, *CAPACITY_FLAGS, "--device", "cuda", *extra),
            eval_limit=200,
            gpu_check_flags=tuple(
                "--only step predictors frames --seconds 2 --batches 64 256 --repeats 20 "
                "--frames 4".split()
            ),
            reserve={"export": 60.0, "eval": 70.0, "gpu_check": 100.0, "pack": 15.0},
        )

    @classmethod
    def toy(cls, extra: tuple[str, ...] = ()) -> Plan:
        """The same stages on the CPU at 32x32, a few steps (CI)."""
        return cls(
            smoke=True,
            minutes=10.0,
            capture_flags=tuple(
                "--renderer gl --resolution 32 --views 4 --elevations 0 --every 90 "
                "--workers 1".split()
            ),
            display_flags=tuple(
                "--renderer gl --resolution 64 --views 4 --elevations 0 --every 180 "
                "--workers 1".split()
            ),
            train_flags=(
                *"--preset tiny --resolution 32 --texture --texture-branch texture".split(),
                *("--device", "cpu", *extra),
            ),
            eval_limit=8,
            gpu_check_flags=tuple(
                "--device cpu --only predictors --resolutions 16 --repeats 2".split()
            ),
        )


class RecipeError(Exception):
    """A step of the recipe failed: what, and what to do (printed without a traceback)."""

    def __init__(self, what: str, fix: str = "") -> None:
        super().__init__(what)
        self.what, self.fix = what, fix


# ---------------------------------------------------------------------------------- prepare


def prepare(root: Path, payload: Path, python: str = PYTHON, level: int = 9) -> dict[str, Any]:
    """Write the payload folder: the wheels' contents as one xz tarball, the EGL debs, and
    payload.json; then check that tree + payload fit TRAVEL_LIMIT."""
    payload.mkdir(parents=True, exist_ok=True)
    pins = [_pinned(name) for name in PAYLOAD_PACKAGES]
    with tempfile.TemporaryDirectory() as tmp:
        wheels, site = Path(tmp) / "wheels", Path(tmp) / "site"
        _say(f"prepare: downloading the cp{python.replace('.', '')} wheels of {', '.join(pins)}")
        _check_call(_pip_download(pins, wheels, python), "pip download")
        for wheel in sorted(wheels.glob("*.whl")):
            with zipfile.ZipFile(wheel) as archive:
                archive.extractall(site)
        for drop in DROP_FROM_SITE:
            shutil.rmtree(site / drop, ignore_errors=True)
        stripped = _strip(site)
        raw = sum(p.stat().st_size for p in site.rglob("*") if p.is_file())
        _say(f"prepare: {raw / 2**20:.0f} MiB unpacked ({stripped}); packing (xz -{level})")
        archive_tmp = payload / f".{SITE_ARCHIVE}.tmp"
        with (
            lzma.open(archive_tmp, "wb", preset=level) as xz,
            tarfile.open(fileobj=xz, mode="w") as tar,
        ):
            tar.add(site, arcname=".")
        os.replace(archive_tmp, payload / SITE_ARCHIVE)
        versions = {w.name.split("-")[0]: w.name.split("-")[1] for w in wheels.glob("*.whl")}
    debs = _download_debs(payload / "debs")
    info = {
        "python": python,
        "packages": versions,
        "debs": sorted(d.name for d in debs),
        "bytes": {p.name: p.stat().st_size for p in (payload / SITE_ARCHIVE, *debs)},
    }
    (payload / PAYLOAD_FILE).write_text(json.dumps(info, indent=2) + "\n")
    info["travel"] = travel_check(root, payload)
    return info


def _pinned(name: str) -> str:
    """`name==version` of the copy installed here (so the GPU runs what tests ran), else the
    bare name."""
    from importlib import metadata

    try:
        return f"{name}=={metadata.version(name)}"
    except metadata.PackageNotFoundError:
        return name


def _pip_download(pins: list[str], into: Path, python: str) -> list[str]:
    command = [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps"]
    command += ["--only-binary=:all:", "--python-version", python, "--implementation", "cp"]
    for platform in PLATFORMS:
        command += ["--platform", platform]
    return [*command, "-d", str(into), *pins]


def _strip(site: Path) -> str:
    """Strip the shared libraries' symbol tables (their dynamic symbols stay): usd-core ships
    them unstripped, a third of its size."""
    strip = shutil.which("strip")
    if strip is None:
        return "no strip here: libraries kept as they are"
    libraries = [str(p) for p in site.rglob("*.so*") if p.is_file() and not p.is_symlink()]
    before = sum(Path(p).stat().st_size for p in libraries)
    subprocess.run([strip, "--strip-unneeded", *libraries], check=True, capture_output=True)
    after = sum(Path(p).stat().st_size for p in libraries)
    return f"{len(libraries)} libraries stripped, {before / 2**20:.0f} -> {after / 2**20:.0f} MiB"


def _download_debs(folder: Path) -> list[Path]:
    """Debian's EGL loaders for amd64 (the GPU machine's architecture), via apt-get download."""
    folder.mkdir(parents=True, exist_ok=True)
    apt = shutil.which("apt-get")
    if apt is None:
        raise RecipeError(
            "prepare needs apt-get (Debian's EGL loader packages for the GPU machine)",
            "run prepare on a Debian or Ubuntu machine",
        )
    options = ["-oAPT::Architecture=amd64", "-oAPT::Architectures=amd64"]
    command = [apt, *options, "download", *EGL_DEBS]
    if subprocess.run(command, cwd=folder, capture_output=True).returncode != 0:
        lists = Path(tempfile.gettempdir()) / "rigspace-apt-amd64"
        (lists / "partial").mkdir(parents=True, exist_ok=True)
        options.append(f"-oDir::State::Lists={lists}")
        _check_call([apt, *options, "update", "-qq"], "apt-get update")
        _check_call([apt, *options, "download", *EGL_DEBS], "apt-get download", cwd=folder)
    return sorted(folder.glob("*.deb"))


def tree_bytes(root: Path) -> int:
    """Bytes of what a device call sends of the tree: tracked files and untracked files git
    does not ignore."""
    return sum(tree_sizes(root).values())


def tree_sizes(root: Path) -> dict[str, int]:
    """Each file a device call sends of the tree (tree_bytes) and its size."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=root, check=True, capture_output=True,
    ).stdout  # fmt: skip
    names = {n for n in listed.decode().split("\0") if n}
    return {n: (root / n).stat().st_size for n in names if (root / n).is_file()}


def largest_folders(sizes: dict[str, int], depth: int = 3, count: int = 3) -> list[tuple[str, int]]:
    """The `count` folders `depth` deep that send the most bytes (samples/models/film...)."""
    folders: dict[str, int] = {}
    for name, size in sizes.items():
        folder = "/".join(name.split("/")[:depth])
        folders[folder] = folders.get(folder, 0) + size
    return sorted(folders.items(), key=lambda kv: -kv[1])[:count]


def travel_check(root: Path, payload: Path) -> dict[str, int]:
    """Tree + payload against TRAVEL_LIMIT less TRAVEL_MARGIN; RecipeError when over, naming
    the tree's largest folders (docs/gpu.md, "When the tree is too large")."""
    sizes = tree_sizes(root)
    tree = sum(sizes.values())
    carried = sum(p.stat().st_size for p in payload.rglob("*") if p.is_file())
    total = tree + carried
    if total > TRAVEL_LIMIT - TRAVEL_MARGIN:
        largest = ", ".join(f"{f} {b / 2**20:.1f} MiB" for f, b in largest_folders(sizes))
        raise RecipeError(
            f"the tree ({tree / 2**20:.1f} MiB) and the payload ({carried / 2**20:.1f} MiB) "
            f"come to {total / 2**20:.1f} MiB; a device call carries at most "
            f"{TRAVEL_LIMIT / 2**20:.0f} MiB (this recipe keeps {TRAVEL_MARGIN / 2**20:.0f} free)."
            f" The largest folders: {largest}",
            "leave folders the call does not need out of the index for the call and put them "
            'back after it (docs/gpu.md, "When the tree is too large"), or make the payload '
            "smaller (PAYLOAD_PACKAGES)",
        )
    return {"tree": tree, "payload": carried, "total": total, "limit": TRAVEL_LIMIT}


# -------------------------------------------------------------------------------------- run


class Run:
    """One `run`: its deadline, its log under --out, the numbers so far, its environment."""

    def __init__(self, out: Path, plan: Plan, work: Path) -> None:
        self.out, self.plan, self.work = out, plan, work
        self.began = time.monotonic()
        self.deadline = self.began + 60.0 * plan.minutes
        self.env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.numbers: dict[str, Any] = {"smoke": plan.smoke, "stages": {}, "minutes": plan.minutes}
        out.mkdir(parents=True, exist_ok=True)
        self.log = (out / "log.txt").open("a", encoding="utf-8")
        self.last_stderr = ""

    def left(self) -> float:
        return self.deadline - time.monotonic()

    def say(self, line: str) -> None:
        stamped = f"[{time.monotonic() - self.began:6.1f} s] {line}"
        _say(stamped)
        self.log.write(stamped + "\n")
        self.log.flush()

    def python(self, *args: str, stage: str, limit: float | None = None) -> str:
        """`python -m ...` under the installed environment; its output goes to the log (and
        is returned); a failure raises RecipeError naming the stage."""
        command = [sys.executable, "-m", *args]
        self.say(f"{stage}: {' '.join(command[2:])}")
        start = time.monotonic()
        try:
            done = subprocess.run(
                command, env=self.env, capture_output=True, text=True, timeout=limit,
            )  # fmt: skip
        except subprocess.TimeoutExpired as exc:
            raise RecipeError(
                f"{stage} ran past its {limit:.0f} s", "give it more --minutes"
            ) from exc
        self.log.write(done.stderr[-20000:])
        self.log.flush()
        self.last_stderr = done.stdout + done.stderr
        seconds = round(time.monotonic() - start, 1)
        self.numbers["stages"].setdefault(stage, 0.0)
        self.numbers["stages"][stage] += seconds
        if done.returncode != 0:
            tail = "\n".join((done.stderr or done.stdout).strip().splitlines()[-8:])
            raise RecipeError(f"{stage} failed (exit {done.returncode}):\n{tail}", "see log.txt")
        self.say(f"{stage}: done in {seconds} s")
        return done.stdout

    def save(self) -> None:
        self.numbers["seconds"] = round(time.monotonic() - self.began, 1)
        _write(self.out / "numbers.json", json.dumps(self.numbers, indent=2) + "\n")


def run(out: Path, plan: Plan, root: Path, payload: Path, keep: bool = False) -> int:
    """The whole recipe (module doc); every stage's numbers are in --out as soon as it ends.
    `keep`: leave the working folder (datasets, the run) in place and say where."""

    def body(r: Run) -> int:
        stages(r, root)
        return 0

    return _installed(out, plan, root, payload, body, keep=keep)


def _installed(
    out: Path,
    plan: Plan,
    root: Path,
    payload: Path,
    body: Callable[[Run], int],
    keep: bool = False,
    verb: str = "recipe",
) -> int:
    """`body`'s exit status, run with rigspace installed (from the payload where it is not):
    a RecipeError is said and recorded (exit 1); the numbers are saved whatever happens, and
    the working folder removed unless `keep`."""
    work = Path(tempfile.mkdtemp(prefix=f"rigspace-{verb}-"))
    r = Run(out, plan, work)
    try:
        if not _importable("rigspace.sdk", r.env):
            install(r, root, payload)
        return body(r)
    except RecipeError as exc:
        r.numbers["failed"] = exc.what + (f" Fix: {exc.fix}" if exc.fix else "")
        r.say(f"{verb}: {exc.what}" + (f"\nFix: {exc.fix}" if exc.fix else ""))
        return 1
    finally:
        if keep:
            r.say(f"{verb}: the datasets and the run are kept in {work}")
        r.save()
        r.log.close()
        if not keep:
            shutil.rmtree(work, ignore_errors=True)


def install(r: Run, root: Path, payload: Path) -> None:
    """The payload into a site folder on PYTHONPATH, the EGL loaders into /, rigspace itself."""
    start = time.monotonic()
    if not (payload / SITE_ARCHIVE).is_file():
        raise RecipeError(
            f"rigspace is not installed here and there is no {payload / SITE_ARCHIVE}",
            "run `python -m rigspace.apps.recipe prepare` on a machine with a registry and "
            f"carry {payload} to this one",
        )
    site = r.work / "site"
    site.mkdir()
    r.say(f"install: {payload / SITE_ARCHIVE} -> {site}")
    with tarfile.open(payload / SITE_ARCHIVE, "r:xz") as tar:
        extract(tar, site)
    debs = sorted((payload / "debs").glob("*.deb"))
    if debs and os.geteuid() == 0:  # the GPU machine runs commands as root
        for deb in debs:
            _check_call(["dpkg", "-x", str(deb), "/"], f"dpkg -x {deb.name}")
        _check_call(["ldconfig"], "ldconfig")
    if Path(NVIDIA_EGL_VENDOR).is_file():
        r.env["__EGL_VENDOR_LIBRARY_FILENAMES"] = NVIDIA_EGL_VENDOR
    r.env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(site), r.env.get("PYTHONPATH")]))
    command = [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-index"]
    command += ["--no-build-isolation", "--target", str(site), str(root)]
    _check_call(command, "pip install rigspace", env=r.env)
    if not _importable("rigspace.sdk", r.env):
        raise RecipeError("rigspace does not import after the install", "see log.txt")
    r.numbers["stages"]["install"] = round(time.monotonic() - start, 1)
    r.say(f"install: done in {r.numbers['stages']['install']} s")


def stages(r: Run, root: Path) -> None:
    """Capture, train (and export fp32), pack; evaluate, pack; the GPU check, pack; the int8
    graphs with the time left, pack (module doc): what matters most comes back first."""
    plan, work = r.plan, r.work
    dataset, display, model = work / "dataset", work / "display", work / "model"
    warm = _warm_kernels(r, root)  # numba compiles the runtime's kernels beside the capture
    r.python("rigspace.sdk", "capture", str(root / SCENE), "--out", str(dataset),
             *plan.capture_flags, stage="capture")  # fmt: skip
    r.python("rigspace.sdk", "capture", str(root / SCENE), "--out", str(display),
             *plan.display_flags, stage="capture display")  # fmt: skip
    budget = ["--steps-per-level", "3"] if plan.smoke else ["--minutes", f"{_train_minutes(r):.2f}"]
    if not plan.smoke:
        r.say(f"train: {budget[1]} minutes left for training after the other stages' reserve")
    r.python("rigspace.sdk", "train", str(dataset), "--out", str(model), *plan.train_flags,
             "--no-int8", *budget, stage="train")  # fmt: skip
    training = json.loads((model / "manifest.json").read_text())["training"]
    rate = re.search(r"trained (\d+) steps in ([\d.]+) s \(([\d.]+) images/s\)", r.last_stderr)
    r.numbers["train"] = {
        "steps": training["steps"],
        "trained_levels": training["trained_levels"],
        "seconds": float(rate.group(2)) if rate else None,
        "images_per_second": float(rate.group(3)) if rate else None,
        "flags": [*plan.train_flags, *budget],
    }
    pack(r, model)
    evaluate(r, model, dataset, display)
    pack(r, model)
    _finish_warm(r, warm)
    gpu = work / "gpu_check.json"
    if optional(r, "gpu check", "rigspace.apps.gpu_check", "--out", str(gpu),
                *plan.gpu_check_flags):  # fmt: skip
        r.numbers["gpu_check"] = json.loads(gpu.read_text())
        pack(r, model)
    # int8 last: the runtime draws fp32 unless asked, and the export's check offered int8 at
    # no level of the sample model on 2 CPU cores; a bundle without them gets them here with
    # `python -m rigspace.apps.quantize samples/models/sample DATASET`.
    if optional(r, "int8", "rigspace.apps.quantize", str(model), str(dataset)):
        r.numbers["int8"] = r.last_stderr.strip().splitlines()[-40:]
        pack(r, model)


def optional(r: Run, stage: str, *args: str) -> bool:
    """A stage the bundle does not need: run with the time left (30 s at least), and on a
    failure or timeout say so in numbers.json and go on."""
    if not r.plan.smoke and r.left() < 30:
        r.numbers.setdefault("skipped", {})[stage] = "under 30 s left"
        r.say(f"{stage}: skipped, under 30 s left")
        return False
    limit = None if r.plan.smoke else r.left() - 5
    try:
        r.python(*args, stage=stage, limit=limit)
    except RecipeError as exc:
        r.numbers.setdefault("skipped", {})[stage] = exc.what
        r.say(f"{stage}: {exc.what}")
        return False
    return True


def _train_minutes(r: Run) -> float:
    left = r.left() - sum(r.plan.reserve.values())
    if left < 60:
        raise RecipeError(
            f"only {left:.0f} s would be left for training", "give the run more --minutes"
        )
    return left / 60.0


def evaluate(r: Run, model: Path, dataset: Path, display: Path) -> None:
    limit = str(r.plan.eval_limit)
    results: dict[str, Any] = {}
    for split in ("heldout-views", "heldout-clips"):
        text = r.python("rigspace.sdk", "eval", str(model), str(dataset), "--split", split,
                        "--limit", limit, "--record", "--json", stage=f"eval {split}")  # fmt: skip
        results[split] = json.loads(text)
    text = r.python("rigspace.sdk", "eval", str(model), str(display), "--display", "--limit",
                    limit, "--record", "--json", stage="eval display")  # fmt: skip
    results["display"] = json.loads(text)
    r.numbers["eval"] = results
    r.save()


def _warm_kernels(r: Run, root: Path) -> subprocess.Popen | None:
    """Start one small frame of the sample shot in the background: numba compiles and caches
    the shadow and texture kernels while the capture runs (the first frame waits on it)."""
    if r.plan.smoke:
        return None
    command = [sys.executable, "-m", "rigspace.sdk", "render", str(root / SCENE), "--out",
               str(r.work / "warm"), "--frames", "300:300", "--resolution", "160x90"]  # fmt: skip
    return subprocess.Popen(command, env=r.env, stdout=subprocess.DEVNULL, stderr=r.log)


def _finish_warm(r: Run, warm: subprocess.Popen | None) -> None:
    if warm is not None and warm.wait() != 0:
        r.say("warm-up frame failed (the GPU check's first frame compiles the kernels)")


def pack(r: Run, model: Path) -> list[Path]:
    """The bundle (the files its manifest lists, and its training folder without the
    checkpoint) and numbers.json into results.tar parts of at most PART_BYTES, beside
    numbers.json and log.txt: at most MAX_FILES files under --out."""
    r.save()
    buffer = io.BytesIO()
    listed = set(json.loads((model / "manifest.json").read_text()).get("files", {}))
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        for path in sorted(model.rglob("*")):
            name = path.relative_to(model)
            kept = (
                name.parts[0] == "training" or path.name == "manifest.json" or str(name) in listed
            )
            if path.is_file() and kept and not path.name.startswith(("checkpoint", ".checkpoint")):
                tar.add(path, arcname=f"model/{name}")
        tar.add(r.out / "numbers.json", arcname="numbers.json")
    data = buffer.getvalue()
    for old in r.out.glob("results.tar.*"):
        old.unlink()
    parts = []
    for i in range(0, max(len(data), 1), PART_BYTES):
        parts.append(r.out / f"results.tar.{i // PART_BYTES:03d}")
        _write(parts[-1], data[i : i + PART_BYTES])
    files = list(r.out.iterdir())
    if len(files) > MAX_FILES:
        raise RecipeError(
            f"{len(files)} files under {r.out}; at most {MAX_FILES} come back",
            "leave fewer graphs in the bundle (--no-int8) or raise PART_BYTES",
        )
    r.numbers["packed"] = {
        "parts": [p.name for p in parts],
        "bytes": len(data),
        "sha256": hashlib.sha256(data).hexdigest(),
    }
    r.save()
    r.say(f"pack: {len(data) / 2**20:.1f} MiB in {len(parts)} part(s)")
    return parts


# ------------------------------------------------------------------------------------- test

HANG_SECONDS = 120
"""`test`: a test still running after this long has every thread's stack written to
pytest.txt (pytest's faulthandler_timeout), so a hang on CUDA or the NVIDIA EGL says where."""


def test_suite(out: Path, root: Path, payload: Path, minutes: float, args: list[str]) -> int:
    """Part of the suite on the GPU machine (module doc): the payload installed, then the
    machine's own pytest (its image has pytest, hypothesis, pytest-xdist) on `args`; torch
    trains on CUDA there (`--device auto`) and the gl renderer draws through the NVIDIA EGL.
    pytest.txt, junit.xml and numbers.json land under `out` as they are written."""

    def body(r: Run) -> int:
        command = [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-ra"]
        command += ["-o", f"faulthandler_timeout={HANG_SECONDS}", "--durations=25"]
        command += ["--junitxml", str(out / "junit.xml"), *args]
        r.say(f"test: {' '.join(command[2:])}")
        start = time.monotonic()
        with (out / "pytest.txt").open("w", encoding="utf-8") as log:
            try:
                code = subprocess.call(
                    command, cwd=root, env=r.env, stdout=log, stderr=subprocess.STDOUT,
                    timeout=max(r.left(), 1.0),
                )  # fmt: skip
            except subprocess.TimeoutExpired:
                code = 124
        r.numbers["stages"]["test"] = round(time.monotonic() - start, 1)
        r.numbers["pytest"] = {"exit": code, **_junit_counts(out / "junit.xml")}
        r.say(f"test: exit {code} in {r.numbers['stages']['test']} s ({r.numbers['pytest']})")
        return 0 if code == 0 else 1

    plan = replace(Plan.toy(), minutes=minutes)  # the deadline; test runs no recipe stage
    return _installed(out, plan, root, payload, body, verb="test")


def _junit_counts(path: Path) -> dict[str, int]:
    """tests / failures / errors / skipped of pytest's junit XML ({} before it is written: a
    run stopped at its limit)."""
    import xml.etree.ElementTree as ET

    if not path.is_file():
        return {}
    root = ET.parse(path).getroot()
    suite = root if root.tag == "testsuite" else root.find("testsuite")
    if suite is None:
        return {}
    return {k: int(suite.get(k, 0)) for k in ("tests", "failures", "errors", "skipped")}


# ----------------------------------------------------------------------------------- unpack


def unpack(files: Path, docs: Path, bundle_into: Path | None) -> dict[str, Any]:
    """Join and check results.tar.*, extract the bundle into `bundle_into` (replacing it) and
    write the GPU table (`docs`/gpu.md and gpu.json) from numbers.json."""
    numbers = json.loads((files / "numbers.json").read_text())
    packed = numbers.get("packed")
    if not packed:
        raise RecipeError(f"{files / 'numbers.json'} records no packed results", "see log.txt")
    data = b"".join((files / name).read_bytes() for name in packed["parts"])
    if hashlib.sha256(data).hexdigest() != packed["sha256"]:
        raise RecipeError(
            f"the results in {files} do not match the sha256 numbers.json records",
            "fetch the files again, or rerun the recipe",
        )
    with tempfile.TemporaryDirectory() as tmp:
        with tarfile.open(fileobj=io.BytesIO(data)) as tar:
            extract(tar, Path(tmp))
        model = Path(tmp) / "model"
        if bundle_into is not None and (model / "manifest.json").is_file():
            _replace_folder(model, bundle_into)
    table = gpu_table(numbers)
    docs.mkdir(parents=True, exist_ok=True)
    _write(docs / "gpu.md", table)
    _write(docs / "gpu.json", json.dumps(numbers, indent=2) + "\n")
    return numbers


def extract(tar: tarfile.TarFile, into: Path) -> None:
    """Every member of `tar` into `into`, refusing any that is not a plain file or folder
    inside it (tarfile's "data" filter where this Python has it: 3.11.4 and later; the same
    rule by hand before, as Debian 12's 3.11.2)."""
    if hasattr(tarfile, "data_filter"):
        tar.extractall(into, filter="data")
        return
    root = into.resolve()
    for member in tar.getmembers():
        target = (root / member.name).resolve()
        if not (member.isfile() or member.isdir()) or not target.is_relative_to(root):
            raise RecipeError(
                f"the archive's member {member.name!r} is not a plain file or folder inside {into}",
                "rebuild the archive (prepare, or the recipe's pack)",
            )
    tar.extractall(into)


def _replace_folder(new: Path, home: Path) -> None:
    """`home` becomes `new`'s content (staged beside it, then swapped in)."""
    staged = home.with_name(f".{home.name}.new")
    shutil.rmtree(staged, ignore_errors=True)
    shutil.copytree(new, staged)
    old = home.with_name(f".{home.name}.old")
    shutil.rmtree(old, ignore_errors=True)
    if home.exists():
        os.replace(home, old)
    os.replace(staged, home)
    shutil.rmtree(old, ignore_errors=True)


def gpu_table(numbers: dict[str, Any]) -> str:
    """The GPU table in Markdown: the run's stages, training, the evaluations, the GPU check."""
    lines = ["# The GPU recipe's last run", ""]
    lines.append(f"`python3 apps/recipe.py run` ({'smoke, on the CPU' if numbers['smoke'] else 'GPU'}), "
                 f"{numbers.get('seconds', 0):.0f} s in all.")  # fmt: skip
    if "failed" in numbers:
        lines.append(f"\nIt stopped: {numbers['failed']}")
    lines += ["", "| stage | seconds |", "|---|---|"]
    lines += [f"| {k} | {v:.1f} |" for k, v in numbers.get("stages", {}).items()]
    train = numbers.get("train")
    if train:
        lines += ["", f"Training: {train.get('steps')} steps, levels {train.get('trained_levels')}, "
                  f"{train.get('images_per_second') or 0:.0f} images/s end to end; flags "
                  f"`{' '.join(train.get('flags', []))}`."]  # fmt: skip
    evaluation = numbers.get("eval", {})
    for split in ("heldout-views", "heldout-clips"):
        if split in evaluation:
            lines += ["", f"{split}:", "", *_metric_rows(evaluation[split])]
    if "display" in evaluation:
        lines += ["", "At display size:", "", *_metric_rows(evaluation["display"])]
    check = numbers.get("gpu_check")
    if check:
        lines += ["", "GPU check (apps/gpu_check.py):", "", "```",
                  json.dumps(check.get("parts", {}), indent=1)[:6000], "```"]  # fmt: skip
    return "\n".join(lines) + "\n"


def _metric_rows(result: Any) -> list[str]:
    """Whatever eval --json printed, as a compact list of its predictors' rows."""
    rows: list[str] = []

    def walk(node: Any, path: str) -> None:
        if isinstance(node, dict) and "rows" in node:
            for row in node["rows"]:
                if isinstance(row, dict):
                    name = row.get("predictor") or row.get("name") or "?"
                    values = {k: v for k, v in row.items() if isinstance(v, int | float)}
                    shown = ", ".join(f"{k} {v:.4g}" for k, v in values.items())
                    rows.append(f"- {path}{name}: {shown}")
        elif isinstance(node, dict):
            for key, value in node.items():
                walk(value, f"{path}{key} / " if path or key not in ("results",) else path)

    walk(result, "")
    return rows or ["- (no rows)"]


# ------------------------------------------------------------------------------- the command


def _importable(module: str, env: dict[str, str]) -> bool:
    probe = [sys.executable, "-c", f"import {module}"]
    return subprocess.run(probe, env=env, capture_output=True).returncode == 0


def _check_call(command: list[str], what: str, **kwargs: Any) -> None:
    done = subprocess.run(command, capture_output=True, text=True, **kwargs)
    if done.returncode != 0:
        tail = "\n".join((done.stderr or done.stdout).strip().splitlines()[-8:])
        raise RecipeError(f"{what} failed (exit {done.returncode}):\n{tail}", "see above")


def _write(path: Path, data: str | bytes) -> None:
    """Atomic: a temporary file beside `path`, then os.replace (stdlib only: see the top)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(data.encode() if isinstance(data, str) else data)
    os.replace(tmp, path)


def _say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m rigspace.apps.recipe",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    verbs = parser.add_subparsers(dest="verb", required=True)
    p = verbs.add_parser("prepare", help="gather the GPU machine's payload into .gpu/")
    p.add_argument("--payload", type=Path, default=PAYLOAD)
    p.add_argument("--python", default=PYTHON, help="the GPU machine's Python (default 3.12)")
    p.add_argument("--level", type=int, default=9, help="xz preset (default 9)")
    p.add_argument("--check-only", action="store_true", help="only check what would travel")
    r = verbs.add_parser("run", help="the recipe itself (on the GPU machine, or --smoke)")
    r.add_argument("--out", type=Path, required=True, help="results folder (the device's $OUT)")
    r.add_argument("--payload", type=Path, default=PAYLOAD)
    r.add_argument("--minutes", type=float, default=9.0, help="the whole run's time (default 9)")
    r.add_argument("--smoke", action="store_true", help="on the CPU at 32x32, a few steps")
    r.add_argument("--keep", action="store_true", help="keep the datasets and the run")
    r.add_argument("--train-flag", action="append", default=[], metavar="FLAG",
                   help="an extra `rigspace train` argument (repeat; e.g. --train-flag=--bf16)")  # fmt: skip
    s = verbs.add_parser("test", help="part of the suite on the GPU machine (after --)")
    s.add_argument("--out", type=Path, required=True, help="results folder (the device's $OUT)")
    s.add_argument("--payload", type=Path, default=PAYLOAD)
    s.add_argument("--minutes", type=float, default=9.0, help="the whole run's time (default 9)")
    s.add_argument("pytest_args", nargs="*", metavar="PYTEST_ARG",
                   help="what pytest gets, after `--` (e.g. -- -x -n 8 tests/train)")  # fmt: skip
    u = verbs.add_parser("unpack", help="the returned files into the tree")
    u.add_argument("files", type=Path, help="the folder the device's files came back to")
    u.add_argument("--bundle-into", type=Path, default=BUNDLE_HOME)
    u.add_argument("--docs", type=Path, default=Path("docs/bench"), help="where gpu.md goes")
    u.add_argument("--no-bundle", action="store_true", help="write the GPU table only")
    args = parser.parse_args(argv)
    root = Path.cwd()
    if not (root / SCENE).is_file():
        print(f"recipe: run it from the repository root ({SCENE} is not here)", file=sys.stderr)
        return 2
    try:
        if args.verb == "prepare":
            info = (
                {"travel": travel_check(root, args.payload)}
                if args.check_only
                else prepare(root, args.payload, args.python, args.level)
            )
            t = info["travel"]
            _say(
                f"prepare: tree {t['tree'] / 2**20:.1f} MiB + payload {t['payload'] / 2**20:.1f} "
                f"MiB = {t['total'] / 2**20:.1f} MiB of {t['limit'] / 2**20:.0f} MiB: it travels"
            )
            return 0
        if args.verb == "test":
            return test_suite(args.out, root, args.payload, args.minutes, args.pytest_args)
        if args.verb == "run":
            extra = tuple(args.train_flag)
            plan = Plan.toy(extra) if args.smoke else Plan.gpu(args.minutes, extra)
            return run(args.out, plan, root, args.payload, args.keep)
        numbers = unpack(args.files, args.docs, None if args.no_bundle else args.bundle_into)
        _say(f"unpack: {', '.join(numbers['stages'])}; docs/bench/gpu.md written")
        return 0
    except RecipeError as exc:
        print(f"recipe: {exc.what}" + (f"\nFix: {exc.fix}" if exc.fix else ""), file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
