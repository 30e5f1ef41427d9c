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

from soft_twin_core.viz.live_view import tube_mesh

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


def _screenshot(browser):
    """A screenshot, or None when the (software-rendering) browser is too
    busy to answer in time on a loaded machine: try again."""
    try:
        return browser.screenshot()
    except TimeoutError:
        return None


def _wait_for_page_text(browser, words, timeout_s=30.0):
    """Wait until the page's text holds every one of ``words`` (the GUI panel
    can fill in after the scene shows: once in a full suite run the arm was
    drawn while the panel had no slider yet); (all found, the text last read)."""
    from chromium_cdp import wait_for
    seen = {"text": ""}

    def found():
        try:
            seen["text"] = browser.evaluate("document.body.innerText")
        except TimeoutError:
            return False
        return all(w in seen["text"] for w in words)
    return wait_for(found, timeout_s, 0.25), seen["text"]


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
        ok, text = _wait_for_page_text(browser, ["tendon_z_pos", "soft_twin"])
        assert ok, text

        tip0 = client.tip_pose.pose.position.z
        client.send_actuation(["tendon_z_pos"], [18.0])
        assert client.wait_until(lambda: client.tip_pose.pose.position.z > tip0 + 0.05, 20.0), "the twin did not lift"

        def moved():
            png = _screenshot(browser)
            if png is None:
                return False
            shots["after"] = png
            after = arm_pixels(png)
            inter, union = (before & after).sum(), (before | after).sum()
            return after.sum() > 400 and inter / union < 0.6
        assert wait_for(moved, 30.0, 0.5), "the arm in the page did not move"
        (tmp_path / "after.png").write_bytes(shots["after"])
        ok, text = _wait_for_page_text(browser, ["18"])
        assert ok, text
    finally:
        if browser is not None:
            browser.close()
        client.close()
        rc = proc.stop()
    assert rc == 0, proc.output()[-3000:]


def link_pixels(png):
    """Boolean mask of the rigid links' blue shapes (live_view.SHAPE_COLOR) in a screenshot."""
    from PIL import Image
    a = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=int)
    r, g, b = a[..., 0], a[..., 1], a[..., 2]
    return (b > r + 50) & (b > g + 30)


def test_shape_meshes_are_closed_and_have_the_sizes():
    from soft_twin_core.viz.live_view import shape_mesh
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.2, 0.3]
    V, F = shape_mesh({"shape": "box", "size": [0.05, 0.04, 0.03]}, T)
    assert np.allclose(V.max(axis=0) - V.min(axis=0), [0.05, 0.04, 0.03], atol=1e-7)
    # outward winding: the signed volume is the box's
    vol = np.sum(np.einsum("ij,ij->i", V[F[:, 0]] - T[:3, 3], np.cross(V[F[:, 1]] - T[:3, 3], V[F[:, 2]] - T[:3, 3]))) / 6
    assert vol == pytest.approx(0.05 * 0.04 * 0.03, rel=1e-5)
    V, F = shape_mesh({"shape": "cylinder", "radius": 0.04, "length": 0.06}, T)
    d = V - T[:3, 3]
    assert np.isclose(np.abs(d[:, 2]).max(), 0.03, atol=1e-7) and np.hypot(d[:, 0], d[:, 1]).max() == pytest.approx(0.04, rel=1e-6)
    V, F = shape_mesh({"shape": "sphere", "radius": 0.02}, T)
    assert np.linalg.norm(V - T[:3, 3], axis=1).max() == pytest.approx(0.02, rel=1e-6)
    for V_, F_ in (shape_mesh({"shape": "box", "size": [1, 1, 1]}, T),
                   shape_mesh({"shape": "cylinder", "radius": 0.04, "length": 0.06}, T)):
        edges = np.sort(np.concatenate([F_[:, [0, 1]], F_[:, [1, 2]], F_[:, [2, 0]]]), axis=1)
        _, counts = np.unique(edges, axis=0, return_counts=True)
        assert np.all(counts == 2)                 # closed surfaces


@pytest.mark.ros
@pytest.mark.slow
def test_browser_shows_an_articulated_robot_and_follows_a_joint_command(tmp_path):
    """The pan-tilt arm in the page: its soft arm (orange tube) and its rigid
    links (blue pan cylinder and tilt box); a pan command turns the arm in
    the page."""
    pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")
    from chromium_cdp import Browser, chromium_path, wait_for
    from soft_twin.client import TwinClient, start_twin, stop_twin
    assert chromium_path(), "no chromium on PATH: `make setup` installs Debian's chromium"
    port = free_port()
    name = "twin_live_view_art"
    proc, client = start_twin(name, ["-p", f"live_view_port:={port}", "-p", "robot_description_file:=pan_tilt_arm",
                                     "-p", "mode:=quasi_static", "-p", "republish_rate_hz:=20.0"],
                              tmp_path / "node.log", TwinClient.TOPICS + ("joint_states",), 120.0,
                              ready=lambda c: c.pub_joints.get_subscription_count() > 0)
    browser = None
    try:
        browser = Browser(width=1000, height=700)
        browser.open(f"http://127.0.0.1:{port}")
        shots = {}

        def robot_visible():               # and the page settled (it fades the scene in)
            prev, png = shots.get("before"), _screenshot(browser)
            if png is None:
                return False
            shots["before"] = png
            arm, links = arm_pixels(png), link_pixels(png)
            return (arm.sum() > 300 and links.sum() > 300 and prev is not None
                    and np.array_equal(arm, arm_pixels(prev)) and np.array_equal(links, link_pixels(prev)))
        assert wait_for(robot_visible, 120.0, 0.5), "the page shows no arm and links"
        (tmp_path / "before.png").write_bytes(shots["before"])
        before, links_before = arm_pixels(shots["before"]), link_pixels(shots["before"])
        ok, text = _wait_for_page_text(browser, ["tendon_z_pos", "joint pan"])
        assert ok, text

        stamp = client.send_joint_command(["pan"], positions=[0.9])
        assert client.wait_until(lambda: client.state_after(stamp), 20.0), "the joint command was not applied"
        assert client.wait_until(lambda: client.history["joint_states"]
                                 and abs(client.history["joint_states"][-1][1].position[0] - 0.9) < 1e-9, 30.0)

        def moved():
            png = _screenshot(browser)
            if png is None:
                return False
            shots["after"] = png
            after = arm_pixels(png)
            inter, union = (before & after).sum(), (before | after).sum()
            return after.sum() > 100 and inter / union < 0.5
        ok = wait_for(moved, 60.0, 0.5)
        if "after" in shots:
            (tmp_path / "after.png").write_bytes(shots["after"])
        assert ok, "the arm in the page did not turn with the pan joint"
        assert link_pixels(shots["after"]).sum() > 300
        assert not np.array_equal(links_before, link_pixels(shots["after"]))     # the tilt box turned too
        ok, text = _wait_for_page_text(browser, ["0.9"])
        assert ok, text
    finally:
        if browser is not None:
            browser.close()
        stop_twin(proc, client)
