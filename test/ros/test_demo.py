"""`make demo` (scripts/demo.py) end to end (issue 12): the table, the PNG,
the animation of the run and the node's MCAP recording, each file opened
and checked."""
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")

ROOT = Path(__file__).resolve().parents[2]
# quiet: the node follows a 50 Hz command stream in real time and must record every command; on a machine
# busy with other tests it fell behind (482-497 of 502 recorded in two fresh-clone runs)
pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.quiet]


def test_demo_writes_png_animation_and_recording(tmp_path):
    png, anim, rec = tmp_path / "demo.png", tmp_path / "demo.mp4", tmp_path / "demo.mcap"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "demo.py"), "--out", str(png),
                           "--animation", str(anim), "--record", str(rec)],
                          capture_output=True, text=True, timeout=500, env=env, cwd=tmp_path)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-4000:]
    # it says where each file is
    assert f"wrote the backbone shapes: {png}" in out
    assert f"wrote the animation: {anim}" in out
    assert str(rec) in out and "node shut down cleanly" in out
    from PIL import Image
    with Image.open(png) as im:
        assert im.size[0] >= 800 and np.mean(np.asarray(im.convert("L")) < 200) > 0.01
    import imageio.v2 as iio
    with iio.get_reader(str(anim)) as r:
        meta = r.get_meta_data()
        frames = [f for f in r]
    assert meta["fps"] == pytest.approx(20.0)
    assert 195 <= len(frames) <= 205                 # 10 s at 20 frames/s, real time
    assert np.mean(np.any(frames[0] != frames[len(frames) // 2], axis=2)) > 0.002   # the arm moved
    # the recording: every topic, the commands sent, the counts the node wrote
    from mcap.reader import make_reader
    from soft_twin_core.files.recording import read_messages
    ns = "/soft_twin_demo"
    msgs = read_messages(str(rec), [f"{ns}/actuation", f"{ns}/tip_pose"])    # (decoding every topic: 5 s)
    with open(rec, "rb") as fh:
        reader = make_reader(fh)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        counts = {}
        for _, channel, _ in reader.iter_messages():            # every message, read but not decoded
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    for t in ("backbone", "tip_pose", "strains", "tip_wrench", "base_wrench", "actuation", "tip_wrench_command"):
        assert f"{ns}/{t}" in counts, t
    assert "/tf" in counts and "/diagnostics" in counts
    sent = int(out.split(" commands sent")[0].rsplit("of the ", 1)[1])
    assert len(msgs[f"{ns}/actuation"]) == counts[f"{ns}/actuation"] == sent > 400
    assert {k: int(v) for k, v in meta["soft_twin.counts"].items()} == counts
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in msgs[f"{ns}/tip_pose"]]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    assert len(stamps) > 300       # states over the ~12 s run (200 Hz nominal; 898 at a load of 5)
    from soft_twin_core.files.recording import read_node_recording
    from soft_twin_core.robot.mechanism import load_mechanism
    run = read_node_recording(str(rec), load_mechanism("tendon_arm"), "/soft_twin_demo")
    _the_recordings_time_aligns_with_the_table(out, run)
    _scrub_the_recording_in_the_page(rec, run, tmp_path)


def _the_recordings_time_aligns_with_the_table(out, run):
    """Issue 31: figures drawn from the demo's recording started about 2 s
    before the table's t = 0 (the recording starts with the node). The
    demo prints the time of its sweep's start in the recording as the
    replay command's ``--t0``; from it, the recording's first state is the
    table's t = 0 row (its tip to 1 mm: the row is read at the sweep's
    start, a state or two from the one stamped)."""
    import re
    from soft_twin_core.files.runs import shifted_run
    t0 = float(re.search(r"--t0 ([0-9.]+)", out).group(1))
    assert 0.5 < t0 < 30.0, out[-2000:]
    row = re.search(r"^\s*0\s+[-0-9.]+\s+[-0-9.]+\s+\|\s+([-0-9.]+)\s+([-0-9.]+)\s+([-0-9.]+)", out, re.M)
    run = shifted_run(run, t0)
    assert 0.0 <= run["time"][0] < 0.05 and run["members_time"][0] == run["time"][0]      # (a state or few later)
    tip = np.asarray(run["frame_poses"][0][0], dtype=float)[:3, 3]           # the tip frame's, first state
    np.testing.assert_allclose(1e3 * tip, [float(v) for v in row.groups()], atol=1.0)


def _scrub_the_recording_in_the_page(rec, run, tmp_path):
    """Issue 31: the demo's recording played back in the browser
    (``soft-twin-sim view``), paused and scrubbed with the page's time
    slider in headless Chromium to two times: the state shown and the
    plotted signal (the tip's z [m]) are the recording's at that time
    (read back here with the mcap library)."""
    import re
    import socket
    import threading
    from chromium_cdp import Browser, chromium_path, wait_for
    from soft_twin_core import cli
    from soft_twin_core.robot.mechanism import load_mechanism
    from soft_twin_core.viz import render
    from soft_twin_core.viz.scene import run_snapshots
    assert chromium_path(), "no chromium on PATH: `make setup` installs Debian's chromium"
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    mech = load_mechanism("tendon_arm")
    times = np.array([s.time for s in run_snapshots(run, mech)])
    tip = run["frame_names"][0]
    tip_z = np.array([poses[0][2][3] for poses in run["frame_poses"]])
    args = cli._parser().parse_args(["view", str(rec), "--robot", "tendon_arm", "--node", "/soft_twin_demo",
                                     "--port", str(port), "--seconds", "300"])
    stop = threading.Event()
    th = threading.Thread(target=render.view_main, args=(args, stop), daemon=True)
    th.start()
    browser = None

    def shown(browser):
        text = browser.evaluate("document.body.innerText") or ""
        m = re.search(r"t = ([-0-9.]+) s.*?(\S+ z \[m\]): ([-0-9.e+]+)", text, re.S)
        return (float(m.group(1)), m.group(2), float(m.group(3))) if m else None

    try:
        browser = Browser(width=1000, height=800)
        assert wait_for(lambda: _opened(browser, port), 60.0, 0.5), "the view did not serve its page"
        assert wait_for(lambda: shown(browser) is not None and "time [s]" in browser.evaluate(
            "document.body.innerText"), 60.0, 0.25), browser.evaluate("document.body.innerText")
        row = """(() => {{ const lab = [...document.querySelectorAll('*')].filter(e =>
            e.textContent.trim() === {label!r}).pop(); let p = lab; while (p && !p.querySelector({sel!r}))
            p = p.parentElement; return p ? p.querySelector({sel!r}) : null; }})()"""
        playing = row.format(label="playing", sel="input[type=checkbox]")

        unticked_at = []

        def pause():
            """Untick "playing" until the view says it paused. A click before
            the page's controls are live toggles the box but never reaches
            the view: a box left unticked 3 s with no "(paused)" is ticked
            again, to be unticked on the next call."""
            if "(paused)" in browser.evaluate("document.body.innerText"):
                return True
            box = browser.rect(playing)
            if browser.evaluate(f"{playing}.checked"):
                browser.click(box["x"] + 0.5 * box["width"], box["y"] + 0.5 * box["height"])     # untick
                unticked_at[:] = [time.monotonic()]
            elif not unticked_at:
                unticked_at[:] = [time.monotonic()]
            elif time.monotonic() - unticked_at[0] > 3.0:
                browser.click(box["x"] + 0.5 * box["width"], box["y"] + 0.5 * box["height"])     # tick again
                unticked_at.clear()
            return False
        assert wait_for(pause, 40.0, 0.5), browser.evaluate("document.body.innerText")
        thumb = browser.rect(row.format(label="time [s]", sel="[role=slider]"))
        track = browser.rect(row.format(label="time [s]", sel=".mantine-Slider-track"))
        for k, frac in enumerate((0.6, 0.2)):
            y = thumb["y"] + 0.5 * thumb["height"]
            target = times[0] + frac * (times[-1] - times[0])

            def settled():
                got = shown(browser)
                return got is not None and abs(got[0] - target) < 0.05 * (times[-1] - times[0])
            # a drag the page drops (seen once in a full run: the second one never reached the view) is
            # made again, up to three times; the view must then show the time dragged to
            for _ in range(3):
                x0 = browser.rect(row.format(label="time [s]", sel="[role=slider]"))
                browser.drag(x0["x"] + 0.5 * x0["width"], y, track["x"] + frac * track["width"], y)
                if wait_for(settled, 10.0, 0.25):
                    break
            assert settled(), (shown(browser), target)
            t, label, z = shown(browser)
            i = int(np.argmin(np.abs(times - t)))          # (the page shows t to 0.1 ms; samples ~5 ms apart)
            assert label == f"{tip} z [m]"
            assert t == pytest.approx(times[i], abs=1e-4) and z == pytest.approx(tip_z[i], rel=1e-5, abs=1e-9)
            (tmp_path / f"playback_{k}.png").write_bytes(browser.screenshot())
    finally:
        stop.set()
        if browser is not None:
            browser.close()
        th.join(30)


def _opened(browser, port):
    try:
        browser.open(f"http://127.0.0.1:{port}", timeout=5.0)
        return True
    except Exception:
        return False
