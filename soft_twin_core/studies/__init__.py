"""Design studies: a study file to cases (:mod:`study`), one case
(:mod:`case`), running them on Dask (:mod:`cluster`), the summary
(:mod:`report`) and the ``study``/``workspace`` command lines (:mod:`cli`).
"""
