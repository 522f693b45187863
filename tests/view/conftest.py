"""Viewer fixtures: data-only apps (no engines) for the endpoints, served viewers for the browser."""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator

import pytest

with warnings.catch_warnings():  # starlette 1.x suggests httpx2; httpx is what it runs on here
    warnings.simplefilter("ignore")
    from starlette.testclient import TestClient

from rigspace.apps.view import build, in_background
from rigspace.runtime.view.scene import SceneModel
from rigspace.runtime.view.server import Viewer, create_app
from rigspace.runtime.view.viewport import FrameService
from tests.conftest import REPO

PREVIS = REPO / "samples" / "scenes" / "previs.usda"
LIVE = REPO / "samples" / "scenes" / "live.usda"
BROKEN = REPO / "tests" / "fixtures" / "broken_character.usda"
CHROMIUM = "/usr/bin/chromium"


def data_viewer(scene) -> Viewer:
    """A viewer whose engines are not opened: the data endpoints only (fast)."""
    model = SceneModel(scene)
    return Viewer(model, FrameService(scene, model.lock))


def data_client(scene) -> Iterator[TestClient]:
    """A test client of data_viewer(scene)'s app, the viewer closed after it."""
    viewer = data_viewer(scene)
    with TestClient(create_app(viewer), base_url="http://127.0.0.1") as client:
        yield client
    viewer.close()


@pytest.fixture(scope="module")
def previs_client() -> Iterator[TestClient]:
    yield from data_client(PREVIS)


@pytest.fixture(scope="module")
def broken_client() -> Iterator[TestClient]:
    yield from data_client(BROKEN)


@contextlib.contextmanager
def served(scene, **options) -> Iterator[tuple[Viewer, str]]:
    """A viewer of `scene` with its engines, served by uvicorn on a free loopback port."""
    viewer = build(str(scene), **options)
    server, url = in_background(viewer)
    try:
        yield viewer, url
    finally:
        server.should_exit = True
        viewer.close()


@pytest.fixture(scope="session")
def previs_served() -> Iterator[tuple[Viewer, str]]:
    """One served previs viewer for the session (opening its engines takes seconds)."""
    with served(PREVIS) as pair:
        yield pair


@pytest.fixture(scope="session")
def browser():
    playwright = pytest.importorskip("playwright.sync_api")
    import os

    if not os.path.exists(CHROMIUM):
        pytest.skip("Debian's chromium is not installed (apt-get install chromium)")
    with playwright.sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        yield chromium
        chromium.close()
