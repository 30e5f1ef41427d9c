"""Pause, single step and slow motion of the twin (issue 31): the ``~/pause``
(std_srvs/SetBool) and ``~/step`` (std_srvs/Trigger) services and the
``time_scale`` parameter, on a node in a second process, through real
service clients and the diagnostics it publishes."""
import re
import time

import pytest

pytestmark = pytest.mark.ros


def _twin_time(message):
    return float(re.search(r"t = ([-0-9.e+]+) s", message).group(1))


def test_pause_stops_the_steps_step_takes_one_dt_and_time_scale_slows_the_twin(tmp_path):
    pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")
    from rclpy.parameter import Parameter
    from std_srvs.srv import SetBool, Trigger
    from soft_twin.client import start_twin, stop_twin
    name = "twin_run_controls"
    proc, client = start_twin(name, ["-p", "diagnostics_rate_hz:=20.0"], tmp_path / "node.log")
    try:
        dt = 1.0 / 200.0
        r = client.call("step", Trigger.Request())
        assert not r.success and "pause it first" in r.message

        r = client.call("pause", SetBool.Request(data=True))
        assert r.success and "paused" in r.message
        d0 = client.wait_diagnostics(lambda d: d["paused"] == "true", 10.0)
        assert d0 is not None and d0["step_rate_target_hz"] == "paused"
        # a command arrives while paused: counted, applied to the inputs, but no step takes it
        client.send_actuation(["tendon_z_pos"], [15.0])
        d1 = client.wait_diagnostics(lambda d: int(d["commands_applied_total"]) >= 1, 10.0)
        assert d1 is not None
        for _ in range(5):                    # five periods of the diagnostics (50 ms each): no step in any
            d2 = client.wait_diagnostics(timeout=10.0)
            assert float(d2["step_rate_hz"]) == 0.0
        assert d2["steps_total"] == d0["steps_total"] and d2["twin_time_s"] == d0["twin_time_s"]
        assert "paused" in client.diagnostics()["message"]

        t = [_twin_time(client.call("step", Trigger.Request()).message) for _ in range(3)]
        assert t[1] - t[0] == pytest.approx(dt, abs=1e-9) and t[2] - t[1] == pytest.approx(dt, abs=1e-9)
        d3 = client.wait_diagnostics(timeout=10.0)
        assert int(d3["steps_total"]) == int(d0["steps_total"]) + 3
        assert client.call("pause", SetBool.Request(data=True)).message.endswith("(it already was)")

        # slow motion: twin time never runs ahead of time_scale x wall time (plus a step)
        from rcl_interfaces.srv import SetParameters
        setp = client.node.create_client(SetParameters, f"/{name}/set_parameters")
        assert setp.wait_for_service(timeout_sec=10.0)
        fut = setp.call_async(SetParameters.Request(parameters=[Parameter("time_scale", value=0.25).to_parameter_msg()]))
        assert client.wait_until(fut.done, 10.0) and fut.result().results[0].successful
        r = client.call("pause", SetBool.Request(data=False))
        assert r.success and "running" in r.message
        w0, s0 = time.monotonic(), _twin_time(r.message)
        d4 = client.wait_diagnostics(lambda d: float(d["twin_time_s"]) > s0 + 0.05, 30.0)
        w1 = time.monotonic()
        assert d4 is not None, "the twin did not run again"
        assert d4["time_scale"] == "0.25" and d4["step_rate_target_hz"] == "50.000"
        assert float(d4["twin_time_s"]) - s0 <= 0.25 * (w1 - w0) + 2 * dt
        fut = setp.call_async(SetParameters.Request(parameters=[Parameter("time_scale", value=0.0).to_parameter_msg()]))
        assert client.wait_until(fut.done, 10.0)
        assert not fut.result().results[0].successful and "time_scale" in fut.result().results[0].reason
    finally:
        stop_twin(proc, client)
