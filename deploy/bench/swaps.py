"""`vamppi bench swaps`: hot swaps and fail-overs of the planner, measured in realtime
episodes (the stale plant steps around each, the time from a fault to the standby's first
applied command)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from common.config import Config
from common.messages import State
from deploy.bench.device import device_info
from deploy.bench.faults import Pipeline, Proc, plant_record
from deploy.launch.swap import promote
from deploy.launch.up import service_command

SWAP_RUN = ['episode.scenario="offroad"', 'planner.controller="va"', "planner.samples=800",
            'episode.clock="realtime"', "episode.timeout_s=40"]


def _episode_with_standby(tmp: Path, during: Any, overrides: list[str] = SWAP_RUN
                          ) -> dict[str, Any]:
    """A realtime episode with planner 0 active and planner 1 standing by, `during(p,
    standby)` run while it drives; the states and events from its recording."""
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
    states, events = plant_record(p.path)
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
    """The configuration of a `deploy.bench.faults.Pipeline`, as a client of its router."""
    return p.cfg.replace(**{"bus.connect": [p.endpoint], "bus.mode": "client"})


def bench_swaps(cfg: Config, tmp: Path, reps: int = 2) -> dict[str, Any]:
    """Realtime, VA-MPPI at K = 800 on offroad: episodes with 20 swaps between two warm
    planners alternated with the same episode without, and fail-overs after SIGKILL and
    SIGSTOP of the authority."""
    import signal as _signal

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
