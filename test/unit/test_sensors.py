"""Measurement models (soft_twin_core.estimation.sensors) on a classic rod (a
one-member mechanism): predictions against the numpy kinematics
reference, analytic Jacobians against central finite differences, the
actuation matrix against the reference residual, input checks and files.
(The tree robot's sensors, joint encoders and the base wrench:
test_tree_estimation.py.)"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from soft_twin_core import lie
from soft_twin_core.engine.forces import actuation_matrix, actuator_arrays
from soft_twin_core.engine.loads import Loads
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.estimation import sensors as sn
from soft_twin_core.reference import kinematics as kin
from soft_twin_core.reference import statics as st
from soft_twin_core.robot.mechanism import from_robot_model
from soft_twin_core.robot.model import load_model, model_from_dict, benchmark_cantilever_dict


@pytest.fixture(scope="module")
def arm():
    model = load_model("tracked_arm")
    return model, from_robot_model(model)


@pytest.fixture(scope="module")
def arm_all_modes():
    model = model_from_dict(benchmark_cantilever_dict(n_sections=5, free_modes="all", length=0.4))
    return model, from_robot_model(model)


def _q(model, seed=0, scale=1.0):
    rng = np.random.default_rng(seed)
    return model.q0 + scale * rng.normal(size=model.n_dof)


def _placement():
    P = np.eye(4)
    P[:3, :3] = lie.exp_so3([0.3, -0.2, 0.5])
    P[:3, 3] = [0.004, -0.01, 0.007]
    return P


def _residual(mech, ws, q, sen, where, z):
    return sn.residual_and_jacobian(ws, sn.forward(ws, q), sen, where, z)


def _fd(f, q, h=1e-6):
    cols = []
    for k in range(len(q)):
        dq = np.zeros_like(q)
        dq[k] = h
        cols.append((f(q + dq) - f(q - dq)) / (2 * h))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("which", ["arm", "arm_all_modes"])
@pytest.mark.parametrize("s_frac", [0.0, 0.33, 0.6, 1.0])
def test_sensor_pose_matches_numpy_kinematics(request, which, s_frac):
    model, mech = request.getfixturevalue(which)
    q = _q(model, 1)
    s = s_frac * model.total_length
    sen = sn.PoseSensor("em", 1e-3, 1e-2, s=s, placement=_placement())
    ref = kin.poses(model, q[None], [s])[0, 0] @ _placement()     # numpy chain (batch path)
    assert np.allclose(sn.sensor_pose(mech, q, sen), ref, atol=1e-12)
    mk = sn.marker("mk", 1e-3, [0.0, 0.005, -0.003], s=s)
    _, where = sn.check_sensors(mech, [mk])
    g = kin.poses(model, q[None], [s])[0, 0]
    read = sn.predict_readings(Workspace(mech.tree), q, [mk], where)["mk"]
    assert np.allclose(read, g[:3, 3] + g[:3, :3] @ [0.0, 0.005, -0.003], atol=1e-12)


@pytest.mark.parametrize("which", ["arm", "arm_all_modes"])
def test_pose_residual_jacobian_matches_finite_differences(request, which):
    model, mech = request.getfixturevalue(which)
    q = _q(model, 2)
    sen = sn.PoseSensor("em", 1e-3, 1e-2, s=0.7 * model.total_length, placement=_placement())
    _, where = sn.check_sensors(mech, [sen])
    ws = Workspace(mech.tree)
    # a measurement away from h(q) so that the rotation residual (and Jr^-1) is far from identity
    z = sn.sensor_pose(mech, q, sen).copy()
    z[:3, :3] = z[:3, :3] @ lie.exp_so3([0.4, 0.7, -0.5])
    z[:3, 3] += [0.01, -0.02, 0.03]
    e, H = _residual(mech, ws, q, sen, where["em"], z)
    assert np.linalg.norm(e[3:]) > 0.9                    # a large rotation error really is tested
    Hfd = _fd(lambda x: _residual(mech, ws, x, sen, where["em"], z)[0], q)
    assert np.abs(H - Hfd).max() <= 1e-7 * max(1.0, np.abs(Hfd).max())


def test_marker_residual_jacobian_matches_finite_differences(arm):
    model, mech = arm
    q = _q(model, 3)
    mk = sn.marker("mk", 1e-3, [0.002, 0.009, -0.004], s=0.31)
    _, where = sn.check_sensors(mech, [mk])
    ws = Workspace(mech.tree)
    z = np.array([0.3, 0.1, -0.1])
    e, H = _residual(mech, ws, q, mk, where["mk"], z)
    assert e.shape == (3,) and H.shape == (3, model.n_dof)
    Hfd = _fd(lambda x: _residual(mech, ws, x, mk, where["mk"], z)[0], q)
    assert np.abs(H - Hfd).max() <= 1e-7 * np.abs(Hfd).max()


def test_rotation_residual_sign_and_noise_level():
    """e_R = log(R_meas^T R): for R_meas = R exp(n) it is exactly -n, and the
    simulated noise has the stated standard deviations."""
    rng = np.random.default_rng(4)
    sen = sn.PoseSensor("em", 2e-3, 0.03, s=0.0)
    T = np.eye(4)
    T[:3, :3] = lie.exp_so3([0.1, 0.2, 0.3])
    samples = np.array([sn.simulate_measurement(sen, T, rng) for _ in range(4000)])
    ep = samples[:, :3, 3] - T[:3, 3]
    er = lie.log_so3(np.swapaxes(samples[:, :3, :3], -1, -2) @ T[:3, :3])
    assert np.allclose(ep.std(axis=0), 2e-3, rtol=0.06)
    assert np.allclose(er.std(axis=0), 0.03, rtol=0.06)
    n = np.array([0.01, -0.02, 0.005])
    z = T.copy()
    z[:3, :3] = T[:3, :3] @ lie.exp_so3(n)
    assert np.allclose(lie.log_so3(z[:3, :3].T @ T[:3, :3]), -n, atol=1e-15)


def test_quaternion_measurement_matches_scipy():
    rng = np.random.default_rng(5)
    quat = rng.normal(size=4)
    T = sn.pose_from_position_quaternion([1, 2, 3], quat)
    assert np.allclose(T[:3, :3], Rotation.from_quat(quat / np.linalg.norm(quat)).as_matrix(), atol=1e-14)
    sen = sn.PoseSensor("em", 1e-3, 1e-2, s=0.0)
    assert np.allclose(sn.measurement_vector(sen, np.r_[[1, 2, 3], quat]), T)


def test_actuation_matrix_matches_reference_residual(arm):
    """B(q) = d tau_act/du: the numpy reference residual R = K (q - q0) - Q
    - tau_act(q, u) is linear in u, so column k is R(u=0) - R(u=e_k)."""
    model, mech = arm
    q = _q(model, 6, 0.5)
    B = actuation_matrix(mech.tree, Workspace(mech.tree), actuator_arrays(mech.tree), q)
    loads = Loads(gravity=False)
    R0 = st.residual(model, q, np.zeros(4), loads)
    ref = np.stack([R0 - st.residual(model, q, e, loads) for e in np.eye(4)], axis=1)
    assert np.abs(ref).max() > 1e-4
    assert np.allclose(B, ref, atol=1e-12 * np.abs(ref).max())


@pytest.mark.parametrize("bad, match", [
    (np.full(3, np.nan), "NaN"), (np.zeros(4), "shape"), (np.zeros((3, 3)), "shape")])
def test_bad_measurements_are_refused(bad, match):
    mk = sn.marker("mk", 1e-3, s=0.1)
    em = sn.PoseSensor("em", 1e-3, 1e-2, s=0.1)
    with pytest.raises(ValueError, match=match):
        sn.measurement_vector(mk if bad.ndim == 1 else em, bad)


def test_sensor_configuration_is_checked(arm):
    _, mech = arm
    with pytest.raises(ValueError, match=r"sensors\[1\].*s: expected an arc length in \[0, 0.4\] m"):
        sn.check_sensors(mech, [sn.marker("a", 1e-3, s=0.1), sn.marker("b", 1e-3, s=0.5)])
    with pytest.raises(ValueError, match="duplicate"):
        sn.check_sensors(mech, [sn.marker("a", 1e-3, s=0.1), sn.marker("a", 1e-3, s=0.2)])
    with pytest.raises(ValueError, match="unknown actuator"):
        sn.check_sensors(mech, [sn.TensionSensor("t", "nope", 0.1)])
    with pytest.raises(ValueError, match="positive"):
        sn.check_sensors(mech, [sn.PoseSensor("a", 1e-3, 0.0, s=0.1)])
    with pytest.raises(ValueError, match="frame.*unknown|no frame"):
        sn.check_sensors(mech, [sn.PoseSensor("a", 1e-3, 0.01, frame="nope")])
    with pytest.raises(ValueError, match="not both"):
        sn.check_sensors(mech, [sn.PoseSensor("a", 1e-3, 0.01, frame="tip", member="backbone")])


def test_sensor_files_round_trip(arm):
    """Every kind from plain dicts and back; an unknown field or type is named."""
    _, mech = arm
    items = [{"name": "em0", "type": "pose", "s": 0.16, "sigma_position": 1e-3, "sigma_rotation": 0.01,
              "offset": [0.0, 0.01, 0.0], "rpy": [0.1, 0.0, 0.0]},
             {"name": "em_tip", "type": "pose", "frame": "tip", "sigma_position": 1e-3, "sigma_rotation": 0.01},
             {"name": "mk", "type": "marker", "member": "backbone", "s": 0.4, "sigma_position": 5e-4},
             {"name": "t_y", "type": "tension", "actuator": "tendon_y_pos", "sigma": 0.2}]
    sens = sn.sensors_from_list(items, mech)
    again = sn.sensors_from_list(sn.sensors_to_list(sens), mech)
    q = _q(load_model("tracked_arm"), 7, 0.3)
    ws = Workspace(mech.tree)
    _, w1 = sn.check_sensors(mech, sens)
    _, w2 = sn.check_sensors(mech, again)
    r1, r2 = sn.predict_readings(ws, q, sens, w1), sn.predict_readings(ws, q, again, w2)
    assert set(r1) == {"em0", "em_tip", "mk"}
    for k in r1:
        assert np.allclose(r1[k], r2[k], atol=1e-14)
    assert np.allclose(r1["em_tip"], sn.sensor_pose(mech, q, sn.PoseSensor("x", 1.0, 1.0, s=0.4)), atol=1e-12)
    with pytest.raises(ValueError, match=r"sensors\[0\]: unknown field\(s\) \['sigma_rotation'\]"):
        sn.sensors_from_list([{**items[2], "sigma_rotation": 0.1}], mech)
    with pytest.raises(ValueError, match=r"sensors\[0\].type"):
        sn.sensors_from_list([{**items[0], "type": "laser"}], mech)
    with pytest.raises(ValueError, match=r"sensors\[0\].s: missing"):
        sn.sensors_from_list([{k: v for k, v in items[0].items() if k != "s"}], mech)
