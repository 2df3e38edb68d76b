"""Quantum affine bodies (paper, section "General quantization ideas" and the last section).

Layers, bottom to top (no module imports one above it; only core and kinematics modules of
:mod:`affinebody` are used, except the application layer ``config`` / ``cli``):

- :mod:`.levels`       results (Sector, Level, Block, Spectrum), Settings, AffineInertia, the
                       merging and counting of levels (LevelCollector).
- :mod:`.bases`        Gauss / Laguerre / Hermite bases, the Haar conjugation g = sqrt(x/sinh x),
                       the dense block solver with its error estimate.
- :mod:`.intervals`    interval arithmetic on potential expressions (certified inf V on cells);
                       :class:`~.intervals.ExpressionPotential`, a potential that keeps its text.
- :mod:`.bounds`       certified lower bounds of each n = 2 sector's lowest level: the stopping
                       rule of the sector search (docs/theory/two-polar.md).
- :mod:`.n2`           n = 2: the reduced blocks of every sector (s, k) and the sector search.
- :mod:`.covariants3`, :mod:`.channels3`, :mod:`.n3`: n = 3, every SO(3) x SO(3) sector (j, j')
                       (covariants restricted to diagonal matrices, chamber quadratures,
                       dedicated (0, 0), (1, 1) bases).
- :mod:`.thermal`      partition functions and the classical limit.
- :mod:`.spectra`      :func:`~.spectra.solve`, dispatching to n2 / n3 / channels3.
- :mod:`.densities`    probability densities of the states.
- :mod:`.tensor_operators3` n = 3 operators expanded in Wigner D functions of L and R
                       (polynomials in the components of phi, G, C), Wigner D^j, the invariants
                       of V_j (x) V_j' (x) V_l.
- :mod:`.transitions`  matrix elements of configuration operators between levels, reduced
                       strengths, selection rules (docs/quantum-transitions.md).
- :mod:`.orientations3`, :mod:`.green3`: n = 3 orientation densities of states,
                       superpositions and thermal mixtures; densities of the components
                       of G (diagonal and off-diagonal).
- :mod:`.evolution`    exact evolution of an n = 2 wave packet: the sector (0, 0), or a Gaussian
                       in phi around a classical (phi, pi) over every sector it populates.
- :mod:`.evolution3`   exact evolution of an n = 3 wave packet of the sector (0, 0).
- :mod:`.config`, :mod:`.cli`: TOML configs, the ``spectrum`` / ``density`` commands
                       (application layer).

The independent reference the reduced solvers are tested against (autodiff on Cartesian wave
functions, no reduction; used only by the tests):

- :mod:`.operators`    Hilbert-space measures (88)-(91), momenta (92), (113), affine spins (93),
                       their Hermitian corrections (107)-(112), the unitary groups (94)-(102).
- :mod:`.hamiltonians` kinetic operators of every model (76a)-(85) by substitution, H = T + V
                       (114), (115).
- :mod:`.reduction`    reduction of doubly isotropic Hamiltonians to the deformation invariants
                       in two-polar coordinates (radial operator, centrifugal/sector terms).

Submodules are imported explicitly (``from affinebody.quantum import operators``) so that the
package import stays light.
"""
