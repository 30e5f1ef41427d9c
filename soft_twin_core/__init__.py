"""soft_twin_core: ROS-free Cosserat-rod (PCS) model of soft continuum robots.

Conventions (see docs in each module): 6-vectors are ordered [linear; angular],
expressed in the local (body) frame of the cross-section unless a name says
``_world``. SI units, radians.
"""

__version__ = "0.1.0"
