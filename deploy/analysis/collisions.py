"""What each collision of an experiment was on: `vamppi collisions DIR`.

A run record of an experiment (deploy/sim/experiment.py) whose outcome is a
collision carries `collision`: the colliding pose and speed, and every scenario
obstacle under the footprint with its `hidden` flag and the time the map first
showed it, and when each of the scenario's hidden obstacles first appeared
(deploy/sim/runner.py, `collision_record`). The paper separates collisions with
obstacles in unobserved space from the rest; this table does it with the runs'
own maps: how long the map had shown what was hit, and whether the vehicle had
travelled farther since than it needed to stop (`room_to_stop`).

Records written before the field existed have none. `--rerun` runs each such
collision again in this process with the directory's configuration (the
episodes are deterministic for a seed); a rerun whose outcome or end time
differs from the record's is reported as not reproduced, never attributed.
The attributions a rerun makes are kept beside the runs, in
`DIR/collisions.json` (runs.jsonl is never rewritten), and used from then on.
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path
from typing import Any

import numpy as np

from common.config import Config
from deploy.analysis.reveal import stopping_distance
from deploy.sim.experiment import KEY_FIELDS, config_digest, run_layout, run_one
from deploy.sim.runner import Cores

UNATTRIBUTED = "unattributed"
NOT_REPRODUCED = "not reproduced"
SAVED = "collisions.json"


def _key(r: dict[str, Any]) -> tuple:
    return tuple(r[k] for k in KEY_FIELDS) + (r.get("config_digest"),)


def room_to_stop(cfg: Config, path: Any, c: dict[str, Any]) -> dict[str, Any] | None:
    """From the moment the map showed the last of the collision's obstacles to the collision:
    the distance travelled along the recorded 10 Hz path (t, X, Y, V[, psi]), the speed then, and
    the distance needed to stop from that speed (`deploy.analysis.reveal.stopping_distance`: one
    control tick, the brake ramp, full braking). None where an obstacle was never shown or
    the collision is off the map only."""
    shown = [o["mapped_at_s"] for o in c["obstacles"]]
    if not shown or any(s is None for s in shown):
        return None
    t_m = max(shown)
    p = np.asarray(path, float)[:, :4]                   # (t, X, Y, V), with or without psi
    p = np.vstack([p[p[:, 0] < c["t_s"] - 1e-9], [c["t_s"], c["x"], c["y"], c["speed_mps"]]])
    at = [float(np.interp(t_m, p[:, 0], p[:, k])) for k in (1, 2, 3)]
    later = p[p[:, 0] > t_m]
    xy = np.vstack([at[:2], later[:, 1:3]])
    travelled = float(np.sum(np.hypot(*np.diff(xy, axis=0).T)))
    stop = stopping_distance(cfg, at[2])
    return {"travelled_m": round(travelled, 2), "speed_mps": round(at[2], 2),
            "stopping_m": round(stop, 2), "could_stop": travelled > stop}


def attribute(cfg: Config, runs: list[dict[str, Any]], rerun: bool = False,
              progress: bool = False, saved: list[dict[str, Any]] = ()
              ) -> list[dict[str, Any]]:
    """One row per collided run: its keys and its `collision` record (status "recorded",
    or "rerun": found by a rerun now or in `saved`, the rows of an earlier one), or a
    `status` of UNATTRIBUTED (an older record, no rerun) or NOT_REPRODUCED (the rerun
    differs)."""
    from tqdm import tqdm
    collided = [r for r in runs if r["outcome"] == "collision"]
    earlier = {_key(s): s for s in saved if s.get("status") == "rerun"}
    cores: dict[int, dict[tuple, Cores]] = {}          # per scenario layout
    digest = config_digest(cfg)
    rows = []
    for r in tqdm(collided, desc="collisions", unit="run", disable=not progress):
        row = {k: r[k] for k in KEY_FIELDS}
        row["config_digest"] = r.get("config_digest")
        if "collision" in r:
            rows.append({**row, "status": "recorded", "collision": r["collision"]})
            continue
        if _key(r) in earlier:
            rows.append({**row, "status": "rerun", "collision": earlier[_key(r)]["collision"]})
            continue
        if not rerun:
            rows.append({**row, "status": UNATTRIBUTED, "collision": None})
            continue
        if r.get("config_digest", digest) != digest:
            rows.append({**row, "status": NOT_REPRODUCED, "collision": None,
                         "why": f"config digest {r['config_digest']}, this one {digest}"})
            continue
        # the digest covers every parameter but the run's keys (the scenario's seed too)
        layout = run_layout(r)
        _, res = run_one(cfg.replace(**{"episode.layout": layout}),
                         tuple(r[k] for k in KEY_FIELDS), cores.setdefault(layout, {}))
        if res.outcome != "collision" or abs(res.sim_time_s - r["sim_time_s"]) > 1e-6:
            rows.append({**row, "status": NOT_REPRODUCED, "collision": None,
                         "why": f"rerun: {res.outcome} at {res.sim_time_s:.2f} s, "
                                f"recorded: collision at {r['sim_time_s']:.2f} s"})
            continue
        rows.append({**row, "status": "rerun", "collision": res.collision})
    for row, r in zip(rows, collided, strict=True):
        if row["collision"] is not None and r.get("path"):
            row["room"] = room_to_stop(cfg, r["path"], row["collision"])
    return rows


def load_saved(directory: Path) -> list[dict[str, Any]]:
    """The rows an earlier rerun kept in `directory` (none if it kept none)."""
    path = directory / SAVED
    if not path.exists():
        return []
    try:
        rows = json.loads(path.read_text())
        if not isinstance(rows, list) or not all(
                isinstance(r, dict) and all(k in r for k in (*KEY_FIELDS, "status", "collision"))
                for r in rows):
            raise ValueError("not a list of attribution rows")
    except ValueError as exc:
        raise ValueError(f"{path}: unreadable ({exc}); remove it and attribute again "
                         "with --rerun") from None
    return rows


def save(directory: Path, earlier: list[dict[str, Any]], rows: list[dict[str, Any]]) -> None:
    """Keep every rerun's attribution, earlier and new, in `directory` (atomically)."""
    kept = {_key(r): r for r in [*earlier, *rows] if r["status"] == "rerun"}
    tmp = directory / (SAVED + ".tmp")
    tmp.write_text(json.dumps(list(kept.values()), indent=1) + "\n")
    tmp.replace(directory / SAVED)


def _obstacle_label(o: dict[str, Any]) -> str:
    return f"{o['kind']} ({o['x']:g}, {o['y']:g})" + (", hidden" if o["hidden"] else "")


def _span(values: list[float], unit: str) -> str:
    if not values:
        return "—"
    lo, hi, med = min(values), max(values), statistics.median(values)
    return f"{med:.2f} {unit} ({lo:.2f}-{hi:.2f})" if len(values) > 1 else f"{med:.2f} {unit}"


def hidden_lead(c: dict[str, Any]) -> float | None | str:
    """Seconds from the moment the map first showed the last-shown of the scenario's hidden
    obstacles to the collision; None if none had been shown; "" where the record predates
    the field."""
    if "hidden" not in c:
        return ""
    shown = [h["mapped_at_s"] for h in c["hidden"] if h["mapped_at_s"] is not None]
    return round(c["t_s"] - max(shown), 3) if shown else None


def _hidden_cell(leads: list[float | None | str]) -> str:
    known = [x for x in leads if x != ""]
    if not known:
        return "—"
    shown = [x for x in known if x is not None]
    text = _span(shown, "s") if shown else "none shown"
    return text + (f"; none shown in {len(known) - len(shown)}" if shown
                   and len(shown) < len(known) else "")


def table(rows: list[dict[str, Any]]) -> str:
    """Per scenario, controller and sample count: the collisions on each obstacle, how
    long the map had shown it, how far the vehicle went from then on against the distance
    it needed to stop, how many could have stopped, and the speed at impact; then the runs
    left unattributed."""
    groups: dict[tuple, dict[str, list]] = {}
    other: dict[tuple, list[str]] = {}
    for r in rows:
        g = (r["scenario"], r["controller"], r["samples"])
        c = r["collision"]
        if c is None:
            other.setdefault(g, []).append(f"seed {r['seed']}: {r['status']}")
            continue
        names = [_obstacle_label(o) for o in c["obstacles"]] + (["off the map"] if c["off_map"]
                                                               else [])
        what = " + ".join(names) or "an obstacle cell of no listed obstacle"
        shown = [o["mapped_for_s"] for o in c["obstacles"]]
        groups.setdefault(g, {}).setdefault(what, []).append({
            "shown": None if any(s is None for s in shown) or not shown else min(shown),
            "room": r.get("room"), "speed": c["speed_mps"], "seed": r["seed"],
            "hidden": hidden_lead(c)})
    lines = ["| scenario | controller | K | on | collisions | map showed it for | never shown "
             "| then travelled | needed to stop | could have stopped | speed at impact "
             "| a hidden obstacle appeared before impact | seeds |", "|" + "---|" * 13]
    for g in sorted(set(groups) | set(other)):
        for what, hits in sorted(groups.get(g, {}).items(), key=lambda kv: -len(kv[1])):
            shown = [h["shown"] for h in hits if h["shown"] is not None]
            room = [h["room"] for h in hits if h["room"] is not None]
            seeds = ", ".join(str(h["seed"]) for h in sorted(hits, key=lambda h: h["seed"]))
            lines.append(
                f"| {g[0]} | {g[1]} | {g[2]} | {what} | {len(hits)} | {_span(shown, 's')} "
                f"| {len(hits) - len(shown)} | {_span([x['travelled_m'] for x in room], 'm')} "
                f"| {_span([x['stopping_m'] for x in room], 'm')} "
                f"| {sum(x['could_stop'] for x in room)} "
                f"| {_span([h['speed'] for h in hits], 'm/s')} "
                f"| {_hidden_cell([h['hidden'] for h in hits])} | {seeds} |")
        if g in other:
            lines.append(f"| {g[0]} | {g[1]} | {g[2]} | (not attributed) | {len(other[g])} "
                         f"| | | | | | | | {'; '.join(other[g])} |")
    return "\n".join(lines)


def counts(rows: list[dict[str, Any]]) -> dict[str, int]:
    """How many rows are attributed (recorded or rerun) and how many not."""
    out = {"collisions": len(rows)}
    for r in rows:
        out[r["status"]] = out.get(r["status"], 0) + 1
    return out

