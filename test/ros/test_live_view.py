"""The live 3D view in a real browser (issue 12): the node serves it
(``live_view_port``), headless Chromium (Debian's package, driven over the
DevTools protocol) loads the page, and screenshots must show the arm and
change when the actuation moves it. Plus the tube mesh against its
definition."""
import io
import re
import socket

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


def test_the_floor_grid_is_the_squares_lines():
    """``grid_segments(1, 0.05)``: 21 lines along each axis, spanning the
    square centred on the origin, 5 cm apart, in the xy plane."""
    from soft_twin_core.viz.live_view import grid_segments
    S = grid_segments(1.0, 0.05)
    assert S.shape == (42, 2, 3) and S.dtype == np.float32 and np.all(S[:, :, 2] == 0)
    along_y, along_x = S[:21], S[21:]
    assert np.allclose(along_y[:, 0, 0], np.linspace(-0.5, 0.5, 21)) and np.allclose(along_y[:, :, 1], [-0.5, 0.5])
    assert np.allclose(along_x[:, 0, 1], np.linspace(-0.5, 0.5, 21)) and np.allclose(along_x[:, :, 0], [-0.5, 0.5])


def arm_pixels(png):
    """Boolean mask of the tube's orange pixels in a screenshot."""
    from PIL import Image
    a = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=int)
    r, g, b = a[..., 0], a[..., 1], a[..., 2]
    return (r > g + 40) & (r > b + 80) & (r > 120)


def tube_orange_pixels(png):
    """Boolean mask of pixels of the tube's own orange hue (TUBE_COLOR, any
    shade: green about half the red, little blue), which no colour of the
    members' value scale has."""
    from PIL import Image
    a = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=float)
    r, g, b = a[..., 0], a[..., 1], a[..., 2]
    return (r > 80) & (g > 0.38 * r) & (g < 0.68 * r) & (b < 0.38 * r)


def ghost_pixels(png):
    """Boolean mask of pixels of the IK ghost's violet (GHOST_COLOR, any
    shade: blue high, red about 0.6 of it, little green), which neither the
    force magenta, the chambers' blue nor the value scale's blue has."""
    from PIL import Image
    a = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=float)
    r, g, b = a[..., 0], a[..., 1], a[..., 2]
    return (b > 120) & (r > 0.42 * b) & (r < 0.8 * b) & (g < 0.6 * r)


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


def _wait_for_ik_answer(browser, accept, timeout_s=30.0):
    """Wait until the page shows an IK answer whose target [m] ``accept``s (a
    drag sends many targets and the node answers the newest when it is free:
    the first answer shown can be for a point part of the way); (target,
    reach, the text last read)."""
    from chromium_cdp import wait_for
    seen = {"text": "", "answer": None}

    def found():
        try:
            seen["text"] = browser.evaluate("document.body.innerText")
        except TimeoutError:
            return False
        m = re.search(r"target \[([^\]]+)\] m: .*?the tip reaches \[([^\]]+)\] m", seen["text"], re.S)
        if m is None:
            return False
        seen["answer"] = tuple(np.array([float(v) for v in g.split(",")]) for g in m.groups())
        return bool(accept(seen["answer"][0]))
    ok = wait_for(found, timeout_s, 0.25)
    assert ok, (seen["answer"], seen["text"])
    return (*seen["answer"], seen["text"])


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.quiet        # drags in a browser, with timeouts: alone (a drag was lost on a loaded machine)
def test_browser_shows_the_arm_follows_the_actuation_and_drives_the_twin(tmp_path):
    """The node's page shows the arm and follows a topic command; then the
    page drives the twin (:func:`_drive_from_the_page`)."""
    pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")
    from chromium_cdp import Browser, chromium_path, wait_for
    from soft_twin.client import NodeProcess, TwinClient
    assert chromium_path(), "no chromium on PATH: `make setup` installs Debian's chromium"
    port = free_port()
    proc = NodeProcess(["-p", f"live_view_port:={port}", "-p", "diagnostics_rate_hz:=20.0"], node_name=HERE_NODE,
                       log_path=tmp_path / "node.log")
    client = TwinClient(HERE_NODE, client_name=f"{HERE_NODE}_client")
    browser = None
    try:
        client.wait_ready(120.0)
        browser = Browser(width=1000, height=1000)      # (tall enough for the whole panel)
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
        rest = np.array([[p.position.x, p.position.y, p.position.z] for p in client.backbone.poses])
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
        _drive_from_the_page(browser, client, tmp_path, rest)
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
@pytest.mark.quiet        # drags in a browser, with timeouts: alone (a drag was lost on a loaded machine)
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


_FIND_ROW = """(() => {{ const lab = [...document.querySelectorAll('*')].filter(e =>
    e.textContent.trim() === {label!r}).pop(); let p = lab; while (p && !p.querySelector({sel!r})) p = p.parentElement;
    return p ? p.querySelector({sel!r}) : null; }})()"""


def _control(browser, label, selector):
    """The page rectangle of the ``selector`` element in the GUI row labelled ``label``."""
    return browser.rect(_FIND_ROW.format(label=label, sel=selector))


def _centre(r):
    return r["x"] + 0.5 * r["width"], r["y"] + 0.5 * r["height"]


def _drive_from_the_page(browser, client, tmp_path, rest):
    """Issue 31, driven as a user would: dragging the ``tendon_y_pos [N]``
    slider sends a command through the node's own input path (its
    counters show it applied, the panel shows the tension in N, the tip
    moves to +y); ticking "paused" stops the twin's steps (the
    diagnostics' count stands still over five periods); "step" takes one;
    "colour by" colours the arm; "reset" brings it back to rest; dragging the tip target (at the rest
    tip: ``rest``, the rest backbone [m]) shows the node's IK answer, and
    "apply" takes the tip there; dragging it in "push" mode lifts the tip
    with a spring while held, and the load goes when let go. Screenshots of each stage are kept in the
    test's folder."""
    from chromium_cdp import wait_for
    ok, text = _wait_for_page_text(browser, ["tendon_y_pos [N]", "paused", "time scale"], 60.0)
    assert ok, text
    # the sliders follow the twin's inputs: tendon_z_pos shows the 18 N sent on the topic
    z_thumb = _FIND_ROW.format(label="tendon_z_pos [N]", sel="[role=slider]")
    assert wait_for(lambda: browser.evaluate(f"{z_thumb}.getAttribute('aria-valuenow')") == "18", 20.0, 0.25)
    before = client.wait_diagnostics(timeout=10.0)
    tip0 = client.tip_pose.pose.position.y

    # 1. drag the tension slider's thumb to 80 % of its track
    thumb = _control(browser, "tendon_y_pos [N]", "[role=slider]")
    track = _control(browser, "tendon_y_pos [N]", ".mantine-Slider-track")
    assert thumb and track, text
    x0, y0 = _centre(thumb)
    browser.drag(x0, y0, track["x"] + 0.8 * track["width"], y0)
    d = client.wait_diagnostics(lambda d: int(d["commands_applied_total"]) > int(before["commands_applied_total"]),
                                20.0)
    assert d is not None, "the slider sent no command the node applied"
    assert int(d["commands_received_total"]) >= 1 and int(d["rejected_actuation_total"]) == 0
    ok, text = _wait_for_page_text(browser, ["tendon_y_pos: 1"], 20.0)     # 16 N or so, with its unit
    assert ok and re.search(r"tendon_y_pos: 1\d(\.\d+)? N", text), text
    assert client.wait_until(lambda: client.tip_pose.pose.position.y > tip0 + 0.02, 20.0), "the tip did not move to +y"
    (tmp_path / "1_slider_moved.png").write_bytes(browser.screenshot())

    # 2. pause: the steps stop
    box = _control(browser, "paused", "input[type=checkbox]")
    assert box, text
    browser.click(*_centre(box))
    d0 = client.wait_diagnostics(lambda d: d["paused"] == "true", 20.0)
    assert d0 is not None, "the page's pause did not pause the twin"
    for _ in range(5):
        d = client.wait_diagnostics(timeout=10.0)
        assert d["steps_total"] == d0["steps_total"]
    ok, text = _wait_for_page_text(browser, ["paused)"], 20.0)
    assert ok, text
    (tmp_path / "2_paused.png").write_bytes(browser.screenshot())

    # 3. one step
    step = browser.rect("[...document.querySelectorAll('button')].find(b => b.textContent.trim() === 'step')")
    assert step, text
    browser.click(*_centre(step))
    d = client.wait_diagnostics(lambda d: int(d["steps_total"]) == int(d0["steps_total"]) + 1, 20.0)
    assert d is not None, "the page's step did not take one step"
    (tmp_path / "3_stepped.png").write_bytes(browser.screenshot())
    # the page's inputs are counted once each: the drag's, none echoed back by the sliders following
    d = client.wait_diagnostics(timeout=10.0)
    assert int(d["rejected_actuation_total"]) == 0

    # 4. colour the arm by its bending moment: the legend in N m, the tube no longer plain orange
    orange = tube_orange_pixels(browser.screenshot()).sum()
    menu = _control(browser, "colour by", "input")
    assert menu, text
    browser.click(*_centre(menu))
    option = "[...document.querySelectorAll('[role=option]')].find(e => e.textContent.trim() === 'bending moment [N m]')"
    assert wait_for(lambda: browser.rect(option) is not None, 10.0, 0.25), "no colouring menu"
    browser.click(*_centre(browser.rect(option)))
    ok, text = _wait_for_page_text(browser, ["colour: bending moment [N m], blue 0 to red"], 20.0)
    assert ok, text
    assert orange > 400
    assert wait_for(lambda: tube_orange_pixels(browser.screenshot()).sum() < 0.2 * orange, 20.0, 0.5), \
        "the arm kept its colour"
    (tmp_path / "4_coloured.png").write_bytes(browser.screenshot())

    # 5. running again, drag the tip target (a gizmo at the rest tip) up by its z arrow: the node's IK
    # answers in the panel; "apply" sends its inputs and the tip goes where the answer says
    browser.click(*_centre(_control(browser, "paused", "input[type=checkbox]")))
    assert client.wait_diagnostics(lambda d: d["paused"] == "false", 20.0) is not None
    reset = browser.rect("[...document.querySelectorAll('button')].find(b => b.textContent.trim() === 'reset')")
    browser.click(*_centre(reset))                  # back to rest (and no input): the IK's answer is near
    assert client.wait_until(lambda: abs(client.tip_pose.pose.position.z - rest[-1][2]) < 2e-3, 20.0), \
        "the page's reset did not bring the arm back to rest"
    from soft_twin_core.viz.live_view import camera_framing, project
    from soft_twin_core.viz.scene import Snapshot, bounds
    camera, look = camera_framing(*bounds([Snapshot(members=[rest])], pad=0.3))
    w, h = browser.evaluate("(() => { const r = document.querySelector('canvas').getBoundingClientRect(); "
                            "return [r.width, r.height]; })()")
    (x0, y0), = project(rest[-1] + [0.0, 0.0, 0.06], camera, look, w, h)     # on the gizmo's z arrow (scale 0.08)
    browser.drag(x0, y0, x0, y0 - 40, steps=10)
    target, reach, text = _wait_for_ik_answer(browser, lambda t: t[2] > rest[-1][2] + 0.01)
    assert np.allclose(target[:2], rest[-1][:2], atol=2e-3), (target, rest[-1])
    # the answer's shape is drawn as a violet ghost until it is applied
    assert "the violet ghost" in text, text
    assert wait_for(lambda: ghost_pixels(browser.screenshot()).sum() > 50, 20.0, 0.5), "no ghost of the IK answer"
    (tmp_path / "5_ik_ghost.png").write_bytes(browser.screenshot())
    applied = int(client.wait_diagnostics(timeout=10.0)["commands_applied_total"])
    apply = browser.rect("[...document.querySelectorAll('button')].find(b => b.textContent.trim() === 'apply')")
    browser.click(*_centre(apply))
    assert client.wait_diagnostics(lambda d: int(d["commands_applied_total"]) > applied, 20.0) is not None

    def at_reach():
        p = client.tip_pose.pose.position
        return np.linalg.norm([p.x - reach[0], p.y - reach[1], p.z - reach[2]]) < 0.01
    assert client.wait_until(at_reach, 30.0), f"the tip did not go to the IK's answer {reach}"
    assert wait_for(lambda: ghost_pixels(browser.screenshot()).sum() < 5, 20.0, 0.5), "the ghost stayed"
    (tmp_path / "5_ik_applied.png").write_bytes(browser.screenshot())

    # 5b. the planner from the page: the gizmo dragged back down, "plan a line here" plans the tip along a
    # straight line to it and runs the plan through the twin's inputs; the planned path is the ghost
    (x0, y0), = project(target + [0.0, 0.0, 0.06], camera, look, w, h)
    browser.drag(x0, y0, x0, y0 + 40, steps=10)         # back down by the 40 px it went up: near the rest tip
    _wait_for_ik_answer(browser, lambda t: t[2] < target[2] - 0.01)
    applied = int(client.wait_diagnostics(timeout=10.0)["commands_applied_total"])
    plan = browser.rect("[...document.querySelectorAll('button')].find(b => b.textContent.trim() === "
                        "'plan a line here')")
    assert plan, "no plan button"
    browser.click(*_centre(plan))
    ok, text = _wait_for_page_text(browser, ["the planned tip path and the shape it ends in (violet) end at"],
                                   60.0)
    assert ok, text
    assert "executing" in text, text
    end = np.array([float(v) for v in re.search(r"\(violet\) end at \[([^\]]+)\] m", text).group(1).split(",")])
    assert end[2] < reach[2] - 0.005, (end, reach)                 # down, towards where the gizmo went
    (tmp_path / "5b_plan.png").write_bytes(browser.screenshot())
    assert wait_for(lambda: ghost_pixels(browser.screenshot()).sum() > 50, 20.0, 0.5), "no plan drawn"

    def at_end():
        p = client.tip_pose.pose.position
        return np.linalg.norm([p.x - end[0], p.y - end[1], p.z - end[2]]) < 0.005
    assert client.wait_until(at_end, 30.0), f"the tip did not follow the plan to {end}"
    assert int(client.wait_diagnostics(timeout=10.0)["commands_applied_total"]) > applied + 5   # the plan's samples

    # 6. push the tip: the gizmo back on the tip; held 60 px above it, a spring pulls the tip up (a tip
    # load through the node's own ~/tip_wrench_command, counted); let go, the load is gone
    browser.click(*_centre(_control(browser, "drag to", "input")))
    option = "[...document.querySelectorAll('[role=option]')].find(e => e.textContent.trim() === 'push a point (spring)')"
    assert wait_for(lambda: browser.rect(option) is not None, 10.0, 0.25), "no gizmo menu"
    browser.click(*_centre(browser.rect(option)))
    ok, text = _wait_for_page_text(browser, ["a spring of 10 N/m"], 20.0)
    assert ok, text
    wrenches = int(client.wait_diagnostics(timeout=10.0)["wrenches_applied_total"])
    # where the page put the gizmo (the tip then; the arm may still be settling: not the tip now)
    tip = np.array([float(v) for v in re.search(r"drag the gizmo \(at \[([^\]]+)\] m\)", text).group(1).split(",")])
    (x0, y0), = project(tip + [0.0, 0.0, 0.06], camera, look, w, h)
    browser.mouse("mousePressed", x0, y0)
    for k in range(1, 11):
        browser.mouse("mouseMoved", x0, y0 - 6 * k)
    assert client.wait_until(lambda: client.tip_pose.pose.position.z > tip[2] + 0.01, 30.0), "the push did not lift"
    ok, text = _wait_for_page_text(browser, ["pushing the tip with", "tip force:"], 20.0)
    assert ok, text
    assert int(client.wait_diagnostics(timeout=10.0)["wrenches_applied_total"]) > wrenches
    (tmp_path / "6_pushing.png").write_bytes(browser.screenshot())
    browser.mouse("mouseReleased", x0, y0 - 60)
    assert wait_for(lambda: "tip force:" not in browser.evaluate("document.body.innerText"), 20.0, 0.25), \
        "the push's load stayed after letting go"
    # 7. push a point picked on the page: a click on the arm's middle picks the backbone point nearest the
    # click (the page names it, <member>@<s>) and puts the gizmo there; held 60 px above it, the spring
    # pulls that point (the node's own ~/point_wrench_command, counted with the wrenches), the panel lists
    # the force on it; let go, the load is gone
    assert client.wait_until(lambda: client.tip_pose.pose.position.z < tip[2] + 0.005, 30.0), "not back down"
    # (the projection of the page's camera is good to some 30 px: clicks across the drawn arm, from its
    # middle's projection outwards, until one lands on it, as a user would aim)
    P = np.array([[q.position.x, q.position.y, q.position.z] for q in client.backbone.poses])
    mid = P[len(P) // 2]
    (xm, ym), (xa, ya) = project(np.array([mid, P[len(P) // 2 + 2]]), camera, look, w, h)
    across = np.array([ya - ym, xm - xa]) / max(np.hypot(ya - ym, xm - xa), 1e-9)
    for off in (0, 6, -6, 12, -12, 18, -18, 24, -24, 30, -30, 36, -36, 42, -42):
        browser.click(xm + off * across[0], ym + off * across[1])
        ok, text = _wait_for_page_text(browser, ["picked "], 2.0)
        if ok:
            break
    assert ok, text
    m = re.search(r"picked (\S+)@([0-9.]+) at \[([^\]]+)\] m", text)         # (the name in code type)
    assert m, text
    picked = np.array([float(v) for v in m.group(3).split(",")])
    assert np.linalg.norm(picked - mid) < 0.03, (picked, mid)           # the point under the click
    wrenches = int(client.wait_diagnostics(timeout=10.0)["wrenches_applied_total"])
    (x0, y0), = project(picked + [0.0, 0.0, 0.06], camera, look, w, h)
    browser.mouse("mousePressed", x0, y0)
    for k in range(1, 11):
        browser.mouse("mouseMoved", x0, y0 - 6 * k)
    ok, text = _wait_for_page_text(browser, [f"pushing {m.group(1)}@", f"force on {m.group(1)}@"], 30.0)
    assert ok, text
    assert int(client.wait_diagnostics(timeout=10.0)["wrenches_applied_total"]) > wrenches
    (tmp_path / "7_pushing_a_point.png").write_bytes(browser.screenshot())
    browser.mouse("mouseReleased", x0, y0 - 60)
    assert wait_for(lambda: f"force on {m.group(1)}@" not in browser.evaluate("document.body.innerText"), 20.0,
                    0.25), "the point's load stayed after letting go"


def _box_js(label, selector):
    """JS giving the page box {x, y, width, height, page} (page: the page's
    height) of the ``selector`` element in the GUI row labelled ``label``
    (null: none), not scrolled (:meth:`Browser.rect` scrolls)."""
    return ("(() => { const e = " + _FIND_ROW.format(label=label, sel=selector) + "; if (!e) return null; "
            "const r = e.getBoundingClientRect(); return {x: r.x, y: r.y, width: r.width, height: r.height, "
            "page: innerHeight}; })()")


def _wheel_until_visible(browser, box_js, at, notches=60):
    """Turn the mouse wheel over the page point ``at`` (down) a notch at a
    time until the element of ``box_js`` is whole inside the page; its box
    once the scroll has come to rest (the panel scrolls smoothly: a box read
    during the glide is not where the element stops)."""
    import time

    def at_rest():
        box = browser.evaluate(box_js)
        for _ in range(50):
            time.sleep(0.05)
            again = browser.evaluate(box_js)
            if again == box:
                return box
            box = again
        return box
    box = at_rest()
    for _ in range(notches):
        if 0 <= box["y"] and box["y"] + box["height"] <= box["page"]:
            break
        browser.call("Input.dispatchMouseEvent", type="mouseWheel", x=at[0], y=at[1], deltaX=0, deltaY=120)
        box = at_rest()
    return box


@pytest.mark.slow
@pytest.mark.quiet        # drags in a browser, with timeouts: alone (a drag was lost on a loaded machine)
def test_a_short_window_scrolls_the_panel_to_its_last_control_and_it_works():
    """Issue 31: in a window shorter than the panel (a laptop's browser
    beside an editor: 1000 x 450, the page about 300 px high), with the
    node's four folders (run, eight sliders, the target, what to see), the
    last slider and the last box lie below the page's bottom; the mouse
    wheel over the panel scrolls each into view, and each works as in a
    tall window (the slider dragged sends its value, the box ticked turns
    the frames on). The panel's own box stays inside the page. The page
    is opened as the docs say for a browser without a GPU (``?fixedDpr=0.5``):
    the 3D canvas draws half the pixels across, the panel is unchanged."""
    from chromium_cdp import Browser, chromium_path, wait_for
    from soft_twin_core.viz.live_view import Control, LiveView
    assert chromium_path(), "no chromium on PATH: `make setup` installs Debian's chromium"
    view = LiveView(port=0)
    sent, frames = [], []
    view.set_controls([Control("actuation", f"tendon_{k}", 0.0, 20.0, 0.1, "N") for k in range(8)],
                      lambda c, v: sent.append((c.name, v)), on_pause=lambda b: None, on_step=lambda: None,
                      on_reset=lambda: None, on_time_scale=lambda x: None)
    view.set_target(np.zeros(3), lambda p, phase: None, lambda: None, on_plan=lambda: None)
    view.set_view_options(("none", "bending moment [N m]"), lambda c: None, lambda b: None, on_routes=lambda b: None,
                          on_frames=frames.append)
    thumb_js = _box_js("tendon_7 [N]", "[role=slider]")
    box_js = _box_js("frames", "input[type=checkbox]")
    try:
        with Browser(width=1000, height=450) as browser:
            browser.open(f"http://127.0.0.1:{view.port}/?fixedDpr=0.5")
            ok, text = _wait_for_page_text(browser, ["tendon_7 [N]", "frames", "plan a line here"])
            assert ok, text
            widest = ("(() => { const c = [...document.querySelectorAll('canvas')].sort((a, b) => b.width - "
                      "a.width)[0]; return c ? [c.width, c.clientWidth, window.devicePixelRatio] : null; })()")
            assert wait_for(lambda: (browser.evaluate(widest) or [0])[0] > 0, 20.0, 0.2)
            canvas = browser.evaluate(widest)
            assert canvas[2] == 1 and canvas[1] > 500 and abs(canvas[0] - 0.5 * canvas[1]) <= 1, canvas

            def settled():      # the folders' opening animation over: the last box stands still
                a = browser.evaluate(box_js)
                return a is not None and a == browser.evaluate(box_js)
            assert wait_for(settled, 20.0, 0.3)
            thumb = browser.evaluate(thumb_js)
            assert thumb["y"] > thumb["page"], f"the panel fits the page ({thumb}): the test needs a longer panel"
            panel = browser.evaluate("(() => { const r = document.querySelector('.mantine-ScrollArea-viewport')"
                                     ".getBoundingClientRect(); return {x: r.x, y: r.y, width: r.width, "
                                     "height: r.height}; })()")
            assert panel["y"] + panel["height"] <= thumb["page"] + 1, panel
            at = (panel["x"] + 0.5 * panel["width"], panel["y"] + 0.5 * panel["height"])
            thumb = _wheel_until_visible(browser, thumb_js, at)
            assert 0 <= thumb["y"] and thumb["y"] + thumb["height"] <= thumb["page"], thumb
            track = browser.evaluate(_box_js("tendon_7 [N]", ".mantine-Slider-track"))
            cx, cy = thumb["x"] + 0.5 * thumb["width"], thumb["y"] + 0.5 * thumb["height"]
            browser.drag(cx, cy, track["x"] + 0.6 * track["width"], cy)
            assert wait_for(lambda: any(n == "tendon_7" and v > 5.0 for n, v in sent), 20.0, 0.2), sent
            assert not any(n != "tendon_7" for n, _ in sent), sent
            box = _wheel_until_visible(browser, box_js, at)
            assert 0 <= box["y"] and box["y"] + box["height"] <= box["page"], box
            browser.click(box["x"] + 0.5 * box["width"], box["y"] + 0.5 * box["height"])
            assert wait_for(lambda: frames == [True], 20.0, 0.2), frames
    finally:
        view.close()
