"""Open a replay in headless Chromium and take a screenshot: what the tests and ``qpctl replay
--screenshot`` use.

Chromium (Debian's ``chromium`` package, or any Chrome on ``PATH``) is driven through its DevTools
protocol over a pipe (``--remote-debugging-pipe``: file descriptors 3 and 4, no socket), rendering
WebGL with SwiftShader on the CPU. :func:`render` loads the page from disk, waits until the replay
reports that it has drawn the requested time (``?t=``, see :mod:`qpctl.replay.page`), takes a PNG of
the window and returns it with what the page logged: console errors, uncaught exceptions, and every
request for a resource that is not inside the file itself (``http:``, ``https:``, another file).
"""

from __future__ import annotations

import base64
import fcntl
import json
import os
import queue
import shutil
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import urlencode

import numpy as np

from qpctl.errors import ReplayError

if TYPE_CHECKING:
    from typing_extensions import Self

#: Names under which Chromium is looked up on PATH (Debian's package installs ``chromium``).
BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")

_FLAGS = (
    "--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    "--disable-gpu", "--no-first-run", "--no-default-browser-check", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--disable-extensions", "--mute-audio",
    "--hide-scrollbars", "--remote-debugging-pipe",
)


def find_browser() -> str:
    """The path of a Chromium on PATH; :class:`ReplayError` naming the package to install if none."""
    for name in BROWSERS:
        path = shutil.which(name)
        if path:
            return path
    raise ReplayError(f"no Chromium on PATH (looked for {', '.join(BROWSERS)}): install Debian's chromium "
                      "package (apt-get install chromium)")


@dataclass
class Rendered:
    """A page as headless Chromium drew it.

    Attributes:
        png: the screenshot (PNG bytes, ``width`` × ``height`` pixels).
        errors: console errors and uncaught exceptions, one line each.
        requests: URLs the page asked for that are not part of the file (anything but ``data:``,
            ``blob:`` and the page's own ``file:`` URL).
        state: the replay's own report (``window.qpctlReplay``: the time and frame it shows).
        seconds: wall time from launch to screenshot [s].
    """

    png: bytes
    errors: list[str] = field(default_factory=list)
    requests: list[str] = field(default_factory=list)
    state: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0


class _Pipe:
    """DevTools protocol messages over Chromium's pipe: JSON, each ended by a NUL byte."""

    def __init__(self, proc: subprocess.Popen[bytes], write_fd: int, read_fd: int) -> None:
        self.proc = proc
        self._out = os.fdopen(write_fd, "wb", buffering=0)
        self._in = os.fdopen(read_fd, "rb", buffering=0)
        self._next = 0
        self.events: queue.Queue[dict[str, Any]] = queue.Queue()
        self._replies: dict[int, queue.Queue[dict[str, Any]]] = {}
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        buf = b""
        while True:
            chunk = self._in.read(1 << 16)
            if not chunk:
                return
            buf += chunk
            while b"\0" in buf:
                raw, buf = buf.split(b"\0", 1)
                msg = json.loads(raw)
                if "id" in msg:
                    with self._lock:
                        box = self._replies.get(msg["id"])
                    if box is not None:
                        box.put(msg)
                else:
                    self.events.put(msg)

    def call(self, method: str, params: dict[str, Any] | None = None, *, session: str | None = None,
             timeout: float = 30.0) -> dict[str, Any]:
        with self._lock:
            self._next += 1
            ident = self._next
            box: queue.Queue[dict[str, Any]] = queue.Queue()
            self._replies[ident] = box
        msg: dict[str, Any] = {"id": ident, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        try:
            self._out.write(json.dumps(msg).encode() + b"\0")
        except BrokenPipeError:
            raise ReplayError(f"Chromium exited (status {self.proc.poll()}) before {method}") from None
        try:
            reply = box.get(timeout=timeout)
        except queue.Empty:
            raise ReplayError(f"Chromium did not answer {method} within {timeout:.0f} s") from None
        finally:
            with self._lock:
                self._replies.pop(ident, None)
        if "error" in reply:
            raise ReplayError(f"Chromium: {method} failed: {reply['error'].get('message', reply['error'])}")
        return dict(reply.get("result", {}))

    def close(self) -> None:
        for f in (self._out, self._in):
            try:
                f.close()
            except OSError:
                pass


def _launch(width: int, height: int, profile: str) -> _Pipe:
    exe = find_browser()
    to_chrome_r, to_chrome_w = os.pipe()
    from_chrome_r, from_chrome_w = os.pipe()

    # the protocol's fds in the child are 3 (commands in) and 4 (replies out): bash moves the pipes
    # there and execs Chromium (no preexec_fn, which is unsafe beside threads; dash takes no fd above 9)
    r, w = (fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 10) for fd in (to_chrome_r, from_chrome_w))  # clear of 3, 4
    for fd in (to_chrome_r, from_chrome_w):
        os.close(fd)
    args = [shutil.which("bash") or "/bin/bash", "-c", f'exec "$@" 3<&{r} 4>&{w}', "sh", exe, *_FLAGS,
            f"--user-data-dir={profile}", f"--window-size={width},{height}", "about:blank"]
    try:
        proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, pass_fds=(r, w))
    finally:
        os.close(r)
        os.close(w)
    return _Pipe(proc, to_chrome_w, from_chrome_r)


def _page_url(path: Path, at: float | None, params: dict[str, str] | None) -> str:
    query = dict(params or {})
    if at is not None:
        query["t"] = repr(float(at))
    url = path.resolve().as_uri()
    return url + ("?" + urlencode(query) if query else "")


class Browser:
    """One headless Chromium for several pages (a test module, a series of screenshots); a context
    manager. :class:`ReplayError` if there is no Chromium or it fails to start."""

    def __init__(self) -> None:
        self._profile = tempfile.mkdtemp(prefix="qpctl-chromium-")
        self._pipe = _launch(1280, 800, self._profile)
        try:
            targets = self._pipe.call("Target.getTargets")["targetInfos"]
            page = next(t for t in targets if t["type"] == "page")
            self._session = self._pipe.call("Target.attachToTarget", {"targetId": page["targetId"],
                                                                      "flatten": True})["sessionId"]
            for domain in ("Page", "Runtime", "Log", "Network"):
                self._pipe.call(f"{domain}.enable", session=self._session)
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def render(self, path: str | Path, *, at: float | None = None, width: int = 1280, height: int = 800,
               params: dict[str, str] | None = None, timeout: float = 120.0) -> Rendered:
        """Open the replay page ``path`` at ``at`` [s] (paused there; None: as it opens, playing) in a
        ``width`` × ``height`` window and screenshot it once the replay reports that it has drawn
        that time and the picture has settled (playing: once it has drawn a few frames). ``params``: more query parameters for the page's URL.
        :class:`ReplayError` if the page does not report ready within ``timeout`` [s]."""
        path = Path(path)
        if not path.is_file():
            raise ReplayError(f"no such replay file: {path}")
        t0 = time.perf_counter()
        pipe, session = self._pipe, self._session
        errors: list[str] = []
        requests: list[str] = []
        own = path.resolve().as_uri()
        pipe.call("Page.navigate", {"url": "about:blank"}, session=session)
        _drain(pipe, [], [], own)  # what the page before logged
        pipe.call("Emulation.setDeviceMetricsOverride", {"width": width, "height": height, "deviceScaleFactor": 1,
                                                         "mobile": False}, session=session)
        pipe.call("Page.navigate", {"url": _page_url(path, at, params)}, session=session)
        deadline = time.perf_counter() + timeout
        while True:
            _drain(pipe, errors, requests, own)
            reply = pipe.call("Runtime.evaluate", {"expression": "JSON.stringify(window.qpctlReplay || null)",
                                                   "returnByValue": True}, session=session)
            value = reply.get("result", {}).get("value")
            state: dict[str, Any] = json.loads(value) if isinstance(value, str) else {}
            if state and state.get("ready"):
                break
            if time.perf_counter() > deadline:
                raise ReplayError(f"the replay did not report ready within {timeout:.0f} s (state: {state or 'none'}; "
                                  f"errors: {errors or 'none'})")
            time.sleep(0.2)
        if at is None:  # playing: the picture never settles, take it as it is
            png = base64.b64decode(pipe.call("Page.captureScreenshot", {"format": "png"}, session=session,
                                             timeout=timeout)["data"])
        else:
            png = _settled(pipe, session, deadline)
        _drain(pipe, errors, requests, own)
        return Rendered(png, errors, requests, state, time.perf_counter() - t0)

    def close(self) -> None:
        pipe = self._pipe
        if pipe.proc.poll() is None:
            try:
                pipe.call("Browser.close", timeout=10)
            except ReplayError:
                pass
        try:
            pipe.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            pipe.proc.kill()
            pipe.proc.wait()
        pipe.close()
        shutil.rmtree(self._profile, ignore_errors=True)


def render(path: str | Path, **kwargs: Any) -> Rendered:
    """:meth:`Browser.render` in a browser of its own (started and closed for this page)."""
    with Browser() as browser:
        return browser.render(path, **kwargs)


def _settled(pipe: _Pipe, session: str, deadline: float) -> bytes:
    """A screenshot once the page has stopped changing: two in a row alike (lights and materials
    finish loading a few frames after the scene's messages are applied)."""
    import io

    from PIL import Image

    last: np.ndarray | None = None
    while True:
        png = base64.b64decode(pipe.call("Page.captureScreenshot", {"format": "png"}, session=session,
                                         timeout=max(deadline - time.perf_counter(), 10.0))["data"])
        pixels = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), np.int16)
        if last is not None and (last.shape == pixels.shape and float(np.abs(pixels - last).mean()) < 0.02):
            return png
        if time.perf_counter() > deadline:
            raise ReplayError("the replay's picture did not settle before the time-out")
        last = pixels
        time.sleep(0.25)


def _drain(pipe: _Pipe, errors: list[str], requests: list[str], own: str) -> None:
    """Sort the events received so far into console errors and outside requests."""
    while True:
        try:
            ev = pipe.events.get_nowait()
        except queue.Empty:
            return
        method, p = ev.get("method"), ev.get("params", {})
        if method == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
            errors.append("console: " + " ".join(str(a.get("value", a.get("description", ""))) for a in p.get("args", [])))
        elif method == "Runtime.exceptionThrown":
            d = p.get("exceptionDetails", {})
            errors.append("exception: " + str(d.get("exception", {}).get("description", d.get("text", ""))))
        elif method == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
            e = p["entry"]
            errors.append(f"log ({e.get('source')}): {e.get('text')} {e.get('url', '')}".strip())
        elif method == "Network.requestWillBeSent":
            url = str(p.get("request", {}).get("url", ""))
            if not (url.startswith(("data:", "blob:")) or url.split("?", 1)[0] == own):
                requests.append(url)
