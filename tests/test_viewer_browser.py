"""`livescene view` in a real browser: Debian's Chromium (headless) driven by Playwright.

Load the page on a trained toy room, jump to a training camera, drag the door's slider from closed to open: low
resolution images follow the drag, a sharp one comes at rest, and the image changed where the door is (the
simulator's truth) and nowhere else. Orbit with the mouse, save the view. The screenshot is saved under
$VIEWER_SCREENSHOT_DIR (else the test's tmp folder) and its path printed.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_livescene_toy import ToyScene  # noqa: E402
from test_viewer import train_tiny_run  # noqa: E402

pytestmark = pytest.mark.browser



@pytest.fixture(scope="module")
def server(tmp_path_factory, one_thread):
    from livescene.trainer import load_run
    from livescene.viewer import ViewerServer
    from livescene.viewer.session import ViewerSession

    run_dir = train_tiny_run(tmp_path_factory.mktemp("viewer_browser"))
    session = ViewerSession(load_run(run_dir, device="cpu"), low=48, sharp=96)
    srv = ViewerServer(session, port=0).start()
    yield srv, session
    srv.stop()


def rest(page, timeout: float = 120000) -> None:
    """Wait until the page shows the sharp image of its current view."""
    page.wait_for_function("document.body.dataset.sharp === '1'", timeout=timeout)


def pixels(page) -> np.ndarray:
    """The canvas at its own resolution (the rendered image), (H, W, 3) in [0, 1]."""
    data = page.evaluate("""() => { const c = document.getElementById('view');
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        return {w: c.width, h: c.height, d: Array.from(d)}; }""")
    return np.asarray(data["d"], np.float32).reshape(data["h"], data["w"], 4)[..., :3] / 255


def test_drag_a_slider_changes_the_object_only(browser, server, tmp_path):
    srv, session = server
    run = session.run
    errors: list[str] = []
    foreign: list[str] = []
    origin = f"http://127.0.0.1:{srv.port}/"
    # bypass_csp: Playwright's wait_for_function evaluates strings, which the page's CSP forbids
    ctx = browser.new_context(viewport={"width": 1280, "height": 800}, bypass_csp=True)
    page = ctx.new_page()
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.on("request", lambda r: None if r.url.startswith(origin) or r.url.startswith(("data:", "blob:"))
            else foreign.append(r.url))
    page.goto(srv.url)
    page.wait_for_selector('body[data-ready="1"]', timeout=120000)
    rest(page)
    assert page.locator("#objects input[type=range]").count() == 1
    assert page.locator("#cameras option").count() == len(run.views.times)

    # jump to a training camera that sees the door, close the door
    i = int(run.views.train[5])
    page.select_option("#cameras", str(i))
    page.evaluate("() => { window.viewer.setStates({door: 0}); window.viewer.changed(); }")
    rest(page)
    closed = pixels(page)
    assert closed.shape == (72, 96, 3)

    # drag the door's slider all the way open with the mouse
    low_before = int(page.get_attribute("body", "data-low-frames"))
    box = page.locator("#state-0").bounding_box()
    y = box["y"] + box["height"] / 2
    page.mouse.move(box["x"] + 2, y)
    page.mouse.down()
    for k in range(1, 9):
        page.mouse.move(box["x"] + box["width"] * k / 8 + 4, y)
        page.wait_for_timeout(120)
    page.mouse.up()
    rest(page)
    assert page.input_value("#state-0") == "1"
    assert int(page.get_attribute("body", "data-low-frames")) > low_before  # low-res images followed the drag
    opened = pixels(page)
    view = page.evaluate("() => window.viewer.view('sharp')")
    assert view["states"] == {"door": 1}

    # where the door is: the simulator's truth in either state; static: what the model also calls static
    from livescene.render import render_view
    from livescene.viewer.session import View

    v = View(np.asarray(view["camera"]["c2w"]).reshape(4, 4), 96, 72, view["camera"]["fov_y"], {})
    assert np.allclose(v.c2w, run.views.c2w_gl[i], atol=1e-5)
    intr = v.intrinsics()
    door = (ToyScene(1).render(v.c2w, [0.0], intr)[2] == 1) | (ToyScene(1).render(v.c2w, [1.0], intr)[2] == 1)
    probs = [render_view(run, v.c2w, intr, {"door": s})["probs"][..., 0] for s in (0.0, 1.0)]
    static = ~door & (probs[0] < 0.5) & (probs[1] < 0.5)
    diff = np.abs(opened - closed).max(-1)
    assert door.mean() > 0.03 and static.mean() > 0.5
    assert diff[door].mean() > 0.05, diff[door].mean()
    assert np.percentile(diff[static], 95) < 0.02, np.percentile(diff[static], 95)

    # orbit with the mouse: the camera moves, the image follows
    cbox = page.locator("#view").bounding_box()
    cx, cy = cbox["x"] + cbox["width"] / 2, cbox["y"] + cbox["height"] / 2
    page.mouse.move(cx, cy)
    page.mouse.down()
    page.mouse.move(cx + 60, cy + 10, steps=6)
    page.mouse.up()
    rest(page)
    moved = page.evaluate("() => window.viewer.view('sharp').camera.c2w")
    assert not np.allclose(moved, view["camera"]["c2w"], atol=1e-3)
    assert np.abs(pixels(page) - opened).mean() > 0.01

    # fly forward with W, zoom out with the wheel
    def where() -> np.ndarray:
        return np.asarray(page.evaluate("() => window.viewer.view('sharp').camera.c2w")).reshape(4, 4)

    before = where()
    page.keyboard.down("w")
    page.wait_for_timeout(300)
    page.keyboard.up("w")
    after = where()
    step = after[:3, 3] - before[:3, 3]
    assert np.linalg.norm(step) > 0 and step @ -before[:3, 2] > 0.9 * np.linalg.norm(step)  # along the view
    page.mouse.move(cx, cy)
    page.mouse.wheel(0, 300)
    page.wait_for_timeout(100)
    target = np.asarray(page.evaluate("() => window.viewer.state.cam.t"))
    assert np.linalg.norm(where()[:3, 3] - target) > np.linalg.norm(after[:3, 3] - target)
    rest(page)

    # save the view into RUN/views
    page.click("#save")
    page.wait_for_function("document.getElementById('message').dataset.kind === 'ok'", timeout=120000)
    saved = sorted((run.run_dir / "views").glob("view_*.png"))
    assert saved and "saved" in page.inner_text("#message")

    shots = Path(os.environ.get("VIEWER_SCREENSHOT_DIR", tmp_path))
    shots.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(shots / "viewer.png"))
    print(f"screenshot: {shots / 'viewer.png'}")
    assert not errors, errors
    assert not foreign, f"the page reached outside the server: {foreign}"
    ctx.close()

    # the page itself needs no exception to its Content-Security-Policy
    strict = browser.new_context()
    page = strict.new_page()
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(srv.url)
    page.wait_for_selector('body[data-ready="1"]', timeout=120000)
    assert not errors, errors
    strict.close()
