"""The goal distance along a drivable path (common.geometry.goal_path_length) against a
slow float64 reference: every path of one or two arcs and straights, walked in 2 cm steps
until it first comes within the goal circle."""

from __future__ import annotations

import numpy as np
import pytest

from common.geometry import TURN_DISTANCES, dubins_to_point, goal_path_length, turning_radius

H = 0.02                         # the reference's step along a path, m


def walked(px: float, py: float, r: float, reach: float, smax: float = 60.0
           ) -> tuple[float, str]:
    """The shortest first entry into the circle of radius `reach` round (px, py), body
    frame, over paths of an arc (left or right, any length), then a straight or an arc
    the other way, each sampled every H metres; plus `reach`. Also which kind won."""
    if np.hypot(px, py) <= reach:
        return float(np.hypot(px, py)), "inside"
    best, kind = np.inf, ""
    a = np.arange(0.0, 2.0 * np.pi * r, H)
    s = np.arange(0.0, smax, H)
    for side in (1.0, -1.0):
        th = side * a / r                                    # heading after the first arc
        pos = np.stack([r * np.sin(np.abs(th)), side * r * (1.0 - np.cos(th))], -1)
        seconds = {
            "arc, straight": pos[:, None] + s[None, :, None]
            * np.stack([np.cos(th), np.sin(th)], -1)[:, None],
        }
        centre = pos - side * r * np.stack([-np.sin(th), np.cos(th)], -1)
        back = s[s <= 2.0 * np.pi * r]
        h2 = th[:, None] - side * back[None] / r
        seconds["arc, arc"] = centre[:, None] + side * r * np.stack([-np.sin(h2), np.cos(h2)], -1)
        inside = np.hypot(pos[:, 0] - px, pos[:, 1] - py) <= reach
        if inside.any() and a[inside.argmax()] < best:
            best, kind = a[inside.argmax()], "arc"
        for name, q in seconds.items():
            hit = np.hypot(q[..., 0] - px, q[..., 1] - py) <= reach
            if hit.any():
                length = np.where(hit.any(1), a + s[:q.shape[1]][hit.argmax(1)], np.inf)
                if length.min() < best:
                    best, kind = float(length.min()), name
    return best + reach, kind


def test_goal_path_length_matches_the_walked_paths_on_fresh_points():
    seed = int(np.random.SeedSequence().entropy % 2**32)
    rng = np.random.default_rng(seed)
    r = turning_radius(3.6, 0.6)
    seen = set()
    for _ in range(10):
        px, py = rng.uniform(-14.0, 14.0, 2)
        yaw = rng.uniform(-np.pi, np.pi)
        reach = float(rng.choice([0.5, 2.0]))
        ref, kind = walked(px, py, r, reach)
        # the same point as a world offset from a pose heading yaw
        dx, dy = np.cos(yaw) * px - np.sin(yaw) * py, np.sin(yaw) * px + np.cos(yaw) * py
        got = float(goal_path_length(dx, dy, yaw, r, reach))
        seen.add(kind)
        # the reference overshoots by up to a step; two arcs: an upper bound, for the
        # second arc's centre is tried at TURN_DISTANCES (17) distances; against 801 of
        # them it is at most 1.12 of their spacing longer (0.279 m at reach 2, 0.065 m at
        # 0.5; 800,000 and 400,000 uniform points; 0.3 % of points at reach 2 over 0.09 m)
        spacing = 2.0 * reach / (TURN_DISTANCES - 1)
        high = 1.12 * spacing if kind == "arc, arc" else 1e-6
        assert -2.0 * H <= got - ref <= high, (seed, px, py, yaw, reach, kind, got, ref)
        assert got >= np.hypot(px, py) - 1e-9
    assert seen - {"inside"}, seed


@pytest.mark.parametrize("xp_name", ["numpy", "jax"])
def test_a_goal_dead_ahead_is_its_straight_line_distance_others_a_turn_away(xp_name):
    import jax.numpy as jnp
    xp = np if xp_name == "numpy" else jnp
    r = turning_radius(3.6, 0.6)
    ahead = goal_path_length(xp.asarray([20.0, 20.0, 5.0]), xp.asarray([0.0, 1e-7, -1e-7]),
                             xp.asarray([0.0, 0.0, 0.0]), r, 2.0, xp)
    np.testing.assert_allclose(np.asarray(ahead), [20.0, 20.0, 5.0], rtol=1e-6)
    # 10 m straight behind: a half turn (pi r), then back along the far side of the circle
    behind = float(dubins_to_point(-10.0, 0.0, 0.0, r))
    assert behind > np.pi * r + 10.0 - 2.0 * r
    # its last leg is a straight: the goal circle's reach taken off it is added back
    assert float(goal_path_length(-10.0, 0.0, 0.0, r, 2.0)) == pytest.approx(behind)
    # 10 m to the left: inside the left turning circle, yet the left turn alone passes
    # within 2 m of it, much shorter than the way to the point itself
    assert float(goal_path_length(0.0, 10.0, 0.0, r, 2.0)) < float(
        dubins_to_point(0.0, 10.0, 0.0, r)) - 3.0


def test_goal_distance_at_speed_is_the_path_of_the_turn_the_tyres_allow_on_fresh_poses():
    """`planner.turn_radius_speed`: against a float64 construction at the radius the tyres
    allow, max(R, V^2 / D g), into a goal circle as much wider; below that speed the same
    number as the tightest turn's, and a goal beside the vehicle farther the faster."""
    import jax.numpy as jnp

    from common.config import load_config
    from services.planner.costs import CostParams, goal_distance
    seed = int(np.random.SeedSequence().entropy % 2**32)
    rng = np.random.default_rng(seed)
    on, off = (CostParams.from_config(load_config(overrides={
        "planner.goal_distance": "turning", "planner.turn_radius_speed": f}))
        for f in (True, False))
    n = 200
    states = np.zeros((n, 6))
    states[:, 0] = rng.uniform(0.0, 12.0, n)                      # V
    states[:, 3:5] = rng.uniform(-25.0, 25.0, (n, 2))             # X, Y
    states[:, 5] = rng.uniform(-np.pi, np.pi, n)                  # psi
    goal = np.array([*rng.uniform(-10.0, 10.0, 2), 0.0])
    got = np.asarray(goal_distance(on, jnp.asarray(states, jnp.float32),
                                   jnp.asarray(goal, jnp.float32), jnp))
    r, reach, a_lat = on.turn_radius, on.goal_radius_m, on.stop.lateral_accel_mps2
    scale = np.maximum(states[:, 0] ** 2 / (a_lat * r), 1.0)
    ref = np.array([float(goal_path_length(goal[0] - x, goal[1] - y, psi, r * k, reach * k))
                    for x, y, psi, k in zip(*states[:, 3:6].T, scale, strict=True)])
    # float32 through the k-scaled path: 5.3e-6 the largest seen on 30,000 poses
    # (150 seeds); the tightest turn alone reaches 2.7e-6 on the same poses
    np.testing.assert_allclose(got, ref, rtol=6e-6, err_msg=str(seed))
    slow = states[:, 0] ** 2 < a_lat * r
    plain = np.asarray(goal_distance(off, jnp.asarray(states, jnp.float32),
                                     jnp.asarray(goal, jnp.float32), jnp))
    np.testing.assert_array_equal(got[slow], plain[slow])
    beside = np.zeros((4, 6), np.float32)
    beside[:, 0] = [4.0, 6.0, 8.0, 10.0]
    d = np.asarray(goal_distance(on, jnp.asarray(beside), jnp.array([0.0, 15.0, 0.0]), jnp))
    assert (np.diff(d) > 0).all() and d[0] == pytest.approx(float(
        goal_path_length(0.0, 15.0, 0.0, r, reach)), rel=1e-6)
