"""Measurement models (soft_twin_core.sensors): predictions against the numpy
kinematics reference, analytic Jacobians against central finite
differences, the actuation matrix against the reference residual, input
checks."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from soft_twin_core import kinematics as kin
from soft_twin_core import lie
from soft_twin_core import sensors as sn
from soft_twin_core import statics as st
from soft_twin_core.loads import Loads
from soft_twin_core.model import load_model, model_from_dict, benchmark_cantilever_dict


@pytest.fixture(scope="module")
def arm():
    return load_model("tracked_arm")


@pytest.fixture(scope="module")
def arm_all_modes():
    return model_from_dict(benchmark_cantilever_dict(n_sections=5, free_modes="all", length=0.4))


def _q(model, seed=0, scale=1.0):
    rng = np.random.default_rng(seed)
    return model.q0 + scale * rng.normal(size=model.n_dof)


def _placement():
    P = np.eye(4)
    P[:3, :3] = lie.exp_so3([0.3, -0.2, 0.5])
    P[:3, 3] = [0.004, -0.01, 0.007]
    return P


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
    model = request.getfixturevalue(which)
    q = _q(model, 1)
    s = s_frac * model.total_length
    sen = sn.PoseSensor("em", s, 1e-3, 1e-2, _placement())
    ref = kin.poses(model, q[None], [s])[0, 0] @ _placement()     # numpy chain (batch path)
    assert np.allclose(sn.sensor_pose(model, q, sen), ref, atol=1e-12)
    mk = sn.PositionMarker("mk", s, 1e-3, np.array([0.0, 0.005, -0.003]))
    g = kin.poses(model, q[None], [s])[0, 0]
    assert np.allclose(sn.predict_measurement(model, q, mk), g[:3, 3] + g[:3, :3] @ [0.0, 0.005, -0.003],
                       atol=1e-12)


@pytest.mark.parametrize("which", ["arm", "arm_all_modes"])
def test_pose_residual_jacobian_matches_finite_differences(request, which):
    model = request.getfixturevalue(which)
    q = _q(model, 2)
    sen = sn.PoseSensor("em", 0.7 * model.total_length, 1e-3, 1e-2, _placement())
    # a measurement away from h(q) so that the rotation residual (and Jr^-1) is far from identity
    z = sn.sensor_pose(model, q, sen).copy()
    z[:3, :3] = z[:3, :3] @ lie.exp_so3([0.4, 0.7, -0.5])
    z[:3, 3] += [0.01, -0.02, 0.03]
    e, H = sn.residual_and_jacobian(model, q, sen, z)
    assert np.linalg.norm(e[3:]) > 0.9                    # a large rotation error really is tested
    Hfd = _fd(lambda x: sn.residual(model, x, sen, z), q)
    assert np.abs(H - Hfd).max() <= 1e-7 * max(1.0, np.abs(Hfd).max())


def test_marker_residual_jacobian_matches_finite_differences(arm):
    q = _q(arm, 3)
    mk = sn.PositionMarker("mk", 0.31, 1e-3, np.array([0.002, 0.009, -0.004]))
    z = np.array([0.3, 0.1, -0.1])
    e, H = sn.residual_and_jacobian(arm, q, mk, z)
    assert e.shape == (3,) and H.shape == (3, arm.n_dof)
    Hfd = _fd(lambda x: sn.residual(arm, x, mk, z), q)
    assert np.abs(H - Hfd).max() <= 1e-7 * np.abs(Hfd).max()


def test_rotation_residual_sign_and_noise_level():
    """e_R = log(R_meas^T R): for R_meas = R exp(n) it is exactly -n, and the
    simulated noise has the stated standard deviations."""
    rng = np.random.default_rng(4)
    sen = sn.PoseSensor("em", 0.0, 2e-3, 0.03)
    T = np.eye(4)
    T[:3, :3] = lie.exp_so3([0.1, 0.2, 0.3])
    samples = np.array([sn.simulate_measurement(T, sen, rng) for _ in range(4000)])
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
    sen = sn.PoseSensor("em", 0.0, 1e-3, 1e-2)
    assert np.allclose(sn.measurement_vector(sen, np.r_[[1, 2, 3], quat]), T)


def test_actuation_matrix_matches_reference_residual(arm):
    """B(q) = d tau_act/du: the numpy reference residual R = K (q - q0) - Q
    - tau_act(q, u) is linear in u, so column k is R(u=0) - R(u=e_k)."""
    q = _q(arm, 6, 0.5)
    B = sn.actuation_matrix(arm, q)
    loads = Loads(gravity=False)
    R0 = st.residual(arm, q, np.zeros(4), loads)
    ref = np.stack([R0 - st.residual(arm, q, e, loads) for e in np.eye(4)], axis=1)
    assert np.abs(ref).max() > 1e-4
    assert np.allclose(B, ref, atol=1e-12 * np.abs(ref).max())


@pytest.mark.parametrize("bad, match", [
    (np.full(3, np.nan), "NaN"), (np.zeros(4), "shape"), (np.zeros((3, 3)), "shape")])
def test_bad_measurements_are_refused(bad, match):
    mk = sn.PositionMarker("mk", 0.1, 1e-3)
    em = sn.PoseSensor("em", 0.1, 1e-3, 1e-2)
    with pytest.raises(ValueError, match=match):
        sn.measurement_vector(mk if bad.ndim == 1 else em, bad)


def test_sensor_configuration_is_checked(arm):
    with pytest.raises(ValueError, match=r"sensors\[1\].*s: expected an arc length"):
        sn.check_sensors(arm, [sn.PositionMarker("a", 0.1, 1e-3), sn.PositionMarker("b", 0.5, 1e-3)])
    with pytest.raises(ValueError, match="duplicate"):
        sn.check_sensors(arm, [sn.PositionMarker("a", 0.1, 1e-3), sn.PositionMarker("a", 0.2, 1e-3)])
    with pytest.raises(ValueError, match="unknown actuator"):
        sn.check_sensors(arm, [sn.TensionSensor("t", "nope", 0.1)])
    with pytest.raises(ValueError, match="positive"):
        sn.check_sensors(arm, [sn.PoseSensor("a", 0.1, 1e-3, 0.0)])
