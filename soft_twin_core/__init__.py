"""soft_twin_core: ROS-free digital twin of soft robots (Cosserat rods, PCS)
on a multibody engine.

Conventions (see docs/CONVENTIONS.md): 6-vectors are ordered [linear;
angular], expressed in the local (body) frame of the cross-section unless a
name says ``_world``. SI units, radians.

The names a user needs most are importable from here, e.g.
``from soft_twin_core import load_mechanism, solve_equilibrium``; each
lives in one module of its folder (see :data:`PUBLIC`) and is imported on
first use, so ``import soft_twin_core`` stays light (no numba).
"""

__version__ = "0.1.0"

#: public name -> the module that defines it
PUBLIC = {
    "load_mechanism": "soft_twin_core.robot.mechanism",
    "Mechanism": "soft_twin_core.robot.mechanism",
    "load_model": "soft_twin_core.robot.model",
    "Loads": "soft_twin_core.engine.loads",
    "PointLoad": "soft_twin_core.engine.loads",
    "DistributedLoad": "soft_twin_core.engine.loads",
    "FrameLoad": "soft_twin_core.solve.constrained",
    "solve_equilibrium": "soft_twin_core.solve.constrained",
    "MechanismSimulator": "soft_twin_core.solve.constrained",
    "state_outputs": "soft_twin_core.solve.outputs",
    "load_scenario": "soft_twin_core.files.scenario",
    "Twin": "soft_twin_core.twin",
}
__all__ = sorted(PUBLIC) + ["__version__"]


def __getattr__(name):
    """The public names, imported on first use (PEP 562)."""
    if name not in PUBLIC:
        raise AttributeError(f"module 'soft_twin_core' has no attribute {name!r}")
    import importlib            # here: only when a public name is first used
    value = getattr(importlib.import_module(PUBLIC[name]), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(PUBLIC))
