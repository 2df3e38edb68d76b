"""Quantum affine bodies (paper, section "General quantization ideas" and the last section).

- :mod:`.operators`    Hilbert-space measures (88)-(91), momenta (92), (113), affine spins (93),
                       their Hermitian corrections (107)-(112), the unitary groups (94)-(102);
                       operators act on wave functions given as JAX callables (autodiff).
- :mod:`.hamiltonians` kinetic operators of every model (76a)-(85) by substitution, H = T + V
                       (114), (115).
- :mod:`.reduction`    reduction of doubly isotropic Hamiltonians to the deformation invariants
                       in two-polar coordinates (radial operator, centrifugal/sector terms).
- :mod:`.spectra`      numerical spectra: results, n = 2 sectors, the shared solver machinery.
- :mod:`.n3`           n = 3: every SO(3) x SO(3) sector (j, j'), with the angular parts from
                       :mod:`.covariants3` (covariants restricted to diagonal matrices);
                       :mod:`.channels3`: chamber quadratures, dedicated (0, 0), (1, 1) bases.
- :mod:`.thermal`      partition functions and the classical limit.
- :mod:`.densities`, :mod:`.config`, :mod:`.cli`: probability densities, TOML configs, the
                       ``spectrum`` / ``density`` commands.

Submodules are imported explicitly (``from affinebody.quantum import operators``) so that the
package import stays light.
"""
