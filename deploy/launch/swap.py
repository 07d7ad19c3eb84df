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
5. If it does not start, warm up or get the authority within `timeout_s`, or the episode
   ends first, it is stopped and the old one keeps control; the command says why.
"""

from __future__ import annotations

import json
import subprocess
import threading
import time
from typing import Any

from common.bus import ZenohTransport, open_session
from common.config import Config, ConfigError, as_overrides, config_from_dict, load_config
from common.messages import Handover, Heartbeat, State, encode, on_decoded
from common.protocol import Out, Stamper
from common.topics import admin_key, alive_key, heartbeat_key, launcher_key, topic_key
from deploy.launch.running import runtime_dir


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
    from deploy.launch.up import service_command
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
                runtime_dir().mkdir(mode=0o700, parents=True, exist_ok=True)
                log = runtime_dir() / f"swap-{vehicle}-planner-{instance}.log"
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
                if watch.state is not None and watch.state.outcome:
                    raise fail(f"the episode ended ({watch.state.outcome}) before {source} "
                               "was warm")
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
