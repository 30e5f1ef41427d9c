"""The live browser view under load (issue 31): does the page keep up, and
does the twin keep its step rate while a browser watches?

The node runs in a second process (``python -m soft_twin.node``, the
default tendon arm, dynamic mode at its default 200 Hz, the live view on),
and this process streams actuation commands at 20 Hz over real rclpy (the
arm swings: every state differs from the one before). Three phases of
``--seconds`` each:

1. no browser: the twin's step rate and real-time factor from its
   diagnostics (1 s periods);
2. headless Chromium (Debian's, software WebGL: no GPU here) on the page,
   at each window size of ``--sizes`` and canvas pixel ratio of ``--dprs``
   (viser's adaptive one, and the fixed one for a browser without a GPU):
   the page's frame rate
   (``requestAnimationFrame`` callbacks a second), how many of those frames
   had new data from the node (frames in which a message from the server
   arrived: the view's visible update rate; the node draws at most
   ``live_view_out.RATE_HZ``, 30 a second), the renderer's busy share (the
   DevTools ``TaskDuration`` a second) and the twin's step rate meanwhile;
3. the browser closed again: the step rate.

Goal (issue 31): the view at 30 frames a second or more with the twin at
200 Hz on the 2-core machine, and the twin's step rate unchanged with a
browser connected. Reports the machine's load before and after.

Run: .venv/bin/python benchmarks/bench_live_view.py [--seconds 8] [--step-rate 200] [--sizes 1200x800 800x600]
     [--dprs auto 0.6]
"""

import argparse
import math
import os
from pathlib import Path
import socket
import statistics
import sys
import tempfile
import time

from _timing import machine
from soft_twin.client import NodeProcess, TwinClient

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test" / "ros"))
from chromium_cdp import Browser, chromium_path, wait_for  # noqa: E402  (the tests' DevTools driver)

NAMES = ["tendon_y_pos", "tendon_z_pos"]
SOFTWARE_DPR = 0.5      # the canvas's pixel ratio docs/visualisation.md gives for a browser without a GPU

# counts, from before the page's own scripts run: messages from the server
# (on a websocket, or from the worker that holds it: viser's), animation
# frames, and frames in which a message had arrived since the frame before
_PAGE_COUNTERS = """
(() => {
  window.__ws = 0; window.__frames = 0; window.__fresh = 0;
  const count = (Orig) => {
    function Counted(...args) {
      const ch = new Orig(...args);
      ch.addEventListener('message', () => { window.__ws++; });
      return ch;
    }
    Counted.prototype = Orig.prototype;
    for (const k of ['CONNECTING', 'OPEN', 'CLOSING', 'CLOSED']) if (k in Orig) Counted[k] = Orig[k];
    return Counted;
  };
  window.WebSocket = count(window.WebSocket);     // a page that talks to the server itself
  window.Worker = count(window.Worker);           // viser's: a worker holds the socket, posts the messages
  let seen = 0;
  const tick = () => {
    window.__frames++;
    if (window.__ws !== seen) { window.__fresh++; seen = window.__ws; }
    requestAnimationFrame(tick);
  };
  requestAnimationFrame(tick);
})();
"""


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def stream_and_measure(client, seconds, browser=None):
    """Stream 20 Hz sinusoidal tensions for ``seconds``; the step rates the
    diagnostics report (one per 1 s period) and, with a browser, its
    (frames a second, fresh frames a second, messages a second)."""
    rates, rtf = [], []
    t0 = time.monotonic()
    last_diag = client.counts["diagnostics"]
    page0 = page_counts(browser) if browser else None
    busy0 = busy_seconds(browser) if browser else None
    while time.monotonic() - t0 < seconds:
        t = time.monotonic() - t0
        client.send_actuation(NAMES, [6.0 + 5.0 * math.sin(2 * math.pi * 0.5 * t),
                                      6.0 + 5.0 * math.cos(2 * math.pi * 0.5 * t)])
        client.wait_until(lambda: False, 0.05)              # spin the client 50 ms (not a wait for ROS)
        if client.counts["diagnostics"] > last_diag:
            last_diag = client.counts["diagnostics"]
            d = client.diagnostics()
            rates.append(float(d["step_rate_hz"]))
            rtf.append(float(d["real_time_factor"]))
    wall = time.monotonic() - t0
    page = None
    if browser:
        p1 = page_counts(browser)
        page = tuple((b - a) / wall for a, b in zip(page0, p1)) + ((busy_seconds(browser) - busy0) / wall,)
    return rates[1:] or rates, rtf[1:] or rtf, page         # the first period straddles the phase's start


def page_counts(browser):
    v = browser.evaluate("[window.__frames, window.__fresh, window.__ws]")
    return tuple(float(x) for x in v)


def busy_seconds(browser):
    """The page's renderer time so far [s] (DevTools ``TaskDuration``)."""
    return next(m["value"] for m in browser.call("Performance.getMetrics")["metrics"] if m["name"] == "TaskDuration")


def load():
    return "load {:.2f} {:.2f} {:.2f}".format(*os.getloadavg())


def summary(values):
    if not values:
        return "n/a"
    return f"{statistics.median(values):7.1f} (min {min(values):.1f}, max {max(values):.1f})"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--step-rate", type=float, default=200.0)
    ap.add_argument("--sizes", nargs="+", default=["1200x800", "800x600"], help="browser window sizes (px)")
    ap.add_argument("--dprs", nargs="+", default=["auto", str(SOFTWARE_DPR)],
                    help="device pixel ratios of the 3D canvas: auto (viser's adaptive one, 0.75-1 here) or a "
                         "fixed value (the page's ?fixedDpr=, as docs/visualisation.md gives for a browser "
                         "without a GPU)")
    args = ap.parse_args()
    assert chromium_path(), "no chromium on PATH: `make setup` installs Debian's chromium"
    print(f"machine: {machine()}, {load()}")
    port = free_port()
    with tempfile.TemporaryDirectory() as tmp:
        proc = NodeProcess(["-p", f"live_view_port:={port}", "-p", f"step_rate_hz:={args.step_rate}"],
                           node_name="bench_live_view", log_path=Path(tmp) / "node.log")
        client = TwinClient("bench_live_view", client_name="bench_live_view_client")
        try:
            client.wait_ready(180.0)
            quiet, quiet_rtf, _ = stream_and_measure(client, args.seconds)
            watched = {}
            for size in args.sizes:
                w, h = (int(x) for x in size.split("x"))
                for dpr in args.dprs:
                    with Browser(width=w, height=h) as browser:
                        browser.call("Page.enable")
                        browser.call("Performance.enable")
                        browser.call("Page.addScriptToEvaluateOnNewDocument", source=_PAGE_COUNTERS)
                        browser.open(f"http://127.0.0.1:{port}" + ("" if dpr == "auto" else f"/?fixedDpr={dpr}"))
                        assert wait_for(lambda: (browser.evaluate("window.__fresh") or 0) > 10, 60.0, 0.5), \
                            "the page shows no updates"
                        watched[f"{size} dpr {dpr}"] = stream_and_measure(client, args.seconds, browser)
            after, after_rtf, _ = stream_and_measure(client, args.seconds)
        finally:
            client.close()
            proc.stop()
    print(f"\ntwin at {args.step_rate:g} Hz, tendon arm, tensions streamed at 20 Hz, {args.seconds:g} s a phase")
    print(f"{'phase':32s} {'step rate [Hz] (median of 1 s periods)':44s} real-time factor")
    rows = [("no browser", quiet, quiet_rtf)] + [(f"browser {size}", r, f) for size, (r, f, _) in watched.items()] \
        + [("browser closed again", after, after_rtf)]
    for name, r, f in rows:
        print(f"{name:32s} {summary(r):44s} {statistics.median(f) if f else float('nan'):.3f}")
    print(f"\n{'window, pixel ratio':20s} {'frames/s':>9s} {'with new data/s':>16s} {'messages/s':>11s} "
          f"{'renderer busy':>14s}")
    for size, (_, _, (frames, fresh, msgs, busy)) in watched.items():
        print(f"{size:20s} {frames:9.1f} {fresh:16.1f} {msgs:11.0f} {busy:13.0%}")
    print(f"\nafter: {load()}")


if __name__ == "__main__":
    main()
