"""The plane-strain NumPy references of the engine's 2-D step, in their own layout.

* ``reference.step_np``: one MPM step (P2G, grid update with the boundary planes and the
  sidewall body force, G2P, the point law, the fluidity update of the nonlocal rheology);
* ``fluidity.fluidity_step_np``: the fluidity update alone;
* ``params``: their records' slots (``G_*`` of the grid record, ``S_*`` of the scalar state)
  and the codes (``BC_*``, ``TRANSFER_*``, ``ST_*``) the engine shares.

Plain NumPy, written apart from the compiled kernels (segmpm.engine), which the tests compare
with them to round-off after translating the engine's records into this layout
(tests/test_mpm_reference.py, tests/test_engine.py). The compiled plane-strain engine that once
lived here was removed on 2026-12-07 (docs/architecture.md, "One engine").
"""
