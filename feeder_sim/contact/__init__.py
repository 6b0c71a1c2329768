"""The contact stage every stepping method shares.

* :mod:`.collision`, :mod:`._collision_kernels`: broad phase (sort and sweep) and narrow phase
  (vertex-edge contacts); the numpy reference beside its compiled port.
* :mod:`.candidates`: corners near pieces, watched continuously by the event-driven and
  impulse-based methods.
* :mod:`.dynamics`, :mod:`._island_kernels`: contact sets, Jacobians, Delassus matrices,
  islands, LCP assembly and Kawachi's friction rows; the time step's compiled island work.
* :mod:`.lcp`, :mod:`._lcp_kernels`: the frictional LCP (Baraff-Dantzig, Lemke, PGS, the
  residual every answer is checked with); the compiled Dantzig beside its reference.

Imports the model layer, numpy, scipy and numba only.
"""
