"""The route's detour (services/planner/route.py) against a float64 Dijkstra over the same
lattice, and the running time cost against the paper's instants."""

import dataclasses
import heapq
import math
from functools import lru_cache

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from common.config import ConfigError, load_config
from services.planner import kernels, mppi, route
from services.planner.costs import MapView, goal_distance, time_cost
from services.planner.params import PlannerParams
from services.plant.dynamics import S

CFG = load_config(overrides=["planner.samples=64", 'planner.goal_distance="route"'])
RP = route.RouteParams.from_config(CFG)
RES = CFG.mapper.resolution_m
K = int(round(RP.route_cell_m / RES))          # map cells per lattice cell
N = 16                                         # lattice cells per side: a 12.8 m map


def dijkstra(cost: np.ndarray, turn_cost: np.ndarray, goal_cell: tuple[int, int]
             ) -> np.ndarray:
    """The cost-to-go (16, n, n) float64 over the lattice's moves, one pose at a time: a move
    from pose (h, i, j) costs its length times the mean cost per metre at its sample cells
    (inf where any is off the lattice), exactly as route.py prices it."""
    n = cost.shape[0]
    step = RP.radius_m * 2 * math.pi / route.HEADINGS
    # the graph backwards: from each pose, the poses whose moves end there
    into: dict[tuple[int, int, int], list[tuple[tuple[int, int, int], float]]] = {}
    for h, row in enumerate(route.moves(RP)):
        for a, (h2, dr, dc, cells) in enumerate(row):
            grid = cost if a == 0 else turn_cost
            for i in range(n):
                for j in range(n):
                    vals = [grid[i + r, j + c] if 0 <= i + r < n and 0 <= j + c < n else np.inf
                            for r, c in cells]
                    if 0 <= i + dr < n and 0 <= j + dc < n:
                        into.setdefault((h2, i + dr, j + dc), []).append(
                            ((h, i, j), float(np.mean(vals)) * step))
    v = np.full((route.HEADINGS, n, n), np.inf)
    heap = []
    for i in range(n):
        for j in range(n):
            if ((i - goal_cell[0]) ** 2 + (j - goal_cell[1]) ** 2) * RP.route_cell_m ** 2 <= max(
                    RP.goal_radius_m, RP.route_cell_m / 2) ** 2:
                for h in range(route.HEADINGS):
                    v[h, i, j] = 0.0
                    heapq.heappush(heap, (0.0, (h, i, j)))
    while heap:
        d, s = heapq.heappop(heap)
        if d > v[s]:
            continue
        for prev, c in into.get(s, ()):
            if d + c < v[prev]:
                v[prev] = d + c
                heapq.heappush(heap, (d + c, prev))
    return v


M = route._margin(RP)
C = N + M - 1                                  # the centre cell of the empty field


@lru_cache(maxsize=1)
def open_ground() -> np.ndarray:
    """Dijkstra's cost-to-go on empty ground twice the test map's size and a margin, to its
    centre."""
    ones = np.ones((2 * C + 1,) * 2)
    return dijkstra(ones, ones, (C, C))


def detour(p, mean, variance, goal):
    return np.asarray(route.detour(p, jnp.asarray(mean, jnp.float32),
                                   None if variance is None else jnp.asarray(variance, jnp.float32),
                                   jnp.zeros(2, jnp.float32), RES, jnp.asarray(goal, jnp.float32)))


def test_the_empty_field_is_relaxs_fixed_point_bit_for_bit():
    """empty_field sweeps in place; its field is relax's, swept from the target to
    convergence, to the bit (every route, and so every table, depends on it)."""
    m = route._margin(RP)
    size, c, r = 2 * (N + m) - 1, N + m - 1, route._reach(RP)
    target = route.target_cells(RP, size, (c, c), np)
    ones = np.ones((size, size))
    edges = route.edge_costs(RP, ones, ones, np)
    vp = np.full((route.HEADINGS, size + 2 * r, size + 2 * r), np.inf)
    vp[:, r:-r, r:-r] = np.where(target, 0.0, np.inf)
    while not np.array_equal(new := np.minimum(vp[:, r:-r, r:-r],
                                               route.relax(RP, vp, edges, target, np)),
                             vp[:, r:-r, r:-r]):
        vp[:, r:-r, r:-r] = new
    assert route.empty_field.__wrapped__(RP, N).tobytes() == \
        vp[:, r:-r, r:-r].astype(np.float32).tobytes()


def test_the_empty_lattices_field_is_dijkstras_and_open_ground_has_no_detour():
    np.testing.assert_allclose(route.empty_field(RP, N), open_ground(), rtol=2e-6)
    # on open ground none, but where a pose faces the map's edge too near to turn back
    n = 40
    flat = np.zeros((n * K, n * K))
    got = detour(RP, flat, np.zeros_like(flat), (15.0, 17.0))
    inner = int(math.ceil((2 * RP.radius_m + 2 * RP.route_cell_m) / RP.route_cell_m))
    assert np.all(got[:, inner:-inner, inner:-inner] == 0.0)
    assert got[0, n // 2, -1] == pytest.approx(RP.route_cap_m)   # at the east edge, facing east


@pytest.mark.parametrize("unseen", [False, True])
def test_the_detour_round_a_wall_and_through_unseen_ground_is_dijkstras(rng, unseen):
    """A random wall (a 1 m step, grown) and, for VA-MPPI, random unseen
    ground: swept to convergence, route.detour is Dijkstra's route minus the empty
    lattice's, capped; the deterministic controller (no variance) sees no unseen ground."""
    mean = np.zeros((N * K, N * K))
    r0, c0 = rng.integers(10, 40, 2)
    mean[r0:r0 + 4, c0:c0 + rng.integers(10, 30)] = 1.0
    variance = np.where(rng.random((N, N)) < 0.3, 3.0, 1e-4).repeat(K, 0).repeat(K, 1)
    goal = rng.uniform(2.0, N * RP.route_cell_m - 2.0, 2)
    p = dataclasses.replace(RP, route_sweeps=400)
    got = detour(p, mean, variance if unseen else None, goal)
    cost, turn = (np.asarray(a, np.float64) for a in route.lattice_costs(
        p, jnp.asarray(mean, jnp.float32), jnp.asarray(variance, jnp.float32) if unseen else None,
        RES))
    assert np.isinf(cost).any() and (unseen == (cost == RP.route_unseen_factor).any())
    cell = tuple(int(x) for x in np.floor(goal[::-1] / RP.route_cell_m))
    full = dijkstra(cost, turn, cell)
    free = open_ground()[:, C - cell[0]:C - cell[0] + N, C - cell[1]:C - cell[1] + N]
    want = np.clip(np.where(np.isfinite(full), full - free, RP.route_cap_m), 0, RP.route_cap_m)
    np.testing.assert_allclose(got, want, atol=1e-4)      # seen: 4e-5
    assert got.max() > 1.0


def test_fewer_sweeps_give_a_lower_bound_exact_near_the_goal(rng):
    mean = np.zeros((N * K, N * K))
    mean[30:34, 4:50] = 1.0
    goal = (6.0, 9.5)
    exact = detour(dataclasses.replace(RP, route_sweeps=400), mean, None, goal)
    few = detour(dataclasses.replace(RP, route_sweeps=4), mean, None, goal)
    assert np.all(few <= exact + 1e-4)
    assert np.any(few < exact - 1.0)


def test_lookup_reads_the_lattice_at_its_poses_and_between_them(rng):
    field = jnp.asarray(rng.uniform(0, 10, (route.HEADINGS, N, N)), jnp.float32)
    origin = jnp.asarray([3.0, -2.0])
    i, j, h = 5, 7, 3
    st = np.zeros((3, 6), np.float32)
    cx, cy = 3.0 + (j + 0.5) * RP.route_cell_m, -2.0 + (i + 0.5) * RP.route_cell_m
    st[0, [S.X, S.Y, S.PSI]] = cx, cy, h * 2 * math.pi / 16
    st[1, [S.X, S.Y, S.PSI]] = cx + RP.route_cell_m / 2, cy, h * 2 * math.pi / 16 + 2 * math.pi
    st[2, [S.X, S.Y, S.PSI]] = cx, cy, (h + 0.5) * 2 * math.pi / 16
    got = np.asarray(route.lookup(RP, field, origin, jnp.asarray(st)))
    f = np.asarray(field, np.float64)
    np.testing.assert_allclose(got, [f[h, i, j], (f[h, i, j] + f[h, i, j + 1]) / 2,
                                     (f[h, i, j] + f[h + 1, i, j]) / 2], rtol=1e-5)


def test_the_running_time_cost_prices_waiting_first_above_stopping_last():
    """The creep's choice (docs/analysis.md): two plans that drive 3 s the same way, one
    after standing 1 s, one before braking for 1 s. The paper's instants price the one
    that waits lower (it is fast at 4 s); the running cost prices it higher (it is
    farther from the goal at every step). And the running cost is 7/4 w_t mean(d/V) over
    steps 1 .. N, d at every fourth step and linear between, in float64."""
    pp = PlannerParams.from_config(CFG)
    n = pp.horizon
    drive = np.tile([0.0, 2500.0], (n - 10, 1))
    stand = np.tile([0.0, 0.0], (10, 1))
    brake = np.tile([0.0, float(pp.limits.lo[1])], (10, 1))
    plans = {"wait first": np.concatenate([stand, drive]),
             "stop last": np.concatenate([drive, brake])}
    goal = jnp.asarray([60.0, 40.0, 0.0])
    x0 = jnp.asarray([0.0, 0, 0, 20.0, 40.0, 0.0], jnp.float32)
    m = MapView(jnp.zeros((400, 400)), jnp.zeros((400, 400)), jnp.zeros(2), RES)
    costs = {}
    for name, u in plans.items():
        states, _, _ = kernels.rollout(pp, x0, jnp.zeros(2), jnp.asarray(u, jnp.float32))
        for form in ("instants", "running"):
            c = dataclasses.replace(pp.cost, time_cost=form)
            costs[form, name] = float(jax.jit(lambda st, c=c: time_cost(c, st, goal, m)[0])(states))
        st = np.asarray(states, np.float64)
        knots = [*range(0, n, 4), n]
        dk = goal_distance(pp.cost, st[knots], np.asarray(goal, np.float64), np)
        d = np.interp(np.arange(n + 1), knots, dk)[1:]
        ref = pp.cost.w_time * 1.75 * np.mean(d / np.maximum(st[1:, S.V], 1.0))
        assert costs["running", name] == pytest.approx(ref, rel=1e-6)
    assert costs["instants", "wait first"] < costs["instants", "stop last"]
    assert costs["running", "wait first"] > costs["running", "stop last"]


def test_the_solve_prices_the_route_round_a_wall():
    """The goal behind a wall across the way: with the route, the goal distance the solve
    reports for a pose facing the wall is longer than the analytic one by the detour."""
    pp = PlannerParams.from_config(CFG)
    mean = jnp.zeros((400, 400)).at[180:220, 150:154].set(2.0)
    m = MapView(mean, jnp.zeros_like(mean), jnp.zeros(2), RES)
    goal = jnp.asarray([40.0, 40.0, 0.0])
    st = jnp.asarray([[0.0, 0, 0, 20.0, 40.0, 0.0]], jnp.float32)
    plain = float(goal_distance(pp.cost, st, goal)[0])
    routed = float(jax.jit(lambda mean, var: goal_distance(
        pp.cost, st, goal, m=mppi.map_view(pp, mean, var, m.origin, RES, goal)))(
            m.mean, m.variance)[0])
    assert plain == pytest.approx(20.0, abs=1e-3)            # dead ahead: the line
    assert routed > plain + 2.0


def test_a_route_cell_that_is_no_block_of_map_cells_is_refused():
    with pytest.raises(ConfigError, match=r"planner\.route_cell_m"):
        load_config(overrides=['planner.goal_distance="route"', "planner.route_cell_m=0.7"])
    load_config(overrides=['planner.goal_distance="route"', "planner.route_cell_m=0.4"])


@pytest.mark.parametrize("offset", range(K))
def test_a_passage_the_footprint_fits_through_stays_open_and_a_narrower_one_shuts(offset):
    """Two walls 1 m high across the map, seen from the lattice: with a gap 0.6 m wider
    than the footprint (the alleyway's 2.6 m beside its hidden cylinder, for a 2 m vehicle)
    a row of lattice cells along it stays open, and with a gap 0.4 m narrower than the
    footprint none does, wherever the gap lies on the lattice (`offset` map cells)."""
    width = 2.0 * RP.half_width_m

    def open_rows(gap):
        """Lattice rows open all along that lie in the gap (a wall's flat top is ground)."""
        mean = np.zeros((N * K, N * K))
        lo, hi = 20 + offset, 20 + offset + int(round(gap / RES))      # the faces, cells
        mean[lo - 5:lo, :] = 1.0
        mean[hi:hi + 5, :] = 1.0
        cost, _ = route.lattice_costs(RP, jnp.asarray(mean, jnp.float32), None, RES)
        rows = np.isfinite(np.asarray(cost)[:, 2:-2]).all(axis=1)   # off the edge's rim
        centre = (np.arange(N) + 0.5) * K
        return (rows & (centre > lo) & (centre < hi)).sum()

    assert open_rows(width + 0.6) >= 1
    assert open_rows(width - 0.4) == 0
