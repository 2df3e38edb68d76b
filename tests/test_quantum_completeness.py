"""Completeness of the quantum spectra (issue 20): the sector search stops only when a certified
lower bound of every unsearched sector lies above the K-th level, an unconverged state keeps
its place in the list, and the K lowest states (with multiplicity) agree with independent
solvers per sector (docs/theory/two-polar.md, "Lower bounds of a sector")."""

import json

import numpy as np
import pytest
from click.testing import CliRunner
from scipy import sparse
from scipy.linalg import eigh_tridiagonal
from scipy.sparse.linalg import eigsh

from affinebody.cli.quantum_dynamics import transitions as transitions_command
from affinebody.quantum import spectra as sp
from affinebody.quantum.bounds import centrifugal_haar_min
from affinebody.quantum.cli import density, spectrum
from affinebody.quantum.config import compile_potential
from affinebody.quantum.densities import densities
from affinebody.quantum.intervals import HaarCells, LebesgueCells, lower_bounds
from affinebody.quantum.levels import LevelCollector, Sector, Settings, Spectrum
from affinebody.quantum.transitions import Operator, transitions

I_, A_, B_ = 1.0, 0.2, 0.1
DEPTH = 24.0
#: a harmonic well in ln det phi plus an attractive well in the shear x = q1 - q2:
#: V = sigma^2 / 2 - DEPTH / (4 cosh^2(x/2)) (Q1 Q2 / (Q1 + Q2)^2 = 1 / (4 cosh^2(x/2)))
SHEAR_WELL = f"0.5*(q1 + q2)**2 + (-{DEPTH})*Q1*Q2/(Q1 + Q2)**2"


def finite_volume_levels(weight, coef, potential, length, cells, count):
    """Lowest eigenvalues of -coef (1/w) (w f')' + potential on (0, length): cell-centred finite
    volumes (zero flux at 0, f = 0 beyond ``length``), symmetrised tridiagonal matrix; second
    order, so one Richardson step (cells, 2 cells) is returned."""
    out = []
    for n in (cells, 2 * cells):
        h = length / n
        r = (np.arange(n) + 0.5) * h
        faces = np.arange(1, n + 1) * h
        w, wf = weight(r), weight(faces)
        diag = coef * (np.concatenate([[0.0], wf[:-1]]) + wf) / (h * h * w) + potential(r)
        off = -coef * wf[:-1] / (h * h * np.sqrt(w[:-1] * w[1:]))
        out.append(eigh_tridiagonal(diag, off, select="i", select_range=(0, count - 1))[0])
    return (4 * out[1] - out[0]) / 3


def shear_well_exact(max_shell=60, top=3.0):
    """Levels (energy, s, k) of af-is with SHEAR_WELL, from the closed form: sigma separates
    (oscillator -hbar^2/(M + 2B) d^2 + sigma^2/2), and in y = x/2 the shear operator is the
    Poeschl-Teller operator kappa[-(1/J)(J f')' ] + (lambda^2 kappa)/sinh^2 y -
    (mu^2 kappa)/cosh^2 y, J = sinh y cosh y, kappa = hbar^2/(4M), lambda = |s + k|/2,
    mu^2 = (s - k)^2/4 + DEPTH/(4 kappa), with bound states
    kappa (1 - (mu - lambda - 1 - 2n)^2), n >= 0 while mu - lambda - 1 - 2n > 0."""
    M, dil, inv_it = I_ + A_, I_ + A_ + 2 * B_, I_ / (I_**2 - A_**2)
    kappa, e = 1 / (4 * M), inv_it / 2
    sigma = [np.sqrt(0.5 / dil) * (2 * n + 1) for n in range(20)]
    out = []
    for s in range(-max_shell, max_shell + 1):
        for k in range(-max_shell, max_shell + 1):
            if (s + k) % 2:
                continue
            lam = abs(s + k) / 2
            mu = np.sqrt((s - k) ** 2 / 4 + DEPTH / 4 / kappa)
            n = 0
            while mu - lam - 1 - 2 * n > 0:
                shear = kappa * (1 - (mu - lam - 1 - 2 * n) ** 2) + e * k * k
                out += [(shear + es, s, k) for es in sigma if shear + es < top]
                n += 1
    return sorted(out)


def test_shear_well_closed_form_matches_finite_volumes():
    """The closed form used as the exact reference agrees with an independent finite-volume
    solution of the 1D reduced operator in x (measure sinh x dx) in four sectors."""
    M, inv_it = I_ + A_, I_ / (I_**2 - A_**2)
    c, e = 1 / (16 * M), inv_it / 2
    exact = shear_well_exact(max_shell=8, top=50.0)
    sigma0 = np.sqrt(0.5 / (M + 2 * B_))
    for s, k in [(0, 0), (1, -1), (7, -1), (3, 1)]:
        p, d = s + k, s - k
        fv = finite_volume_levels(
            np.sinh, 1 / M, lambda x, p=p, d=d, k=k: c * p * p / np.sinh(x / 2) ** 2
            - (c * d * d + DEPTH / 4) / np.cosh(x / 2) ** 2 + e * k * k, 40.0, 2000, 1)
        lowest = min(E for E, a, b in exact if (a, b) == (s, k)) - sigma0
        assert abs(fv[0] - lowest) < 2e-6


def test_af_is_shear_well_k_lowest_states_are_exact_and_complete():
    """The lowest level per shell max(|s|, |k|) is not monotone (shell 7 holds a level below
    shell 6's lowest: the well binds large |s - k|); the certified search still returns the 32
    lowest states: each entry is the exact level or NaN (an unconverged candidate in its place),
    never a higher level, and the counts below thresholds agree."""
    exact = shear_well_exact()
    per_shell = {}
    for E, s, k in exact:
        per_shell[max(abs(s), abs(k))] = min(per_shell.get(max(abs(s), abs(k)), np.inf), E)
    assert per_shell[7] < per_shell[6] - 0.02  # the premise: not monotone in the shell
    K = 32
    s = sp.solve("af-is", 2, compile_potential(SHEAR_WELL, 2), 1.0, I=I_, A=A_, B=B_, levels=K,
                 settings=Settings(basis_size=16))
    assert s.certified
    reference = np.array([E for E, _, _ in exact[:K]])
    got = np.array(s.energies(K))
    assert len(got) == K
    known = ~np.isnan(got)
    assert known.sum() >= K // 2
    assert np.max(np.abs(got[known] - reference[known])) < 1e-7
    assert s.unknown_states(K) == list(np.flatnonzero(~known))
    estimates = np.array([lv.energy for lv in s.states() for _ in range(lv.multiplicity)])[:K]
    assert np.max(np.abs(estimates - reference)) < 1e-3  # unknown ones: estimate in its place
    assert s.complete(K) == bool(known.all())
    for threshold in (-2.0, -1.0, -0.5, -0.25):
        assert np.sum(estimates < threshold) == np.sum(reference < threshold)
    # `density --state k` and `transitions` index this same list: the k-th state is the exact
    # k-th one or refused (never the next level up), the levels of the transitions are the
    # converged levels in order
    for k in np.flatnonzero(known):
        assert abs(s.level_of_state(int(k)).energy - reference[k]) < 1e-7
    for k in s.unknown_states(K):
        with pytest.raises(ValueError, match="not converged"):
            s.level_of_state(k)
    top = int(np.flatnonzero(known)[-1])
    assert abs(densities(s, top)["energy"] - reference[top]) < 1e-7
    table = transitions(s, Operator("det", 2), 0)
    assert [t.final for t in table.transitions] == list(range(len(s.levels)))
    distinct = np.unique(reference[known])
    assert np.max(np.abs([t.E_final for t in table.transitions] - distinct)) < 1e-7


def test_dalembert_shear_well_agrees_with_separated_solvers():
    """d'Alembert, J = Id: V = Tr G / 2 + 0.05 (Q1 - Q2)^4 - 0.8 (Q1 - Q2)^2 separates in the
    conformal / anticonformal radii (Q1 - Q2 = 2|w|): a 2D oscillator in z (levels
    2 n + |m1| + 1) plus a ring well in w (finite volumes per m2); sectors (+-m1, +-m2).
    (For n = 2 d'Alembert the lowest level per shell |m1| + |m2| is monotone whatever V: the
    centrifugal terms hbar^2 m_i^2 / (4 I r_i^2) grow with each |m_i| on one Hilbert space.)"""
    K = 16
    V = compile_potential("0.5*trG + 0.05*(Q1 - Q2)**4 - 0.8*(Q1 - Q2)**2", 2)
    s = sp.solve("dalembert", 2, V, 1.0, inertia=1.0, levels=K, settings=Settings(basis_size=20))
    assert s.certified and s.complete(K)
    levels = []
    for m2 in range(8):
        ring = finite_volume_levels(
            lambda r: r, 0.25, lambda r, m2=m2: m2 * m2 / (4 * r * r) + 0.8 * r**4 - 2.2 * r * r,
            6.0, 3000, 4)
        for m1 in range(8):
            mult = (1 if m1 == 0 else 2) * (1 if m2 == 0 else 2)
            levels += [2 * n1 + m1 + 1 + w for n1 in range(4) for w in ring] * mult
    reference = np.sort(levels)[:K]
    got = np.array(s.energies(K))
    assert np.max(np.abs(got - reference)) < 1e-6
    for threshold in (0.5, 1.0, 1.5, 2.0):
        assert np.sum(got < threshold) == np.sum(np.sort(levels) < threshold)


def finite_volume_block(potential, m1, m2, length, cells, count):
    """Lowest levels of the n = 2 d'Alembert block (|m1|, |m2|), J = Id: -(1/4)(Lap_m1(r1) +
    Lap_m2(r2)) + V on (0, length)^2 under r1 r2 dr1 dr2 (Q = (r1 + r2, r1 - r2)); cell-centred
    finite volumes per axis (the operator of :func:`finite_volume_levels` plus m^2 / r^2),
    Kronecker sum, shift-invert Lanczos; one Richardson step (cells, 2 cells)."""
    out = []
    for n in (cells, 2 * cells):
        h = length / n
        r = (np.arange(n) + 0.5) * h
        faces = np.arange(1, n + 1) * h

        def radial(m, r=r, faces=faces, h=h, n=n):
            diag = (np.concatenate([[0.0], faces[:-1]]) + faces) / (h * h * r) + m * m / r**2
            off = -faces[:-1] / (h * h * np.sqrt(r[:-1] * r[1:]))
            return sparse.diags([off, diag, off], [-1, 0, 1])
        R1, R2 = np.meshgrid(r, r, indexing="ij")
        V = potential(np.stack([R1 + R2, R1 - R2], -1)).ravel()
        eye = sparse.identity(n)
        H = 0.25 * (sparse.kron(radial(m1), eye) + sparse.kron(eye, radial(m2))) \
            + sparse.diags(V)
        out.append(np.sort(eigsh(H.tocsc(), k=count, sigma=-10.0, return_eigenvectors=False)))
    return (4 * out[1] - out[0]) / 3


#: d'Alembert: a deep ring well in the shear |w| = (Q1 - Q2)/2, coupled to the conformal
#: radius |z| = (Q1 + Q2)/2 by (Q1^2 - Q2^2)^2 = 16 |z|^2 |w|^2 (so it does not separate)
COUPLED_RING = "0.5*trG + 0.1*(Q1 - Q2)**4 - 1.5*(Q1 - Q2)**2 + 0.05*(Q1**2 - Q2**2)**2"


def test_dalembert_levels_never_fall_with_the_shell():
    """n = 2 d'Alembert: the block (|m1|, |m2|) is H0 + hbar^2 (m1^2/r1^2 + m2^2/r2^2)/(4I) + V
    on one Hilbert space, so its i-th level is at least the i-th level of (|m1| - 1, |m2|) and
    of (|m1|, |m2| - 1) whatever V (docs/theory/two-polar.md, "The lowest d'Alembert level per
    shell (n = 2)"), and the lowest level per shell |m1| + |m2| never falls -- unlike af-is,
    whose shear wells bind higher shells more deeply (above). Checked for a deep ring well in the
    shear coupled to the conformal radius, on the blocks the certified search solved; and the
    K lowest states and the count below each energy agree with an independent 2D finite-volume
    solver per block."""
    K = 12
    V = compile_potential(COUPLED_RING, 2)
    s = sp.solve("dalembert", 2, V, 1.0, inertia=1.0, levels=K, settings=Settings(basis_size=20))
    assert s.certified and s.complete(K)
    low = {key: block.energies[:3] for key, block in s.blocks.items()}
    for (a, b), E in low.items():
        for below in ((a - 1, b), (a, b - 1)):
            if below in low:
                assert np.all(E >= low[below] - 1e-6), ((a, b), below)
    shells = [min(E[0] for key, E in low.items() if sum(key) == L)
              for L in range(1 + max(map(sum, low)))]
    assert len(shells) >= 6 and np.all(np.diff(shells) > 0)
    got = np.array(s.energies(K))
    reference = []
    for a in range(4):  # shells <= 3; beyond, every level is >= shell 3's lowest (0.85)
        for b in range(4 - a):
            mult = (1 if a == 0 else 2) * (1 if b == 0 else 2)
            reference += list(finite_volume_block(V, a, b, 4.5, 40, 3)) * mult
    reference = np.sort(reference)
    assert np.max(np.abs(got - reference[:K])) < 2e-3
    for threshold in (-0.9, -0.4, 0.2, 0.5, 0.76):
        assert np.sum(got < threshold) == np.sum(reference < threshold)


def test_interval_bounds_hold_on_random_points():
    """Lower bounds of V on cells are never above V at points of the cell (Haar (x, sigma)
    cells and d'Alembert (rho, theta) cells, unbounded ones included)."""
    rng = np.random.default_rng(1)
    x_edges = np.array([0.0, 0.3, 1.0, 3.0, 9.0, np.inf])
    s_edges = np.array([-np.inf, -4.0, -1.0, 0.0, 0.5, 3.0, np.inf])
    XL, SL = np.meshgrid(x_edges[:-1], s_edges[:-1], indexing="ij")
    XH, SH = np.meshgrid(x_edges[1:], s_edges[1:], indexing="ij")
    for text in (SHEAR_WELL, "q1**2 + q2**2 - 3*exp(-(q1 - q2)**2)", "trG - 2*sqrt(det) + K2/10",
                 "cos(q1) * sin(q2) - abs(q1 - 1)/(1 + (q1 + q2)**2)"):
        lb = lower_bounds(text, HaarCells(XL, XH, SL, SH))
        x, sig = rng.uniform(0, 14, 20000), rng.uniform(-8, 8, 20000)
        V = compile_potential(text, 2)(np.exp(np.stack([(sig + x) / 2, (sig - x) / 2], -1)))
        ix = np.searchsorted(x_edges, x, side="right") - 1
        js = np.searchsorted(s_edges, sig, side="right") - 1
        assert np.all(V >= lb[ix, js]), text
    r_edges = np.array([0.0, 0.5, 1.0, 2.0, np.inf])
    t_edges = np.linspace(0, np.pi / 2, 5)
    RL, TL = np.meshgrid(r_edges[:-1], t_edges[:-1], indexing="ij")
    RH, TH = np.meshgrid(r_edges[1:], t_edges[1:], indexing="ij")
    for text in ("0.5*trG + 0.05*(Q1 - Q2)**4 - 0.8*(Q1 - Q2)**2", "0.5*trG + 0.1*(det - 1)**2",
                 "K1 - 2*exp(-(Q1 - Q2 - 2)**2) + sin(Q2)", COUPLED_RING):
        lb = lower_bounds(text, LebesgueCells(RL, RH, TL, TH))
        if text == COUPLED_RING:  # degree 4 vanishes on the edge Q1 = Q2, degree 2 confines
            assert lb[-1, 0] > 0  # the unbounded cell along that edge
        rho, th = rng.uniform(0, 5, 20000), rng.uniform(0, np.pi / 2, 20000)
        r1, r2 = rho * np.cos(th), rho * np.sin(th)
        V = compile_potential(text, 2)(np.stack([r1 + r2, r1 - r2], -1))
        ir = np.searchsorted(r_edges, rho, side="right") - 1
        it = np.minimum(np.searchsorted(t_edges, th, side="right") - 1, 3)
        assert np.all(V >= lb[ir, it]), text


def test_centrifugal_closed_form_is_the_minimum_over_the_strip():
    x = np.linspace(0.2, 3.0, 20001)
    for a, b in [(0.0, 4.0), (1.0, 9.0), (4.0, 1.0), (2.0, 2.0)]:
        f = a / np.sinh(x / 2) ** 2 - b / np.cosh(x / 2) ** 2
        bound = float(centrifugal_haar_min(np.array(a), np.array(b), 0.2, 3.0))
        assert bound <= f.min() + 1e-12 and bound > f.min() - 1e-6


def test_unconverged_state_keeps_its_place():
    """Bookkeeping: a candidate set aside as unconverged holds its index; the K-th entry is
    never a higher converged level, and level_of_state refuses it."""
    settings = Settings()
    found = LevelCollector(settings)
    one = (Sector(0, 0),)
    # one block, three eigenvalues; the middle one's error estimate exceeds the tolerance
    found.record(("b",), one, None, np.array([1.0, 2.0, 3.0]), np.eye(3),
                 np.array([1e-12, 1e-3, 1e-12]))
    levels, pending = found.levels(2)
    s = Spectrum(levels, pending, {}, "dalembert", 2, "all", certified=True, requested=2)
    assert [lv.energy for lv in levels] == [1.0] and [lv.energy for lv in pending] == [2.0]
    got = s.energies(2)
    assert got[0] == 1.0 and np.isnan(got[1]) and s.unknown_states() == [1]
    assert not s.complete()
    with pytest.raises(ValueError, match="not converged"):
        s.level_of_state(1)


AF_IS = f"""
[system]
n = 2
[quantum]
kinetic = "af-is"
I = 1.0
A = 0.2
B = 0.1
potential = "{SHEAR_WELL}"
basis_size = 16
max_spin = 3
"""


def test_cli_json_states_whether_the_list_is_complete(tmp_path):
    """max_spin = 3 is too small to certify the 8 lowest states: the JSON says the list is
    conditional (complete false) and keeps unconverged states as nulls in their place; the
    density of such a list warns."""
    path = tmp_path / "afis.toml"
    path.write_text(AF_IS)
    result = CliRunner().invoke(spectrum, [str(path), "--levels", "8", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.output)
    assert data["complete"] is False and data["certified"] is False
    assert data["certificate"].startswith("conditional")
    assert len(data["energies"]) == 8
    assert [i for i, e in enumerate(data["energies"]) if e is None] == data["unknown_states"]
    exact = [E for E, _, _ in shear_well_exact()[:8]]
    for e, ref in zip(data["energies"], exact, strict=True):
        assert e is None or abs(e - ref) < 1e-6
    known = [i for i, e in enumerate(data["energies"]) if e is not None]
    dens = CliRunner().invoke(density, [str(path), "--state", str(known[0]), "-o",
                                        str(tmp_path / "dens")])
    assert dens.exit_code == 0 and "the sector search is not certified (conditional" in \
        dens.output
    trans = CliRunner().invoke(transitions_command, [str(path), "--operator", "det",
                                                     "--levels", "8", "--json"])
    assert trans.exit_code == 0, trans.output
    tdata = json.loads(trans.output)
    assert any("not certified to be the 8 lowest" in w for w in tdata["warnings"])
    known_levels = sorted({e for e in data["energies"] if e is not None})
    assert np.allclose([t["E_final"] for t in tdata["transitions"]], known_levels, atol=1e-9)
    if data["unknown_states"]:  # an unconverged state has no density, and says why
        dens = CliRunner().invoke(density, [str(path), "--state", str(data["unknown_states"][0]),
                                            "-o", str(tmp_path / "dens2")])
        assert dens.exit_code == 1 and "not converged" in dens.output


def test_an_uncertified_search_says_what_could_certify_it():
    """V = |det phi| does not confine the body (it vanishes on the singular matrices, out to
    infinity), so its certified bound stays at its infimum 0 at every spin and no search
    certifies the list. The warning says so and gives the bound; it had told the user to
    "give the potential as an expression", which it already was. A Python function, which
    has no bound, is still told that."""
    settings = Settings(basis_size=8, max_spin=3)
    kwargs = dict(inertia=1.0, levels=3, settings=settings)
    expression = sp.solve("dalembert", 2, compile_potential("abs(det)", 2), 1.0, **kwargs)
    function = sp.solve("dalembert", 2, lambda q: np.abs(np.prod(q, axis=-1)), 1.0, **kwargs)
    assert not expression.certified and not function.certified
    [said] = [w for w in expression.warnings if "conditional" in w]
    assert "give the potential as an expression" not in said
    bound = float(said.split("the bound beyond the last shell searched is ")[1].split(",")[0])
    assert -1e-9 < bound <= 0.0  # the infimum of |det phi|, less the rounding of the intervals
    assert "does not confine" in said
    [said] = [w for w in function.warnings if "conditional" in w]
    assert "give the potential as an expression" in said


def test_an_incomplete_list_says_why():
    """Spectrum.incomplete_because: a certified list with an unconverged state among the first
    ones names those states (the density command's warning gave the certificate, which reads
    as complete there: "no level below 7.77 > the 101-th candidate 7"); uncertified: the
    certificate; fewer states than asked: how many; all known: None (and complete())."""
    from affinebody.quantum.levels import Level, Sector, Spectrum

    sector = Sector(0, 0, 1, 1)

    def level(energy, converged=True):
        return Level(energy, 1, (sector,), 1e-9, ("b",), 0, converged)

    s = Spectrum([level(1.0), level(3.0)], [level(2.0, False)], {}, "dalembert", 2, "all",
                 certified=True, certificate="certified: no level below 7.77")
    assert s.incomplete_because(1) is None and s.complete(1)
    assert s.incomplete_because(3) == "states [1] among them are unconverged candidates"
    assert s.incomplete_because(4) == "only 3 states were computed"
    s.certified = False
    assert "not certified (certified: no level" in s.incomplete_because(1)
    s.certified, s.bounded_below = True, False
    assert "unbounded below" in s.incomplete_because(1) and not s.complete(1)


def test_the_collectors_running_count_is_the_count_of_every_candidate():
    """LevelCollector keeps its candidates' states and their ascending ladder as blocks come
    (the search asks for the K-th energy before every block); at every point of a search its
    count and K-th energy must be those of all candidates recounted (every state's energy,
    sorted): converged and unconverged candidates, degenerate sectors, equal energies."""

    def kth_energy(known, count):  # the reference: every state listed and sorted
        values = sorted(e for e, sectors in known for s in sectors for _ in range(s.dimension))
        return values[count - 1] if len(values) >= count else np.inf

    rng = np.random.default_rng(7)
    found = LevelCollector(Settings())
    for block in range(40):
        size = int(rng.integers(1, 5))
        energies = np.round(rng.uniform(0.0, 3.0, size), 1)  # ties across blocks
        errors = np.where(rng.random(size) < 0.3, 1e-2, 1e-12)  # some unconverged
        sectors = (Sector(block, 0, dimension=int(rng.integers(1, 4))),)
        found.record(("block", block), sectors, None, energies, None, errors)
        known = ([(e[0], e[2]) for e in found.entries]
                 + [(lv.energy, lv.sectors) for lv in found.unconverged])
        assert found.state_count() == sum(s.dimension for _, sectors in known for s in sectors)
        for count in range(1, found.state_count() + 2):
            assert found.kth_energy(count) == kth_energy(known, count)
    assert found.unconverged and found.entries  # both kinds were counted
