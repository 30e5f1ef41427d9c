"""Explicit sectional properties (``sectional`` instead of ``cross_section`` +
``material``) and the Simo & Vu-Quoc right-angle frame that uses them."""
import copy
import math
import os

import numpy as np
import pytest

from soft_twin_core.robot.model import ModelError, load_model, model_from_dict

ROOT = os.path.join(os.path.dirname(__file__), "..", "..")
ROBOT = os.path.join(ROOT, "config", "robots", "simo_frame.yaml")
SCENARIO = os.path.join(ROOT, "config", "scenarios", "simo_frame_dynamics.yaml")

STIFF = {"EA": 3.0e6, "GA2": 1.1e6, "GA3": 1.2e6, "GJ": 4.0e3, "EI2": 5.0e3, "EI3": 6.0e3}
INERTIA = {"mass_per_length": 1.5, "J1": 21.0, "J2": 11.0, "J3": 12.0}
DAMPING = {"EA": 7.0, "GA2": 0.0, "GA3": 0.5, "GJ": 2.0, "EI2": 3.0, "EI3": 4.0}


def two_segment_dict(sectional=None):
    """A conventional first member and a ``sectional`` second one, so that
    error messages must name ``segments[1]``."""
    return {
        "name": "two", "gravity": [0.0, 0.0, 0.0],
        "segments": [
            {"name": "a", "length": 0.3, "sections": 2,
             "cross_section": {"shape": "solid_circle", "radius": 0.01},
             "material": {"youngs_modulus": 1.0e6, "poisson_ratio": 0.5, "density": 1000.0},
             "offset_to_next": {"rpy": [0.0, 0.0, 0.5]}},
            {"name": "b", "length": 0.6, "sections": 3, "free_modes": "all",
             "sectional": copy.deepcopy(sectional if sectional is not None else
                                        {"stiffness": STIFF, "inertia": INERTIA, "damping": DAMPING})},
        ],
    }


# ------------------------------------------------------------ (a) exact values

def test_explicit_sectional_values_give_exact_diagonals():
    m = model_from_dict(two_segment_dict())
    k = np.array([STIFF[n] for n in ("EA", "GA2", "GA3", "GJ", "EI2", "EI3")])
    c = np.array([DAMPING[n] for n in ("EA", "GA2", "GA3", "GJ", "EI2", "EI3")])
    mu = INERTIA["mass_per_length"]
    md = np.array([mu, mu, mu, INERTIA["J1"], INERTIA["J2"], INERTIA["J3"]])
    secs = [s for s in m.sections if s.segment == "b"]
    assert len(secs) == 3
    for s in secs:
        # exactly the given numbers, and nothing off the diagonal
        assert np.array_equal(s.K, np.diag(k))
        assert np.array_equal(s.D, np.diag(c))
        assert np.array_equal(s.M, np.diag(md))
        assert s.length == pytest.approx(0.2, abs=1e-15)
    # the generalised matrices of the free modes (all six): length * diagonal
    Kb, Db = m.K_q[12:, 12:], m.D_q[12:, 12:]
    assert np.allclose(Kb, np.kron(np.eye(3), np.diag(0.2 * k)), rtol=1e-15, atol=0)
    assert np.allclose(Db, np.kron(np.eye(3), np.diag(0.2 * c)), rtol=1e-15, atol=0)
    assert m.mass == pytest.approx(0.3 * 1000 * math.pi * 0.01**2 + 0.6 * mu, rel=1e-14)


def test_damping_is_optional_and_partial():
    m = model_from_dict(two_segment_dict({"stiffness": STIFF, "inertia": INERTIA}))
    assert np.array_equal(m.sections[-1].D, np.zeros((6, 6)))
    m = model_from_dict(two_segment_dict({"stiffness": STIFF, "inertia": INERTIA, "damping": {"GJ": 2.5}}))
    assert np.array_equal(m.sections[-1].D, np.diag([0, 0, 0, 2.5, 0, 0]))
    m = model_from_dict(two_segment_dict({"stiffness": STIFF, "inertia": INERTIA, "damping": None}))
    assert np.array_equal(m.sections[-1].D, np.zeros((6, 6)))


# ------------------------------------------- (b) both paths give the same model

def test_sectional_equals_cross_section_and_material():
    r, E, nu, rho, eta = 0.012, 2.0e6, 0.45, 1100.0, 3.0e3
    G = E / (2 * (1 + nu))
    A, I = math.pi * r**2, math.pi * r**4 / 4
    J = 2 * I
    geo = {"name": "geo", "gravity": [0, 0, -9.81], "segments": [{
        "length": 0.4, "sections": 4, "free_modes": "all",
        "reference_strain": [1.0, 0.0, 0.0, 0.5, 1.0, -2.0],
        "cross_section": {"shape": "solid_circle", "radius": r},
        "material": {"youngs_modulus": E, "poisson_ratio": nu, "density": rho, "viscosity": eta}}]}
    sec = copy.deepcopy(geo)
    seg = sec["segments"][0]
    del seg["cross_section"], seg["material"]
    # the textbook values of a solid circle (Kelvin-Voigt: 3x on the normal strains)
    seg["sectional"] = {
        "stiffness": {"EA": E * A, "GA2": G * A, "GA3": G * A, "GJ": G * J, "EI2": E * I, "EI3": E * I},
        "inertia": {"mass_per_length": rho * A, "J1": rho * J, "J2": rho * I, "J3": rho * I},
        "damping": {"EA": 3 * eta * A, "GA2": eta * A, "GA3": eta * A, "GJ": eta * J,
                    "EI2": 3 * eta * I, "EI3": 3 * eta * I}}
    m1, m2 = model_from_dict(geo), model_from_dict(sec)
    assert m1.n_dof == m2.n_dof == 24
    for name in ("K_q", "D_q", "q0", "f0", "lengths", "free_mask", "offsets"):
        np.testing.assert_allclose(getattr(m2, name), getattr(m1, name), rtol=1e-14, atol=0, err_msg=name)
    for s1, s2 in zip(m1.sections, m2.sections):
        for name in ("K", "D", "M"):
            np.testing.assert_allclose(getattr(s2, name), getattr(s1, name), rtol=1e-14, atol=0, err_msg=name)
    assert m2.mass == pytest.approx(m1.mass, rel=1e-14)


# ------------------------------------------------------------ (c) bad fields

def _patched(path, value):
    d = two_segment_dict()
    t = d["segments"][1]
    for k in path[:-1]:
        t = t[k]
    if value is _DELETE:
        del t[path[-1]]
    else:
        t[path[-1]] = value
    return d


_DELETE = object()
_W = r"segments\[1\]\.sectional"


@pytest.mark.parametrize("path,value,msg", [
    (("sectional", "stiffness", "EA"), -1.0, _W + r"\.stiffness\.EA: must be > 0, got -1\.0"),
    (("sectional", "stiffness", "GA2"), 0, _W + r"\.stiffness\.GA2: must be > 0, got 0\.0"),
    (("sectional", "stiffness", "GJ"), float("nan"), _W + r"\.stiffness\.GJ: must be finite, got nan"),
    (("sectional", "stiffness", "EI3"), float("inf"), _W + r"\.stiffness\.EI3: must be finite, got inf"),
    (("sectional", "stiffness", "EI2"), "stiff", _W + r"\.stiffness\.EI2: expected a number, got 'stiff'"),
    (("sectional", "stiffness", "GA3"), True, _W + r"\.stiffness\.GA3: expected a number, got True"),
    (("sectional", "stiffness", "EI3"), _DELETE, _W + r"\.stiffness\.EI3: missing \(required\)"),
    (("sectional", "stiffness", "EI4"), 1.0, _W + r"\.stiffness: unknown field\(s\) \['EI4'\]"),
    (("sectional", "stiffness"), [1, 2, 3], _W + r"\.stiffness: expected a mapping"),
    (("sectional", "stiffness"), _DELETE, _W + r"\.stiffness: missing \(required\)"),
    (("sectional", "inertia", "mass_per_length"), -2.0,
     _W + r"\.inertia\.mass_per_length: must be > 0, got -2\.0"),
    (("sectional", "inertia", "J1"), 0.0, _W + r"\.inertia\.J1: must be > 0, got 0\.0"),
    (("sectional", "inertia", "J2"), float("nan"), _W + r"\.inertia\.J2: must be finite, got nan"),
    (("sectional", "inertia", "J3"), "heavy", _W + r"\.inertia\.J3: expected a number, got 'heavy'"),
    (("sectional", "inertia", "J2"), _DELETE, _W + r"\.inertia\.J2: missing \(required\)"),
    (("sectional", "inertia", "rho"), 1.0, _W + r"\.inertia: unknown field\(s\) \['rho'\]"),
    (("sectional", "inertia"), _DELETE, _W + r"\.inertia: missing \(required\)"),
    (("sectional", "damping", "GA2"), -1.0, _W + r"\.damping\.GA2: must be >= 0, got -1\.0"),
    (("sectional", "damping", "EA"), float("nan"), _W + r"\.damping\.EA: must be finite, got nan"),
    (("sectional", "damping", "EI2"), "x", _W + r"\.damping\.EI2: expected a number, got 'x'"),
    (("sectional", "damping", "mass"), 1.0, _W + r"\.damping: unknown field\(s\) \['mass'\]"),
    (("sectional", "damping"), 5, _W + r"\.damping: expected a mapping, got 5"),
    (("sectional", "viscosity"), 1.0, _W + r": unknown field\(s\) \['viscosity'\]"),
    (("sectional",), None, _W + r": expected a mapping, got None"),
    (("sectional",), "stiff", _W + r": expected a mapping, got 'stiff'"),
    # both forms, or neither
    (("material",), {"youngs_modulus": 1e6, "density": 1000.0},
     _W + r": give either sectional or cross_section \+ material, not both \(also got material\)"),
    (("cross_section",), {"shape": "solid_circle", "radius": 0.01},
     _W + r": give either sectional or cross_section \+ material, not both \(also got cross_section\)"),
    (("sectional",), _DELETE, r"segments\[1\]\.cross_section: missing \(required"),
])
def test_bad_sectional_fields_are_named(path, value, msg):
    with pytest.raises(ModelError, match=msg):
        model_from_dict(_patched(path, value))


def test_both_forms_with_all_three_fields_is_an_error():
    d = two_segment_dict()
    d["segments"][1]["cross_section"] = {"shape": "solid_circle", "radius": 0.01}
    d["segments"][1]["material"] = {"youngs_modulus": 1e6, "density": 1000.0}
    with pytest.raises(ModelError, match=_W + r": .*not both \(also got cross_section and material\)"):
        model_from_dict(d)


def test_neither_form_names_the_missing_field():
    d = two_segment_dict()
    del d["segments"][1]["sectional"]
    d["segments"][1]["cross_section"] = {"shape": "solid_circle", "radius": 0.01}
    with pytest.raises(ModelError, match=r"segments\[1\]\.material: missing \(required"):
        model_from_dict(d)


@pytest.mark.filterwarnings("ignore::soft_twin_core.limits.PlausibilityWarning")   # fuzzed files: implausible on purpose
def test_sectional_fuzz_only_model_errors():
    """Any single corrupted field of a sectional description gives a
    ModelError, never a TypeError or the like from deep inside."""
    from conftest import single_field_corruptions
    values = [None, -1, 0, 1e300, float("nan"), float("inf"), "x", [], {}, [1, 2], True, "1e9", {"a": 1}, 3]
    base = two_segment_dict()
    with np.errstate(all="ignore"):   # a 1e300 angle in offset_to_next overflows harmlessly
        for d in single_field_corruptions(base, values, 400, seed=3):
            try:
                model_from_dict(d)
            except ModelError:
                pass


# ------------------------------------------- (d) the Simo & Vu-Quoc frame files

def test_simo_frame_robot_loads():
    m = load_model(ROBOT)
    assert m.n_sections == 10 and m.n_dof == 60 and m.total_length == pytest.approx(20.0)
    assert np.array_equal(m.gravity, np.zeros(3))
    for s in m.sections:
        assert np.array_equal(np.diag(s.K), [1e6, 1e6, 1e6, 1e3, 1e3, 1e3])
        assert np.array_equal(np.diag(s.M), [1.0, 1.0, 1.0, 20.0, 10.0, 10.0])
        assert np.array_equal(s.D, np.zeros((6, 6)))
    from soft_twin_core.reference import kinematics as kin
    tip = kin.tip_pose(m, m.q0)
    assert np.allclose(tip[:3, 3], [10.0, 10.0, 0.0], atol=1e-12)     # right angle in the x-y plane
    assert np.allclose(tip[:3, 0], [0.0, 1.0, 0.0], atol=1e-12)       # second member along +y
    elbow = kin.poses(m, m.q0, np.array([10.0]))[0]
    assert np.allclose(elbow[:3, 3], [10.0, 0.0, 0.0], atol=1e-12)


def test_simo_frame_scenario_profile_and_short_run():
    from soft_twin_core.files.scenario import load_scenario, run_dynamics
    sc = load_scenario(SCENARIO)
    assert sc.gravity is False and sc.model.n_dof == 60
    assert len(sc.loads) == 1

    def elbow_force(t):
        lo = sc.loads_at(t)
        assert len(lo.point) == 1 and not lo.distributed
        p = lo.point[0]
        assert p.s == pytest.approx(10.0) and p.frame == "world"
        w = np.asarray(p.wrench)
        assert np.all(w[[0, 1, 3, 4, 5]] == 0.0)
        return w[2]
    for t in (0.0, 0.25, 0.5, 0.9, 1.0):
        assert elbow_force(t) == pytest.approx(50.0 * t, abs=1e-12)
    for t in (1.2, 1.5, 2.0):
        assert elbow_force(t) == pytest.approx(50.0 * (2.0 - t), abs=1e-12)
    assert elbow_force(1.5) == pytest.approx(25.0, abs=1e-12)
    for t in (2.5, 3.0, 30.0):
        assert elbow_force(t) == 0.0

    out = run_dynamics(sc, 0.05, 0.01)
    assert "error" not in out
    assert len(out["time"]) == 6 and out["time"][-1] == pytest.approx(0.05)
    tip = np.array(out["tip_position"])
    assert np.all(np.isfinite(tip))
    assert np.allclose(tip[0], [10.0, 10.0, 0.0], atol=1e-12)
    # the elbow is pushed up: the frame has started to move out of plane, only just
    assert 0.0 < tip[-1, 2] < 1e-3
