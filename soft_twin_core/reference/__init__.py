"""Independent references the tests hold the engine against: the numpy
PCS kinematics, statics, dynamics and generalised forces of the classic
rod, a numpy multibody by explicit Jacobians, and continuum (ODE) solutions
of the Cosserat rod. No production module imports them.
"""
