"""Structure from motion for thermal (and RGB) image blocks: tie points, tracks, orientation,
georeferencing, flight planning.

Layer: above ``adjustment/``, ``geometry/``, ``camera/`` and ``io/``; below ``dense/``, ``products/`` and
``pipeline/``. It writes the oriented-cameras file (:mod:`thermogrammetry.io.oriented`) that every
product reads.
"""
