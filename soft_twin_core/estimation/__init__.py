"""Sensors, the extended Kalman filter (:mod:`ekf`) and calibration of a
robot's parameters from recorded data (:mod:`calibration`,
:mod:`mcap_data`, the ``calibrate`` command line in :mod:`cli`).
"""
