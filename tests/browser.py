"""Headless Chromium driven over the DevTools protocol on a pipe (--remote-debugging-pipe): no
WebSocket library, no Playwright. Used by the report page's browser test.

`ensure_chromium()` installs Debian's `chromium` package where it is missing (idempotent: a
machine that has it is left alone), so a fresh machine runs the test; where it cannot be
installed (no apt, not root and no password-less sudo, no network) the test is skipped with the
reason.
"""

from __future__ import annotations

import base64
import fcntl
import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

BINARIES = ("chromium", "chromium-browser", "google-chrome")


def find_chromium() -> str | None:
    return next((path for name in BINARIES if (path := shutil.which(name))), None)


def ensure_chromium() -> tuple[str | None, str]:
    """(the browser's path, "") or (None, why it could not be installed)."""
    found = find_chromium()
    if found:
        return found, ""
    if not shutil.which("apt-get"):
        return None, "chromium is not installed and there is no apt-get to install it"
    sudo = [] if os.geteuid() == 0 else ["sudo", "-n"]
    if sudo and not shutil.which("sudo"):
        return None, "chromium is not installed, and installing it needs root (no sudo)"
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    for step in (["apt-get", "update", "-qq"], ["apt-get", "install", "-y", "-qq", "chromium"]):
        done = subprocess.run(sudo + step, capture_output=True, text=True, env=env)
        if done.returncode != 0:
            last = (done.stderr.strip().splitlines() or ["no output"])[-1]
            return None, f"installing chromium failed at `{' '.join(step)}`: {last}"
    found = find_chromium()
    return (found, "") if found else (None, "apt-get installed chromium but it is not on PATH")


class Browser:
    """One headless Chromium; `page(url)` opens a tab and returns its session."""

    def __init__(self, binary: str, width: int = 1400, height: int = 1000):
        to_browser, self._write = _high_pipe()
        self._read, from_browser = _high_pipe()
        self._profile = tempfile.mkdtemp(prefix="retain-chromium-")

        def pipes_at_3_and_4():
            os.dup2(to_browser, 3)
            os.dup2(from_browser, 4)

        self._proc = subprocess.Popen(
            [binary, "--headless=new", "--remote-debugging-pipe", "--no-sandbox",
             "--disable-gpu", "--no-first-run", "--mute-audio", f"--user-data-dir={self._profile}",
             "--autoplay-policy=no-user-gesture-required", f"--window-size={width},{height}",
             "about:blank"],
            preexec_fn=pipes_at_3_and_4, close_fds=False, stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL)
        os.close(to_browser)
        os.close(from_browser)
        self._buffer, self._id = b"", 0
        self._events: list[dict] = []

    def call(self, method: str, session: str | None = None, **params) -> dict:
        """Send a command and wait for its reply (events in between are kept in `_events`)."""
        self._id += 1
        message = {"id": self._id, "method": method, "params": params}
        if session:
            message["sessionId"] = session
        os.write(self._write, json.dumps(message).encode() + b"\0")
        while True:
            reply = self._next()
            if "id" not in reply:
                self._events.append(reply)
            elif reply["id"] == self._id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]

    def _next(self) -> dict:
        while b"\0" not in self._buffer:
            chunk = os.read(self._read, 1 << 20)
            if not chunk:
                raise RuntimeError("chromium closed its DevTools pipe")
            self._buffer += chunk
        message, self._buffer = self._buffer.split(b"\0", 1)
        return json.loads(message)

    def page(self, url: str) -> str:
        """A new tab's session, once `url` has loaded (its load event)."""
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        self.call("Page.enable", session)
        self._events.clear()
        self.call("Page.navigate", session, url=url)
        while not any(e.get("method") == "Page.loadEventFired" and e.get("sessionId") == session
                      for e in self._events):
            self._events.append(self._next())
        return session

    def evaluate(self, session: str, expression: str):
        """A JavaScript expression's value (a promise is awaited)."""
        result = self.call("Runtime.evaluate", session, expression=expression, awaitPromise=True,
                           returnByValue=True, timeout=60000)
        if "exceptionDetails" in result:
            raise RuntimeError(f"page script failed: {result['exceptionDetails']}")
        return result["result"].get("value")

    def screenshot(self, session: str, path: Path, full_page: bool = True) -> None:
        shot = self.call("Page.captureScreenshot", session, format="png",
                         captureBeyondViewport=full_page)
        path.write_bytes(base64.b64decode(shot["data"]))

    def close(self) -> None:
        try:
            self.call("Browser.close")
        except (RuntimeError, OSError):
            pass
        try:
            self._proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._proc.kill()
        for fd in (self._read, self._write):
            os.close(fd)
        shutil.rmtree(self._profile, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _high_pipe() -> tuple[int, int]:
    """A pipe whose ends are above 100, so moving them to fds 3 and 4 in the child never
    overwrites the other end."""
    read, write = os.pipe()
    high = fcntl.fcntl(read, fcntl.F_DUPFD, 100), fcntl.fcntl(write, fcntl.F_DUPFD, 100)
    os.close(read)
    os.close(write)
    return high


# Waits for every video's data, plays them all for a second, and reports each one's state.
PLAY_VIDEOS = """
(async () => {
  if (document.readyState !== 'complete')
    await new Promise(r => window.addEventListener('load', r, {once: true}));
  const videos = [...document.querySelectorAll('video')];
  const loaded = v => new Promise(r => {
    if (v.readyState >= 2 || v.error) return r();
    v.addEventListener('loadeddata', r, {once: true});
    v.addEventListener('error', r, {once: true});
  });
  await Promise.race([Promise.all(videos.map(loaded)), new Promise(r => setTimeout(r, 30000))]);
  const start = videos.map(v => v.currentTime);
  const played = await Promise.all(videos.map(v => v.play().then(() => true, e => String(e))));
  await new Promise(r => setTimeout(r, 1500));
  return videos.map((v, i) => {
    v.pause();
    return {task: v.dataset.task, stage: v.dataset.stage, readyState: v.readyState,
            duration: v.duration, advanced: v.currentTime - start[i], play: played[i],
            error: v.error ? v.error.code : 0, width: v.videoWidth, height: v.videoHeight};
  });
})()
"""
