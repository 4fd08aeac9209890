"""The report in a real browser: headless Chromium driven over the DevTools protocol (``websocket-client``) loads a
page from the file system, collects its console errors and uncaught exceptions, waits until every 3D viewer says its
model loaded (the page's ``#viewer-status``, :mod:`.viewer`) and saves a screenshot."""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
import tempfile
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

from foundation.errors import FailureError

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "chrome")


def find_browser() -> str | None:
    return next((p for p in map(shutil.which, BROWSERS) if p), None)


@dataclass
class PageCheck:
    """What the browser saw of a page."""

    url: str
    viewers: int  #: 3D viewers on the page
    loaded: int  #: of them, those that reported their model loaded
    console_errors: list[str] = field(default_factory=list)  #: console.error, uncaught exceptions, failed loads
    screenshot: str | None = None
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return self.loaded == self.viewers and not self.console_errors


class _Cdp:
    def __init__(self, ws_url: str):
        import websocket

        self.ws = websocket.create_connection(ws_url, timeout=30, suppress_origin=True)
        self.n = 0
        self.events: list[dict] = []

    def call(self, method: str, **params) -> dict:
        self.n += 1
        self.ws.send(json.dumps({"id": self.n, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv())
            if msg.get("id") == self.n:
                if "error" in msg:
                    raise FailureError(f"browser: {method}: {msg['error'].get('message')}")
                return msg.get("result", {})
            self.events.append(msg)

    def close(self) -> None:
        self.ws.close()


def _errors(events: list[dict]) -> list[str]:
    out = []
    for e in events:
        m, p = e.get("method"), e.get("params", {})
        if m == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
            out.append(" ".join(str(a.get("value", a.get("description", ""))) for a in p.get("args", [])))
        elif m == "Runtime.exceptionThrown":
            d = p.get("exceptionDetails", {})
            out.append(d.get("exception", {}).get("description") or d.get("text", "exception"))
        elif m == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
            out.append(p["entry"].get("text", "") + (f" ({p['entry']['url']})" if p["entry"].get("url") else ""))
    return out


def check_page(page: str | Path, screenshot: str | Path | None = None, timeout: float = 90.0,
               size: tuple[int, int] = (1280, 2000)) -> PageCheck:
    """Open ``page`` (an HTML file) in headless Chromium (software WebGL), wait up to ``timeout`` s for its viewers,
    and report; ``screenshot``: where to write the full page as PNG."""
    browser = find_browser()
    if browser is None:
        raise FailureError("no Chromium on PATH (Debian: apt install chromium)")
    url = Path(page).resolve().as_uri()
    t0 = time.perf_counter()
    # Chromium's helper processes may still write into the profile as it is removed
    with tempfile.TemporaryDirectory(prefix="photoreal-browser-", ignore_cleanup_errors=True) as profile:
        proc = subprocess.Popen(
            [browser, "--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader",
             "--enable-unsafe-swiftshader", "--no-first-run", "--no-default-browser-check", "--remote-debugging-port=0",
             f"--user-data-dir={profile}", f"--window-size={size[0]},{size[1]}", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        cdp = None
        try:
            port_file = Path(profile) / "DevToolsActivePort"
            while not port_file.is_file() or not port_file.read_text().strip():
                if proc.poll() is not None or time.perf_counter() - t0 > 30:
                    raise FailureError(f"{browser}: did not start its DevTools endpoint")
                time.sleep(0.1)
            port = int(port_file.read_text().split()[0])
            targets = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json", timeout=10).read())
            cdp = _Cdp(next(t["webSocketDebuggerUrl"] for t in targets if t.get("type") == "page"))
            for m in ("Runtime.enable", "Log.enable", "Page.enable"):
                cdp.call(m)
            cdp.call("Page.navigate", url=url)
            status = {"viewers": -1, "loaded": 0}
            deadline = time.perf_counter() + timeout
            while time.perf_counter() < deadline:
                r = cdp.call("Runtime.evaluate", returnByValue=True, expression=(
                    "(function(){var s=document.getElementById('viewer-status');if(!s)return null;"
                    "return {viewers:+s.dataset.viewers,loaded:+s.dataset.loaded,failed:+s.dataset.failed}})()"))
                value = r.get("result", {}).get("value")
                if value is not None and document_ready(cdp):
                    status = value
                    if status["loaded"] + status.get("failed", 0) >= status["viewers"]:
                        break
                time.sleep(0.25)
            time.sleep(0.5)  # a frame after the last load, for the screenshot
            shot = None
            if screenshot is not None:
                data = cdp.call("Page.captureScreenshot", format="png", captureBeyondViewport=True)["data"]
                Path(screenshot).write_bytes(base64.b64decode(data))
                shot = str(screenshot)
            cdp.call("Runtime.evaluate", expression="0")  # drain the events that came meanwhile
            return PageCheck(url, int(status["viewers"]), int(status["loaded"]), _errors(cdp.events), shot,
                             time.perf_counter() - t0)
        finally:
            if cdp is not None:
                cdp.close()
            _stop(proc)


def document_ready(cdp: _Cdp) -> bool:
    r = cdp.call("Runtime.evaluate", expression="document.readyState", returnByValue=True)
    return r.get("result", {}).get("value") == "complete"


def _stop(proc: subprocess.Popen) -> None:
    """End the browser and its helpers (their own process group)."""
    import os
    import signal

    for sig, wait in ((signal.SIGTERM, 10), (signal.SIGKILL, 5)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(timeout=wait)
            return
        except subprocess.TimeoutExpired:
            continue
