"""`vamppi bench peer`: one plain-MPPI iteration of ours against pytorch_mppi's.

The peer is pytorch_mppi (UM-ARM-Lab, PyPI `pytorch-mppi`), an optional extra
(`pip install -e '.[peer]'`), never a runtime dependency. The problem is the
deterministic controller's, i.e. MPPI without the visibility update, on the
planner benchmark's map and state:

- dynamics: the very functions of services.plant.dynamics (control clamp, RK4
  substeps of the Pacejka model) run on torch tensors through `TorchOps`, so
  both sides integrate the same equations; the peer's state carries the last
  applied control (for the rate limit) and dx/dt (for the dynamic cost);
- cost: services.planner.costs.rollout_cost with zero variance, ported to torch
  (`torch_cost`) and checked on every run against ours on the same rollouts
  (the bench reports the largest relative difference and refuses to time a
  port that disagrees);
- K samples, horizon N, dt, noise and temperature from the same config, float32,
  on the CPU (or the GPU both see).

Timed: our jitted iteration (`mppi.solver`) and the peer's `MPPI.command`, each
repetition blocked on, interleaved, medians.
"""

from __future__ import annotations

import math
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from common.config import Config
from deploy.bench.device import device_info, heading, markdown_table
from deploy.bench.kernels import planner_case, planner_inputs
from services.planner import kernels
from services.planner.costs import (
    CostParams,
    MapView,
    goal_distance,
    per_metre_weight,
    rollout_cost,
)
from services.planner.params import PlannerParams
from services.plant.dynamics import S, clamp_control, derivatives, integrate


class TorchOps:
    """The array namespace the dynamics are written against (`xp`), on torch."""
    pi = math.pi
    inf = math.inf

    def __init__(self, torch: Any, dtype: Any, device: Any):
        self.t, self.dtype, self.device = torch, dtype, device
        for name, fn in (("tanh", torch.tanh), ("tan", torch.tan), ("arctan", torch.atan),
                         ("arctan2", torch.atan2), ("sin", torch.sin), ("cos", torch.cos),
                         ("abs", torch.abs), ("sqrt", torch.sqrt), ("arccos", torch.acos),
                         ("where", torch.where), ("zeros_like", torch.zeros_like)):
            setattr(self, name, fn)

    def asarray(self, a: Any) -> Any:
        return self.t.as_tensor(np.asarray(a), dtype=self.dtype, device=self.device)

    def _t(self, b: Any, like: Any) -> Any:
        return b if self.t.is_tensor(b) else self.t.as_tensor(b, dtype=like.dtype,
                                                              device=like.device)

    def maximum(self, a: Any, b: Any) -> Any:
        return self.t.maximum(a, self._t(b, a))

    def minimum(self, a: Any, b: Any) -> Any:
        return self.t.minimum(a, self._t(b, a))

    def clip(self, a: Any, lo: Any, hi: Any) -> Any:
        return self.t.minimum(self.t.maximum(a, self._t(lo, a)), self._t(hi, a))

    def stack(self, xs: list[Any], axis: int = 0) -> Any:
        return self.t.stack(xs, dim=axis)


def torch_cost(torch: Any, c: CostParams, states: Any, xdots: Any, goal: Any, mean: Any,
               origin: Any, resolution: float) -> Any:
    """rollout_cost's six terms summed, zero variance, for a batch: states (K, N+1, 6),
    dx/dt (K, N, 6); goal (3,) and origin (2,) tensors, mean (H, W)."""
    n = c.horizon
    d = goal_distance(c, states, goal, TorchOps(torch, states.dtype, states.device))
    V = states[..., S.V]
    i2, i3 = int(round(2.0 / c.dt_s)), int(round(3.0 / c.dt_s))
    vf = c.time_speed_floor_mps
    s_time = c.w_time * (d[:, i2] / (4 * V[:, i2].clamp(min=vf))
                         + d[:, i3] / (2 * V[:, i3].clamp(min=vf))
                         + d[:, n] / V[:, n].clamp(min=vf))

    x = states[:, :-1]
    a_y = xdots[..., S.v] + x[..., S.V] * x[..., S.r]
    a_x = xdots[..., S.V] - x[..., S.v] * x[..., S.r]
    a_tot = torch.sqrt(a_x * a_x + a_y * a_y)
    beta = torch.atan2(x[..., S.v], x[..., S.V].clamp(min=0.5))
    s_dyn = c.w_dynamic * ((a_y.abs() >= c.a_roll_mps2).float() + (a_tot >= c.a_max_mps2).float()
                           + (beta.abs() >= c.beta_max_rad).float()
                           + (x[..., S.v].abs() >= c.v_lat_max_mps).float()).sum(-1)

    h, w = mean.shape
    fp = torch.as_tensor(np.asarray(c.footprint), dtype=states.dtype, device=states.device)
    cy, sy = torch.cos(states[..., S.PSI, None]), torch.sin(states[..., S.PSI, None])
    px = states[..., S.X, None] + cy * fp[:, 0] - sy * fp[:, 1]
    py = states[..., S.Y, None] + sy * fp[:, 0] + cy * fp[:, 1]
    col = torch.floor((px - origin[0]) / resolution).long()
    row = torch.floor((py - origin[1]) / resolution).long()
    outside = (col < 1) | (col > w - 2) | (row < 1) | (row > h - 2)
    col, row = col.clamp(1, w - 2), row.clamp(1, h - 2)
    hc = mean[row, col]
    gx = (mean[row, col + 1] - mean[row, col - 1]) / (2 * resolution)
    gy = (mean[row + 1, col] - mean[row - 1, col]) / (2 * resolution)
    step_t = torch.cat([torch.zeros_like(hc[:, :1]), hc[:, 1:] - hc[:, :-1]], dim=1)
    first = (torch.arange(hc.shape[-1], device=hc.device) % c.footprint_points) == 0
    step_a = torch.where(first, torch.zeros_like(hc), hc - torch.roll(hc, 1, dims=-1))
    r0 = int(math.floor((float(states[0, 0, S.Y]) - float(origin[1])) / resolution))
    c0 = int(math.floor((float(states[0, 0, S.X]) - float(origin[0])) / resolution))
    h0 = mean[min(max(r0, 0), h - 1), min(max(c0, 0), w - 1)]
    hits = ((gx.abs() > c.grad_threshold).float() + (gy.abs() > c.grad_threshold).float()
            + (step_t.abs() > c.step_threshold).float()
            + (step_a.abs() > c.step_threshold).float()
            + ((hc - h0).abs() > c.height_threshold_m).float())
    per_step = torch.where(outside, torch.full_like(hits, 5.0), hits)
    if c.surface_distance_m > 0.0:            # priced per metre crossed, as costs.rollout_cost
        per_step = per_step * per_metre_weight(c, V, torch)[..., None]
    s_surf = c.w_surface * per_step.sum((1, 2))

    d0 = d[:, 0]
    phi = torch.sigmoid(2.0 * (c.activation_distance_m - d0))
    ratio = d[:, n] / d0.clamp(min=1e-3)
    s_dist = c.w_dist * (ratio + 2.0 * phi * ratio)
    s_acc = (c.w_acc * V[:, n] ** 2 * V[:, n].abs()
             / (2.0 * d[:, n].clamp(min=c.acc_distance_floor_m)))
    psi_w = torch.arange(n + 1, device=states.device, dtype=states.dtype) / n
    dpsi = (states[..., S.PSI] - goal[2] + math.pi) % (2 * math.pi) - math.pi
    s_or = c.w_orientation * phi * (dpsi.abs() * psi_w).sum(-1)
    return s_time + s_dyn + s_surf + s_dist + s_acc + s_or


class MissingExtra(RuntimeError):
    """The peer benchmark's optional packages are not installed."""


def bench_peer(cfg: Config, samples: list[int], reps: int) -> dict[str, Any]:
    """Ours (deterministic controller, one iteration) against pytorch_mppi, per K."""
    try:
        import torch
        from pytorch_mppi import MPPI
    except ImportError as exc:
        raise MissingExtra("needs the optional extra: "
                           "pip install -e '.[peer]' (torch, pytorch-mppi)") from exc
    from importlib.metadata import version

    inputs = planner_inputs(cfg)
    x0, u0, goal, mean, var, origin, res = inputs
    device = "cuda" if torch.cuda.is_available() and jax.default_backend() == "gpu" else "cpu"
    dt32 = torch.float32
    ops = TorchOps(torch, dt32, device)
    tt = {k: torch.as_tensor(np.asarray(v), dtype=dt32, device=device)
          for k, v in (("x0", x0), ("goal", goal), ("mean", mean), ("origin", origin))}
    cases, agreement = [], {}
    for k in samples:
        params = PlannerParams.from_config(cfg.replace(**{
            "planner.controller": "deterministic", "planner.samples": k, "planner.iterations": 1}))
        ours = planner_case(cfg, "deterministic", k, inputs)
        v, lim = params.vehicle, params.limits

        def dynamics(state: Any, action: Any, v=v, lim=lim, params=params) -> Any:
            x, u_last = state[:, :6], state[:, 6:8]
            u = clamp_control(action, u_last, lim, params.dt_s, ops)
            xdot = derivatives(v, x, u, ops)
            return torch.cat([integrate(v, x, u, params.dt_s, params.substeps, ops), u, xdot], 1)

        def terminal(states: Any, actions: Any, c=params.cost) -> Any:
            s = states[0]
            xs = torch.cat([tt["x0"].expand(s.shape[0], 1, 6), s[..., :6]], dim=1)
            return torch_cost(torch, c, xs, s[..., 8:14], tt["goal"], tt["mean"], tt["origin"],
                              float(res))

        sigma = torch.diag(torch.as_tensor(np.square(params.noise_std), dtype=dt32))
        peer = MPPI(dynamics, lambda s, a: torch.zeros(s.shape[0], dtype=dt32, device=device),
                    14, sigma, num_samples=k, horizon=params.horizon, device=device,
                    terminal_state_cost=terminal, lambda_=params.temperature,
                    u_min=ops.asarray(lim.lo), u_max=ops.asarray(lim.hi))
        state0 = torch.cat([tt["x0"], torch.zeros(8, dtype=dt32, device=device)])

        # the port agrees with ours on the same rollouts (ours: jax, float32)
        ctrl = np.random.default_rng(k).normal(size=(k, params.horizon, 2)) * params.noise_std
        ctrl = ctrl.astype(np.float32)
        xs, _, xd = jax.vmap(kernels.rollout, in_axes=(None, None, None, 0))(
            params, jnp.asarray(x0), jnp.asarray(u0), jnp.asarray(ctrl))
        m = MapView(jnp.asarray(mean), jnp.asarray(var), jnp.asarray(origin), float(res))
        zero = jnp.zeros((params.horizon + 1, 5 * len(params.cost.footprint)), jnp.float32)
        ref = np.asarray(jax.vmap(rollout_cost, in_axes=(None, 0, 0, None, None, None))(
            params.cost, xs, xd, jnp.asarray(goal), m, zero).sum(-1))
        st = torch.as_tensor(np.array(xs), device=device)
        got = torch_cost(torch, params.cost, st, torch.as_tensor(np.array(xd), device=device),
                         tt["goal"], tt["mean"], tt["origin"], float(res)).cpu().numpy()
        rel = float(np.max(np.abs(got - ref) / np.maximum(np.abs(ref), 1.0)))
        agreement[k] = rel
        if rel > 1e-3:
            raise RuntimeError(f"the torch port of the cost disagrees with ours at K={k}: "
                               f"largest relative difference {rel:.2e}")

        peer.command(state0)                                    # warm-up
        t_ours, t_peer = [], []
        for _ in range(reps):
            t0 = time.perf_counter()
            jax.block_until_ready(ours.fn(*ours.args))
            t_ours.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            peer.command(state0)
            if device == "cuda":
                torch.cuda.synchronize()
            t_peer.append(time.perf_counter() - t0)
        for name, t in (("vamppi", t_ours), ("pytorch_mppi", t_peer)):
            a = np.asarray(t) * 1e3
            cases.append({"implementation": name, "samples": k,
                          "median_ms": round(float(np.median(a)), 3),
                          "p95_ms": round(float(np.percentile(a, 95)), 3), "reps": reps})
    return {"benchmark": "peer", **device_info(), "torch": torch.__version__,
            "pytorch_mppi": version("pytorch-mppi"), "torch_device": device,
            "torch_threads": torch.get_num_threads(),
            "settings": {"problem": "deterministic controller, no visibility update",
                         "horizon": cfg.planner.horizon, "reps": reps,
                         "cost_max_rel_diff": agreement},
            "cases": cases}
def peer_table(result: dict[str, Any]) -> str:
    """`vamppi bench peer`'s result as a markdown table."""
    ours = {c["samples"]: c["median_ms"] for c in result["cases"]
            if c["implementation"] == "vamppi"}
    return markdown_table(
        f"{heading(result)}; torch {result['torch']} on {result['torch_device']} "
        f"({result['torch_threads']} threads), pytorch_mppi {result['pytorch_mppi']}",
        ["implementation", "K", "median ms", "p95 ms", "time / ours"],
        [[c["implementation"], c["samples"], f"{c['median_ms']:.1f}", f"{c['p95_ms']:.1f}",
          f"{c['median_ms'] / ours[c['samples']]:.2f}"] for c in result["cases"]])
