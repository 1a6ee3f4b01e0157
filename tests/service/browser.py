"""A headless Chromium driven over the DevTools protocol on a pipe (``--remote-debugging-pipe``:
commands on the browser's fd 3, replies on its fd 4, JSON messages ending in a NUL byte), so
that a test needs the distribution's browser and nothing else: no driver, no download."""

from __future__ import annotations

import base64
import fcntl
import json
import os
import select
import shutil
import subprocess
import tempfile
import threading
import time

BROWSERS = ("chromium", "chromium-browser", "google-chrome")


def find_browser() -> str | None:
    """The path of a Chromium on PATH, or None."""
    for name in BROWSERS:
        path = shutil.which(name)
        if path:
            return path
    return None


class BrowserError(RuntimeError):
    """The browser did not answer, or answered with an error."""


class HeadlessChromium:
    """One headless browser with one page. ``open(url)``, ``evaluate(expression)``, ``close()``."""

    def __init__(self, executable: str, width: int = 1400, height: int = 1000) -> None:
        self._profile = tempfile.mkdtemp(prefix="beamctl-chromium-")
        to_browser_r, self._to_browser = os.pipe()
        self._from_browser, from_browser_w = os.pipe()
        # the browser's ends above fd 4, so that placing one at 3 cannot close the other
        high = [fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 10) for fd in (to_browser_r, from_browser_w)]
        for fd in (to_browser_r, from_browser_w):
            os.close(fd)

        def pipes_at_3_and_4() -> None:     # in the child, before exec: dup2 makes them inheritable
            os.dup2(high[0], 3)
            os.dup2(high[1], 4)

        args = [executable, "--headless", "--remote-debugging-pipe", f"--user-data-dir={self._profile}",
                "--no-first-run", "--no-default-browser-check", "--disable-gpu", "--disable-extensions",
                "--disable-dev-shm-usage", "--mute-audio", f"--window-size={width},{height}", "about:blank"]
        if os.geteuid() == 0:
            args.insert(1, "--no-sandbox")      # Chromium refuses its sandbox to root
        # close_fds off: it would close 3 and 4 after preexec_fn; the test's own descriptors are not
        # inheritable (PEP 446), so nothing else reaches the browser
        self.process = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                        stderr=subprocess.PIPE, close_fds=False, preexec_fn=pipes_at_3_and_4)
        for fd in high:
            os.close(fd)
        self._stderr: list[bytes] = []
        threading.Thread(target=self._drain_stderr, daemon=True).start()
        self._next_id = 0
        self._buffer = b""
        self._session = ""

    def _drain_stderr(self) -> None:
        for line in self.process.stderr:
            self._stderr.append(line)

    def log(self) -> str:
        """The browser's own messages, for a failure's explanation."""
        return b"".join(self._stderr[-30:]).decode(errors="replace")

    def _send(self, method: str, params: dict | None = None, session: str = "",
              timeout_s: float = 60.0) -> dict:
        self._next_id += 1
        message = {"id": self._next_id, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = session
        os.write(self._to_browser, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + timeout_s
        while True:
            while b"\0" not in self._buffer:
                if time.monotonic() > deadline or self.process.poll() is not None:
                    raise BrowserError(f"no answer to {method} (browser exit status {self.process.poll()}):"
                                       f"\n{self.log()}")
                ready, _, _ = select.select([self._from_browser], [], [], 0.5)
                if ready:
                    chunk = os.read(self._from_browser, 1 << 16)
                    if not chunk:
                        raise BrowserError(f"the browser closed its pipe:\n{self.log()}")
                    self._buffer += chunk
            raw, self._buffer = self._buffer.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise BrowserError(f"{method}: {reply['error']}")
                return reply.get("result", {})

    def open(self, url: str) -> None:
        """A new page at ``url``, attached: ``evaluate`` runs in it."""
        target = self._send("Target.createTarget", {"url": url})["targetId"]
        attached = self._send("Target.attachToTarget", {"targetId": target, "flatten": True})
        self._session = attached["sessionId"]
        deadline = time.monotonic() + 60.0
        while self.evaluate("document.readyState + ' ' + location.href") != f"complete {url}":
            if time.monotonic() > deadline:
                raise BrowserError(f"{url} did not load within 60 s:\n{self.log()}")
            time.sleep(0.1)

    def evaluate(self, expression: str):
        """The value of a JavaScript expression in the page (JSON-able values)."""
        result = self._send("Runtime.evaluate", {"expression": expression, "returnByValue": True},
                            session=self._session)
        if "exceptionDetails" in result:
            details = result["exceptionDetails"]
            raise BrowserError(f"{expression}: {details.get('exception', {}).get('description') or details}")
        return result["result"].get("value")

    def screenshot(self, path: str) -> None:
        data = self._send("Page.captureScreenshot", {"format": "png"}, session=self._session)["data"]
        with open(path, "wb") as f:
            f.write(base64.b64decode(data))

    def close(self) -> None:
        try:
            if self.process.poll() is None:
                self._send("Browser.close", timeout_s=5.0)
        except (BrowserError, OSError):
            pass
        finally:
            if self.process.poll() is None:
                self.process.kill()
            self.process.wait(timeout=30)
            for fd in (self._to_browser, self._from_browser):
                try:
                    os.close(fd)
                except OSError:
                    pass
            shutil.rmtree(self._profile, ignore_errors=True)
