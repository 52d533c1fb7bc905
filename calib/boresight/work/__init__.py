"""Work arrays of the GLS estimator (:mod:`calib.boresight.gls`), reused across its iterations.

- :mod:`.normals`: the normal equations assembled as segment Gram matrices (points grouped by
  their unknowns and their knot interval; one batched matrix product per iteration into
  buffers allocated once per solution), never a sparse design matrix;
- :mod:`.schur`: the knots' share of the Schur complement, ``N_xa N_aa⁻¹ N_ax``, by blocks of
  knot rows from the few columns each block touches (only the last rows of each block carry
  the fill of ``L⁻¹ N_ax`` over all the unknowns), or densely where the blocks would touch
  most of them;
- :mod:`.banded`: a blocked triangular solve with a banded factor and many right-hand sides
  (level-3 BLAS instead of one level-2 sweep per column): the dense ``L⁻¹ N_ax`` (the dense
  reduction's, and the group tests');
- :mod:`.linearization`: the linearization of every iteration into buffers (only the columns
  the solution estimates, the poses' cos and sin kept);
- :mod:`.dense`: the reduced normal matrix's Cholesky factor, for the step, the convergence
  test's σ, the covariance and the log-determinant.
"""
