"""The web page in a real headless browser (Debian chromium via Playwright): the map is drawn.

Needs `apt-get install chromium` and `pip install playwright` (dev extra); skipped loudly
without them.
"""

from __future__ import annotations

import io
import shutil
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace

import numpy as np
import pytest
import uvicorn
from fastapi import FastAPI
from PIL import Image
from scanflow import keys
from scanflow.geometry import Pose2D
from scanflow.maps.grid import GridSpec
from scanflow.wire import MapImageMessage, MapMetaMessage, TrajectoryMessage

from services.common.launch import free_port, wait_for_port
from services.gateway.app import create_app

from .conftest import estimate, eventually

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
pytestmark = pytest.mark.skipif(
    shutil.which("chromium") is None,
    reason="BROWSER TEST SKIPPED: Debian's chromium is absent (apt-get install -y chromium)",
)
BACKGROUND = (0x20, 0x24, 0x2A)


@contextmanager
def serving(app: FastAPI) -> Iterator[str]:
    """`app` on a real uvicorn server in a thread; yields its base URL."""
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port,
                                           log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    wait_for_port(port)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(10)


@pytest.fixture
def served(backend, settings) -> Iterator[str]:
    """The gateway app on a real uvicorn server in a thread; yields its base URL."""
    with serving(create_app(settings, backend)) as url:
        yield url


def test_page_draws_the_map_and_trajectory(served, peer, backend):
    image = np.full((40, 60), 254, np.uint8)
    image[:, :3] = 0
    image[:3, :] = 0
    png = io.BytesIO()
    Image.fromarray(image, mode="L").save(png, format="PNG")
    meta = MapMetaMessage.from_spec("r1", GridSpec(-1.0, -1.0, 0.1, 40, 60), 1, 0.0)
    peer.answer(keys.map_key("r1", "meta"), lambda q: meta.encode())
    peer.answer(keys.map_key("r1", "image"),
                lambda q: MapImageMessage("r1", 1, "png", png.getvalue()).encode())
    for seq in range(5):
        peer.put(keys.pose("r1"), estimate("r1", seq, float(seq), seq * 0.8, seq * 0.5).encode())

    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        try:
            page = browser.new_page()
            page.goto(served)
            canvas = page.locator("#robot-r1 canvas")
            canvas.wait_for(timeout=15_000)
            page.wait_for_function(  # the map image loaded and every pose arrived
                "() => { const v = views.get('r1'); return v && v.image && v.path.length >= 5; }",
                timeout=15_000,
            )
            shot = Image.open(io.BytesIO(canvas.screenshot())).convert("RGB")
        finally:
            browser.close()
    pixels = np.asarray(shot).reshape(-1, 3).astype(int)
    drawn = np.abs(pixels - BACKGROUND).sum(axis=1) > 30
    white = (pixels > 240).all(axis=1)
    red = (pixels[:, 0] > 180) & (pixels[:, 1] < 120)
    assert drawn.mean() > 0.3, f"only {drawn.mean():.1%} of the canvas differs from background"
    assert white.sum() > 1000, "the free (white) map cells are not drawn"
    assert red.sum() > 10, "the trajectory (red) is not drawn"


def test_page_loads_the_path_again_when_loop_closure_redraws_the_map(served, peer, backend):
    old_path = (np.arange(4.0), np.column_stack((np.arange(4.0), np.zeros(4), np.zeros(4))))
    served_path = {"now": old_path}  # (stamps, poses), swapped whole
    peer.answer(keys.trajectory("r2"),
                lambda q: TrajectoryMessage("r2", *served_path["now"]).encode())
    for seq in range(4):
        peer.put(keys.pose("r2"), estimate("r2", seq, float(seq), float(seq), 0.0).encode())

    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        try:
            page = browser.new_page()
            page.goto(served)
            page.wait_for_function(
                "() => { const v = views.get('r2'); return v && v.path.length >= 4; }",
                timeout=15_000,
            )
            # That path came from the trajectory query; the redraw comes on the event stream,
            # which a loaded machine may not have opened yet (the redraw then went unseen).
            eventually(lambda: backend.events.clients >= 1, "the page's event stream",
                       timeout_s=15.0)
            redrawn = replace(estimate("r2", 4, 4.0, 4.0, 5.0), correction=Pose2D(0.0, 5.0, 0.0))
            peer.put(keys.pose("r2"), redrawn.encode())  # before the map server has redrawn
            page.wait_for_timeout(600)  # the page asks meanwhile, and must wait for the path
            served_path["now"] = (  # the map server has redrawn: the corrected path
                np.arange(5.0), np.column_stack((np.arange(5.0), np.full(5, 5.0), np.zeros(5)))
            )
            page.wait_for_function(  # every point of the path now comes from the corrected one
                "() => { const p = views.get('r2').path;"
                " return p.length >= 5 && p.every(([x, y]) => y === 5); }",
                timeout=15_000,
            )
        finally:
            browser.close()


def test_page_says_why_it_shows_nothing_when_reads_need_the_key(backend, settings):
    """With guard_reads the page's own requests carry no key (an event stream cannot send the
    header): it says so rather than 'gateway unreachable'."""
    guarded = settings.model_copy(update={"guard_reads": True})
    with serving(create_app(guarded, backend)) as url, sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        try:
            page = browser.new_page()
            page.goto(url)
            status = page.locator("#status")
            status.filter(has_text="needs its API key").wait_for(timeout=15_000)
            assert "GUARD_READS" in status.inner_text()
        finally:
            browser.close()
