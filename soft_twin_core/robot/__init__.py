"""Robot files to a mechanism: the classic segments schema (:mod:`model`),
the tree schema and every robot as one :class:`mechanism.Mechanism`, URDF
export, material stresses and the plausibility checks of a file.
"""
