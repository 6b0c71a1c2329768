"""The contact stage every stepping method shares.

* :mod:`.collision`: vertex-edge contacts of polygon bodies (``find_contacts``), the broad
  phase alone (``candidate_pairs``) and gaps of known features at another configuration.
* :mod:`._collision_kernels`: the compiled narrow phase and contact clean-up of
  ``find_contacts``.
* :mod:`.candidates`: corners near pieces, watched continuously by the event-driven and
  impulse-based methods.
* :mod:`.dynamics`: contact sets, Jacobians, Delassus matrices, islands, LCP assembly,
  Kawachi's friction rows and the solver statistics.
* :mod:`._island_kernels`: the time step's compiled island work (islands, contact rows,
  Dantzig and projected Gauss-Seidel per island, impulses applied to velocities).
* :mod:`.lcp`: the frictional LCP in Python (Baraff-Dantzig, Lemke, PGS, the fallback
  ladder and the residual every answer is checked with).
* :mod:`._lcp_kernels`: the compiled Dantzig beside that reference, the compiled residual,
  and the contact LCP reduced, solved and re-solved on known row states.

Imports the model layer, numpy, scipy and numba only.
"""
