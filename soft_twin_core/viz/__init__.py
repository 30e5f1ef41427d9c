"""What a person looks at: snapshots of the robot (:mod:`scene`), figures,
animations, the ``--plot``/``--animate`` options and the live browser view.
"""
