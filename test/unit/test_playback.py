"""The playback clock of a run in the browser view (issue 31): play,
pause, speed and seek on a wall clock given by the caller (no sleeping),
the sample shown at a run time, and the signals offered for plotting."""
import numpy as np
import pytest

from soft_twin_core.viz.playback import PlaybackClock, frame_signals, sample_at


def test_the_clock_plays_loops_pauses_seeks_and_changes_speed():
    c = PlaybackClock(1.0, 3.0, now=100.0)
    assert c.time(100.0) == 1.0 and c.time(101.5) == pytest.approx(2.5)
    assert c.time(102.5) == pytest.approx(1.5)                 # 2.5 s of a 2 s run: round once
    c.set_playing(False, 101.0)
    assert c.time(101.0) == pytest.approx(2.0) and c.time(500.0) == pytest.approx(2.0)     # stands
    c.seek(2.75, 600.0)
    assert c.time(700.0) == 2.75                               # paused: where it was put
    c.set_playing(True, 700.0)
    assert c.time(700.2) == pytest.approx(2.95)
    c.set_speed(0.25, 700.2)
    assert c.time(701.0) == pytest.approx(1.0 + (2.95 + 0.2 - 1.0) % 2.0)      # 0.8 s at x0.25 = 0.2 s
    c.seek(-5.0, 800.0)
    assert c.time(800.0) == 1.0                                # clipped to the run
    with pytest.raises(ValueError, match="speed"):
        c.set_speed(0.0, 800.0)
    with pytest.raises(ValueError, match="before it starts"):
        PlaybackClock(2.0, 1.0, now=0.0)
    assert PlaybackClock(1.0, 1.0, now=0.0).time(50.0) == 1.0  # a run of one state


def test_the_sample_shown_is_the_latest_at_or_before_the_time():
    times = [0.0, 0.1, 0.2, 0.3]
    assert [sample_at(times, t) for t in (-1.0, 0.0, 0.05, 0.1, 0.2999, 0.3, 9.0)] == [0, 0, 0, 1, 2, 3, 3]


def test_frame_signals_are_each_axis_of_each_frame_with_its_unit():
    poses = []
    for k in range(4):
        T = np.eye(4)
        T[:3, 3] = [k, 2 * k, -k]
        poses.append([T, np.eye(4)])
    sig = frame_signals(["tip", "base"], poses)
    assert list(sig)[:3] == ["tip x [m]", "tip y [m]", "tip z [m]"] and len(sig) == 6
    np.testing.assert_array_equal(sig["tip y [m]"], [0, 2, 4, 6])
    np.testing.assert_array_equal(sig["base z [m]"], 0)
    with pytest.raises(ValueError, match="2 frames a sample, but 1 names"):
        frame_signals(["tip"], poses)


def test_the_views_playback_plot_holds_the_signal_up_to_the_time_shown():
    """LiveView's playback controls (no browser: the server's side): the
    plot holds the chosen signal's samples up to the time shown, the time
    slider follows it, and a value the view sets itself (following the
    run) is not taken for the page's (no callback)."""
    from soft_twin_core.viz.live_view import LiveView
    view = LiveView(port=0)
    try:
        calls = []
        times = np.linspace(0.0, 1.0, 11)
        sig = {"tip z [m]": times ** 2, "tip x [m]": -times}
        view.set_playback(0.0, 1.0, 0.1, list(sig), on_play=calls.append, on_seek=calls.append,
                          on_speed=calls.append, on_signal=calls.append)
        view.show_playback(0.5, times, "tip z [m]", sig["tip z [m]"])
        x, y = view._plot.data
        np.testing.assert_array_equal(x, times[:6])
        np.testing.assert_array_equal(y, times[:6] ** 2)
        assert view._time_slider.value == pytest.approx(0.5) and calls == []
        view.show_playback(0.95, times, "tip x [m]", sig["tip x [m]"])
        x, y = view._plot.data
        assert len(x) == 10 and y[-1] == pytest.approx(-0.9) and view._plot.axes[1]["label"] == "tip x [m]"
    finally:
        view.close()


def test_value_colours_run_blue_grey_red_and_outlines_split_at_nan():
    from soft_twin_core.viz.live_view import VALUE_COLORS, polyline_segments, value_colors
    c = value_colors([0.0, -0.5, 1.0, 3.0, 0.25], 1.0)
    np.testing.assert_array_equal(c[0], VALUE_COLORS[0])
    np.testing.assert_array_equal(c[1], VALUE_COLORS[1])           # |value|
    np.testing.assert_array_equal(c[2], VALUE_COLORS[2])
    np.testing.assert_array_equal(c[3], VALUE_COLORS[2])           # above the scale: red
    np.testing.assert_array_equal(c[4], np.round(0.5 * (VALUE_COLORS[0] + VALUE_COLORS[1])))
    P = np.array([[0, 0, 0], [1, 0, 0], [np.nan] * 3, [0, 1, 0], [0, 2, 0], [0, 3, 0]], dtype=float)
    seg = polyline_segments([P])
    assert seg.shape == (3, 2, 3)
    np.testing.assert_array_equal(seg[1], [[0, 1, 0], [0, 2, 0]])


def test_the_view_draws_coloured_members_the_tip_path_obstacles_and_contact_forces():
    """LiveView.show (the server's side): a member coloured by values is
    sent as a mesh with a colour per vertex (its ring's point's value); the
    tip path grows a segment per millimetre moved and forgets what is older
    than TRAIL_SECONDS; obstacles' outlines and contact forces are drawn."""
    from soft_twin_core.viz.live_view import TRAIL_SECONDS, LiveView
    from soft_twin_core.viz.scene import Snapshot
    view = LiveView(port=0)
    try:
        P = np.c_[np.linspace(0, 0.3, 7), np.zeros(7), np.zeros(7)]
        outline = np.array([[0, 0, -0.1], [1, 0, -0.1], [np.nan] * 3, [1, 1, -0.1], [0, 1, -0.1]])
        for k in range(5):
            tip = np.eye(4)
            tip[:3, 3] = [0.3, 0.002 * k, 0.0]
            snap = Snapshot(members=[P], time=0.1 * k, obstacles=[outline])
            view.show(snap, 0.01, tip_pose=tip, values=("bending moment [N m]", [np.linspace(0, 2, 7)]), trail=True,
                      contacts=(np.array([[0.1, 0, -0.01]]), np.array([[0, 0, 1.0]])))
        assert {"/twin/member_0", "/twin/tip_path", "/world/obstacles", "/world/contact_forces"} <= set(view._sent)
        assert len(view._trail) == 5 and "blue 0 to red 2" in view._text.content
        snap = Snapshot(members=[P], time=0.4 + TRAIL_SECONDS + 0.05)
        view.show(snap, 0.01, tip_pose=tip, trail=True)          # the tip stood still: only the old points went
        assert len(view._trail) == 0 or view._trail[0][0] >= 0.05 + 0.4
        view.show(snap, 0.01, tip_pose=tip, trail=False)
        assert "/twin/tip_path" not in view._sent and "/world/contact_forces" not in view._sent
    finally:
        view.close()


def test_panel_values_round_off_to_zero():
    from soft_twin_core.viz.live_view import shown_value
    assert [shown_value(v) for v in (1.483e-10, -3e-12, 2.05123, 1e-6)] == ["0", "0", "2.051", "1e-06"]


def test_a_run_shifted_to_its_t0_drops_the_earlier_samples_of_every_series():
    """``--t0`` (render, view): a dynamics JSON's history series and member
    samples each cut with their own clock, a recording's lists with its
    one clock, names kept, times shifted; a t0 past the end refused."""
    from soft_twin_core.files.runs import shifted_run
    js = {"time": [0.0, 0.5, 1.0, 1.5], "tip_position": [[0, 0, k] for k in range(4)], "newton_iterations": [1, 2, 3, 4],
          "history_fields": ["time", "tip_position", "newton_iterations"], "members_time": [0.0, 1.0],
          "members": [{"a": 0}, {"a": 1}], "frame_poses": [0, 1], "member_names": ["a", "b", "c", "d"]}
    r = shifted_run(js, 1.0)
    assert r["time"] == [0.0, 0.5] and r["tip_position"] == [[0, 0, 2], [0, 0, 3]] and r["newton_iterations"] == [3, 4]
    assert r["members_time"] == [0.0] and r["members"] == [{"a": 1}] and r["frame_poses"] == [1]
    assert r["member_names"] == ["a", "b", "c", "d"] and js["time"][0] == 0.0          # (a copy)
    rec = {"time": [0.0, 0.25, 0.5], "members_time": [0.0, 0.25, 0.5], "members": [0, 1, 2], "frame_poses": [0, 1, 2],
           "frame_positions": [0, 1, 2], "frame_names": ["tip", "x", "y"]}
    r = shifted_run(rec, 0.25)
    assert r["time"] == r["members_time"] == [0.0, 0.25] and r["members"] == [1, 2] and r["frame_positions"] == [1, 2]
    assert r["frame_names"] == ["tip", "x", "y"]
    with pytest.raises(ValueError, match="ends at 0.5 s"):
        shifted_run(rec, 2.0)


def test_the_camera_projection_is_a_pinhole_of_the_views_field_of_view():
    """live_view.project (the browser tests aim their drags with it): the
    point looked at lands on the canvas centre; a point at distance d on
    the camera's up direction by d tan(fov/2) on the top edge, on its
    right by d tan(fov/2) width/height on the right edge; the framing
    puts the box's centre on the canvas, left of the middle."""
    from soft_twin_core.viz.live_view import FOV_DEG, camera_framing, project
    cam, look = np.array([1.0, -2.0, 1.0]), np.array([0.2, 0.1, -0.1])
    w, h = 1000.0, 800.0
    f = (look - cam) / np.linalg.norm(look - cam)
    r = np.cross(f, [0, 0, 1.0])
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    d, tn = np.linalg.norm(look - cam), np.tan(np.radians(FOV_DEG) / 2)
    P = project(np.array([look, look + d * tn * u, look + d * tn * (w / h) * r]), cam, look, w, h)
    np.testing.assert_allclose(P, [[500, 400], [500, 0], [1000, 400]], atol=1e-9)
    lo, hi = np.array([0.0, -0.05, -0.3]), np.array([0.3, 0.05, 0.0])
    cam, look = camera_framing(lo, hi)
    (x, y), = project(0.5 * (lo + hi), cam, look, w, h)
    assert 0 < x < 500 and abs(y - 400) < 1e-6
