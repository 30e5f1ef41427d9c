"""Headless Chromium (Debian's package) driven over the DevTools protocol
with the pinned ``websockets`` client: load a page, take screenshots. Used
by the browser tests of the live view; no WebDriver, no browser download.

    with Browser() as b:
        b.open("http://127.0.0.1:8080")
        png = b.screenshot()        # PNG bytes
"""
import base64
import itertools
import json
import os
import re
import shutil
import subprocess
import tempfile
import time
import urllib.request


def chromium_path():
    for name in ("chromium", "chromium-browser", "google-chrome"):
        p = shutil.which(name)
        if p:
            return p
    return None


class Browser:
    def __init__(self, width=1000, height=700, timeout=60.0):
        exe = chromium_path()
        if exe is None:
            raise FileNotFoundError("no chromium on PATH (the set-up installs Debian's chromium)")
        self._profile = tempfile.mkdtemp(prefix="soft_twin_chromium_")
        self.proc = subprocess.Popen(
            [exe, "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
             "--use-angle=swiftshader", "--no-first-run", "--no-default-browser-check",
             f"--window-size={width},{height}", "--remote-debugging-port=0",
             f"--user-data-dir={self._profile}", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        self._ids = itertools.count(1)
        end = time.monotonic() + timeout
        port = None
        while port is None:
            line = self.proc.stderr.readline()
            if not line:
                if self.proc.poll() is not None or time.monotonic() > end:
                    raise RuntimeError("chromium did not start its DevTools server")
                continue
            m = re.search(r"DevTools listening on ws://[^:]+:(\d+)/", line)
            if m:
                port = int(m.group(1))
        # drain stderr so the browser never blocks on a full pipe
        import threading
        threading.Thread(target=lambda: [None for _ in self.proc.stderr], daemon=True).start()
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
            pages = [t for t in json.load(r) if t["type"] == "page"]
        from websockets.sync.client import connect
        self.ws = connect(pages[0]["webSocketDebuggerUrl"], max_size=None, open_timeout=10)

    def call(self, method, timeout=30.0, **params):
        i = next(self._ids)
        self.ws.send(json.dumps({"id": i, "method": method, "params": params}))
        end = time.monotonic() + timeout
        while True:
            msg = json.loads(self.ws.recv(timeout=max(0.1, end - time.monotonic())))
            if msg.get("id") == i:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    def open(self, url, timeout=30.0):
        """Navigate and wait for the load event."""
        self.call("Page.enable")
        i = next(self._ids)
        self.ws.send(json.dumps({"id": i, "method": "Page.navigate", "params": {"url": url}}))
        end = time.monotonic() + timeout
        while True:
            msg = json.loads(self.ws.recv(timeout=max(0.1, end - time.monotonic())))
            if msg.get("method") == "Page.loadEventFired":
                return

    def evaluate(self, expression):
        return self.call("Runtime.evaluate", expression=expression, returnByValue=True)["result"].get("value")

    def mouse(self, kind, x, y, buttons=1):
        """One mouse event (``kind``: mousePressed, mouseMoved, mouseReleased)
        at page pixel (x, y), left button."""
        self.call("Input.dispatchMouseEvent", type=kind, x=float(x), y=float(y), button="left",
                  buttons=buttons if kind != "mouseReleased" else 0, clickCount=1 if kind != "mouseMoved" else 0)

    def click(self, x, y):
        self.mouse("mousePressed", x, y)
        self.mouse("mouseReleased", x, y)

    def drag(self, x0, y0, x1, y1, steps=8):
        """Press at (x0, y0), move in ``steps`` to (x1, y1), release: a user's drag."""
        self.mouse("mousePressed", x0, y0)
        for k in range(1, steps + 1):
            self.mouse("mouseMoved", x0 + (x1 - x0) * k / steps, y0 + (y1 - y0) * k / steps)
        self.mouse("mouseReleased", x1, y1)

    def rect(self, js_element):
        """The page rectangle {x, y, width, height} of the element the JS
        expression ``js_element`` gives (None: none), scrolled into view
        first (as a user scrolls a long panel to reach it)."""
        return self.evaluate(f"(() => {{ const e = {js_element}; if (!e) return null; "
                             "e.scrollIntoView({block: 'center', inline: 'center'}); const r = "
                             "e.getBoundingClientRect(); return {x: r.x, y: r.y, width: r.width, height: r.height}; })()")

    def screenshot(self, timeout=20.0):
        end = time.monotonic() + timeout
        while True:
            try:
                return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
            except RuntimeError:       # between documents while navigating: try again
                if time.monotonic() > end:
                    raise
                time.sleep(0.2)

    def close(self):
        try:
            self.ws.close()
        except Exception:
            pass
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)
        shutil.rmtree(self._profile, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def wait_for(predicate, timeout, step=0.2):
    """Poll ``predicate`` until true or ``timeout`` s; returns its last value."""
    end = time.monotonic() + timeout
    while True:
        v = predicate()
        if v or time.monotonic() > end:
            return v
        time.sleep(step)


if __name__ == "__main__":       # python test/chromium_cdp.py URL OUT.png
    import sys
    with Browser() as b:
        b.open(sys.argv[1])
        time.sleep(float(os.environ.get("WAIT", "5")))
        open(sys.argv[2], "wb").write(b.screenshot())
