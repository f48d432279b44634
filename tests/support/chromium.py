"""Headless Chromium driven over the DevTools protocol, for pages that keep changing after they load (a viser
client draws its scene as the server streams it): a test waits for what it expects instead of guessing a time.

Debian's ``chromium`` with software WebGL (SwiftShader), so it runs on a machine without a GPU; the protocol's
websocket is spoken with the ``websockets`` package (viser's own dependency)."""

from __future__ import annotations

import base64
import contextlib
import io
import json
import shutil
import subprocess
import tempfile
import time
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path

import imageio.v3 as iio
import numpy as np
from websockets.sync.client import connect

CHROMIUM = shutil.which("chromium")


class Page:
    """One browser tab: ``evaluate`` JavaScript, take a ``screenshot``, ``wait_until`` a condition holds."""

    def __init__(self, socket) -> None:
        self.socket = socket
        self.calls = 0

    def call(self, method: str, **params) -> dict:
        self.calls += 1
        self.socket.send(json.dumps({"id": self.calls, "method": method, "params": params}))
        while True:  # events arrive between the answers; only this call's answer is wanted
            message = json.loads(self.socket.recv(timeout=60))
            if message.get("id") == self.calls:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message["result"]

    def evaluate(self, expression: str):
        return self.call("Runtime.evaluate", expression=expression, returnByValue=True)["result"].get("value")

    def screenshot(self) -> np.ndarray:
        """The tab as H x W x 3 uint8."""
        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return iio.imread(io.BytesIO(data), extension=".png")[..., :3]

    def wait_until(self, condition: Callable[[], bool], timeout: float = 90.0, what: str = "the page") -> None:
        """Poll ``condition`` until it holds; fail naming ``what`` after ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if condition():
                return
            time.sleep(0.5)
        raise AssertionError(f"{what} did not appear within {timeout:.0f} s")


@contextlib.contextmanager
def open_page(url: str, width: int = 1000, height: int = 700) -> Iterator[Page]:
    """``url`` in a fresh headless Chromium (its own profile, removed afterwards)."""
    with tempfile.TemporaryDirectory() as profile:
        browser = subprocess.Popen(
            [CHROMIUM, "--headless=new", "--no-sandbox", "--use-gl=swiftshader", "--enable-unsafe-swiftshader",
             "--hide-scrollbars", f"--window-size={width},{height}", "--remote-debugging-port=0",
             f"--user-data-dir={profile}", "about:blank"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            port_file = Path(profile) / "DevToolsActivePort"  # Chromium writes the port it chose here
            deadline = time.monotonic() + 60
            while not (port_file.is_file() and port_file.read_text().strip()) and time.monotonic() < deadline:
                time.sleep(0.1)
            port = port_file.read_text().split()[0]
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json", timeout=30) as listing:
                tab = next(t for t in json.load(listing) if t["type"] == "page")
            with connect(tab["webSocketDebuggerUrl"], max_size=None) as socket:
                page = Page(socket)
                page.call("Page.enable")
                page.call("Page.navigate", url=url)
                yield page
        finally:
            browser.terminate()
            browser.wait(timeout=30)
