"""The operator page in headless Chromium (Debian's chromium, driven over the DevTools
protocol): power the simulated robot on through the buttons, start and stop a move,
and check a screenshot.

Chromium is looked up on the PATH (``chromium``, ``chromium-browser``, ``google-chrome``)
or taken from ``$FXCELL_CHROMIUM``. Without one the test is skipped, unless
``FXCELL_REQUIRE_BROWSER=1`` (set by CI) makes that a failure.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import io
import itertools
import json
import math
import os
import shutil
import subprocess
import tempfile
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest
import websockets

from fxcell.daemon.process import DaemonProcess

TOKEN = "web-test-token-0123456789abcdef"
CONFIG = "robot:\n  host: null\ndaemon:\n  token_file: {token_file}\n"
SCREENSHOT_DIR = Path(os.environ.get("FXCELL_SCREENSHOT_DIR", tempfile.gettempdir()))

pytestmark = pytest.mark.slow


def find_chromium() -> str | None:
    explicit = os.environ.get("FXCELL_CHROMIUM")
    if explicit:
        return explicit
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        path = shutil.which(name)
        if path:
            return path
    return None


class Browser:
    """Just enough of the Chrome DevTools protocol: evaluate, click, screenshot."""

    def __init__(self, ws: Any) -> None:
        self._ws = ws
        self._ids = itertools.count(1)
        self.console: list[str] = []
        self.held: list[str] = []  # requests whose responses the browser holds (hold_responses)

    async def call(self, method: str, **params: Any) -> dict[str, Any]:
        msg_id = next(self._ids)
        await self._ws.send(json.dumps({"id": msg_id, "method": method, "params": params}))
        while True:
            msg = json.loads(await self._ws.recv())
            if msg.get("id") == msg_id:
                if "error" in msg:
                    raise AssertionError(f"{method}: {msg['error']}")
                return msg.get("result", {})  # type: ignore[no-any-return]
            if msg.get("method") == "Runtime.exceptionThrown":
                self.console.append(json.dumps(msg["params"]["exceptionDetails"])[:500])
            elif msg.get("method") == "Fetch.requestPaused":
                self.held.append(msg["params"]["requestId"])
            elif msg.get("method") == "Runtime.consoleAPICalled":
                args = msg["params"].get("args", [])
                self.console.append(" ".join(str(a.get("value", "")) for a in args))

    async def js(self, expression: str) -> Any:
        result = await self.call(
            "Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True
        )
        if "exceptionDetails" in result:
            raise AssertionError(f"{expression}: {result['exceptionDetails']}")
        return result["result"].get("value")

    async def wait_for(self, expression: str, within: float = 20.0) -> Any:
        """Poll a JavaScript expression until it is truthy."""
        deadline = time.monotonic() + within
        while True:
            try:
                value = await self.js(expression)
            except AssertionError:  # e.g. the page is still loading
                value = None
            if value:
                return value
            if time.monotonic() > deadline:
                state = await self.js("document.querySelector('#cell-state').textContent")
                log = await self.js("document.querySelector('#log').innerText")
                log += "\nform errors: " + await self.js(
                    "[...document.querySelectorAll('.error')].map(e => e.textContent).join(' | ')"
                )
                raise AssertionError(
                    f"timed out waiting for {expression} (state {state}); log:\n{log}\n"
                    f"console: {self.console}"
                )
            await asyncio.sleep(0.05)

    async def hold_responses(self, url_pattern: str) -> None:
        """Hold the responses to requests matching ``url_pattern`` until release_held()."""
        await self.call(
            "Fetch.enable", patterns=[{"urlPattern": url_pattern, "requestStage": "Response"}]
        )

    async def release_held(self, within: float = 20.0) -> None:
        """Let the held response through (waiting for it to be held first); hold no more."""
        deadline = time.monotonic() + within
        while not self.held:  # each call reads the browser's events
            assert time.monotonic() < deadline, "no response was held"
            await self.js("0")
        for request_id in self.held:
            await self.call("Fetch.continueRequest", requestId=request_id)
        self.held.clear()
        await self.call("Fetch.disable")

    async def click(self, selector: str) -> None:
        """A real mouse click in the middle of the element (fails if it is disabled)."""
        box = await self.js(
            f"(() => {{ const e = document.querySelector({json.dumps(selector)});"
            "e.scrollIntoView({block: 'center'}); const r = e.getBoundingClientRect();"
            "return {x: r.x + r.width / 2, y: r.y + r.height / 2, disabled: e.disabled}; })()"
        )
        assert not box["disabled"], f"{selector} is disabled"
        for kind in ("mousePressed", "mouseReleased"):
            await self.call(
                "Input.dispatchMouseEvent",
                type=kind,
                x=box["x"],
                y=box["y"],
                button="left",
                clickCount=1,
            )

    async def screenshot(self) -> bytes:
        result = await self.call("Page.captureScreenshot", format="png")
        return base64.b64decode(result["data"])


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DaemonProcess]:
    tmp = tmp_path_factory.mktemp("web")
    config = tmp / "cell.yaml"
    config.write_text(CONFIG.format(token_file=tmp / "token"))
    with DaemonProcess.start(
        config, token=TOKEN, extra_args=("--sim-time-scale", "0.2")
    ) as process:
        process.wait_connected()
        yield process


@pytest.fixture
async def browser(daemon: DaemonProcess, tmp_path: Path) -> AsyncIterator[Browser]:
    async with headless_chromium(tmp_path / "profile", 1440, 1100) as b:
        yield b


@contextlib.asynccontextmanager
async def headless_chromium(profile: Path, width: int, height: int) -> AsyncIterator[Browser]:
    """Debian's headless Chromium on a page of ``width`` × ``height`` pixels, driven over
    its DevTools protocol; skipped without Chromium (a failure with
    ``FXCELL_REQUIRE_BROWSER``, as in CI)."""
    chromium = find_chromium()
    if chromium is None:
        if os.environ.get("FXCELL_REQUIRE_BROWSER"):
            pytest.fail("no Chromium found (apt-get install chromium)")
        pytest.skip("no Chromium found (apt-get install chromium); set FXCELL_CHROMIUM")
    proc = subprocess.Popen(  # noqa: ASYNC220 - started once, before the loop is busy
        [
            chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
            "--no-first-run", "--disable-background-networking", "--disable-component-update",
            "--disable-sync", "--disable-dev-shm-usage", "--hide-scrollbars",
            f"--user-data-dir={profile}", "--remote-debugging-port=0",
            f"--window-size={width},{height}", "about:blank",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )  # fmt: skip
    try:
        port_file = profile / "DevToolsActivePort"
        deadline = time.monotonic() + 30
        while not (port_file.exists() and port_file.read_text().count("\n") >= 1):
            assert proc.poll() is None, "chromium exited while starting"
            assert time.monotonic() < deadline, "chromium did not open its DevTools port"
            await asyncio.sleep(0.05)
        port = int(port_file.read_text().split()[0])
        targets = await asyncio.to_thread(_get_json, f"http://127.0.0.1:{port}/json/list")
        page = next(t for t in targets if t["type"] == "page")
        async with websockets.connect(page["webSocketDebuggerUrl"], max_size=None) as ws:
            browser = Browser(ws)
            await browser.call("Runtime.enable")
            await browser.call("Page.enable")
            await browser.call(
                "Emulation.setDeviceMetricsOverride", width=width, height=height,
                deviceScaleFactor=1, mobile=False,
            )  # fmt: skip
            yield browser
    finally:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def _get_json(url: str) -> Any:
    import urllib.request

    with urllib.request.urlopen(url, timeout=10) as response:
        return json.loads(response.read())


def state_is(*states: str) -> str:
    names = json.dumps(list(states))
    return f"{names}.includes(document.querySelector('#cell-state').dataset.state)"


async def test_operator_powers_on_moves_and_stops_from_the_page(
    browser: Browser, daemon: DaemonProcess, tmp_path: Path
) -> None:
    await browser.call("Page.navigate", url=f"{daemon.url}/#token={TOKEN}")
    await browser.wait_for("document.querySelector('#link').textContent === 'daemon live'")
    await browser.wait_for(state_is("power_off"))
    assert await browser.js("location.hash") == ""  # the token left the address bar
    disabled = await browser.js(
        "Object.fromEntries([...document.querySelectorAll('button[data-command]')]"
        ".map(b => [b.dataset.command, b.disabled]))"
    )
    assert disabled["power_on"] is False
    assert disabled["brake_release"] is True  # the statechart forbids it with power off
    assert disabled["go_home"] is True  # moves need external control
    assert await browser.js("document.querySelector('#form-joint button[type=submit]').disabled")

    # power_on's answer, which brings the page its control lease, arrives only after the
    # stream showed power_on done and the operator clicked brake_release (a busy machine once
    # did that): the click waits for the answer, not refused for the page's own control
    await browser.hold_responses("*/api/cell/power_on*")
    await browser.click("button[data-command=power_on]")
    await browser.wait_for(state_is("idle"))
    await browser.click("button[data-command=brake_release]")
    await browser.release_held()
    await browser.wait_for(state_is("running.program_stopped"))
    assert "refused" not in await browser.js("document.querySelector('#log').innerText")
    await browser.click("button[data-command=start_external_control]")
    await browser.wait_for(state_is("running.external_control_ready"))
    assert await browser.js("document.querySelector('#form-joint button[type=submit]').disabled") \
        is False  # fmt: skip

    # a malformed form is refused in the page and nothing moves
    await browser.js("document.querySelector('#form-joint').elements.q0.value = ''")
    await browser.click("#form-joint button[type=submit]")
    assert "enter a number" in await browser.js(
        "document.querySelector('#form-joint .error').textContent"
    )

    # start a long base move, then press STOP
    await browser.click("#copy-joints")
    q0 = await browser.js("Number(document.querySelector('#form-joint').elements.q0.value)")
    await browser.js(
        f"document.querySelector('#form-joint').elements.q0.value = {q0 + 1.5};"
        "document.querySelector('#vf').value = 0.3; document.querySelector('#af').value = 0.5;"
    )
    await browser.click("#form-joint button[type=submit]")
    await browser.wait_for(state_is("running.moving"))
    await browser.wait_for(f"Number(document.querySelector('#q0').textContent) > {q0 + 0.05}")
    await browser.click("#stop")
    await browser.wait_for(state_is("running.external_control_ready"))
    await browser.wait_for(
        "document.querySelector('#operations li[data-status=cancelled]') !== null"
    )
    await browser.wait_for("Math.abs(Number(document.querySelector('#v0').textContent)) < 1e-3")
    reached = await browser.js("Number(document.querySelector('#q0').textContent)")
    assert q0 + 0.05 < reached < q0 + 1.5 - 0.01  # it moved, and stopped short of the target

    # the state-machine diagram highlights the current state
    current = await browser.js(
        "[...document.querySelectorAll('#statechart .state.current')].map(e => e.dataset.state)"
    )
    assert current == ["running.external_control_ready"]
    log = await browser.js("document.querySelector('#log').innerText")
    assert "running.moving" in log
    assert "running.stopping" in log or "running.external_control_ready" in log

    png = await browser.screenshot()
    path = SCREENSHOT_DIR / "fxcell-web-page.png"
    path.write_bytes(png)
    (tmp_path / "page.png").write_bytes(png)
    regions = await browser.js(
        "Object.fromEntries(['#stop', '#arm', '#statechart .state.current rect', '#cell-state']"
        ".map(s => { const r = document.querySelector(s).getBoundingClientRect();"
        "return [s, [r.x, r.y, r.width, r.height]]; }))"
    )
    check_screenshot(png, regions)
    assert not [c for c in browser.console if "Error" in c], browser.console


def check_screenshot(png: bytes, regions: dict[str, list[float]]) -> None:
    """Non-blank, the red STOP button, the arm drawn, the current state highlighted."""
    import numpy as np
    from PIL import Image

    image = Image.open(io.BytesIO(png)).convert("RGB")
    assert image.size == (1440, 1100)
    small = np.asarray(image.resize((144, 110))).reshape(-1, 3)
    assert len({tuple(p) for p in small}) > 50  # not a blank page

    def crop(selector: str) -> Image.Image:
        x, y, w, h = regions[selector]
        return image.crop((math.ceil(x), math.ceil(y), int(x + w), int(y + h)))

    def share(region: Image.Image, test: Any) -> float:
        pixels = [tuple(int(c) for c in p) for p in np.asarray(region).reshape(-1, 3)]
        return sum(1 for p in pixels if test(p)) / len(pixels)

    def reddish(p: tuple[int, int, int]) -> bool:
        return p[0] > 150 and p[1] < 80 and p[2] < 90

    def accent(p: tuple[int, int, int]) -> bool:
        return p[2] > 180 and p[0] < 80 and 80 < p[1] < 150

    def arm(p: tuple[int, int, int]) -> bool:  # the arm's links #3d5a80 and joints
        return p[2] > p[0] + 30 and p[0] < 90 and p[1] < 110

    assert share(crop("#stop"), reddish) > 0.5
    assert share(crop("#statechart .state.current rect"), accent) > 0.5
    assert share(crop("#arm"), arm) > 0.003  # a stick figure of ~0.9 m on a 1.2 m view

    def greenish(p: tuple[int, int, int]) -> bool:  # the "ready" colours
        return p[1] > p[0] + 15 and p[1] > p[2] + 10

    assert share(crop("#cell-state"), greenish) > 0.5


async def test_the_page_says_why_and_what_to_do_next_on_a_small_screen(
    browser: Browser, daemon: DaemonProcess
) -> None:
    import httpx

    await browser.call(
        "Emulation.setDeviceMetricsOverride", width=1366, height=768,
        deviceScaleFactor=1, mobile=False,
    )  # fmt: skip
    await browser.call("Page.navigate", url=f"{daemon.url}/#token={TOKEN}")
    await browser.wait_for("document.querySelector('#link').textContent === 'daemon live'")
    await browser.wait_for("document.querySelector('#remote').textContent === 'remote control'")
    banner = "document.querySelector('#situation')"

    async def situation() -> dict[str, Any]:
        value: dict[str, Any] = await browser.js(
            f"(() => {{ const r = {banner}.getBoundingClientRect();"
            "return {text: document.querySelector('#situation-text').textContent,"
            f"kind: {banner}.dataset.kind,"
            "top: r.top, bottom: r.bottom}; })()"
        )
        return value

    other = {"Authorization": f"Bearer {TOKEN}", "X-Fxcell-Client": "intruder@lab"}
    async with httpx.AsyncClient(base_url=daemon.url, timeout=30) as http:
        # someone else takes control and powers the robot off: the page says to run init
        r = await http.post("/api/control", json={"force": True}, headers=other)
        lease = r.json()["lease"]
        r = await http.post("/api/cell/power_off", headers={**other, "X-Fxcell-Lease": lease})
        assert r.status_code == 200, r.text
        await browser.wait_for(state_is("power_off"))
        await browser.wait_for(f"{banner}.textContent.includes('run init')")
        seen = await situation()
        assert seen["kind"] == "warn"
        assert seen["top"] >= 0  # where the operator looks
        assert seen["bottom"] <= 768
        (SCREENSHOT_DIR / "fxcell-page-power-off.png").write_bytes(await browser.screenshot())

        # a command refused because another client holds control: the reason, in the banner
        await browser.click("button[data-command=power_on]")
        await browser.wait_for(f"{banner}.dataset.kind === 'bad'")
        seen = await situation()
        assert "refused" in seen["text"]
        assert "controlled by 'intruder@lab'" in seen["text"]
        assert seen["bottom"] <= 768
        (SCREENSHOT_DIR / "fxcell-page-refused.png").write_bytes(await browser.screenshot())
        assert "intruder@lab" in await browser.js("document.querySelector('#control').textContent")
        r = await http.request("DELETE", "/api/control", headers={**other, "X-Fxcell-Lease": lease})
        assert r.json() == {"released": True}

    # the page's own command now goes through and clears the refusal
    await browser.click("button[data-command=init]")
    await browser.wait_for(state_is("running.external_control_ready"), within=30)
    await browser.wait_for(f"{banner}.dataset.kind === 'ok'")
    assert (await situation())["text"] == "Ready for moves."
    assert await browser.js("document.querySelector('#control').textContent") == (
        "control: this page"
    )
    await browser.click("#release-control")
    await browser.wait_for("document.querySelector('#control').textContent === 'control: free'")
    # state names fit their box, the joint inputs show their whole values
    assert await browser.js(
        "(() => { const e = document.querySelector('#cell-state');"
        "return e.scrollWidth <= e.clientWidth; })()"
    )
    assert await browser.js(
        "[...document.querySelectorAll('#form-joint input')]"
        ".every(i => i.scrollWidth <= i.clientWidth + 1)"
    )
    assert await browser.js("document.querySelector('link[rel=icon]') !== null")


async def test_the_page_says_why_the_robot_is_not_connected(
    browser: Browser, tmp_path: Path
) -> None:
    config = tmp_path / "cell.yaml"
    config.write_text(
        f"robot:\n  host: 127.0.0.254\n  connect_timeout: 0.5\n"
        f"daemon:\n  token_file: {tmp_path / 'token'}\n"
    )
    with DaemonProcess.start(config, token=TOKEN) as unreachable:
        await browser.call(
            "Emulation.setDeviceMetricsOverride", width=1366, height=768,
            deviceScaleFactor=1, mobile=False,
        )  # fmt: skip
        await browser.call("Page.navigate", url=f"{unreachable.url}/#token={TOKEN}")
        await browser.wait_for("document.querySelector('#link').textContent === 'daemon live'")
        text = "document.querySelector('#situation-text').textContent"
        await browser.wait_for(f"{text}.startsWith('Robot not connected: ')", within=30)
        assert await browser.js("document.querySelector('#situation').dataset.kind") == "bad"
        assert "127.0.0.254" in await browser.js(text)  # the reason names the robot
        assert await browser.js("document.querySelector('#robot-mode').textContent") in (
            "–",
            "no link",
        )
        (SCREENSHOT_DIR / "fxcell-page-not-connected.png").write_bytes(await browser.screenshot())


async def test_the_pages_arm_view_draws_each_robot_kind_from_its_own_model(
    browser: Browser, daemon: DaemonProcess
) -> None:
    """app.js's own chain code, run in the browser: the UR3e from the daemon's model and a
    Ned2 from its kind's description end on the TCP each kind's kinematics computes."""
    from fxcell.geometry import Pose
    from fxcell.motion import ned2
    from fxcell.motion.kinematics import Kinematics
    from fxcell.robots.ned2 import ned2_description

    await browser.call("Page.navigate", url=f"{daemon.url}/#token={TOKEN}")
    await browser.wait_for("ARM !== null && page.info !== null && page.info.tcp !== undefined")
    tcp = await browser.js("page.info.tcp")
    q = [0.6, -0.3, 0.2, 0.4, -0.5, 0.3]
    drawn = await browser.js(f"armPoints({json.dumps(q)})")
    assert drawn["joints"] == [1, 3, 5, 7, 9, 11]  # a marker at each joint, as before
    expected = Kinematics.ur3e(tcp).forward(q).position
    assert max(abs(a - b) for a, b in zip(drawn["pts"][-1], expected, strict=True)) < 1e-9

    model = ned2_description(Pose.identity()).chain_json()
    ned2_tcp = [0.05, 0.0, 0.01, 0.0, 0.2, 0.0]
    drawn = await browser.js(
        f"(() => {{ const ur = [ARM, page.info.tcp]; ARM = {json.dumps(model)}; "
        f"page.info.tcp = {json.dumps(ned2_tcp)}; const out = armPoints({json.dumps(q)}); "
        "[ARM, page.info.tcp] = ur; return out; })()"
    )
    assert len(drawn["joints"]) == 6
    expected = ned2.Ned2Kinematics(Pose.from_ur(ned2_tcp)).forward(q).position
    assert max(abs(a - b) for a, b in zip(drawn["pts"][-1], expected, strict=True)) < 1e-9
