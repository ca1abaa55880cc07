"""Headless Chromium for the tests of the HTML views: a page opened offline, awaited until it says it is drawn,
its pixels captured, all over the DevTools protocol on a pipe.

Chromium's own ``--screenshot`` with ``--virtual-time-budget`` hung now and then (one run in three on a busy
machine, once in CI) on a page that unpacks plotly.js through a stream: virtual time waits for the stream and
the stream for virtual time. Here the time is real and the wait ends when the page sets
``document.documentElement.dataset.drawn`` (:mod:`scanreg.eval.view3d`)."""

import base64
import contextlib
import json
import os
import select
import shutil
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest


def chromium() -> str:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.skip("headless Chromium not installed (Debian: apt-get install -y chromium); the HTML view is not "
                    "rendered")
    return exe


class _DevTools:
    """The protocol's messages on a pipe: JSON, each ended by a NUL byte; replies matched to requests by id,
    events passed over."""

    def __init__(self, write_fd: int, read_fd: int, deadline: float):
        self.w, self.r, self.deadline, self.buf, self.last = write_fd, read_fd, deadline, b"", 0

    def __call__(self, method: str, session: str | None = None, **params) -> dict:
        self.last += 1
        msg = {"id": self.last, "method": method, "params": params, **({"sessionId": session} if session else {})}
        os.write(self.w, json.dumps(msg).encode() + b"\0")
        while True:
            reply = self._next()
            if reply.get("id") == self.last:
                if "error" in reply:
                    raise RuntimeError(f"Chromium: {method}: {reply['error']}")
                return reply.get("result", {})

    def _next(self) -> dict:
        while b"\0" not in self.buf:
            wait = self.deadline - time.monotonic()
            if wait <= 0 or not select.select([self.r], [], [], wait)[0]:
                raise TimeoutError("Chromium did not answer in time")
            chunk = os.read(self.r, 1 << 20)
            if not chunk:
                raise RuntimeError("Chromium closed the pipe")
            self.buf += chunk
        msg, _, self.buf = self.buf.partition(b"\0")
        return json.loads(msg)


def _launch(exe: str, profile: Path, to_browser: int, from_browser: int) -> subprocess.Popen:
    """Chromium reading the protocol on its fd 3 and writing on its fd 4 (a shell puts the pipes there: the
    test process's own fds 3 and 4 may be anything); networking off (a proxy that does not exist, no DNS): the
    page must be whole by itself."""
    cmd = [exe, "--headless=new", "--no-sandbox", "--disable-gpu", "--use-gl=swiftshader",
           "--enable-unsafe-swiftshader", "--proxy-server=http://127.0.0.1:9", "--proxy-bypass-list=<-loopback>",
           "--host-resolver-rules=MAP * ~NOTFOUND", f"--user-data-dir={profile}", "--remote-debugging-pipe",
           "about:blank"]
    # (left to right: 3 first, from the lower of the two pipe ends, neither of which is 3 unless it is this one)
    shell = f'exec "$@" 3<&{to_browser} 4>&{from_browser}'
    with open(profile / "chromium.log", "wb") as log:
        return subprocess.Popen(["bash", "-c", shell, "bash", *cmd], stdin=subprocess.DEVNULL, stdout=log,
                                stderr=log, pass_fds=(to_browser, from_browser), start_new_session=True)


def screenshot(html: Path, out: Path, size=(1100, 1000), timeout: float = 300.0) -> np.ndarray:
    """Render ``html`` at ``size`` (pixels) and write the screenshot to ``out``; the pixels as an RGB array.
    Fails when the page has not drawn its view within ``timeout`` seconds, with what the page shows."""
    from PIL import Image

    exe = chromium()
    profile = out.parent / f"{out.stem}-chromium-profile"
    profile.mkdir(parents=True, exist_ok=True)
    to_r, to_w = os.pipe()
    from_r, from_w = os.pipe()
    proc = _launch(exe, profile, to_r, from_w)
    os.close(to_r)
    os.close(from_w)
    cdp = _DevTools(to_w, from_r, time.monotonic() + timeout)
    try:
        target = cdp("Target.createTarget", url="about:blank")["targetId"]
        s = cdp("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        cdp("Emulation.setDeviceMetricsOverride", s, width=size[0], height=size[1], deviceScaleFactor=1,
            mobile=False)
        cdp("Page.navigate", s, url=html.as_uri())
        state = "document.documentElement.dataset.drawn || ''"
        while (drawn := cdp("Runtime.evaluate", s, expression=state, returnByValue=True)["result"].get("value")
               or "") != "true":
            if drawn or time.monotonic() > cdp.deadline - 5:
                shown = cdp("Runtime.evaluate", s, expression="document.body.innerText.slice(0, 300)",
                            returnByValue=True)["result"].get("value")
                pytest.fail(f"{html.name} not drawn ({drawn or f'not in {timeout:.0f} s'}); the page shows: "
                            f"{shown!r}; Chromium's log ends: {_tail(profile / 'chromium.log')!r}")
            time.sleep(0.25)
        frames = "new Promise(r => requestAnimationFrame(() => requestAnimationFrame(() => r(true))))"
        cdp("Runtime.evaluate", s, expression=frames, awaitPromise=True)
        out.write_bytes(base64.b64decode(cdp("Page.captureScreenshot", s, format="png")["data"]))
        with contextlib.suppress(RuntimeError, TimeoutError, OSError):  # (it may close the pipe before it answers)
            cdp("Browser.close")
    finally:
        os.close(to_w)
        os.close(from_r)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return np.asarray(Image.open(out).convert("RGB")).astype(int)


def _tail(path: Path, n: int = 600) -> str:
    try:
        return path.read_text(errors="replace")[-n:]
    except OSError:
        return ""
