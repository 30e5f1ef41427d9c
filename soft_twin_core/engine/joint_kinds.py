"""The joint kinds of the multibody engine, defined once (ground floor: no
import of the package). The compiled kernels compare ``Model.kind[i]`` with
these integers (numba freezes module-level integers at compile time)."""

FIXED, REVOLUTE, PRISMATIC, SPHERICAL, FREE, SOFT = range(6)
JOINT_KINDS = ("fixed", "revolute", "prismatic", "spherical", "free", "soft")    # name of kind k: JOINT_KINDS[k]
RIGID_JOINT_TYPES = {name: k for k, name in enumerate(JOINT_KINDS) if k != SOFT}  # a robot file's joint ``type``
NQ = {FIXED: 0, REVOLUTE: 1, PRISMATIC: 1, SPHERICAL: 4, FREE: 7}     # a rigid joint's configuration size
NV = {FIXED: 0, REVOLUTE: 1, PRISMATIC: 1, SPHERICAL: 3, FREE: 6}     # and velocity size
