"""Scenario files and runs of any robot (:mod:`scenario` parses,
:mod:`runs` computes), their time line, and MCAP recordings.
"""
