"""Solving a mechanism: static equilibrium (:mod:`equilibrium`, compiled
Newton without constraints), the constrained statics and dynamics with joint
control and closed chains (:mod:`constrained`), and what a state gives the
user (:mod:`outputs`).
"""
