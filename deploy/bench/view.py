"""`vamppi bench view`: does a live viewer slow the pipeline? `make demo`'s episode
(`vamppi up`, alleyway, VA-MPPI, lockstep, seed 0) without a viewer and with `--view`
and a Foxglove client subscribed to every channel (it receives every frame and, as an
app drawing on another machine would, leaves decoding to that app: the schema checks
are tests/test_view.py's), alternated, side by side in one run. In lockstep the plant
waits for each command, so the command rate (control ticks per wall second) is the
pipeline's speed; the trajectory must be the same."""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import threading
from typing import Any

from common.config import Config
from deploy.bench.device import device_info, heading, markdown_table
from deploy.launch.up import free_port
from deploy.recording.view import watch

DEMO = ["--scenario", "alleyway", "--controller", "va", "--clock", "lockstep", "--seed", "0"]


def _episode(cfg: Config, view: bool) -> dict[str, Any]:
    port = free_port()
    cmd = [sys.executable, "-m", "deploy", "up", *DEMO,
           *(["--view", "--view-port", str(port)] if view else [])]
    client: dict[str, Any] = {}
    up = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    thread = None
    if view:
        def follow() -> None:
            got = watch(port, 600.0, check=False)
            client.update({t: len(m) for t, m in got.items()})
        thread = threading.Thread(target=follow, daemon=True)
        thread.start()
    out, _ = up.communicate(timeout=900)
    if thread is not None:
        thread.join(timeout=30)
    s = json.loads(out.strip().splitlines()[-1])
    ticks = round(s["sim_time_s"] / cfg.planner.dt_s) if s["sim_time_s"] else 0
    return {"view": view, "outcome": s["outcome"], "time_to_goal_s": s["time_to_goal_s"],
            "wall_time_s": s["wall_time_s"], "ticks": ticks,
            "command_rate_hz": round(ticks / s["wall_time_s"], 3) if s["wall_time_s"] else None,
            "client_received": client, "viewer": s.get("view")}


def bench_view(cfg: Config, reps: int) -> dict[str, Any]:
    episodes = [_episode(cfg, view) for _ in range(reps) for view in (False, True)]
    cases = []
    for view in (False, True):
        mine = [e for e in episodes if e["view"] == view]
        rates = [e["command_rate_hz"] for e in mine if e["command_rate_hz"]]
        cases.append({"case": "with --view and a client" if view else "without a viewer",
                      "episodes": len(mine),
                      "outcomes": sorted({e["outcome"] for e in mine}),
                      "time_to_goal_s": sorted({e["time_to_goal_s"] for e in mine}, key=str),
                      "command_rate_hz_median": round(statistics.median(rates), 3),
                      "command_rate_hz": rates})
    ratio = cases[1]["command_rate_hz_median"] / cases[0]["command_rate_hz_median"]
    return {"benchmark": "view", **device_info(), "episode": " ".join(DEMO),
            "reps": reps, "cases": cases, "rate_ratio_with_to_without": round(ratio, 3),
            "episodes": episodes}


def view_table(result: dict[str, Any]) -> str:
    rows = [[c["case"], c["episodes"], ", ".join(c["outcomes"]),
             ", ".join(map(str, c["time_to_goal_s"])), c["command_rate_hz_median"],
             ", ".join(f"{r:.2f}" for r in c["command_rate_hz"])] for c in result["cases"]]
    return "\n".join([markdown_table(heading(result), [
        "case", "episodes", "outcome", "time to goal, s", "command rate, Hz (median)",
        "each episode"], rows), "", f"with / without: {result['rate_ratio_with_to_without']}"])
