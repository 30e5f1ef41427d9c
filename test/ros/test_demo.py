"""`make demo` (scripts/demo.py) end to end (issue 12): the table, the PNG,
the animation of the run and the node's MCAP recording, each file opened
and checked."""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")

ROOT = Path(__file__).resolve().parents[2]
pytestmark = [pytest.mark.ros, pytest.mark.slow]


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
    msgs = read_messages(str(rec))
    ns = "/soft_twin_demo"
    for t in ("backbone", "tip_pose", "strains", "tip_wrench", "base_wrench", "actuation", "tip_wrench_command"):
        assert f"{ns}/{t}" in msgs, t
    assert "/tf" in msgs and "/diagnostics" in msgs
    sent = int(out.split(" commands sent")[0].rsplit("of the ", 1)[1])
    assert len(msgs[f"{ns}/actuation"]) == sent > 400
    with open(rec, "rb") as fh:
        meta = {m.name: m.metadata for m in make_reader(fh).iter_metadata()}
    assert {k: int(v) for k, v in meta["soft_twin.counts"].items()} == {k: len(v) for k, v in msgs.items()}
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in msgs[f"{ns}/tip_pose"]]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    assert len(stamps) > 300       # states over the ~12 s run (200 Hz nominal; 898 at a load of 5)
