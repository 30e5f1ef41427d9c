"""The multibody engine: an immutable kinematic tree of rigid and soft
joints (:mod:`multibody`), its workspace, the loads it takes, and the free
algorithms over them (:mod:`algorithms`, :mod:`forces`, :mod:`integrators`),
on the compiled passes of :mod:`kernels`. No robot-file schema here.
"""
