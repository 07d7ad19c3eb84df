"""The planner's protocol: which (state, map) pairs it solves on, and how it warm-starts.

    on_state(params, run, state, wall) -> (run, verdict, outputs)
    on_map(params, run, map, wall) -> (run, verdict)
    due(params, run, wall) -> Job | None
    solve(params, run, job, wall) -> (run, outputs)
    recover(params, run, cmd) -> run

Inputs are checked (common.protocol.check; a map against the configured grid) before they
change anything. In lockstep the planner solves each tick once, on the state and the map
of that tick's stamp, in order; a repeat of a tick it has answered (the plant re-offering
it) is answered with the outputs of that solve. In realtime it solves as soon as a new
map is in, on the newest state, at most once per half tick; with no new map for 1.5
ticks, once a tick on the last map.

**Warm start.** Each solve starts from the last one's nominal, shifted by the ticks
between them (`mppi.advance`), which assumes the plant applied that nominal meanwhile.
`warm_start` checks it against the plant's own account: the control the state says was
applied (`u_applied`) must be the nominal's for that time, up to what one control period
of the actuators' rate limits explains (the plant follows a new command through them). If
it is not (the plant braked on stale commands or perception, another planner drove, the
plan ran out) the nominal is started afresh, the sampler's key kept: a nominal shifted
past what really happened had held the vehicle braking at a standstill after an outage,
where every sample's braking force does nothing and MPPI has no gradient to leave it.

**Recovery.** The plant's last obeyed command carries the nominal it applies and the
sampler state after that solve (`Cmd.rng`): a restarted planner goes on from them
(`recover`), exactly where the one before left off.

**Authority and roles.** Every state names the planner the plant obeys (source, process,
epoch). A planner commands only while a state names it (`commands`); the others follow
the authority's commands (`on_cmd`: its nominal and sampler key become theirs), so that
whoever takes over next continues the same plan: a `standby` only follows (the plant
promotes it when the authority's heartbeat stops), a `candidate` (a swap) also solves
each tick and publishes its plans on the `shadow` topic until it is handed authority. A
planner that becomes the authority at a tick solves it only once it has followed the
command the plant obeyed for the tick before (the state names it among its inputs), so
that its first command continues the old plan; a `replay` planner (`vamppi replay
--feed`) commands every tick, as no plant judges it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import jax.numpy as jnp
import numpy as np

from common.config import Config
from common.messages import Cmd, Map, State
from common.protocol import (
    ACCEPTED,
    EPS,
    NEW,
    REPEAT,
    Episodes,
    Order,
    Out,
    after_rejection,
    context,
    judge,
    newer,
    on_tick,
    ref,
)
from common.scenarios import Scenario
from common.topics import topic_key
from services.planner import mppi
from services.planner.costs import TERMS
from services.planner.params import PlannerParams

PENDING = 8                # lockstep: states / maps kept waiting for their partner


@dataclass(frozen=True)
class PlannerProtocolParams:
    mppi: PlannerParams
    goal: np.ndarray                  # (3,) x, y, yaw
    truth: np.ndarray                 # the scenario's heightmap (prescient)
    grid: tuple[int, float, tuple[float, float]]   # cells, resolution, origin
    lockstep: bool
    plant_dt: float
    state_ahead_s: float
    map_ahead_s: float
    follow_tol: tuple[float, float]   # steer, force: one tick of the actuators' rate limits
    state_key: str
    map_key: str

    @classmethod
    def from_config(cls, cfg: Config, scenario: Scenario) -> PlannerProtocolParams:
        p = PlannerParams.from_config(cfg)
        g, v, dt = scenario.goal, cfg.vehicle, cfg.planner.dt_s
        return cls(mppi=p, goal=np.array([g.x, g.y, g.yaw]), truth=scenario.heightmap,
                   grid=(cfg.mapper.size_cells, cfg.mapper.resolution_m,
                         (float(scenario.origin[0]), float(scenario.origin[1]))),
                   lockstep=cfg.episode.clock == "lockstep", plant_dt=1.0 / cfg.plant.rate_hz,
                   state_ahead_s=dt, map_ahead_s=max(dt, 1.0 / cfg.sensor.rate_hz),
                   follow_tol=(v.steer_rate_max_radps * dt, v.force_rate_max_nps * dt),
                   state_key=topic_key(cfg.episode.vehicle, "state"),
                   map_key=topic_key(cfg.episode.vehicle, "map"))

    @property
    def dt(self) -> float:
        return self.mppi.dt_s


@dataclass(frozen=True)
class PlannerCtx:
    """One episode's: accepted inputs, those waiting to be solved on, the warm-start state
    and the last solve's outputs."""
    states: Order = field(default_factory=Order)
    maps: Order = field(default_factory=Order)
    waiting_states: tuple[State, ...] = ()       # lockstep: by stamp; realtime: the newest
    waiting_maps: tuple[Map, ...] = ()
    map: Map | None = None                       # realtime: the map it solves on
    fresh_map: bool = False
    qs: mppi.PlannerState | None = None
    last_t: float | None = None
    last_wall: float = 0.0
    answer: tuple[Out, ...] = ()
    cold_starts: int = 0
    authority: tuple[str, int, int] = ("", 0, -1)  # source, boot, epoch of the newest state
    needed_t0: float | None = None     # authority since a tick: the obeyed command before it
    needed_wall: float = 0.0
    cmds: Order = field(default_factory=Order)    # the authority's commands followed
    shadow_t: float | None = None      # a candidate: the last tick it solved in shadow
    followed: tuple[tuple[float, mppi.PlannerState], ...] = ()  # the last few, by t0


@dataclass(frozen=True)
class PlannerRun:
    seed: int = 0                                # episode.seed: the sampler's first key
    episodes: Episodes[PlannerCtx] = field(default_factory=Episodes)
    held_state: State | None = None
    held_map: Map | None = None
    source: str = "planner/0"                    # this instance and process
    boot: int = 0
    role: str = "active"                         # active | standby | candidate | replay

    def names_me(self, authority: tuple[str, int, int]) -> bool:
        source, boot, _ = authority
        return source == self.source and boot in (0, self.boot)


# how long a new authority waits for the command it must follow: in lockstep (time waits)
# a second; in realtime one control period, well inside the plant's command timeout, after
# which it solves from the plan it has followed so far
FOLLOW_WAIT_S = 1.0


@dataclass(frozen=True)
class Job:
    episode: int
    state: State
    map: Map


def map_problem(p: PlannerProtocolParams, m: Map) -> str:
    n, res, origin = p.grid
    if m.mean.shape != (n, n):
        return f"wrong size {m.mean.shape}, the grid is {(n, n)}"
    if m.resolution != res or tuple(float(v) for v in m.origin) != origin:
        return "origin or resolution are not the configured grid's"
    return ""


def on_state(p: PlannerProtocolParams, run: PlannerRun, msg: State, wall: float
             ) -> tuple[PlannerRun, str, tuple[Out, ...]]:
    h = msg.header
    ctx = context(run.episodes, h.episode, PlannerCtx)
    states, verdict = judge(ctx.states, h, wall, p.state_ahead_s, not p.lockstep,
                           "plant", p.dt)
    if verdict not in ACCEPTED:
        return after_rejection(run, h.episode, replace(ctx, states=states),
                               states is not ctx.states), verdict, ()
    ctx = replace(ctx, states=states)
    if msg.epoch >= ctx.authority[2]:
        named = (msg.authority, msg.authority_boot, msg.epoch)
        if run.names_me(named) and not run.names_me(ctx.authority) and ctx.authority[0]:
            obeyed = [i.stamp for i in h.inputs if i.key.endswith("/cmd")]
            needed = max(obeyed) if obeyed else None
            ctx = replace(ctx, needed_t0=needed, needed_wall=wall)
            # followed beyond what the plant obeyed (the old planner's command for the tick
            # the handover took): go back to the one obeyed
            back = [qs for t0, qs in ctx.followed if needed is not None
                    and abs(t0 - needed) <= EPS]
            if back and ctx.last_t is not None and ctx.last_t > needed + EPS:
                ctx = replace(ctx, qs=back[0], last_t=needed, answer=())
        ctx = replace(ctx, authority=named)
    outs: tuple[Out, ...] = ()
    boundary = on_tick(h.stamp, p.dt)
    if p.lockstep:
        if verdict == REPEAT and ctx.last_t is not None and abs(h.stamp - ctx.last_t) <= EPS:
            outs = ctx.answer if commands(run, ctx) else ()
        elif verdict == NEW and boundary and (ctx.last_t is None or h.stamp > ctx.last_t + EPS):
            ctx = replace(ctx, waiting_states=(*ctx.waiting_states, msg)[-PENDING:])
    else:
        ctx = replace(ctx, waiting_states=(msg,))
    held = msg if (boundary or msg.outcome) and newer(run.held_state, msg) else run.held_state
    return (replace(run, episodes=run.episodes.put(h.episode, ctx), held_state=held),
            verdict, outs)


def on_map(p: PlannerProtocolParams, run: PlannerRun, m: Map, wall: float
           ) -> tuple[PlannerRun, str]:
    h = m.header
    problem = map_problem(p, m)
    if problem:
        return run, problem
    ctx = context(run.episodes, h.episode, PlannerCtx)
    maps, verdict = judge(ctx.maps, h, wall, p.map_ahead_s, not p.lockstep, "mapper")
    if verdict not in ACCEPTED:
        return after_rejection(run, h.episode, replace(ctx, maps=maps),
                               maps is not ctx.maps), verdict
    ctx = replace(ctx, maps=maps)
    if verdict == NEW:
        if p.lockstep:
            if ctx.last_t is None or h.stamp > ctx.last_t + EPS:
                ctx = replace(ctx, waiting_maps=(*ctx.waiting_maps, m)[-PENDING:])
        else:
            ctx = replace(ctx, map=m, fresh_map=True)
    held = m if newer(run.held_map, m) else run.held_map
    return replace(run, episodes=run.episodes.put(h.episode, ctx), held_map=held), verdict


def realtime_due(last_t: float | None, t: float, fresh_map: bool, dt: float,
                 since_last_s: float) -> bool:
    """Whether a realtime solve is due on the newest state (stamp t): the first; half a tick
    after the last on a new map; a tick after it on the last map once no new one has come
    for 1.5 ticks of wall time."""
    if last_t is None:
        return True
    if fresh_map:
        return t >= last_t + 0.5 * dt - EPS
    return since_last_s >= 1.5 * dt and t >= last_t + dt - EPS


def commands(run: PlannerRun, ctx: PlannerCtx) -> bool:
    """Whether this planner commands in this episode: the plant names it (or it replays)."""
    return run.role == "replay" or run.names_me(ctx.authority)


def due(p: PlannerProtocolParams, run: PlannerRun, wall: float) -> Job | None:
    """The solve to make now, if any: in the newest episode that has one. A standby that is
    not the authority never solves; a new authority not before it has followed the command
    obeyed before its first tick (or waited FOLLOW_WAIT_S, in realtime a period, for it)."""
    for episode, ctx in reversed(run.episodes.items):
        mine = commands(run, ctx)
        if not mine and run.role != "candidate":
            continue
        wait_s = FOLLOW_WAIT_S if p.lockstep else p.dt
        if (mine and ctx.needed_t0 is not None and wall - ctx.needed_wall < wait_s
                and (ctx.last_t is None or ctx.last_t < ctx.needed_t0 - EPS)):
            continue
        last = ctx.last_t
        if not mine and ctx.shadow_t is not None:     # a shadow solve keeps no state
            last = ctx.shadow_t if last is None else max(last, ctx.shadow_t)
        if p.lockstep:
            maps = {round(m.header.stamp / EPS): m for m in ctx.waiting_maps}
            for st in sorted(ctx.waiting_states, key=lambda s: s.header.stamp):
                m = maps.get(round(st.header.stamp / EPS))
                if m is not None and (last is None or st.header.stamp > last + EPS):
                    return Job(episode, st, m)
        elif ctx.waiting_states and ctx.map is not None:
            st = ctx.waiting_states[-1]
            if realtime_due(last, st.header.stamp, ctx.fresh_map, p.dt, wall - ctx.last_wall):
                return Job(episode, st, ctx.map)
    return None


def warm_start(p: PlannerProtocolParams, qs: mppi.PlannerState, last_t: float, t: float,
               u_applied: np.ndarray) -> tuple[mppi.PlannerState, bool]:
    """The state to solve from at `t`, after the last solve at `last_t`, and whether it had
    to start afresh: the nominal shifted to `t` where the plant applied it meanwhile."""
    ticks = int(round((t - last_t) / p.dt))
    if ticks <= 0:
        return qs, False
    nominal = np.asarray(qs.nominal)
    i = int(math.floor((t - p.plant_dt - last_t) / p.dt + 1e-9))  # the entry applied last
    follows = 0 <= i < len(nominal) and ticks < len(nominal) and bool(
        np.all(np.abs(np.asarray(u_applied, np.float64) - nominal[i]) <= p.follow_tol))
    if not follows:
        return qs._replace(nominal=jnp.asarray(np.zeros(nominal.shape, np.float32))), True
    return mppi.advance(qs, ticks), False


def _finite(v: Any) -> float:
    """A cost for the stats message: inf (every rollout invalid) becomes float max."""
    return float(np.nan_to_num(float(v), posinf=np.finfo(np.float32).max))


def solve(p: PlannerProtocolParams, run: PlannerRun, job: Job, wall: float
          ) -> tuple[PlannerRun, tuple[Out, ...]]:
    """One solve on the job's state and map: the cmd, plan and stats to publish."""
    ctx = context(run.episodes, job.episode, PlannerCtx)
    st, m = job.state, job.map
    t = st.header.stamp
    cold = False
    if ctx.qs is None or ctx.last_t is None or t < ctx.last_t - EPS:
        qs = mppi.initial_state(p.mppi, run.seed)
    else:
        qs, cold = warm_start(p, ctx.qs, ctx.last_t, t, st.u_applied)
    mean, var = mppi.planning_map(p.mppi, p.truth, m.mean, m.variance)
    t_solve = time.perf_counter()
    qs, out = mppi.solve(p.mppi, qs, st.x, st.u_applied, p.goal, mean, var, m.origin,
                         m.resolution)
    controls = np.asarray(out.controls)
    solve_ms = (time.perf_counter() - t_solve) * 1e3
    inputs = (ref(p.state_key, st), ref(p.map_key, m))
    ep = job.episode
    mine = commands(run, ctx)
    outs = (
        Out("cmd", t, {"t0": t, "dt": p.dt, "controls": controls,
                       "rng": np.asarray(qs.key, dtype="<u4")}, inputs, ep),
        Out("plan", t, {"controller": p.mppi.controller, "optimal": np.asarray(out.optimal),
                        "nominal": controls, "rollouts": np.asarray(out.rollouts_xy),
                        "rollout_costs": np.nan_to_num(np.asarray(out.rollout_costs, np.float32),
                                                       posinf=np.finfo(np.float32).max)},
            inputs, ep),
        Out("stats", t, {"controller": p.mppi.controller, "samples": p.mppi.samples,
                         "solve_ms": solve_ms, "cost_min": _finite(out.cost_min),
                         "cost_mean": _finite(out.cost_mean),
                         "terms": dict(zip(TERMS, map(float, np.asarray(out.terms)),
                                           strict=True))}, inputs, ep))
    if not mine:    # a candidate: its plan on the shadow topic; it keeps the authority's state
        ctx = replace(ctx, shadow_t=t, last_wall=wall, fresh_map=False)
        return replace(run, episodes=run.episodes.put(ep, ctx)), (replace(outs[1],
                                                                           topic="shadow"),)
    ctx = replace(ctx, qs=qs, last_t=t, last_wall=wall, answer=outs, fresh_map=False,
                  needed_t0=None if mine else ctx.needed_t0,
                  cold_starts=ctx.cold_starts + cold,
                  waiting_states=tuple(s for s in ctx.waiting_states
                                       if s.header.stamp > t + EPS) if p.lockstep else (),
                  waiting_maps=tuple(x for x in ctx.waiting_maps if x.header.stamp > t + EPS))
    return replace(run, episodes=run.episodes.put(ep, ctx)), outs


def on_cmd(p: PlannerProtocolParams, run: PlannerRun, cmd: Cmd, wall: float
           ) -> tuple[PlannerRun, str]:
    """Follow the authority's command (another planner's): its nominal and sampler key
    become this planner's, so that it continues the same plan if it takes over."""
    h = cmd.header
    if h.source == run.source:
        return run, "mine"
    ctx = run.episodes.get(h.episode)
    if ctx is None:
        return run, "another episode"
    src, boot, _ = ctx.authority
    if h.source != src or (boot and h.boot != boot):
        return run, "not the authority"
    cmds, verdict = judge(ctx.cmds, h, wall, math.inf, False, "planner")
    if verdict not in ACCEPTED:
        return run, verdict
    if commands(run, ctx) or (ctx.last_t is not None and cmd.t0 < ctx.last_t - EPS):
        return replace(run, episodes=run.episodes.put(h.episode, replace(ctx, cmds=cmds))), \
            "not followed"
    run = recover(p, replace(run, episodes=run.episodes.put(h.episode,
                                                             replace(ctx, cmds=cmds))), cmd)
    return run, verdict


def handover_request(run: PlannerRun, episode: int | None = None, retire: bool = True,
                     reason: str = "swap") -> Out | None:
    """The Handover asking the plant for the authority in force (of the newest episode), once
    this candidate has solved in shadow on the inputs it accepted (a planner that cannot
    work here, a grid or camera not the running one's, never asks)."""
    got = run.episodes.current() if episode is None else (episode, run.episodes.get(episode))
    if got is None or got[1] is None or not got[1].authority[0] or got[1].shadow_t is None:
        return None
    ep, ctx = got
    src, _, epoch = ctx.authority
    if run.names_me(ctx.authority):
        return None
    return Out("handover", 0.0 if ctx.last_t is None else ctx.last_t,
               {"to": run.source, "to_boot": run.boot, "current": src, "epoch": epoch,
                "retire": retire, "reason": reason}, (), ep)


def recover(p: PlannerProtocolParams, run: PlannerRun, cmd: Cmd) -> PlannerRun:
    """Go on from the plant's last obeyed command: its controls are the nominal it applies,
    its rng the sampler's state after that solve."""
    if cmd.controls.shape != (p.mppi.horizon, 2) or not cmd.rng.any():
        return run
    ctx = context(run.episodes, cmd.header.episode, PlannerCtx)
    qs = mppi.PlannerState(jnp.asarray(cmd.controls, jnp.float32),
                           jnp.asarray(cmd.rng, jnp.uint32))
    t0 = cmd.t0          # (what waits for a partner stays: `due` takes only later stamps)
    ctx = replace(ctx, qs=qs, last_t=t0, answer=(), followed=(*ctx.followed, (t0, qs))[-4:])
    return replace(run, episodes=run.episodes.put(cmd.header.episode, ctx))
