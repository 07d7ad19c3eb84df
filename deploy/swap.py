"""`vamppi swap planner`: a new planner instance takes over from the running one.

1. The new instance's configuration is the running planner's (queried from its admin
   key; the plant's if it does not answer) with the command's `--config` and `--set` on
   top, so that a swap changes only what it names.
2. The new instance starts beside the running one: as a child of `vamppi up` when a
   launcher is on the bus (supervised like the others), else as a process of its own that
   outlives this command (its log in the temporary directory).
3. It compiles (from the cache) and follows the authority's commands (their nominal and
   sampler key) without disturbing anything; its heartbeat says `ready` once warm.
4. It solves in shadow for `shadow_s` (its plans on `vamppi/<vehicle>/planner/shadow`,
   recorded like any topic), then asks the plant for the authority (a Handover naming
   the authority and epoch in force); the plant grants it at the next tick boundary, its
   first command continuing the old plan, and the replaced planner retires (or, with
   `keep_old`, stands by).
5. If it does not start, warm up or get the authority within `timeout_s`, it is stopped
   and the old one keeps control; the command says why.
"""

from __future__ import annotations

import json
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from common.bus import (
    ZenohTransport,
    admin_key,
    alive_key,
    heartbeat_key,
    launcher_key,
    open_session,
    topic_key,
)
from common.config import Config, ConfigError, as_overrides, config_from_dict, load_config
from common.messages import Handover, Heartbeat, State, encode, on_decoded
from common.protocol import Out, Stamper


class SwapError(RuntimeError):
    """The swap did not happen; the old planner keeps control."""


def candidate_args(shadow_s: float, keep_old: bool) -> list[str]:
    """What `vamppi service planner` is given to run as a candidate."""
    return ["--role", "candidate", "--take-over-after", str(shadow_s),
            *(["--keep-old"] if keep_old else [])]


class _Watch:
    """The newest state and the beats of one planner instance, from the bus."""

    def __init__(self, bus: ZenohTransport, vehicle: str, source: str):
        self.source = source
        self.state: State | None = None
        self.status = ""
        self._lock = threading.Lock()
        self._subs = [
            bus.subscriber(topic_key(vehicle, "state"), on_decoded(State, self._on_state)),
            bus.subscriber(heartbeat_key(vehicle, "planner"), on_decoded(Heartbeat,
                                                                         self._on_beat))]

    def _on_state(self, s: State) -> None:
        with self._lock:
            if self.state is None or s.header.stamp >= self.state.header.stamp:
                self.state = s

    def _on_beat(self, hb: Heartbeat) -> None:
        if hb.header.source == self.source:
            with self._lock:
                self.status = hb.status

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()


def running_config(bus: ZenohTransport, vehicle: str, authority: str, path: str | None,
                   overrides: list[str]) -> Config:
    """The configuration a new planner runs: the authority's effective one (the plant's if
    the authority does not answer), `path` and `overrides` on top."""
    service, _, instance = authority.partition("/")
    keys = ([admin_key(vehicle, service, instance, "config")] if instance else []) + [
        admin_key(vehicle, "plant", "*", "config")]
    replies = next((r for r in (bus.query(k, timeout=2.0) for k in keys) if r), None)
    if not replies:
        raise SwapError(f"neither {authority or 'a planner'} nor the plant answers on its "
                        "config key")
    try:
        base = config_from_dict(json.loads(replies[0][1]))
        return load_config(path, overrides, base=base)
    except (ConfigError, ValueError) as exc:
        raise SwapError(f"the new planner's configuration: {exc}") from exc


def promote(cfg: Config, to: str, keep_old: bool = True, timeout_s: float = 10.0
            ) -> dict[str, Any]:
    """Hand the authority to a planner instance that runs already (a standby): a Handover
    naming it, then wait until a state names it."""
    vehicle, source = cfg.episode.vehicle, f"planner/{to}"
    t0 = time.monotonic()
    with open_session(cfg.bus) as session:
        bus = ZenohTransport(session)
        watch = _Watch(bus, vehicle, source)
        try:
            deadline = t0 + timeout_s
            while watch.state is None or not watch.status:
                if time.monotonic() > deadline:
                    raise SwapError(f"no episode on the bus, or no {source} beating")
                time.sleep(0.02)
            s = watch.state
            if s.authority == source:
                raise SwapError(f"{source} is the authority already")
            h = Stamper(f"swap/{time.time_ns() % 1_000_000}").make(Handover, Out(
                "handover", s.header.stamp, {"to": source, "to_boot": 0, "current": s.authority,
                                             "epoch": s.epoch, "retire": not keep_old,
                                             "reason": "vamppi swap --to"},
                (), s.header.episode))
            session.put(topic_key(vehicle, "handover"), encode(h))
            while watch.state.authority != source:
                if time.monotonic() > deadline:
                    raise SwapError(f"{source} not granted the authority in {timeout_s:.0f} s; "
                                    f"{s.authority} keeps control")
                time.sleep(0.005)
            g = watch.state
            return {"from": s.authority, "to": source, "epoch": g.epoch,
                    "granted_at_s": round(g.header.stamp, 6), "tick": g.tick,
                    "took_s": round(time.monotonic() - t0, 3),
                    "old": "standby" if keep_old else "retired"}
        finally:
            watch.close()


def swap(cfg: Config, instance: str | None, overrides: list[str], config_path: str | None,
         shadow_s: float = 0.0, timeout_s: float = 120.0, keep_old: bool = False
         ) -> dict[str, Any]:
    """Swap the planner of the episode on the bus (module docstring); the report."""
    from deploy.launch import service_command
    vehicle = cfg.episode.vehicle
    instance = instance or f"s{time.time_ns() % 1_000_000}"
    source = f"planner/{instance}"
    own = [o for o in overrides if not o.startswith("bus.")]
    t0 = time.monotonic()
    with open_session(cfg.bus) as session:
        bus = ZenohTransport(session)
        watch = _Watch(bus, vehicle, source)
        try:
            deadline = time.monotonic() + 5.0
            while watch.state is None and time.monotonic() < deadline:
                time.sleep(0.05)
            if watch.state is None:
                raise SwapError("no episode on the bus (no plant state in 5 s)")
            old = watch.state.authority
            if old == source:
                raise SwapError(f"{source} is the authority already")
            launched = bool(bus.tokens(alive_key(vehicle, "launcher", "0"), timeout=1.0))
            args = candidate_args(shadow_s, keep_old)
            own = as_overrides(running_config(bus, vehicle, old, config_path, own),
                               skip=("bus",))
            own += [f"bus.{k}={json.dumps(v)}" for k, v in             # the operator's trust
                    (("certs", cfg.bus.certs), ("credentials", cfg.bus.credentials)) if v]
            proc, log = None, None
            if launched:
                session.put(launcher_key(vehicle), json.dumps(
                    {"spawn": {"name": "planner", "instance": instance, "args": args,
                               "overrides": own, "config": None}}).encode())
            else:
                log = Path(tempfile.gettempdir()) / f"vamppi-planner-{instance}.log"
                cmd = service_command("planner", cfg.bus.connect[0] if cfg.bus.connect
                                      else "tcp/127.0.0.1:7447", own, None, instance,
                                      with_parent=False) + args
                with open(log, "ab") as f:
                    proc = subprocess.Popen(cmd, stdout=f, stderr=f, stdin=subprocess.DEVNULL,
                                            start_new_session=True)

            def fail(why: str) -> SwapError:
                if launched:
                    session.put(launcher_key(vehicle), json.dumps({"stop": source}).encode())
                elif proc is not None and proc.poll() is None:
                    proc.terminate()
                return SwapError(f"{why}; {old} keeps control" + (f" (log: {log})" if log
                                                                  else ""))
            deadline = t0 + timeout_s
            while watch.status not in ("ready", "stalled"):
                if proc is not None and proc.poll() is not None:
                    raise fail(f"{source} exited with code {proc.returncode} before it was "
                               "ready")
                if time.monotonic() > deadline:
                    raise fail(f"{source} not warm after {timeout_s:.0f} s")
                time.sleep(0.05)
            warm = time.monotonic() - t0
            while watch.state is None or watch.state.authority != source:
                if proc is not None and proc.poll() is not None:
                    raise fail(f"{source} exited with code {proc.returncode}")
                if watch.state is not None and watch.state.outcome:
                    raise fail(f"the episode ended ({watch.state.outcome})")
                if time.monotonic() > deadline:
                    raise fail(f"{source} not granted the authority in {timeout_s:.0f} s")
                time.sleep(0.02)
            s = watch.state
            return {"from": old, "to": source, "epoch": s.epoch,
                    "granted_at_s": round(s.header.stamp, 6), "tick": s.tick,
                    "warm_up_s": round(warm, 3), "took_s": round(time.monotonic() - t0, 3),
                    "shadow_s": shadow_s, "old": "standby" if keep_old else "retired",
                    "by": "vamppi up" if launched else f"pid {proc.pid}",
                    **({"log": str(log)} if log else {})}
        finally:
            watch.close()


# ----------------------------------------------------------------------------- figures
SWAP_RUN = ['episode.scenario="offroad"', 'planner.controller="va"', "planner.samples=800",
            'episode.clock="realtime"', "episode.timeout_s=40"]


def _episode_with_standby(tmp: Path, during: Any, overrides: list[str] = SWAP_RUN
                          ) -> dict[str, Any]:
    """A realtime episode with planner 0 active and planner 1 standing by, `during(p,
    standby)` run while it drives; the states and events from its recording."""
    from deploy.faults import Pipeline, Proc, _plant_record
    from deploy.launch import service_command
    with Pipeline(overrides, tmp) as p:
        standby = Proc(service_command("planner", p.endpoint, overrides, None, "1")
                       + ["--standby"], tmp / "planner1.log")
        p.up()
        p.wait(lambda: any(b.header.source == "planner/1" and b.status == "ready"
                           for _, b in p.beats), 300, "the standby ready")
        p.wait(lambda: p.t >= 0.5, 120, "t >= 0.5 s")
        marks = during(p, standby)
        ev = p.wait_outcome(300)
        p.close()
        standby.stop()
    states, events = _plant_record(p.path)
    return {"outcome": ev.kind, "marks": marks, "states": states, "events": events,
            "path": p.path}


def _stale(states: list[State], after: float = 0.5) -> list[float]:
    return [s.header.stamp for s in states if s.header.stamp > after and not s.header.inputs]


def _spans(stamps: list[float], dt: float = 0.02) -> list[list[float]]:
    """Consecutive plant periods as [first, last] stamps."""
    out: list[list[float]] = []
    for t in sorted(stamps):
        if out and t - out[-1][1] <= 1.5 * dt:
            out[-1][1] = round(t, 3)
        else:
            out.append([round(t, 3), round(t, 3)])
    return out


def swaps_case(tmp: Path, swaps: int) -> dict[str, Any]:
    """`swaps` handovers between the two warm planners, every 0.6 s from t = 1 s, or none."""
    def during(p: Any, standby: Any) -> list[float]:
        cfg = load_cfg(p)
        at = []
        for i in range(swaps):
            p.wait(lambda i=i: p.t >= 1.0 + 0.6 * i or p.outcome() is not None, 120, "a swap")
            if p.outcome() is not None:
                break
            r = promote(cfg, "1" if i % 2 == 0 else "0", keep_old=True)
            at.append(r["granted_at_s"])
        return at
    r = _episode_with_standby(tmp, during)
    stale = _stale(r["states"])
    near = [t for t in stale if any(0.0 <= t - g <= 0.5 for g in r["marks"])]
    changes = [e for e in r["events"] if e.kind == "authority" and "handover" in e.detail]
    return {"case": "swaps", "swaps": len(changes), "outcome": r["outcome"],
            "stale_steps": len(stale), "stale_steps_within_0.5_s_of_a_swap": len(near),
            "stale_at_s": _spans(stale),
            "states": len(r["states"]),
            "time_to_goal_s": next((e.time_to_goal_s for e in r["events"]
                                    if e.kind == "success"), None)}


def failover_case(tmp: Path, sig: int, at_s: float = 5.0) -> dict[str, Any]:
    """The authority (planner 0) killed or stopped at speed with planner 1 standing by:
    control periods from the fault to the standby's first applied command."""
    import signal as _signal

    def during(p: Any, standby: Any) -> list[float]:
        p.wait(lambda: p.t >= at_s, 120, f"t >= {at_s}")
        t = time.time()
        p.procs["planner"].signal(sig)
        return [t]
    r = _episode_with_standby(tmp, during)
    fault_wall = r["marks"][0]
    before = [s for s in r["states"] if s.header.wall_time <= fault_wall]
    t_fault = before[-1].header.stamp
    first = next(s for s in r["states"] if s.header.stamp > t_fault and any(
        i.key.endswith("/cmd") and i.stamp > t_fault + 1e-6 for i in s.header.inputs))
    change = next(e for e in r["events"] if e.kind == "authority" and "fail-over" in e.detail)
    dt = 0.1
    return {"case": "fail-over", "signal": _signal.Signals(sig).name,
            "fault_at_s": round(t_fault, 3), "promoted_after_s": round(
                change.header.stamp - t_fault, 3),
            "first_command_applied_after_s": round(first.header.stamp - t_fault, 3),
            "control_periods": round((first.header.stamp - t_fault) / dt, 2),
            "stale_steps": len(_stale(r["states"])), "stale_steps_after_the_fault": sum(
                t > t_fault for t in _stale(r["states"])),
            "stale_at_s": _spans(_stale(r["states"])),
            "outcome": r["outcome"],
            "detail": change.detail}


def load_cfg(p: Any) -> Config:
    """The configuration of a `deploy.faults.Pipeline`, as a client of its router."""
    return p.cfg.replace(**{"bus.connect": [p.endpoint], "bus.mode": "client"})


def bench_swaps(cfg: Config, tmp: Path, reps: int = 2) -> dict[str, Any]:
    """Realtime, VA-MPPI at K = 800 on offroad: episodes with 20 swaps between two warm
    planners alternated with the same episode without, and fail-overs after SIGKILL and
    SIGSTOP of the authority."""
    import signal as _signal

    from deploy.bench import device_info
    cases = []
    for rep in range(reps):
        for swaps in (20, 0):
            d = tmp / f"swaps{swaps}-{rep}"
            d.mkdir()
            cases.append(swaps_case(d, swaps))
    for sig in (_signal.SIGKILL, _signal.SIGSTOP):
        for rep in range(reps):
            d = tmp / f"failover{sig}-{rep}"
            d.mkdir()
            cases.append(failover_case(d, sig))
    return {"benchmark": "swaps", **device_info(),
            "settings": {"overrides": SWAP_RUN,
                         "planner_deadline_s": cfg.supervision.planner_deadline_s},
            "cases": cases}


def swaps_table(result: dict[str, Any]) -> str:
    lines = [f"swaps: {result['device']}", "", "| case | swaps or signal | stale steps "
             "| of them within 0.5 s of a swap, or after the fault "
             "| fault to first command s (periods) | outcome |", "|---|---|---|---|---|---|"]
    for c in result["cases"]:
        if c["case"] == "swaps":
            lines.append(f"| swaps | {c['swaps']} | {c['stale_steps']} "
                         f"| {c['stale_steps_within_0.5_s_of_a_swap']} | | {c['outcome']} |")
        else:
            lines.append(f"| fail-over | {c['signal']} | {c['stale_steps']} "
                         f"| {c['stale_steps_after_the_fault']} "
                         f"| {c['first_command_applied_after_s']} ({c['control_periods']}) "
                         f"| {c['outcome']} |")
    return "\n".join(lines)
