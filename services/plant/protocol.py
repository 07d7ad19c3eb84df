"""The plant's protocol: which commands it obeys, when it brakes, and what it publishes.

    start(params, episode, wall) / resume(params, state, wall) -> (run, outputs)
    on_cmd(params, run, cmd, wall, watch) -> (run, verdict, outputs)
    realtime_step(params, run) -> (run, outputs)           one plant period
    lockstep_idle(params, run, wall, missing) -> (run, outputs)

**Authority.** The plant obeys one planner: the instance `plant.authority` names, one
process of it at a time (`Authority`: source, boot, epoch). Commands of any other source,
of an older process, or of a newer one while the current one still beats its heartbeat
(common.supervision) are rejected; a newer process takes over once the old one's beats
have stopped (a restart), and each change raises the epoch. Every state carries it.
Only two things change it besides: a `Handover` (`on_handover`) that a planner sends
naming the current authority and epoch, granted at the next tick boundary if it beats
(a swap); and a fail-over (`_failover`), when the authority's beats stop and a planner
beats as `standby`: that one takes over at once.

**Acceptance.** A command must belong to this episode, have `dt > 0` and at least one
control, cover the whole tick in lockstep, and stay within the actuators' limits (the
plant clamps rates and bounds anyway; a value beyond them is not a command). In lockstep
it must be for the pending tick (`t0` the pending state's stamp); in realtime it must not
come from the future (`t0` after the plant's time) nor be older than the one in force.

**Braking.** The plant holds the steering and brakes fully while there is no usable
command: none yet, one older than `plant.cmd_timeout_s` (realtime), one run past its end,
or one computed on a map older than `plant.perception_timeout_s` (its `t0` less the
stamp of the map it names among its inputs: perception lost behind a live planner).
An event says what degraded and when it recovered; with usable commands back the vehicle
drives on.

**Lockstep.** The plant publishes the pending tick's state and waits for its command.
When none has come for `plant.reoffer_s` it publishes that state again (a re-offer:
same stamp, new seq), and again every `reoffer_s`, so that a service that restarted or
lost a message on the way answers it; after `plant.lockstep_wait_s` without an answer
the episode ends as `aborted`. Each "waiting" event names the services whose heartbeat
has stopped, raised again when that changes. A restarted plant `resume`s the episode from the newest
tick state on the bus (the sensor and planner hold it), bit for bit where it left off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from common.config import Config, by_name
from common.messages import Cmd, Handover, State
from common.protocol import EPS, NEW, REPEAT, Order, Out, accept, check, on_tick, ref
from common.supervision import Watch, alive, is_alive, newest, other_world
from common.topics import topic_key
from services.plant import core
from services.plant.dynamics import S

ABORTED = "aborted"
OUTCOMES = (*core.OUTCOMES, ABORTED)   # how an episode on the bus ends: judged, or given up
NOBODY = Watch()                       # no heartbeat heard (the in-process runner)


@dataclass(frozen=True)
class PlantProtocolParams:
    sim: core.PlantParams
    mode: str                          # lockstep | realtime
    cmd_timeout_s: float
    perception_timeout_s: float
    reoffer_s: float
    lockstep_wait_s: float
    authority: str                     # "planner/<instance>"
    cmd_key: str
    map_key: str

    @classmethod
    def from_config(cls, cfg: Config, sim: core.PlantParams) -> PlantProtocolParams:
        pc, vehicle = cfg.plant, cfg.episode.vehicle
        return by_name(cls, pc, sim=sim, mode=cfg.episode.clock,
                       authority=f"planner/{pc.authority}", cmd_key=topic_key(vehicle, "cmd"),
                       map_key=topic_key(vehicle, "map"))

    @property
    def lockstep(self) -> bool:
        return self.mode == "lockstep"


@dataclass(frozen=True)
class Authority:
    source: str                        # the planner instance obeyed
    boot: int                          # its process; 0: the next one of it to command
    epoch: int                         # +1 at each change


@dataclass(frozen=True)
class PlantRun:
    sim: core.PlantState
    episode: int
    authority: Authority
    cmd: Cmd | None = None             # the command in force (lockstep: the last obeyed)
    order: Order = field(default_factory=Order)
    degraded: str = ""                 # what keeps the plant braking now, "" if nothing
    degraded_since: float = 0.0        # sim time (lockstep waits: wall time)
    offered_wall: float = 0.0          # lockstep: the pending tick's last offer
    waiting_since: float = 0.0         # lockstep: its first
    silent: str = ""                   # lockstep: what the last "waiting" event named
    handover: Authority | None = None  # granted, takes effect at the next tick boundary
    handover_why: str = ""
    stale_steps: int = 0

    @property
    def done(self) -> bool:
        return self.sim.done


# ----------------------------------------------------------------------------- outputs
def state_out(p: PlantProtocolParams, run: PlantRun, inputs: tuple = ()) -> Out:
    st = run.sim
    return Out("state", st.t, {
        "x": np.array(st.x, dtype=np.float64),
        "z": core.ground_z(p.sim, st.x[S.X], st.x[S.Y]),
        "u_applied": np.array(st.u_applied, dtype=np.float64),
        "tick": core.tick_of(p.sim, st), "authority": run.authority.source,
        "epoch": run.authority.epoch, "authority_boot": run.authority.boot,
        "outcome": st.outcome,
        "goal_region": st.reached_goal_region}, inputs, run.episode)


def clock_out(p: PlantProtocolParams, run: PlantRun) -> Out:
    return Out("clock", run.sim.t, {"tick": core.tick_of(p.sim, run.sim), "mode": p.mode},
               (), run.episode)


def event_out(run: PlantRun, kind: str, detail: str = "") -> Out:
    st = run.sim
    return Out("events", st.t, {"kind": kind, "outcome": st.outcome,
                                "time_to_goal_s": st.time_to_goal_s, "detail": detail},
               (), run.episode)


def outcome_detail(p: PlantProtocolParams, st: core.PlantState) -> str:
    detail = (f"t={st.t:.2f} x={st.x[S.X]:.2f} y={st.x[S.Y]:.2f} "
              f"speed={math.hypot(st.x[S.V], st.x[S.v]):.2f}")
    if st.outcome == "collision":
        detail += " on=" + core.collision_text(p.sim, st.x)
    return detail


# ----------------------------------------------------------------------------- start
def start(p: PlantProtocolParams, episode: int, wall: float) -> tuple[PlantRun, tuple[Out, ...]]:
    run = PlantRun(core.initial_state(p.sim), episode, Authority(p.authority, 0, 0),
                   offered_wall=wall, waiting_since=wall)
    scn = p.sim.scenario
    return run, (event_out(run, "start", f"scenario={scn.name} clock={p.mode}"),
                 state_out(p, run), clock_out(p, run))


def resumable(p: PlantProtocolParams, m: State) -> bool:
    """Whether a recovered state can be resumed from: one of an episode still running, on a
    tick boundary (a lockstep tick is stepped whole)."""
    return not m.outcome and on_tick(m.header.stamp, p.sim.tick_s)


def resume(p: PlantProtocolParams, m: State, wall: float) -> tuple[PlantRun, tuple[Out, ...]]:
    """Go on with the episode of state `m` (the newest on the bus) from where it was."""
    t = m.header.stamp
    sim = core.PlantState(t, int(round(t / p.sim.dt)), np.array(m.x, dtype=np.float64),
                          np.array(m.u_applied, dtype=np.float64), bool(m.goal_region))
    run = PlantRun(sim, m.header.episode,
                   Authority(m.authority or p.authority, m.authority_boot, m.epoch),
                   offered_wall=wall, waiting_since=wall)
    return run, (event_out(run, "resume", f"t={t:.2f} from {m.header.source}"),
                 state_out(p, run, m.header.inputs), clock_out(p, run))


# ----------------------------------------------------------------------------- commands
def cmd_problem(p: PlantProtocolParams, run: PlantRun, cmd: Cmd) -> str:
    """Why a command cannot be obeyed whoever sent it, or ''."""
    if cmd.header.episode != run.episode:
        return "another episode"
    if not cmd.dt > 0.0:
        return f"dt {cmd.dt} is not positive"
    n = len(cmd.controls)
    if n < 1:
        return "no controls"
    if p.lockstep and n * cmd.dt < p.sim.tick_s - EPS:
        return f"{n} controls of {cmd.dt} s do not cover the tick"
    lo, hi = p.sim.limits.lo, p.sim.limits.hi
    slack = 1e-6 * np.maximum(np.abs(lo), np.abs(hi))
    c = cmd.controls.astype(np.float64)
    if np.any(c < lo - slack) or np.any(c > hi + slack):
        return "controls beyond the actuator limits"
    return ""


def on_cmd(p: PlantProtocolParams, run: PlantRun, cmd: Cmd, wall: float,
           watch: Watch = NOBODY) -> tuple[PlantRun, str, tuple[Out, ...]]:
    """Judge a command; obey it if it is the authority's. In lockstep a command for the
    pending tick steps that tick (its states are the outputs)."""
    if run.done:
        return run, "the episode is over", ()
    problem = cmd_problem(p, run, cmd)
    if problem:
        return run, problem, ()
    h, a = cmd.header, run.authority
    if h.source != a.source:
        return run, "not the authority", ()
    if other_world(newest(watch, h.source), p.sim.scenario.digest):
        return run, "another scenario (its heartbeat's digest differs)", ()
    if a.boot and h.boot < a.boot:
        return run, "superseded boot", ()
    verdict = check(run.order, h, wall, math.inf, False)
    if verdict not in (NEW, REPEAT):
        return run, verdict, ()
    t = run.sim.t
    if h.stamp > t + EPS or cmd.t0 > t + EPS:
        return run, "future", ()
    if p.lockstep and cmd.t0 < t - EPS:
        return run, "stale", ()
    if not p.lockstep and run.cmd is not None and cmd.t0 <= run.cmd.t0 + EPS:
        return run, "stale" if cmd.t0 < run.cmd.t0 - EPS else "repeat", ()
    outs: tuple[Out, ...] = ()
    if h.boot != a.boot:
        if a.boot and alive(watch, a.source, wall, a.boot):
            return run, "another process of the authority still beats", ()
        a = Authority(a.source, h.boot, a.epoch + 1)
        run = replace(run, authority=a)
        outs += (event_out(run, "authority", f"{a.source} boot {a.boot} epoch {a.epoch}"),)
    run = replace(run, cmd=cmd, order=accept(run.order, h, wall))
    if p.lockstep:
        run, stepped = lockstep_tick(p, run, wall)
        outs += stepped
    return run, NEW, outs


def on_handover(p: PlantProtocolParams, run: PlantRun, h: Handover, wall: float,
                watch: Watch = NOBODY) -> tuple[PlantRun, str, tuple[Out, ...]]:
    """Judge a request that planner `h.to` take over; grant it if it names the authority and
    epoch in force and `h.to` beats. It takes effect at the next tick boundary: in
    lockstep the pending tick (offered again, naming the new authority)."""
    a = run.authority
    if run.done:
        return run, "the episode is over", ()
    if h.header.episode != run.episode:
        return run, "another episode", ()
    if h.to.split("/")[0] != "planner":
        return run, f"{h.to} is not a planner", ()
    if h.current != a.source or h.epoch != a.epoch:
        return run, f"names {h.current} epoch {h.epoch}, not {a.source} epoch {a.epoch}", ()
    beat = newest(watch, h.to) if not h.to_boot else watch.beats.get((h.to, h.to_boot))
    if beat is None or not is_alive(beat, wall):
        return run, f"{h.to} does not beat", ()
    if (h.to, beat.boot) == (a.source, a.boot):
        return run, "already the authority", ()
    why = f"handover from {a.source}" + (f": {h.reason}" if h.reason else "")
    run = replace(run, handover=Authority(h.to, beat.boot, a.epoch + 1), handover_why=why)
    if p.lockstep:        # the pending tick offered again, naming its new authority
        run, outs = _take_over(run)
        inputs = () if run.cmd is None else (ref(p.cmd_key, run.cmd),)
        return replace(run, offered_wall=wall), NEW, (*outs, state_out(p, run, inputs))
    return run, NEW, ()


def _take_over(run: PlantRun) -> tuple[PlantRun, tuple[Out, ...]]:
    """A granted handover in effect."""
    a = run.handover
    if a is None:
        return run, ()
    run = replace(run, authority=a, handover=None)
    return run, (event_out(run, "authority", f"{a.source} boot {a.boot} epoch {a.epoch} "
                                             f"({run.handover_why})"),)


def _failover(run: PlantRun, watch: Watch, wall: float) -> tuple[PlantRun, tuple[Out, ...]]:
    """The authority's beats have stopped (it had beaten) and a planner beats as standby:
    the standby (the first by name) takes over now."""
    a = run.authority
    beat = newest(watch, a.source)
    if not a.boot or beat is None or alive(watch, a.source, wall, a.boot):
        return run, ()
    standby = sorted((b for b in watch.beats.values() if b.role == "standby"
                      and b.source.startswith("planner/") and is_alive(b, wall)),
                     key=lambda b: b.source)
    if not standby:
        return run, ()
    s = standby[0]
    run = replace(run, handover=Authority(s.source, s.boot, a.epoch + 1),
                  handover_why=f"fail-over from {a.source}: no heartbeat for "
                               f"{wall - beat.wall:.2f} s")
    return _take_over(run)


def map_stamp(p: PlantProtocolParams, cmd: Cmd) -> float | None:
    """The stamp of the map a command names among its inputs."""
    stamps = [i.stamp for i in cmd.header.inputs if i.key == p.map_key]
    return max(stamps) if stamps else None


def control(p: PlantProtocolParams, run: PlantRun) -> tuple[np.ndarray, str]:
    """The control to apply now and, when it is the brake, why."""
    st, cmd = run.sim, run.cmd
    brake = core.brake_control(p.sim, st)
    if cmd is None:
        return brake, "no command yet"
    if not p.lockstep and st.t - cmd.t0 > p.cmd_timeout_s + EPS:
        return brake, f"commands stale: the newest is {st.t - cmd.t0:.2f} s old"
    u = core.control_at(st.t, cmd.t0, cmd.dt, cmd.controls)
    if u is None:
        return brake, "the command ran out"
    seen = map_stamp(p, cmd)
    if seen is None:
        return brake, "perception stale: the command names no map"
    if cmd.t0 - seen > p.perception_timeout_s + EPS:
        return brake, f"perception stale: the command's map is {cmd.t0 - seen:.2f} s old"
    return u, ""


def _step(p: PlantProtocolParams, run: PlantRun) -> tuple[PlantRun, tuple[Out, ...]]:
    """One plant period with the control in force; its state, clock and events."""
    u, why = control(p, run)
    outs: tuple[Out, ...] = ()
    inputs = () if why or run.cmd is None else (ref(p.cmd_key, run.cmd),)
    sim = core.plant_step(p.sim, run.sim, u)
    run = replace(run, sim=sim, stale_steps=run.stale_steps + bool(why))
    what, was = why.split(":")[0], run.degraded.split(":")[0]
    if why and what != was and why != "no command yet":      # braking before the first
        outs += (event_out(run, "degraded", why),)              # command is no fault
        run = replace(run, degraded=why, degraded_since=sim.t)
    elif not why and run.degraded:
        outs += (event_out(run, "recovered",
                           f"{was} for {sim.t - run.degraded_since:.2f} s"),)
        run = replace(run, degraded="")
    outs += (state_out(p, run, inputs),)
    if sim.step % p.sim.steps_per_tick == 0:
        outs += (clock_out(p, run),)
    if sim.done:
        outs += (event_out(run, sim.outcome, outcome_detail(p, sim)),)
    return run, outs


def lockstep_tick(p: PlantProtocolParams, run: PlantRun, wall: float
                  ) -> tuple[PlantRun, tuple[Out, ...]]:
    """The pending tick stepped with the command in force."""
    outs: tuple[Out, ...] = ()
    if run.degraded.startswith("waiting"):
        outs += (event_out(run, "recovered",
                           f"answered after {wall - run.waiting_since:.1f} s"),)
        run = replace(run, degraded="", silent="")
    for _ in range(p.sim.steps_per_tick):
        run, step_outs = _step(p, run)
        outs += step_outs
        if run.done:
            break
    return replace(run, offered_wall=wall, waiting_since=wall), outs


def realtime_step(p: PlantProtocolParams, run: PlantRun, wall: float = 0.0,
                  watch: Watch = NOBODY) -> tuple[PlantRun, tuple[Out, ...]]:
    """One plant period on the wall clock's beat (the shell keeps the beat): a fail-over
    or, on a tick boundary, a granted handover first."""
    if run.done:
        return run, ()
    run, outs = _failover(run, watch, wall)
    if run.handover is not None and run.sim.step % p.sim.steps_per_tick == 0:
        run, more = _take_over(run)
        outs += more
    run, stepped = _step(p, run)
    return run, outs + stepped


def lockstep_idle(p: PlantProtocolParams, run: PlantRun, wall: float, missing: str = "",
                  watch: Watch = NOBODY) -> tuple[PlantRun, tuple[Out, ...]]:
    """No command for the pending tick yet: fail over to a standby if the authority's beats
    have stopped (the state re-offered at once, naming it); else re-offer the tick when due,
    end the episode when it has waited too long. `missing` names what is not beating."""
    if run.done:
        return run, ()
    run, outs = _failover(run, watch, wall)
    if outs:
        inputs = () if run.cmd is None else (ref(p.cmd_key, run.cmd),)
        return replace(run, offered_wall=wall), (*outs, state_out(p, run, inputs))
    if wall - run.offered_wall < p.reoffer_s:
        return run, ()
    waited = wall - run.waiting_since
    outs: tuple[Out, ...] = ()
    if waited >= p.lockstep_wait_s:
        sim = replace(run.sim, outcome=ABORTED)
        run = replace(run, sim=sim)
        why = f"no command for t={sim.t:.2f} in {waited:.0f} s" + (
            f" ({missing})" if missing else "")
        return run, (event_out(run, ABORTED, why), state_out(p, run))
    if not run.degraded.startswith("waiting") or missing != run.silent:
        why = f"waiting: no command for t={run.sim.t:.2f} after {waited:.1f} s" + (
            f" ({missing})" if missing else "")
        outs += (event_out(run, "degraded", why),)
        run = replace(run, degraded=why, degraded_since=run.sim.t, silent=missing)
    inputs = () if run.cmd is None else (ref(p.cmd_key, run.cmd),)
    return replace(run, offered_wall=wall), (*outs, state_out(p, run, inputs))
