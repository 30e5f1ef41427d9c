"""The live 3D view in a real browser (issue 12): the node serves it
(``live_view_port``), headless Chromium (Debian's package, driven over the
DevTools protocol) loads the page, and screenshots must show the arm and
change when the actuation moves it. Plus the tube mesh against its
definition."""
import io
import socket
import time

import numpy as np
import pytest

from soft_twin_core.live_view import tube_mesh

HERE_NODE = "twin_live_view"


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_tube_mesh_rings_are_normal_to_the_backbone_at_the_radius():
    t = np.linspace(0, 1, 40)
    P = np.c_[0.3 * np.cos(t), 0.3 * np.sin(t), 0.1 * t]          # a helix
    r = np.linspace(0.01, 0.005, 40)
    V, F = tube_mesh(P, r, sides=12)
    assert V.shape == (40 * 12 + 2, 3) and F.max() == len(V) - 1
    ring = V[:-2].reshape(40, 12, 3) - P[:, None, :]
    assert np.allclose(np.linalg.norm(ring, axis=2), r[:, None], rtol=1e-5)
    T = np.gradient(P, axis=0)
    T /= np.linalg.norm(T, axis=1, keepdims=True)
    assert np.max(np.abs(np.einsum("pkj,pj->pk", ring, T))) < 1e-6
    # a closed surface: every edge is shared by exactly two triangles
    edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)


def arm_pixels(png):
    """Boolean mask of the tube's orange pixels in a screenshot."""
    from PIL import Image
    a = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=int)
    r, g, b = a[..., 0], a[..., 1], a[..., 2]
    return (r > g + 40) & (r > b + 80) & (r > 120)


@pytest.mark.ros
@pytest.mark.slow
def test_browser_shows_the_arm_and_follows_the_actuation(tmp_path):
    pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")
    from chromium_cdp import Browser, chromium_path, wait_for
    from soft_twin.client import NodeProcess, TwinClient
    assert chromium_path(), "no chromium on PATH: `make setup` installs Debian's chromium"
    port = free_port()
    proc = NodeProcess(["-p", f"live_view_port:={port}"], node_name=HERE_NODE, log_path=tmp_path / "node.log")
    client = TwinClient(HERE_NODE, client_name=f"{HERE_NODE}_client")
    browser = None
    try:
        client.wait_ready(120.0)
        browser = Browser(width=1000, height=700)
        browser.open(f"http://127.0.0.1:{port}")
        shots = {}

        def arm_visible():
            shots["before"] = browser.screenshot()
            return arm_pixels(shots["before"]).sum() > 400
        assert wait_for(arm_visible, 60.0, 0.5), "the page shows no arm"
        (tmp_path / "before.png").write_bytes(shots["before"])
        before = arm_pixels(shots["before"])
        text = browser.evaluate("document.body.innerText")
        assert "tendon_z_pos" in text and "soft_twin" in text

        tip0 = client.tip_pose.pose.position.z
        client.send_actuation(["tendon_z_pos"], [18.0])
        assert client.wait_until(lambda: client.tip_pose.pose.position.z > tip0 + 0.05, 20.0), "the twin did not lift"

        def moved():
            shots["after"] = browser.screenshot()
            after = arm_pixels(shots["after"])
            inter, union = (before & after).sum(), (before | after).sum()
            return after.sum() > 400 and inter / union < 0.6
        assert wait_for(moved, 30.0, 0.5), "the arm in the page did not move"
        (tmp_path / "after.png").write_bytes(shots["after"])
        assert "18" in browser.evaluate("document.body.innerText")
    finally:
        if browser is not None:
            browser.close()
        client.close()
        rc = proc.stop()
    assert rc == 0, proc.output()[-3000:]
