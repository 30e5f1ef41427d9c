"""The two structured arguments of every compiled pass: the model's packed
arrays (:class:`ModelArrays`, read-only) and the workspace's arrays
(:class:`WorkArrays`, written by the passes), plus the per-call loads
(:class:`LoadArrays`).

Python reads them as named tuples of arrays; the kernels receive the same
arrays as a numba *structref* (:func:`kernel_struct`), passed by reference:
a named tuple of ~50 arrays as an argument cost about a second of
compilation per function taking it, a structref about a tenth of that. The
structref's constructors below are compiled once and cached on disk.
"""

from collections import namedtuple

import numba as nb
import numpy as np
from numba.core import types
from numba.experimental import structref

from soft_twin_core.engine.joint_kinds import SOFT
from soft_twin_core.lie import Ad, se3_inv

def kernel_array(x, dtype=float):
    """``x`` as the compiled kernels take an array: C-contiguous, of
    ``dtype``, writable. numba types a read-only array (a model's frozen
    q0 or gravity) apart from a writable one, so one reaching a kernel
    compiles a second copy of it and of every pass it calls."""
    x = np.ascontiguousarray(x, dtype=dtype)
    return x if x.flags.writeable else x.copy()


ModelArrays = namedtuple("ModelArrays", [
    "parent",      # (n,) int: parent joint, -1 = world
    "kind",        # (n,) int: multibody.FIXED .. SOFT
    "placement",   # (n, 4, 4): input frame in the parent's output frame
    "Ad_pl_inv",   # (n, 6, 6): Ad(placement^-1) (parent output twist -> input frame)
    "axis",        # (n, 3): revolute / prismatic axis
    "iq", "iv", "nv",   # (n,) int: offsets into q and v, velocity size
    "inertia",     # (n, 6, 6): rigid spatial inertia about the output frame
    "rigid_mass",  # (n,) bool: the joint carries a rigid body
    "length",      # (n,) soft section length [m]
    "f0",          # (n, 6) reference strain
    "kmap",        # (n,) int: kinematic map of a soft section, 0 exponential, 1 Cayley
    "modes",       # (n, 6) int: free strain modes (first nv entries)
    "npt",         # (n,) int: quadrature points of the section
    "px", "pw",    # (n, P): abscissae [m] and weights [m]
    "mc",          # (n, 6): diagonal inertia density [kg/m, kg m]
    "Kb", "Db",    # (n, 6, 6): joint-space stiffness / damping blocks (nv x nv used)
    "q0",          # (nq,) reference configuration
    "ef_q", "ef_v",  # (nr,) int: the elastic fields' coordinates in q and v (multibody.ElasticField)
    "ef_P",        # (nz, nr): z = ef_P (q[ef_q] - q0[ef_q]) (the fields' blocks, block-diagonal)
    "ef_K", "ef_D",  # (nz, nz): their stiffness and damping in z
])

WorkArrays = namedtuple("WorkArrays", [
    "Jq",          # (n, 4, 4) joint transform input -> output
    "g_in", "g_out",   # (n, 4, 4) world poses of the input / output frames
    "Ad_J_inv",    # (n, 6, 6) Ad(Jq^-1): input-frame twist -> output frame
    "S",           # (n, 6, 6) motion subspace (output frame), nv columns used
    "strain", "strain_rate",   # (n, 6)
    "V", "A", "Vin", "Ain",    # (n, 6) body twist / acceleration of output and input frames
    "gp",          # (n, P, 4, 4) soft point pose in the input frame, exp(x f)
    "Ad_p_inv",    # (n, P, 6, 6) Ad(gp^-1)
    "Sp",          # (n, P, 6, 6) point subspace x T(x f) B
    "Vp", "Ap",    # (n, P, 6)
    "f",           # (n, 6) wrench at the output frame of everything beyond it
    "f_in",        # (n, 6) wrench transmitted through the joint, at its input frame
    "fp",          # (n, P, 6) inertial-minus-applied wrench of each soft point
    "IA", "pA",    # (n, 6, 6), (n, 6): articulated / composite inertia at output frames, bias
    "U", "Dinv",   # (n, 6, 6): ABA joint terms (input frame)
    "Sf", "Xf",    # (n, 6, 6): S and Ad(Jq^-1) at the factorisation's configuration
    "u",           # (n, 6)
    "As",          # (n, 6) accelerations of the solve pass
    "scratch",     # (16, 6, 6)
    "vscratch",    # (16, 6)
])

LoadArrays = namedtuple("LoadArrays", [
    "joint",       # (L,) int
    "x",           # (L,) abscissa in a soft section [m]; -1 = the joint's output frame
    "wrench",      # (L, 6) [force; moment]
    "world",       # (L,) bool: dead load (world axes at the point) or follower (body axes)
])


def empty_loads():
    return LoadArrays(np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 6)), np.zeros(0, np.bool_))


def pack_model(model):
    """ModelArrays of a :class:`multibody.Model`."""
    n = model.n_joints
    P = max([len(j.section.mass_points[0]) for j in model.joints if j.kind == SOFT] + [1])
    arr = dict(
        parent=model.parents.copy(), kind=model.kinds.copy(),
        placement=np.array([j.placement for j in model.joints]).reshape(n, 4, 4),
        Ad_pl_inv=np.array([Ad(se3_inv(j.placement)) for j in model.joints]).reshape(n, 6, 6),
        axis=np.array([j.axis for j in model.joints], dtype=float).reshape(n, 3),
        iq=model.idx_q.copy(), iv=model.idx_v.copy(),
        nv=np.array([j.nv for j in model.joints], dtype=np.int64),
        inertia=np.array([j.inertia for j in model.joints], dtype=float).reshape(n, 6, 6),
        rigid_mass=np.array([bool(np.any(j.inertia != 0)) for j in model.joints], dtype=np.bool_),
        length=np.zeros(n), f0=np.zeros((n, 6)), kmap=np.zeros(n, np.int64), modes=np.zeros((n, 6), np.int64),
        npt=np.zeros(n, np.int64), px=np.zeros((n, P)), pw=np.zeros((n, P)), mc=np.zeros((n, 6)),
        Kb=np.zeros((n, 6, 6)), Db=np.zeros((n, 6, 6)), q0=model.q0.copy(),
    )
    for i, j in enumerate(model.joints):
        if j.kind == SOFT:
            s = j.section
            m = s.modes
            arr["length"][i] = s.length
            arr["f0"][i] = s.f0
            arr["kmap"][i] = 1 if s.kinematic_map == "cayley" else 0
            arr["modes"][i, :len(m)] = m
            xg, wg = s.mass_points
            arr["npt"][i] = len(xg)
            arr["px"][i, :len(xg)] = xg
            arr["pw"][i, :len(xg)] = wg
            arr["mc"][i] = np.diag(s.Mc) if np.ndim(s.Mc) == 2 else s.Mc
            k = len(m)
            arr["Kb"][i, :k, :k] = s.length * s.K[np.ix_(m, m)]
            arr["Db"][i, :k, :k] = s.length * s.D[np.ix_(m, m)]
        elif j.nv == 1:
            arr["Kb"][i, 0, 0] = j.stiffness
            arr["Db"][i, 0, 0] = j.damping
    arr.update(_elastic_fields(model, arr))
    return ModelArrays(**{k: np.ascontiguousarray(v) for k, v in arr.items()})


def _elastic_fields(model, arr):
    """The packed :class:`multibody.ElasticField` s (one block-diagonal
    P, K, D over their coordinates), their joints' own blocks zeroed."""
    fields = model.elastic_fields
    nr = sum(f.P.shape[1] for f in fields)
    nz = sum(f.P.shape[0] for f in fields)
    out = dict(ef_q=np.zeros(nr, np.int64), ef_v=np.zeros(nr, np.int64), ef_P=np.zeros((nz, nr)),
               ef_K=np.zeros((nz, nz)), ef_D=np.zeros((nz, nz)))
    r = c = 0
    for f in fields:
        for j in f.joints:
            k = model.joints[j].nv
            out["ef_q"][r:r + k] = model.idx_q[j] + np.arange(k)
            out["ef_v"][r:r + k] = model.idx_v[j] + np.arange(k)
            arr["Kb"][j] = 0.0
            arr["Db"][j] = 0.0
            r += k
        nz_f, nr_f = f.P.shape
        out["ef_P"][c:c + nz_f, r - nr_f:r] = f.P
        out["ef_K"][c:c + nz_f, c:c + nz_f] = f.K
        out["ef_D"][c:c + nz_f, c:c + nz_f] = f.D
        c += nz_f
    return out


def make_work(mo):
    """WorkArrays sized for the packed model ``mo`` (allocated once)."""
    n = mo.parent.shape[0]
    P = mo.px.shape[1]
    z = np.zeros
    return WorkArrays(
        Jq=z((n, 4, 4)), g_in=z((n, 4, 4)), g_out=z((n, 4, 4)), Ad_J_inv=z((n, 6, 6)), S=z((n, 6, 6)),
        strain=z((n, 6)), strain_rate=z((n, 6)), V=z((n, 6)), A=z((n, 6)), Vin=z((n, 6)), Ain=z((n, 6)),
        gp=z((n, P, 4, 4)), Ad_p_inv=z((n, P, 6, 6)), Sp=z((n, P, 6, 6)), Vp=z((n, P, 6)), Ap=z((n, P, 6)),
        f=z((n, 6)), f_in=z((n, 6)), fp=z((n, P, 6)), IA=z((n, 6, 6)), pA=z((n, 6)), U=z((n, 6, 6)),
        Dinv=z((n, 6, 6)), Sf=z((n, 6, 6)), Xf=z((n, 6, 6)), u=z((n, 6)), As=z((n, 6)), scratch=z((16, 6, 6)), vscratch=z((16, 6)))


# ----------------------------------------------------------------------------
# structrefs for the kernels
# ----------------------------------------------------------------------------

class ArraysType(types.StructRef):
    """The numba type of a structref of arrays (each kind registers a
    subclass of its own, defined at module level: numba's cache names it)."""

    def preprocess_fields(self, fields):
        return tuple((n, types.unliteral(t)) for n, t in fields)


def declare(proxy, typ, fields):
    """``proxy`` (a StructRefProxy class) as the Python side of ``typ`` (a
    registered :class:`ArraysType`) with ``fields``."""
    structref.define_constructor(proxy, typ, list(fields))
    structref.define_boxing(typ, proxy)


@structref.register
class ModelArraysType(ArraysType):
    pass


@structref.register
class WorkArraysType(ArraysType):
    pass


class ModelArraysRef(structref.StructRefProxy):
    """Kernel view of :class:`ModelArrays` (same arrays)."""


class WorkArraysRef(structref.StructRefProxy):
    """Kernel view of :class:`WorkArrays` (same arrays)."""


declare(ModelArraysRef, ModelArraysType, ModelArrays._fields)
declare(WorkArraysRef, WorkArraysType, WorkArrays._fields)


@nb.njit(cache=True)
def _make_model_ref(
        parent, kind, placement, Ad_pl_inv, axis, iq, iv, nv, inertia, rigid_mass, length, f0,
        kmap, modes, npt, px, pw, mc, Kb, Db, q0, ef_q, ef_v, ef_P, ef_K, ef_D):
    return ModelArraysRef(
        parent, kind, placement, Ad_pl_inv, axis, iq, iv, nv, inertia, rigid_mass, length, f0,
        kmap, modes, npt, px, pw, mc, Kb, Db, q0, ef_q, ef_v, ef_P, ef_K, ef_D)


@nb.njit(cache=True)
def _make_work_ref(
        Jq, g_in, g_out, Ad_J_inv, S, strain, strain_rate, V, A, Vin, Ain, gp, Ad_p_inv, Sp, Vp,
        Ap, f, f_in, fp, IA, pA, U, Dinv, Sf, Xf, u, As, scratch, vscratch):
    return WorkArraysRef(
        Jq, g_in, g_out, Ad_J_inv, S, strain, strain_rate, V, A, Vin, Ain, gp, Ad_p_inv, Sp, Vp,
        Ap, f, f_in, fp, IA, pA, U, Dinv, Sf, Xf, u, As, scratch, vscratch)


class ArraysRef(structref.StructRefProxy):
    """Named arrays as the kernels take them: a structref, passed by
    reference (a named tuple's arrays are typed one by one at every call
    from Python: 2-4 us for 12-17 arrays, a structref under 1 us; and it
    compiles faster). Python reads the same arrays as attributes; pickled
    as its arrays. A subclass names its ``FIELDS`` and gets its compiled
    constructor (cached on disk) as ``make``; :meth:`of` builds one."""
    FIELDS = ()
    make = None

    @classmethod
    def of(cls, *arrays):
        """One of these arrays, in FIELDS' order (C-contiguous; shared, not copied)."""
        arrays = tuple(np.ascontiguousarray(x) for x in arrays)
        out = cls.make(*arrays)
        out.__dict__["arrays"] = arrays
        out.__dict__.update(zip(cls.FIELDS, arrays))      # read as plain attributes (50 ns, not 0.5 us)
        return out

    def __reduce__(self):
        return type(self).of, self.__dict__["arrays"]


def kernel_struct(arrays):
    """The structref of a ModelArrays or WorkArrays named tuple."""
    if isinstance(arrays, ModelArrays):
        return _make_model_ref(*arrays)
    return _make_work_ref(*arrays)
