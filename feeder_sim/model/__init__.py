"""The model: a scene file becomes a world of bodies as arrays, with its drives.

* :mod:`.geometry`: polygons (area, centroid, inertia, convexity, convex decomposition).
* :mod:`.scene`: YAML scene files to validated dataclasses; the lists of stepping methods and
  body kinds.
* :mod:`.world`: bodies as arrays, the state, energies, the contact material table.
* :mod:`.arrays`: a world's constants as the compiled stepping methods take them (``BodyArrays``,
  ``ShapeArrays``).
* :mod:`.vibration`: the prescribed motion of vibrating bodies and the commands that change it.
* :mod:`.builders`: conveyor and test scenes from design numbers.

Imports numpy, scipy and PyYAML only: nothing of the contact stage, the stepping methods or
any output.
"""
