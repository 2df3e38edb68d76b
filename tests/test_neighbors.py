"""Cell and neighbour lists: the list is exactly the brute-force set of pairs in range (free,
orthorhombic, triclinic), its reach follows the largest singular value of the phi's, the
rebuild criterion keeps it complete, and overflows are reported and fixed by reallocation."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from affinebody import neighbors as nb
from affinebody.mutual import affine_distance
from affinebody.space import free_space, orthorhombic, triclinic

BODIES = 40
BOXES = {
    "free": free_space(),
    "orthorhombic": orthorhombic((4.6, 5.0, 4.8)),
    "triclinic": triclinic([[4.8, 1.0, 0.6], [0.0, 4.9, -0.7], [0.0, 0.0, 5.0]]),
}


def system(rng, space, stretch: float = 0.15):
    if space.periodic:  # spread over several periodic copies: wrapping is tested too
        s = rng.uniform(-1.0, 2.0, size=(BODIES, 3))
        x = s @ space.matrix.T
    else:  # two bodies at fixed corners: the same grid (and compiled build) for every draw
        x = rng.uniform(-2.5, 2.5, size=(BODIES, 3))
        x[:2] = [[-2.5, -2.5, -2.5], [2.5, 2.5, 2.5]]
    phi = np.eye(3) + stretch * rng.normal(size=(BODIES, 3, 3))
    phi[np.linalg.det(phi) < 0, 0] *= -1
    return jnp.asarray(x), jnp.asarray(phi)


def pair_set(array) -> set:
    return set(map(tuple, np.asarray(array).tolist()))


@settings(max_examples=4, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
@pytest.mark.parametrize("kind", list(BOXES))
def test_list_is_exactly_the_pairs_within_reach_plus_skin(kind, seed):
    rng = np.random.default_rng(seed)
    space = BOXES[kind]
    x, phi = system(rng, space)
    # fixed capacities: one compiled build per kind of space for all draws
    spec, nbrs = nb.allocate(space, x, phi, 1.7, "r", 0.3, capacity=BODIES * (BODIES - 1) // 2,
                             cell_capacity=BODIES)
    assert nbrs.i.shape[0] >= int(nbrs.count) > 0
    listed = nb.pairs_of(nbrs)
    assert np.all(listed[:, 0] < listed[:, 1])
    assert pair_set(listed) == pair_set(nb.brute_force_pairs(space, x, 2.0))
    assert len(listed) == len(pair_set(listed))  # no pair twice
    # padding after count
    assert np.all(np.asarray(nbrs.i[int(nbrs.count):]) == BODIES)


def test_largest_singular_values_closed_form_matches_svd():
    rng = np.random.default_rng(0)
    for n in (1, 2, 3, 4):
        phi = rng.normal(size=(200, n, n)) * np.exp(rng.uniform(-2, 2, size=(200, 1, 1)))
        phi[:3] = np.eye(n) * 1.7  # degenerate spectrum
        s = np.asarray(nb.largest_singular_values(jnp.asarray(phi)))
        expected = np.linalg.svd(phi, compute_uv=False)[:, 0]
        assert np.all(s >= expected)
        np.testing.assert_allclose(s, expected, rtol=1e-9)


def test_reach_of_an_affine_cutoff_covers_every_pair_with_small_affine_distance():
    # D < D_cut implies |u| < D_cut max(s_K, s_L): strongly stretched bodies reach farther
    rng = np.random.default_rng(1)
    space = orthorhombic((14.0, 14.0, 14.0))
    x = jnp.asarray(rng.uniform(0, 14, size=(BODIES, 3)))
    stretch = np.diag([3.0, 1.0, 0.5])
    phi = jnp.asarray(np.eye(3) + 0.1 * rng.normal(size=(BODIES, 3, 3))) @ stretch
    d_cut = 1.5
    spec, nbrs = nb.allocate(space, x, phi, d_cut, "D", 0.2, capacity=BODIES * (BODIES - 1) // 2)
    assert float(nbrs.reach) > 2.9 * d_cut
    k, l = np.triu_indices(BODIES, 1)
    u = space.displacement(x[k], x[l])
    d = np.asarray(affine_distance(u, phi[k], jnp.zeros_like(u), phi[l]))
    close = {(a, b) for a, b, dist in zip(k, l, d, strict=True) if dist < d_cut}
    assert close and close <= pair_set(nb.pairs_of(nbrs))


def test_rebuild_criterion_for_motion_and_for_stretching():
    rng = np.random.default_rng(2)
    space = BOXES["triclinic"]
    x, phi = system(rng, space)
    spec, nbrs = nb.allocate(space, x, phi, 1.2, "D", 0.4, capacity=BODIES * (BODIES - 1) // 2)
    needs = jax.jit(nb.needs_rebuild, static_argnums=0)
    assert not bool(needs(spec, nbrs, x, phi))
    assert not bool(needs(spec, nbrs, x.at[3, 0].add(0.19), phi))
    assert bool(needs(spec, nbrs, x.at[3, 0].add(0.21), phi))
    # stretching the most stretched body by 1.4 grows the reach by more than the skin
    widest = int(jnp.argmax(nb.largest_singular_values(phi)))
    stretched = phi.at[widest].multiply(1.4)
    assert bool(needs(spec, nbrs, x, stretched))
    updated = jax.jit(nb.update, static_argnums=0)(spec, nbrs, x, stretched)
    assert float(updated.reach) > float(nbrs.reach)
    if int(updated.overflow) == 0:
        radius = float(updated.reach) + spec.skin
        assert pair_set(nb.pairs_of(updated)) == pair_set(
            nb.brute_force_pairs(space, x, radius))
    # a list that has not moved is kept as it is by update
    kept = jax.jit(nb.update, static_argnums=0)(spec, nbrs, x, phi)
    np.testing.assert_array_equal(kept.i, nbrs.i)


def test_pair_overflow_is_flagged_and_reallocation_fixes_it():
    rng = np.random.default_rng(3)
    space = BOXES["orthorhombic"]
    x, phi = system(rng, space)
    spec, nbrs = nb.allocate(space, x, phi, 1.5, "r", 0.2, cell_capacity=BODIES)
    # all bodies into 60% of the cell: denser, more pairs in range than the capacity holds
    squeezed = 0.6 * space.wrap(x)
    crowded = nb.build_jit(spec, squeezed, phi)
    assert int(crowded.overflow) & nb.PAIR_OVERFLOW
    assert int(crowded.count) > spec.capacity
    with pytest.raises(nb.NeighborListOverflow, match="pair capacity"):
        nb.check(crowded)
    spec2, fixed = nb.allocate(space, squeezed, phi, 1.5, "r", 0.2, cell_capacity=BODIES)
    assert spec2.capacity > spec.capacity and int(fixed.overflow) == 0
    assert pair_set(nb.pairs_of(fixed)) == pair_set(nb.brute_force_pairs(space, squeezed, 1.7))
    assert int(fixed.count) > spec.capacity


@pytest.mark.parametrize("layout", ["crystal", "cluster"])
def test_allocated_capacity_is_the_uniform_floor_or_the_pairs_found(monkeypatch, layout):
    """In a periodic box the capacity is capacity_factor x max(pairs found, pairs of a uniform
    fluid at this density): a crystal (fewer pairs than the fluid) gets the fluid's, from one
    build at that capacity; a cluster (more) the count of its own pairs, after a second build.
    Either list is the brute-force set of pairs in range."""
    space = orthorhombic((6.0, 6.0, 6.0))
    if layout == "crystal":
        x = np.stack(np.meshgrid(*[np.arange(6.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    else:  # all bodies within a third of the box
        x = np.random.default_rng(8).uniform(0.0, 2.0, size=(216, 3))
    x, phi = jnp.asarray(x), jnp.broadcast_to(jnp.eye(3), (216, 3, 3))
    radius = 1.5 + 0.2
    floor = nb.uniform_pair_count(space, 216, radius)
    found = len(nb.brute_force_pairs(space, x, radius))
    assert (found <= floor) == (layout == "crystal")
    builds = []
    build = nb.build_jit
    monkeypatch.setattr(nb, "build_jit", lambda *a: builds.append(a[0]) or build(*a))
    spec, lst = nb.allocate(space, x, phi, 1.5, "r", 0.2)
    assert len(builds) == (1 if layout == "crystal" else 2)
    assert spec.capacity == max(64, int(np.ceil(max(found, floor) * 1.25)))
    assert int(lst.count) == found and int(lst.overflow) == 0
    assert pair_set(nb.pairs_of(lst)) == pair_set(nb.brute_force_pairs(space, x, radius))


def test_cell_and_reach_overflows_are_flagged():
    rng = np.random.default_rng(4)
    space = BOXES["orthorhombic"]
    x, phi = system(rng, space)
    spec, _ = nb.allocate(space, x, phi, 1.0, "D", 0.2, capacity=BODIES * (BODIES - 1) // 2)
    clumped = x.at[:20].set(x[0] + 0.01 * jnp.arange(20)[:, None])  # 20 bodies in one cell
    # the JAX build (GPU) fills cells of a fixed capacity; the host build (CPU) has none
    assert int(jax.jit(nb.build_jax, static_argnums=0)(spec, clumped, phi).overflow) \
        & nb.CELL_OVERFLOW
    host = nb.build_jit(spec, clumped, phi)
    assert nb._host.in_use() and int(host.overflow) == 0
    radius = float(host.reach) + spec.skin
    assert pair_set(nb.pairs_of(host)) == pair_set(nb.brute_force_pairs(space, clumped, radius))
    grown = nb.build_jit(spec, x, phi * 2.0)  # the reach doubles: wider than the cells
    assert int(grown.overflow) & nb.REACH_OVERFLOW
    with pytest.raises(nb.NeighborListOverflow, match="outgrew"):
        nb.check(grown)


def test_a_reallocation_never_takes_back_the_list_radius():
    """Capacities never shrink (``neighbors.reallocate``): the room a reach overflow gave the
    cells (a larger ``max_radius``) stays through a later pair overflow, and each list is
    exactly the pairs within reach + skin."""
    rng = np.random.default_rng(5)
    space = BOXES["orthorhombic"]
    x, phi = system(rng, space)
    spec, _ = nb.allocate(space, x, phi, 0.7, "D", 0.2)
    stretched = 1.3 * phi  # the reach of a D cut-off grows with the bodies
    grown = nb.build_jit(spec, x, stretched)
    assert int(grown.overflow) & nb.REACH_OVERFLOW
    wide, _ = nb.reallocate(spec, x, stretched, flags=int(grown.overflow),
                            pairs=int(grown.count), reach=float(grown.reach))
    assert wide.max_radius > spec.max_radius
    squeezed = 0.5 * space.wrap(x)  # the bodies back to their shapes, crowded: more pairs
    crowded = nb.build_jit(wide, squeezed, phi)
    assert int(crowded.overflow) == nb.PAIR_OVERFLOW
    spec3, fixed = nb.reallocate(wide, squeezed, phi, flags=int(crowded.overflow),
                                 pairs=int(crowded.count), reach=float(crowded.reach))
    assert spec3.max_radius == wide.max_radius and spec3.capacity > wide.capacity
    radius = float(fixed.reach) + spec3.skin
    assert int(fixed.overflow) == 0
    assert pair_set(nb.pairs_of(fixed)) == pair_set(nb.brute_force_pairs(space, squeezed, radius))


def test_allocate_refuses_a_radius_beyond_half_the_box():
    x = jnp.zeros((2, 3)).at[1, 0].set(1.0)
    with pytest.raises(ValueError, match="exceeds half the smallest perpendicular width"):
        nb.allocate(orthorhombic((4.0, 4.0, 4.0)), x, jnp.stack([jnp.eye(3)] * 2), 1.9, "r", 0.3)
    with pytest.raises(ValueError, match="variable must be"):
        nb.allocate(None, x, jnp.stack([jnp.eye(3)] * 2), 1.0, "q")



@pytest.mark.parametrize("cell", [False, True])
def test_a_dilute_box_gets_at_most_two_cells_a_body_and_every_pair_in_range(cell):
    """A few bodies in a box 10^5 wide (a gas, or a config's box mistyped by orders of
    magnitude): cells of the radius would be 10^14 in number (a table of ~10^3 TB, before);
    the cells are made wider instead, at most CELLS_PER_BODY a body, and the list is still
    every pair in range, across the faces of the box too (host and JAX builds alike)."""
    width = 1e5
    space = orthorhombic((width, width, width))
    rng = np.random.default_rng(3)
    centres = rng.uniform(0.0, width, size=(BODIES // 2, 3))
    centres[0] = [0.3, width / 2, width - 0.2]  # its partner is across two faces
    x = np.concatenate([centres, centres + rng.uniform(-1.0, 1.0, size=centres.shape)])
    phi = jnp.stack([jnp.eye(3)] * BODIES)
    spec, nbrs = nb.allocate(space, x, phi, 1.5, "r", 0.3,
                             cell=np.diag([width] * 3) if cell else None)
    assert np.prod(spec.grid) <= nb.CELLS_PER_BODY * BODIES
    expected = pair_set(nb.brute_force_pairs(space, jnp.asarray(x), 1.8))
    assert len(expected) >= BODIES // 2 - 2  # most pairs of partners are in range
    assert pair_set(nb.pairs_of(nbrs)) == expected
    reference = jax.jit(nb.build_jax, static_argnums=0)(
        spec, jnp.asarray(x), phi, jnp.diag(jnp.full(3, width)) if cell else None)
    assert pair_set(nb.pairs_of(reference)) == expected

@pytest.mark.parametrize("kind", list(BOXES))
def test_host_build_and_jax_build_give_the_same_list(kind):
    """The compiled CPU build (what runs on a CPU) and the JAX build (what runs on a GPU)
    give the same pairs in the same order, and the same count, reach and flags."""
    space = BOXES[kind]
    x, phi = system(np.random.default_rng(17), space)
    spec, _ = nb.allocate(space, x, phi, 1.1, "D", 0.25)
    host = jax.jit(nb.build, static_argnums=0)(spec, x, phi)
    reference = jax.jit(nb.build_jax, static_argnums=0)(spec, x, phi)
    assert int(host.count) > BODIES  # many pairs
    for a, b in zip(host, reference, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("kind", list(BOXES))
def test_host_build_in_parts_on_two_threads_is_the_one_pass_list(kind, monkeypatch):
    """The host build searches fixed parts of the bodies on two threads, each writing into
    its share of the rows, then moves the parts together: the list of the JAX build, in its
    order, both when every part's pairs fit in its share and when one part has more (a
    capacity of exactly the pair count: then the bodies are searched again in one pass)."""
    space = BOXES[kind]
    x, phi = system(np.random.default_rng(23), space)
    spec, _ = nb.allocate(space, x, phi, 1.1, "D", 0.25)
    reference = jax.jit(nb.build_jax, static_argnums=0)(spec, x, phi)
    count = int(reference.count)
    monkeypatch.setattr(nb, "HOST_THREAD_MIN_BODIES", 0)
    monkeypatch.setattr(nb._host, "threads", lambda parts: parts)
    searched = []
    one_pass = nb._host_pairs

    def spy(bodies, capacity, pairs_i, pairs_j, search):
        def logged(first, last, offset, room):
            searched.append((first, last))
            return search(first, last, offset, room)
        return one_pass(bodies, capacity, pairs_i, pairs_j, logged)

    monkeypatch.setattr(nb, "_host_pairs", spy)
    for capacity, again in ((4 * count, False), (count, True)):
        searched.clear()
        host = nb.build(dataclasses.replace(spec, capacity=capacity), x, phi)
        assert ((0, BODIES) in searched) == again and len(searched) == 2 + again
        assert int(host.count) == count
        for a, b in ((host.i, reference.i), (host.j, reference.j)):
            np.testing.assert_array_equal(np.asarray(a)[:count], np.asarray(b)[:count])
            assert np.all(np.asarray(a)[count:] == BODIES)


@pytest.mark.parametrize("builder", ["host", "jax"])
def test_the_list_visits_the_bodies_in_an_order_in_space_whatever_their_numbering(builder):
    """A crystal whose bodies are numbered at random (as a liquid's numbering ends up after it
    diffuses) gets its pairs with K in an order in space: consecutive bodies K of the list are
    lattice neighbours (median distance one spacing; visited by number they would be about
    half the box apart), and the list holds the pairs of the crystal numbered row by row,
    renamed."""
    side = 10
    box = orthorhombic((float(side),) * 3)
    grid = np.stack(np.meshgrid(*(np.arange(side),) * 3, indexing="ij"), -1).reshape(-1, 3)
    rows = 0.5 + grid + 0.02 * np.random.default_rng(3).normal(size=grid.shape)
    number = np.random.default_rng(4).permutation(len(rows))  # body number[k] sits at rows[k]
    x = np.empty_like(rows)
    x[number] = rows
    phi = jnp.broadcast_to(jnp.eye(3), (len(rows), 3, 3))
    build = jax.jit(nb.build if builder == "host" else nb.build_jax, static_argnums=0)
    spec, _ = nb.allocate(box, jnp.asarray(x), phi, 1.2, "r", 0.2)
    listed = nb.pairs_of(build(spec, jnp.asarray(x), phi))
    first = listed[np.r_[True, listed[1:, 0] != listed[:-1, 0]], 0]  # the K in list order
    assert len(first) > len(rows) // 2
    step = x[first[1:]] - x[first[:-1]]
    step -= side * np.round(step / side)
    assert np.median(np.linalg.norm(step, axis=-1)) < 1.5
    spec_rows, _ = nb.allocate(box, jnp.asarray(rows), phi, 1.2, "r", 0.2)
    by_rows = nb.pairs_of(build(spec_rows, jnp.asarray(rows), phi))
    renamed = np.sort(number[by_rows], axis=-1)
    assert pair_set(listed) == pair_set(renamed)
