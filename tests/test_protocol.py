"""The services' protocol cores without a bus: acceptance, authority, braking, re-offers,
repeats, restore and resume (services/*/protocol.py, common/protocol.py)."""

from dataclasses import replace

import jax.numpy as jnp
import numpy as np
import pytest

from common.config import load_config
from common.messages import Cmd, Depth, Heartbeat, InputRef, Map, State
from common.protocol import NEW, REPEAT, Episodes, Order, Out, Stamper, accept, check, judge
from common.supervision import Watch, on_beat
from deploy.sim.runner import Cores
from services.mapper import protocol as mapper
from services.planner import mppi
from services.planner import protocol as planner
from services.plant import protocol as plant
from services.sensor import protocol as sensor

SHORT = ["planner.samples=16", 'episode.scenario="open-field"']
EP = 1


@pytest.fixture(scope="module")
def cores():
    return Cores.from_config(load_config(overrides=SHORT))


@pytest.fixture(scope="module")
def rt_cores():
    return Cores.from_config(load_config(overrides=[*SHORT, 'episode.clock="realtime"']))


def stamp(source: str, cls, out: Out, boot: int = 1):
    return Stamper(source, boot, wall=lambda: 0.0).make(cls, out)


def a_cmd(c: Cores, t0: float, *, source="planner/0", boot=1, seq=0, controls=None,
          dt=None, map_t=None, episode=EP) -> Cmd:
    n = c.planner.mppi.horizon
    controls = np.zeros((n, 2), np.float32) if controls is None else controls
    out = Out("cmd", t0, {"t0": t0, "dt": c.planner.dt if dt is None else dt,
                          "controls": controls, "rng": np.array([1, 2], "<u4")},
              (InputRef(c.plant.map_key, 0, t0 if map_t is None else map_t),), episode)
    st = Stamper(source, boot, wall=lambda: 0.0)
    st.seq = seq
    return st.make(Cmd, out)


# ----------------------------------------------------------------------------- acceptance
def test_acceptance_per_source_and_boot():
    h = stamp("plant/0", State, Out("state", 1.0, {"x": np.zeros(6), "z": 0.0,
                                                   "u_applied": np.zeros(2), "tick": 10,
                                                   "authority": ""})).header
    o = accept(Order(), h, 100.0)
    assert check(o, replace(h, seq=1), 100.0, 0.1, False) == REPEAT
    assert check(o, replace(h, seq=0), 100.0, 0.1, False) == "duplicate"
    assert check(o, replace(h, seq=1, stamp=1.1), 100.0, 0.1, False) == NEW
    assert check(o, replace(h, seq=1, stamp=0.9), 100.0, 0.1, False) == "stale"
    assert check(o, replace(h, seq=1, stamp=1.2), 100.0, 0.1, False) == "future"
    # realtime: as far ahead as the wall clock has gone, and some
    assert check(o, replace(h, seq=1, stamp=4.0), 103.0, 0.1, True) == NEW
    assert check(o, replace(h, seq=1, stamp=9.0), 103.0, 0.1, True) == "future"
    # a restarted publisher starts its seq again; an older process is over
    assert check(o, replace(h, seq=0, boot=2), 100.0, 0.1, False) == REPEAT
    # ... and may go back within back_s: a restarted plant resumes from the newest tick
    back = replace(h, seq=0, boot=2, stamp=0.92)
    assert check(o, back, 100.0, 0.1, False, back_s=0.1) == REPEAT
    assert check(o, back, 100.0, 0.1, False) == "stale"
    assert check(o, replace(back, stamp=0.9), 100.0, 0.1, False, back_s=0.1) == "stale"
    assert check(o, replace(back, boot=1, seq=1), 100.0, 0.1, False, back_s=0.1) == "stale"
    assert check(accept(o, replace(h, boot=2), 100.0), replace(h, seq=9), 100.0, 0.1,
                 False) == "superseded boot"
    assert check(o, replace(h, source="rogue/0", stamp=50.0), 100.0, 0.1, False) == NEW
    # with an owner: its service only, and within the episode the instance bound first
    assert check(o, replace(h, seq=1), 100.0, 0.1, False, "plant") == REPEAT
    assert check(o, replace(h, source="rogue/0"), 100.0, 0.1, False, "plant") == (
        "not from the plant")
    assert check(o, replace(h, source="plant/7"), 100.0, 0.1, False, "plant") == (
        "not this episode's plant (plant/0)")


def test_realtime_acceptance_follows_the_source_clock_not_a_late_delivery():
    """After a cut link the plant's queued states arrive in a burst with the current ones:
    one that came late must not make the current ones look like the future (this had
    stalled the sensor for the rest of an episode)."""
    h = stamp("plant/0", State, Out("state", 3.0, {"x": np.zeros(6), "z": 0.0,
                                                   "u_applied": np.zeros(2), "tick": 30,
                                                   "authority": ""})).header
    o = accept(Order(), h, 100.0)                              # prompt: the clock is -97
    o = accept(o, replace(h, seq=40, stamp=3.84), 102.0)        # queued, delivered late
    assert check(o, replace(h, seq=101, stamp=5.06), 102.001, 0.1, True) == NEW
    assert check(o, replace(h, seq=101, stamp=9.0), 102.001, 0.1, True) == "future"
    # a source whose clock really moved: accepted after FUTURE_RUN in a row
    order, verdicts = o, []
    for i in range(4):
        order, v = judge(order, replace(h, seq=200 + i, stamp=12.0 + 0.02 * i), 102.1, 0.1,
                         True)
        verdicts.append(v)
    assert verdicts == ["future", "future", NEW, NEW]
    once, v = judge(o, replace(h, seq=300, stamp=50.0), 102.1, 0.1, True)   # one alone:
    assert v == "future" and judge(once, replace(h, seq=301, stamp=5.1), 102.1, 0.1,
                                   True)[1] == NEW                         # then as before


def test_episodes_keep_the_two_most_recent():
    e = Episodes().put(1, "a").put(2, "b").put(1, "a2").put(3, "c")
    assert e.get(2) is None and e.get(1) == "a2" and e.current() == (3, "c")


# ----------------------------------------------------------------------------- plant
def test_plant_obeys_the_authority_for_the_pending_tick_and_rejects_the_rest(cores):
    p = cores.plant
    run, outs = plant.start(p, EP, 0.0)
    assert [o.topic for o in outs] == ["events", "state", "clock"]
    lim = p.sim.limits
    n = cores.planner.mppi.horizon
    bad = {
        "dt 0.0 is not positive": a_cmd(cores, 0.0, dt=0.0),
        "no controls": a_cmd(cores, 0.0, controls=np.zeros((0, 2), np.float32)),
        "do not cover the tick": a_cmd(cores, 0.0, controls=np.zeros((1, 2), np.float32),
                                       dt=0.02),
        "beyond the actuator limits": a_cmd(cores, 0.0, controls=np.tile(
            np.array([[0.0, lim.hi[1] * 10]], np.float32), (n, 1))),
        "not the authority": a_cmd(cores, 0.0, source="rogue/0"),
        "another episode": a_cmd(cores, 0.0, episode=EP + 1),
        "future": a_cmd(cores, 0.1),
    }
    for why, cmd in bad.items():
        after, verdict, outs = plant.on_cmd(p, run, cmd, 0.0)
        assert why in verdict and after is run and outs == ()
    run, verdict, outs = plant.on_cmd(p, run, a_cmd(cores, 0.0), 0.0)
    assert verdict == NEW and run.sim.step == 5 and run.authority.epoch == 1
    states = [o for o in outs if o.topic == "state"]
    assert [round(o.stamp, 2) for o in states] == [0.02, 0.04, 0.06, 0.08, 0.1]
    assert [o.fields["kind"] for o in outs if o.topic == "events"] == ["authority"]
    assert states[-1].inputs[0].key == p.cmd_key and states[-1].fields["epoch"] == 1
    for why, cmd in {"duplicate": a_cmd(cores, 0.1), "stale": a_cmd(cores, 0.0, seq=1)}.items():
        after, verdict, _ = plant.on_cmd(p, run, cmd, 0.0)
        assert verdict == why and after is run


def test_a_restarted_planner_takes_over_only_once_the_old_one_stops_beating(cores):
    p = cores.plant
    run, _ = plant.start(p, EP, 0.0)
    run, _, _ = plant.on_cmd(p, run, a_cmd(cores, 0.0, boot=1), 10.0)
    beat = stamp("planner/0", Heartbeat, Out("heartbeat", 0.0, {
        "status": "ready", "role": "active", "deadline_s": 1.0, "detail": ""}), boot=1)
    watch = on_beat(Watch(), beat, 10.0)
    new = a_cmd(cores, 0.1, boot=2)
    after, verdict, _ = plant.on_cmd(p, run, new, 10.5, watch)
    assert verdict == "another process of the authority still beats" and after is run
    after, verdict, outs = plant.on_cmd(p, run, new, 11.5, watch)        # its beat is late
    assert verdict == NEW and after.authority.boot == 2 and after.authority.epoch == 2
    old = a_cmd(cores, 0.2, boot=1, seq=1)
    assert plant.on_cmd(p, after, old, 11.5, watch)[1] == "superseded boot"


def test_realtime_plant_brakes_on_stale_commands_and_perception_and_drives_on(rt_cores):
    p = rt_cores.plant
    run, _ = plant.start(p, EP, 0.0)
    go = np.tile(np.array([[0.0, 3000.0]], np.float32), (rt_cores.planner.mppi.horizon, 1))
    run, verdict, _ = plant.on_cmd(p, run, a_cmd(rt_cores, 0.0, controls=go), 0.0)
    assert verdict == NEW
    kinds = []
    for _ in range(40):                                   # 0.8 s on a command of t = 0
        run, outs = plant.realtime_step(p, run)
        kinds += [(round(o.stamp, 2), o.fields["kind"]) for o in outs if o.topic == "events"]
    assert kinds == [(0.54, "degraded")] and run.degraded.startswith("commands stale")
    assert run.sim.u_applied[1] < 0 and run.stale_steps == 14
    t = run.sim.t
    run, verdict, _ = plant.on_cmd(p, run, a_cmd(rt_cores, t, controls=go, seq=1), 0.0)
    run, outs = plant.realtime_step(p, run)
    assert [o.fields["kind"] for o in outs if o.topic == "events"] == ["recovered"]
    # a command computed on a map 0.6 s old: perception is stale
    t = run.sim.t
    stale_map = a_cmd(rt_cores, t, controls=go, seq=2, map_t=t - 0.6)
    run, _, _ = plant.on_cmd(p, run, stale_map, 0.0)
    run, outs = plant.realtime_step(p, run)
    (ev,) = [o for o in outs if o.topic == "events"]
    assert ev.fields["kind"] == "degraded" and "perception stale" in ev.fields["detail"]
    assert run.sim.u_applied[1] < go[0, 1]
    # the realtime plant refuses a command from its future and one older than in force
    assert plant.on_cmd(p, run, a_cmd(rt_cores, run.sim.t + 0.5, seq=3), 0.0)[1] == "future"
    assert plant.on_cmd(p, run, a_cmd(rt_cores, 0.0, seq=4), 0.0)[1] == "stale"


def test_lockstep_plant_reoffers_its_pending_tick_then_gives_up(cores):
    p = replace(cores.plant, reoffer_s=1.0, lockstep_wait_s=5.0)
    run, _ = plant.start(p, EP, 100.0)
    assert plant.lockstep_idle(p, run, 100.5)[1] == ()
    run, outs = plant.lockstep_idle(p, run, 101.0, "no heartbeat: mapper")
    assert [o.topic for o in outs] == ["events", "state"]
    assert outs[0].fields["kind"] == "degraded" and "mapper" in outs[0].fields["detail"]
    assert outs[1].stamp == 0.0
    run, outs = plant.lockstep_idle(p, run, 102.0, "no heartbeat: mapper")
    assert [o.topic for o in outs] == ["state"]               # re-offered again, no new event
    run, outs = plant.lockstep_idle(p, run, 103.0, "no heartbeat: mapper, planner")
    assert [o.topic for o in outs] == ["events", "state"]     # ... but when it names others
    run, outs = plant.lockstep_idle(p, run, 105.5)
    assert run.sim.outcome == plant.ABORTED and outs[0].fields["kind"] == plant.ABORTED
    run2, _ = plant.start(p, EP, 100.0)
    run2, _ = plant.lockstep_idle(p, run2, 101.0)
    run2, _, outs = plant.on_cmd(p, run2, a_cmd(cores, 0.0), 101.2)
    assert [o.fields["kind"] for o in outs if o.topic == "events"] == ["authority", "recovered"]


def test_a_resumed_plant_steps_the_tick_as_the_undisturbed_one(cores):
    p = cores.plant
    run, _ = plant.start(p, EP, 0.0)
    rng = np.random.default_rng(0)
    for k in range(6):
        u = np.stack([rng.uniform(-0.3, 0.3, 40), rng.uniform(-3000, 4000, 40)], -1)
        run, _, outs = plant.on_cmd(p, run, a_cmd(cores, run.sim.t, seq=k,
                                                  controls=u.astype(np.float32)), 0.0)
    last = stamp("plant/0", State, outs[-2] if outs[-1].topic == "clock" else outs[-1])
    assert plant.resumable(p, last)
    resumed, outs = plant.resume(p, last, 0.0)
    assert outs[0].fields["kind"] == "resume" and resumed.episode == EP
    cmd = a_cmd(cores, run.sim.t, seq=9, controls=np.full((40, 2), [0.1, 2500.0], np.float32))
    a, _, _ = plant.on_cmd(p, run, cmd, 0.0)
    b, _, _ = plant.on_cmd(p, resumed, cmd, 0.0)
    assert a.sim.t == b.sim.t and a.sim.x.tobytes() == b.sim.x.tobytes()
    assert a.sim.u_applied.tobytes() == b.sim.u_applied.tobytes()


# ----------------------------------------------------------------------------- sensor
def _state(c: Cores, t: float, seq: int, boot=1, episode=EP) -> State:
    """A plant state at t (the vehicle rolling east from the start at 0.5 m/s), seq given."""
    x = np.zeros(6)
    s = c.scenario.start
    x[3], x[4], x[5] = s.x + 0.5 * t, s.y, s.yaw
    st = Stamper("plant/0", boot, wall=lambda: 0.0)
    st.seq = seq
    return st.make(State, Out("state", t, {"x": x, "z": 0.0, "u_applied": np.zeros(2),
                                           "tick": int(round(t / 0.1)),
                                           "authority": "planner/0"}, (), episode))


def test_sensor_renders_on_its_frame_clock_and_answers_a_repeat_from_its_frame(cores):
    p = cores.sensor
    run = sensor.SensorRun()
    run, v, frames = sensor.on_state(p, run, _state(cores, 0.0, 0), 0.0)
    assert v == NEW and [f.stamp for f in frames] == [0.0]
    run, v, frames = sensor.on_state(p, run, _state(cores, 0.04, 1), 0.0)
    assert v == NEW and frames == ()                           # between frames
    run, v, frames2 = sensor.on_state(p, run, _state(cores, 0.1, 2), 0.0)
    run, v, again = sensor.on_state(p, run, _state(cores, 0.1, 3), 0.0)
    assert v == REPEAT and again == frames2 and run.held_state.header.stamp == 0.1
    assert sensor.on_state(p, run, _state(cores, 0.1, 3), 0.0)[1] == "duplicate"
    assert sensor.on_state(p, run, _state(cores, 0.02, 4), 0.0)[1] == "stale"
    assert sensor.on_state(p, run, _state(cores, 50.0, 5), 0.0)[1] == "future"
    # a new episode starts afresh; the old one's context is still there
    run, v, frames = sensor.on_state(p, run, _state(cores, 0.0, 0, boot=2, episode=EP + 1), 0.0)
    assert v == NEW and [f.stamp for f in frames] == [0.0]
    assert sensor.on_state(p, run, _state(cores, 0.2, 6), 0.0)[1] == NEW


def test_a_restarted_plant_behind_its_dead_incarnation_is_answered_from_the_cache(cores):
    """The plant died having sent states within tick 0.1-0.2; restarted, it re-offers 0.1
    (the newest whole tick held on the bus). Judged stale, that re-offer was refused for
    good and the lockstep episode stalled; it is a repeat, answered from what was cached."""
    maps = _maps(cores, 2)
    srun, prun = sensor.SensorRun(), planner.PlannerRun()
    for m in maps:
        prun, _ = planner.on_map(cores.planner, prun, m, 0.0)
    for seq, t in enumerate((0.0, 0.1)):
        srun, _, frame = sensor.on_state(cores.sensor, srun, _state(cores, t, seq), 0.0)
        prun, _, _ = planner.on_state(cores.planner, prun, _state(cores, t, seq), 0.0)
        prun, answer = planner.solve(cores.planner, prun, planner.due(cores.planner, prun, 0.0),
                                     0.0)
    for seq, t in enumerate((0.12, 0.14), start=2):               # within the tick, then dead
        srun, v, _ = sensor.on_state(cores.sensor, srun, _state(cores, t, seq), 0.0)
        prun, _, _ = planner.on_state(cores.planner, prun, _state(cores, t, seq), 0.0)
    assert srun.held_state.header.stamp == prun.held_state.header.stamp == 0.1
    reoffer = _state(cores, 0.1, 0, boot=2)
    srun, v, again = sensor.on_state(cores.sensor, srun, reoffer, 0.0)
    assert v == REPEAT and again == frame
    prun, v, outs = planner.on_state(cores.planner, prun, reoffer, 0.0)
    assert v == REPEAT and outs == answer
    assert sensor.on_state(cores.sensor, srun, _state(cores, 0.12, 1, boot=2), 0.0)[1] == NEW
    assert sensor.on_state(cores.sensor, srun, _state(cores, 0.0, 9), 0.0)[1] == "superseded boot"


# ----------------------------------------------------------------------------- mapper
def _frames(c: Cores, n: int) -> list[Depth]:
    run, out = sensor.SensorRun(), []
    st = Stamper("sensor/0", 1, wall=lambda: 0.0)
    for i in range(n):
        run, _, frames = sensor.on_state(c.sensor, run, _state(c, 0.1 * i, 0, boot=10 + i),
                                         0.0)
        out += [st.make(Depth, f) for f in frames]
    return out


def test_mapper_fuses_each_frame_once_checks_the_camera_and_resumes_from_a_map(cores):
    p = cores.mapper
    frames = _frames(cores, 4)
    bad = replace(frames[0], depth=np.zeros((10, 10), np.float32))
    assert "wrong size" in mapper.on_depth(p, mapper.MapperRun(), bad, 0.0)[1]
    bad = replace(frames[0], intrinsics=frames[0].intrinsics * 2)
    assert "intrinsics" in mapper.on_depth(p, mapper.MapperRun(), bad, 0.0)[1]
    run, maps, st = mapper.MapperRun(), [], Stamper("mapper/0", 1, wall=lambda: 0.0)
    for f in frames:
        run, v, outs = mapper.on_depth(p, run, f, 0.0)
        maps += [st.make(Map, o) for o in outs]
    again = replace(frames[-1], header=replace(frames[-1].header, seq=99))
    run2, v, outs = mapper.on_depth(p, run, again, 0.0)
    assert v == REPEAT and outs[0].fields["mean"] is maps[-1].mean      # nothing fused twice
    # restored from its map after frame 2, the mapper makes the map of frame 3 exactly
    resumed = mapper.restore(p, mapper.MapperRun(), maps[2])
    _, v, outs = mapper.on_depth(p, resumed, frames[3], 0.0)
    assert v == NEW and outs[0].fields["mean"].tobytes() == maps[3].mean.tobytes()
    assert outs[0].fields["variance"].tobytes() == maps[3].variance.tobytes()
    _, v, outs = mapper.on_depth(p, resumed, frames[2], 0.0)            # the frame it has
    assert v == REPEAT and outs[0].fields["mean"].tobytes() == maps[2].mean.tobytes()
    assert mapper.on_depth(p, resumed, frames[1], 0.0)[1] == "stale"
    state = run.episodes.get(EP).map
    assert (state.observed == (state.variance < p.core.prior_variance)).all()


# ----------------------------------------------------------------------------- planner
def _maps(c: Cores, n: int) -> list[Map]:
    """The mapper's maps of the first `n` frames."""
    run, maps = mapper.MapperRun(), []
    st = Stamper("mapper/0", 1, wall=lambda: 0.0)
    for f in _frames(c, n):
        run, _, outs = mapper.on_depth(c.mapper, run, f, 0.0)
        maps += [st.make(Map, o) for o in outs]
    return maps


def test_planner_pairs_by_stamp_answers_a_repeat_and_checks_the_grid(cores):
    p = cores.planner
    maps = _maps(cores, 2)
    small = replace(maps[0], mean=np.zeros((10, 10), np.float32),
                    variance=np.zeros((10, 10), np.float32))
    assert "wrong size" in planner.on_map(p, planner.PlannerRun(), small, 0.0)[1]
    run = planner.PlannerRun()
    run, _ = planner.on_map(p, run, maps[0], 0.0)
    assert planner.due(p, run, 0.0) is None                     # no state of that stamp yet
    run, _, _ = planner.on_state(p, run, _state(cores, 0.0, 0), 0.0)
    job = planner.due(p, run, 0.0)
    assert job.state.header.stamp == 0.0 == job.map.header.stamp
    run, answer = planner.solve(p, run, job, 0.0)
    assert [o.topic for o in answer] == ["cmd", "plan", "stats"] and planner.due(p, run, 0) is None
    run, v, outs = planner.on_state(p, run, _state(cores, 0.0, 1), 0.0)     # a re-offer
    assert v == REPEAT and outs == answer


def test_warm_start_follows_the_plant_or_starts_afresh(cores):
    p = cores.planner
    qs = mppi.initial_state(p.mppi, 3)
    nominal = np.tile(np.array([[0.05, 2000.0]], np.float32), (p.mppi.horizon, 1))
    qs = qs._replace(nominal=nominal)
    follows, cold = planner.warm_start(p, qs, 1.0, 1.1, np.array([0.05, 1800.0]))
    assert not cold and np.asarray(follows.nominal).tobytes() == np.asarray(
        mppi.advance(qs, 1).nominal).tobytes()
    for t, u in ((1.1, [0.05, -6000.0]),         # the plant braked: not the nominal
                 (1.1, [0.3, 2000.0]),           # steered elsewhere
                 (6.0, [0.05, 2000.0])):         # past the plan's horizon
        fresh, cold = planner.warm_start(p, qs, 1.0, t, np.array(u))
        assert cold and not np.asarray(fresh.nominal).any()
        assert np.asarray(fresh.key).tobytes() == np.asarray(qs.key).tobytes()


def test_a_recovered_planner_solves_as_the_one_that_sent_the_command(cores):
    p = cores.planner
    maps = _maps(cores, 2)
    states = [_state(cores, 0.0, 0), _state(cores, 0.1, 1)]
    run = planner.PlannerRun()
    for s, m in zip(states, maps, strict=True):
        run, _, _ = planner.on_state(p, run, s, 0.0)
        run, _ = planner.on_map(p, run, m, 0.0)
    run, first = planner.solve(p, run, planner.due(p, run, 0.0), 0.0)
    cmd = stamp("planner/0", Cmd, first[0])
    undisturbed, second = planner.solve(p, run, planner.due(p, run, 0.0), 0.0)
    fresh = planner.recover(p, planner.PlannerRun(), cmd)
    fresh, _, _ = planner.on_state(p, fresh, states[1], 0.0)
    fresh, _ = planner.on_map(p, fresh, maps[1], 0.0)
    _, again = planner.solve(p, fresh, planner.due(p, fresh, 0.0), 0.0)
    for a, b in zip(second[:2], again[:2], strict=True):
        for k, v in a.fields.items():
            if isinstance(v, np.ndarray):
                assert v.tobytes() == b.fields[k].tobytes(), k


def test_realtime_solves_on_each_new_map_and_once_a_tick_without_one():
    due, dt = planner.realtime_due, 0.1
    assert due(None, 3.0, False, dt, 0.0)                  # the first solve
    assert due(5.02, 5.12, True, dt, 0.1)                  # the next tick's map is in
    assert due(5.02, 5.08, True, dt, 0.06)                 # ... early
    assert not due(5.02, 5.06, True, dt, 0.04)             # two maps in one tick: one solve
    assert not due(5.02, 5.12, False, dt, 0.10)            # no new map: wait 1.5 ticks ...
    assert due(5.02, 5.18, False, dt, 0.16)                # ... then solve on the last one


@pytest.mark.parametrize("outage_s", [0.5, 1.0, 2.0, 5.0, 10.0])
def test_the_vehicle_drives_on_after_a_command_outage(outage_s):
    """In-process, simulated realtime: the planner cut off at t = 3 s for `outage_s` (the
    plant brakes on stale commands), then back as its node resumes. Shifting its nominal
    past what the plant did had left the vehicle braking at a standstill until the
    timeout after outages of 5 s and more; checked against the plant's applied control,
    the warm start starts afresh and the vehicle reaches the goal."""
    from deploy.sim.runner import run_episode
    cfg = load_config(overrides=["planner.samples=256", 'episode.scenario="open-field"'])
    r = run_episode(cfg, planner_link=lambda t: not (3.0 - 1e-9 <= t < 3.0 + outage_s - 1e-9))
    assert r.outcome == "success", (r.outcome, r.sim_time_s)
    assert r.stale_steps >= round((outage_s - cfg.plant.cmd_timeout_s) * cfg.plant.rate_hz)


def test_advance_shifts_the_nominal_as_slicing_does_for_every_shift(rng):
    from services.planner import mppi
    nom = rng.normal(size=(40, 2)).astype(np.float32)
    for k in (1, 2, 3, 7, 39, 40, 55):
        kk = min(k, 40)
        want = np.concatenate([nom[kk:], np.repeat(nom[-1:], kk, axis=0)])
        got = np.asarray(mppi.advance(mppi.PlannerState(jnp.asarray(nom), None), k).nominal)
        assert got.tobytes() == want.tobytes(), k
