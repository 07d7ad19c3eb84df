"""Timing of a pipeline run: the chain follower shared by `vamppi bench pipeline` (live,
on the bus) and `vamppi timing` (from a recording), and the recording's analysis.

End-to-end latency follows one chain through the input references in the
headers: a command's header names the map it was planned on, the map's the
depth frame it fused; the plant's state names the command it applies. Depth
capture to command applied = the first state applying a command (its publish
wall time) minus the publish wall time of the depth frame at the chain's root.

Across hosts those wall times come from different clocks. The recorder measures each
publisher's offset from its own clock, NTP-style over the bus (a round trip to the
service's clock queryable, the tightest of several: `common.bus.measure_clocks`), and
notes it in the recording; every wall time is put on the recorder's clock before it is
subtracted, so a latency is true within half the round trip of the clocks' measurement
(tens of microseconds on one host, about a link's latency across hosts).
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from common.messages import DecodeError, Heartbeat, decode, peek
from common.protocol import SeqTrack
from common.topics import REPLAY_SOURCE, heartbeat_key, topic_key
from deploy.recording.record import (
    iter_messages,
    read_metadata,
    recorded_clocks,
    recording_label,
)


def stats_ms(times: list[float]) -> dict[str, float]:
    """Median, p95, p99 in ms of times in seconds."""
    t = np.asarray(times) * 1e3
    return {"median_ms": round(float(np.median(t)), 3),
            "p95_ms": round(float(np.percentile(t, 95)), 3),
            "p99_ms": round(float(np.percentile(t, 99)), 3), "reps": len(t)}


class ChainLog:
    """Headers of the pipeline's depth, map, cmd and state messages as they pass
    (bus-level subscriber callbacks; the msgpack header, and a state's authority). A message
    is named by (seq, stamp), a command also by its source: several planners publish on
    `cmd` (a swap, a standby, a rogue), and a state's inputs name the command it applied
    of the authority it names."""

    def __init__(self, vehicle: str, clocks: dict[str, float] | None = None):
        """`clocks`: each publisher's offset ("service/instance" -> s ahead of ours)."""
        self.keys = {t: topic_key(vehicle, t) for t in ("depth", "map", "cmd", "state")}
        self.clocks = clocks or {}
        self.lock = threading.Lock()
        Ref = tuple[int, float]                           # (seq, stamp)
        self.depth: dict[Ref, float] = {}                 # -> publish wall time
        self.map: dict[Ref, tuple[float, Ref | None]] = {}    # -> (wall, its depth)
        self.cmd: dict[tuple[str, int, float], tuple[float, Ref | None]] = {}  # (source, ...)
        self.applied: dict[tuple[str, int, float], float] = {}  # cmd -> first state applying it
        self.states = 0
        self.stale = 0

    def callbacks(self) -> dict[str, Any]:
        return {key: (lambda sample, t=topic: self.on(t, sample.payload.to_bytes()))
                for topic, key in self.keys.items()}

    def _ref(self, h: dict[str, Any], topic: str) -> tuple[int, float] | None:
        for key, seq, stamp in h.get("inputs", []):
            if key == self.keys[topic]:
                return int(seq), round(float(stamp), 6)
        return None

    def on(self, topic: str, payload: bytes) -> None:
        try:
            m = msgpack.unpackb(payload, raw=False)
            h = m["header"]
            wall = float(h["wall_time"]) - self.clocks.get(str(h.get("source", "")), 0.0)
            me = (int(h["seq"]), round(float(h["stamp"]), 6))
        except Exception:          # malformed traffic is the codec tests' business
            return
        with self.lock:
            if topic == "depth":
                self.depth[me] = wall
            elif topic == "map":
                self.map[me] = (wall, self._ref(h, "depth"))
            elif topic == "cmd":
                self.cmd[(str(h.get("source", "")), *me)] = (wall, self._ref(h, "map"))
            else:
                self.states += 1
                ref = self._ref(h, "cmd")
                if ref is None:
                    self.stale += 1
                else:
                    key = (str(m.get("authority", "")), *ref)
                    self.applied.setdefault(key, wall)

    def chains(self) -> list[tuple[float, float, float, float]]:
        """Every complete chain: (depth, map, cmd, first state applying it) wall times."""
        with self.lock:
            out = []
            for cmd, applied in self.applied.items():
                c_wall, m_ref = self.cmd.get(cmd, (None, None))
                m_wall, d_ref = self.map.get(m_ref, (None, None))
                d_wall = self.depth.get(d_ref)
                if None not in (c_wall, m_wall, d_wall):
                    out.append((d_wall, m_wall, c_wall, applied))
            return out

    def summary(self) -> dict[str, Any]:
        chains = self.chains()
        with self.lock:
            cmd_walls = sorted(w for w, _ in self.cmd.values())
        out: dict[str, Any] = {"commands": len(cmd_walls), "chains": len(chains),
                               "states": self.states, "stale_states": self.stale}
        if len(cmd_walls) > 1:
            gaps = np.diff(cmd_walls)
            out["command_rate_hz"] = round((len(cmd_walls) - 1)
                                           / (cmd_walls[-1] - cmd_walls[0]), 2)
            out["command_interval"] = stats_ms(list(gaps))
        if chains:
            a = np.asarray(chains)
            out["end_to_end"] = stats_ms(list(a[:, 3] - a[:, 0]))
            out["depth_to_map"] = stats_ms(list(a[:, 1] - a[:, 0]))
            out["map_to_cmd"] = stats_ms(list(a[:, 2] - a[:, 1]))
            out["cmd_to_applied"] = stats_ms(list(a[:, 3] - a[:, 2]))
        return out




def _ms(values: list[float]) -> dict[str, float]:
    """Mean, std, p50, p95, p99, max in ms of values in seconds (empty: {})."""
    if not values:
        return {}
    a = np.asarray(values) * 1e3
    return {"mean_ms": round(float(a.mean()), 3), "std_ms": round(float(a.std()), 3),
            "p50_ms": round(float(np.median(a)), 3),
            "p95_ms": round(float(np.percentile(a, 95)), 3),
            "p99_ms": round(float(np.percentile(a, 99)), 3), "max_ms": round(float(a.max()), 3)}


def analyse(path: str | Path) -> dict[str, Any]:
    """Per-key rate, jitter, sizes, seq gaps and transport latency; the depth -> command
    applied chain; the planner's solve times. One pass over the recording."""
    meta = read_metadata(path).get("vamppi", {})
    vehicle = meta.get("vehicle") or "ego"
    clocks = recorded_clocks(path)
    chain = ChainLog(vehicle, clocks)
    chain_topics = {key: topic for topic, key in chain.keys.items()}
    per: dict[str, dict[str, Any]] = {}
    solve_ms: list[float] = []
    stats_key = topic_key(vehicle, "stats")
    undecodable = 0
    replay_beat = heartbeat_key(vehicle, REPLAY_SOURCE)
    replayed: set[str] = set()
    for m in iter_messages(path):
        k = per.setdefault(m.key, {"log": [], "latency": [], "sizes": [], "seqs": {}})
        k["log"].append(m.log_time_ns)
        k["sizes"].append(len(m.data))
        try:
            _, header = peek(m.data)
        except DecodeError:
            undecodable += 1
            continue
        if m.key == replay_beat:
            try:
                replayed.add(decode(m.data, Heartbeat).detail)
            except DecodeError:
                undecodable += 1
        wall = header.wall_time - clocks.get(header.source, 0.0)    # on the recorder's clock
        k["latency"].append(m.log_time_ns / 1e9 - wall)
        k["seqs"].setdefault((header.source, header.boot), SeqTrack()).see(header.seq)
        if m.key in chain_topics:
            chain.on(chain_topics[m.key], m.data)
        if m.key == stats_key:
            solve_ms.append(float(msgpack.unpackb(m.data, raw=False)["solve_ms"]))
    topics = []
    for key, k in sorted(per.items()):
        log_s = np.asarray(k["log"], np.float64) / 1e9
        period = np.diff(log_s)
        row = {"key": key, "messages": len(log_s),
               "rate_hz": round((len(log_s) - 1) / (log_s[-1] - log_s[0]), 3)
               if len(log_s) > 1 and log_s[-1] > log_s[0] else None,
               "period": _ms(list(period)),
               "bytes_mean": round(float(np.mean(k["sizes"])), 1),
               "bytes_max": int(np.max(k["sizes"])),
               "publishers": len(k["seqs"]),
               "seq_missing": sum(p.missing for p in k["seqs"].values()),
               "seq_late": sum(p.late for p in k["seqs"].values()),
               "seq_duplicates": sum(p.duplicates for p in k["seqs"].values()),
               "transport": _ms(k["latency"])}
        topics.append(row)
    out: dict[str, Any] = {"recording": str(path), "vehicle": vehicle,
                           **recording_label(path), "git_commit": meta.get("git_commit", ""),
                           "replayed": sorted(replayed),
                           "undecodable": undecodable, "clock_offsets_s": clocks,
                           "topics": topics,
                           "chain": chain.summary()}
    if solve_ms:
        out["solve_ms"] = {**_ms([s / 1e3 for s in solve_ms]), "count": len(solve_ms)}
    out["authority"] = authority_changes(path)
    out["_series"] = {"solve_ms": solve_ms, "chains": chain.chains(),
                      "latency": {key: k["latency"] for key, k in per.items()},
                      "period": {key: list(np.diff(np.asarray(k["log"]) / 1e9))
                                 for key, k in per.items()}}
    return out


def table(result: dict[str, Any]) -> str:
    """The analysis as a Markdown table plus the chain and solve-time lines."""
    def f(v: Any) -> str:
        return "-" if v is None else f"{v:g}" if isinstance(v, float) else str(v)
    lines = [f"timing of {result['recording']} ({result['clock']} clock, scenario "
             f"{result['scenario']}, {result['controller']} K = {result['samples']}, "
             f"commit {result['git_commit'] or '?'})", ""]
    if result.get("replayed"):
        lines += [f"a recording of a replay ({', '.join(result['replayed'])}): rates and "
                  "periods are the replay's; transport is from the replay, which stamps each "
                  "message anew as it republishes it", ""]
    lines += [
             "| key | msgs | rate Hz | period p50 ms | jitter (std) ms | bytes mean | bytes max "
             "| seq gaps | transport p50 ms | p95 ms | p99 ms |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in result["topics"]:
        p, t = r["period"], r["transport"]
        lines.append(f"| {r['key']} | {r['messages']} | {f(r['rate_hz'])} | "
                     f"{f(p.get('p50_ms'))} | {f(p.get('std_ms'))} | {r['bytes_mean']:.0f} | "
                     f"{r['bytes_max']} | {r['seq_missing']} | {f(t.get('p50_ms'))} | "
                     f"{f(t.get('p95_ms'))} | {f(t.get('p99_ms'))} |")
    clocks = result.get("clock_offsets_s") or {}
    lines += ["", "publishers' clocks, ms ahead of the recorder's (corrected for): " + (
        ", ".join(f"{src} {1e3 * off:+.3f}" for src, off in sorted(clocks.items()))
        or "none measurably apart")]
    c = result["chain"]
    lines += ["", f"chains depth -> map -> cmd -> applied: {c['chains']} "
              f"(commands {c['commands']}, states {c['states']}, "
              f"states without a fresh command {c['stale_states']})"]
    if "command_rate_hz" in c:
        lines.append(f"command rate {c['command_rate_hz']} Hz")
    for stage in ("end_to_end", "depth_to_map", "map_to_cmd", "cmd_to_applied"):
        if stage in c:
            s = c[stage]
            lines.append(f"{stage:15s} p50 {s['median_ms']:9.3f} ms   p95 {s['p95_ms']:9.3f} ms"
                         f"   p99 {s['p99_ms']:9.3f} ms   n {s['reps']}")
    if "solve_ms" in result:
        s = result["solve_ms"]
        lines.append(f"planner solve   p50 {s['p50_ms']:9.3f} ms   p95 {s['p95_ms']:9.3f} ms"
                     f"   max {s['max_ms']:9.3f} ms   n {s['count']}")
    if result.get("authority"):
        lines += ["", "| authority at s | how | to | first command of it after s "
                      "| stale steps in between |", "|---|---|---|---|---|"]
        for a in result["authority"]:
            lines.append(f"| {a['stamp_s']} | {a['kind']} | {a['to']} "
                         f"| {f(a['first_command_after_s'])} | {a['stale_steps']} |")
    return "\n".join(lines)


def authority_changes(path: str | Path) -> list[dict[str, Any]]:
    """Every change of the plant's authority (its `authority` events): when, to whom, how
    (start, swap, fail-over, restart), and how long the plant went without a command of the
    new authority: from the change to the first state applying a command of t0 at or
    after it, the plant periods in between that applied no command at all."""
    from common.messages import Event, State
    events, states = [], []
    for m in iter_messages(path):
        if m.key.endswith("/plant/events") or m.key.endswith("/plant/state"):
            try:
                msg = decode(m.data)
            except DecodeError:
                continue
            if isinstance(msg, Event) and msg.kind == "authority":
                events.append((m.log_time_ns, msg))
            elif isinstance(msg, State):
                states.append(msg)
    stamps: dict[float, State] = {}
    for st in states:
        stamps.setdefault(round(st.header.stamp, 6), st)
    ordered = [stamps[k] for k in sorted(stamps)]
    out = []
    for log_ns, e in sorted(events, key=lambda x: x[1].header.stamp):
        t = e.header.stamp
        how = ("fail-over" if "fail-over" in e.detail else "swap" if "handover" in e.detail
               else "start" if t < 1e-9 or "epoch 1" in e.detail else "restart")
        after = [s for s in ordered if s.header.stamp > t + 1e-9]
        first = next((s for s in after if any(i.key.endswith("/cmd") and i.stamp >= t - 1e-6
                                              for i in s.header.inputs)), None)
        between = [s for s in after if first is None or s.header.stamp < first.header.stamp]
        out.append({"stamp_s": round(t, 6), "kind": how, "to": e.detail.split(" ")[0],
                    "detail": e.detail, "wall_time": round(log_ns / 1e9, 3),
                    "first_command_after_s": None if first is None
                    else round(first.header.stamp - t, 3),
                    "stale_steps": sum(not s.header.inputs for s in between)})
    return out


def plots(result: dict[str, Any], out_dir: str | Path) -> list[Path]:
    """Solve-time histogram (the paper's figure), chain latency stages, transport
    latency and inter-arrival per key; PNGs in `out_dir`."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from deploy.analysis.plots import save_figure
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    s = result["_series"]
    title = (f"{Path(result['recording']).name}: {result['controller']} K = {result['samples']}, "
             f"{result['scenario']}, {result['clock']} clock")
    written = []
    if s["solve_ms"]:
        fig, ax = plt.subplots(figsize=(6, 3.5))
        ax.hist(s["solve_ms"], bins=40, color="tab:blue")
        ax.set_xlabel("planner solve time (ms)")
        ax.set_ylabel("ticks")
        ax.set_title("solve-time distribution")
        written.append(save_figure(fig, out / "solve_time.png", title=title))
    if s["chains"]:
        a = np.asarray(s["chains"]) * 1e3
        fig, ax = plt.subplots(figsize=(6, 3.5))
        stages = {"depth -> map": a[:, 1] - a[:, 0], "map -> cmd": a[:, 2] - a[:, 1],
                  "cmd -> applied": a[:, 3] - a[:, 2], "end to end": a[:, 3] - a[:, 0]}
        ax.boxplot(list(stages.values()), showfliers=True)
        ax.set_xticks(range(1, len(stages) + 1), list(stages))
        ax.set_ylabel("ms")
        ax.set_title("chain latency, depth capture to command applied")
        written.append(save_figure(fig, out / "chain_latency.png", title=title))
    keys = sorted(k for k, v in s["latency"].items() if v)
    if keys:
        fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
        periods = np.concatenate([np.asarray(s["period"][k]) * 1e3 for k in keys])
        periods = periods[periods > 0]
        bins = (np.logspace(np.log10(periods.min()), np.log10(periods.max()), 60)
                if len(periods) else 10)
        for key in keys:
            short = key.split("/")[-1]
            lat = np.sort(np.asarray(s["latency"][key]) * 1e3)
            axes[0].plot(lat, np.linspace(0, 1, len(lat)), label=short)
            per = np.asarray(s["period"][key]) * 1e3
            if len(per):
                axes[1].hist(per[per > 0], bins=bins, histtype="step", label=short)
        axes[0].set_xscale("log")
        axes[0].set_xlabel("transport latency, receive - publish (ms)")
        axes[0].set_ylabel("fraction")
        axes[1].set_xlabel("inter-arrival (ms)")
        axes[1].set_xscale("log")
        axes[1].set_yscale("log")
        for ax in axes:
            ax.legend(fontsize=7)
        written.append(save_figure(fig, out / "topics.png", title=title))
    return written


def public(result: dict[str, Any]) -> dict[str, Any]:
    """The analysis without its raw series (what --json prints)."""
    return {k: v for k, v in result.items() if not k.startswith("_")}
