"""Tip paths, the planner, plan files, inverse kinematics of shapes and
the reachable workspace (:mod:`reach`).
"""
