"""Robot-file schema additions: the per-actuator ``limit`` and the shared
number parser."""
import copy
import math

import pytest

from soft_twin_core.robot.model import ModelError, model_from_dict, benchmark_cantilever_dict


def _robot(**act):
    d = benchmark_cantilever_dict(n_sections=2)
    a = {"name": "t", "type": "tendon", "offset": [0.005, 0.0]}
    a.update(act)
    d["actuators"] = [a]
    return d


def test_actuator_limit_default_is_unlimited():
    m = model_from_dict(_robot())
    assert m.actuators[0].limit == math.inf
    assert isinstance(m.actuators[0].limit, float)
    m = model_from_dict(_robot(limit=None))
    assert m.actuators[0].limit == math.inf


@pytest.mark.parametrize("value, expected", [(40, 40.0), (12.5, 12.5), ("1.0e6", 1e6), ("2e5", 2e5)])
def test_actuator_limit_declared(value, expected):
    m = model_from_dict(_robot(limit=value))
    assert m.actuators[0].limit == expected
    assert isinstance(m.actuators[0].limit, float)


def test_chamber_limit_is_pressure():
    m = model_from_dict(_robot(type="chamber", area=4e-5, limit=5.0e4))
    assert m.actuators[0].kind == "chamber" and m.actuators[0].limit == 5.0e4


@pytest.mark.parametrize("bad", [0, -1.0, float("inf"), float("nan"), "abc", True, [1.0]])
def test_actuator_limit_invalid(bad):
    with pytest.raises(ModelError, match=r"actuators\[0\]\.limit"):
        model_from_dict(_robot(limit=bad))
