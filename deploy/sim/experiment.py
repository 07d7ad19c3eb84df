"""`vamppi experiment`: the paper's Monte-Carlo comparison, in-process and lockstep.

For every scenario x controller x sample count, `runs` episodes with planner
seeds `seed, seed + 1, ...` on the same scenario (its terrain fixed by
`episode.scenario_seed`). The same cores as the services, composed by
`deploy.sim.runner`.

Output directory:
  runs.jsonl     one record per finished run (outcome, time to goal, 10 Hz path
                 (t, X, Y, V, heading),
                 solve times; a collision's obstacles and when the map first showed
                 them: deploy/analysis/collisions.py), appended and fsynced as each ends:
                 an interrupted experiment keeps its finished runs and resumes
                 where it stopped (a torn last line is ignored); each record
                 carries the configuration's digest, and resuming with another
                 configuration is refused
  config.toml    the configuration (every parameter; the per-run keys as given,
                 but one scenario and its layout pinned: saved_config):
                 `--config DIR/config.toml` resumes or reruns with it,
                 `vamppi reveal DIR` reads it
  summary.*, *.png  what the runs show (deploy.analysis.summary), written by the
                 command after the runs

With a `runner`, the runs are its (deploy/sim/cluster.py: tasks on a Ray cluster). With
`jobs` > 1 the runs are spread over that many worker processes (each its own
JAX runtime and cores, pinned to its share of this process's CPUs when there are
enough); this process alone writes runs.jsonl, a record as each run ends. A run's
record does not depend on which process ran it (tested), except its solve and wall
times, which are then measured with the other workers competing for the machine.
"""

from __future__ import annotations

import hashlib
import json
import logging
import multiprocessing
import os
import signal
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from common.config import Config, config_toml
from common.memory import share_device
from common.process import when_orphaned
from common.scenarios import ScenarioError, build_scenario, resolve_layout
from deploy.sim.runner import Cores, run_episode
from services.plant.core import OUTCOMES
from services.plant.dynamics import S

log = logging.getLogger(__name__)

KEY_FIELDS = ("scenario", "controller", "samples", "seed")


class ExperimentError(ValueError):
    """An output directory that cannot be resumed with this configuration, or a scenario
    that cannot be built."""


# parameters added after tables were made, at the value that leaves a run as it was: left
# out of the digest there, so those tables' digests and records stay valid
DIGEST_NEUTRAL = {("planner", "turn_radius_speed"): False}


def config_digest(cfg: Config) -> str:
    """Digest of every parameter that shapes a run except the per-run keys (scenario,
    controller, samples, seed); the bus, the clock and the bus protocol's parameters
    (supervision, re-offers, authority, perception timeout) do not matter in-process. The
    runs of one output directory must share it. The scenario's layout is not in it (it
    came after the digest): each record carries its own (`run_layout`); nor is a parameter
    of `DIGEST_NEUTRAL` at its neutral value."""
    d = cfg.to_dict()
    d.pop("bus", None)
    d.pop("supervision", None)
    for section, key in (("plant", "perception_timeout_s"), ("plant", "reoffer_s"),
                         ("plant", "authority"), ("episode", "scenario"), ("episode", "seed"),
                         ("episode", "clock"), ("episode", "layout"), ("episode", "vehicle"),
                         ("planner", "controller"), ("planner", "samples")):
        d[section].pop(key, None)
    for (section, key), neutral in DIGEST_NEUTRAL.items():
        if d[section].get(key) == neutral:
            d[section].pop(key)
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


def saved_config(cfg: Config, scenarios: list[str]) -> Config:
    """The configuration written beside the runs. With one scenario it is pinned there,
    its layout as a number ("the newest", 0, would rebuild another layout once a newer one
    lands), so the file alone reruns the table, or runs its setting in `vamppi up`. Neither
    is in the digest."""
    if len(set(scenarios)) != 1:
        return cfg
    return cfg.replace(**{"episode.scenario": scenarios[0],
                          "episode.layout": resolve_layout(scenarios[0], cfg.episode.layout)})


# what a record holds, by version: 1, a path of (t, X, Y, V); 2, the heading psi added to
# it; 3, the scenario layout too. A record without the field is told by its content.
RECORD_FORMAT = 3


def record_format(r: dict[str, Any]) -> int:
    """A record's format (RECORD_FORMAT's versions)."""
    if "format" in r:
        return int(r["format"])
    if "layout" in r:
        return 3
    return 2 if r.get("path") and len(r["path"][0]) == 5 else 1


def run_layout(r: dict[str, Any]) -> int:
    """The scenario layout a record ran on: a record of format 1 or 2 carries none, and
    ran on layout 1 (common/scenarios/builtin)."""
    return int(r.get("layout", 1))


def run_scenario(cfg: Config, r: dict[str, Any],
                 cache: dict[tuple[str, int, int], Any]) -> Any:
    """The scenario a record ran in (its name, scenario seed and `run_layout`), built once
    per key into `cache`."""
    key = (r["scenario"], int(r.get("scenario_seed", cfg.episode.scenario_seed)), run_layout(r))
    if key not in cache:
        cache[key] = build_scenario(key[0], key[1], cfg.mapper.resolution_m, layout=key[2])
    return cache[key]


def run_record(cfg: Config, result) -> dict[str, Any]:
    """One run's record (format RECORD_FORMAT): the summary, its 10 Hz path (t, X, Y, V,
    psi) and solve times."""
    traj = result.trajectory                     # rows (t, state): S.V, S.X, S.Y, S.PSI at 1 + S.*
    every = max(1, int(round(cfg.plant.rate_hz * cfg.planner.dt_s)))
    path = traj[::every][:, [0, 1 + S.X, 1 + S.Y, 1 + S.V, 1 + S.PSI]]
    speed = np.hypot(traj[:, 1], traj[:, 2])
    rec = result.summary(cfg)
    scn = build_scenario(cfg.episode.scenario, cfg.episode.scenario_seed, cfg.mapper.resolution_m,
                         cfg.episode.layout)
    rec.update(world=scn.name, kind=scn.kind, scenario_digest=scn.digest)
    rec.update(path=np.round(path, 3).tolist(), max_speed_mps=round(float(speed.max()), 3),
               solve_ms=[round(x, 2) for x in result.solve_ms],
               scenario_seed=cfg.episode.scenario_seed,
               layout=resolve_layout(cfg.episode.scenario, cfg.episode.layout),
               config_digest=config_digest(cfg), format=RECORD_FORMAT)
    if result.collision is not None:
        rec["collision"] = result.collision
    return rec


def read_runs(path: Path) -> list[dict[str, Any]]:
    """Every complete record of a runs.jsonl; torn or malformed lines are skipped."""
    runs: list[dict[str, Any]] = []
    if not path.exists():
        return runs
    bad = 0
    with path.open() as f:
        for line in f:
            try:
                rec = json.loads(line)
                if all(k in rec for k in KEY_FIELDS) and rec.get("outcome") in OUTCOMES:
                    runs.append(rec)
                    continue
            except json.JSONDecodeError:
                pass
            bad += 1
    if bad:
        log.warning("%s: skipped %d incomplete or malformed line(s)", path, bad)
    return runs


def _append(path: Path, rec: dict[str, Any]) -> None:
    # a torn last line (a crash mid-write) must not swallow this record
    if path.exists() and path.stat().st_size:
        with path.open("rb") as f:
            f.seek(-1, os.SEEK_END)
            ends_clean = f.read(1) == b"\n"
        if not ends_clean:
            with path.open("a") as f:
                f.write("\n")
    with path.open("a") as f:
        f.write(json.dumps(rec) + "\n")
        f.flush()
        os.fsync(f.fileno())


def expand_scenarios(items: list[str]) -> list[str]:
    """Scenario names and files, a directory standing for every scenario file in it."""
    out: list[str] = []
    for item in items:
        p = Path(item)
        if p.is_dir():
            found = sorted(str(f) for f in p.glob("*.toml"))
            if not found:
                raise ExperimentError(f"{item}: a directory without scenario files (*.toml)")
            out += found
        else:
            out.append(item)
    return out


def check_scenarios(cfg: Config, scenarios: list[str]) -> None:
    """Build every scenario once before any run, so that a missing or broken file (its
    heightmap too) is one error naming it, not a failure in a worker halfway through."""
    for s in scenarios:
        try:
            build_scenario(s, cfg.episode.scenario_seed, cfg.mapper.resolution_m,
                           layout=cfg.episode.layout)
        except (ScenarioError, OSError) as exc:
            why = str(exc)
            raise ExperimentError(why if why.startswith(s) else f"scenario {s}: {why}") from None


def run_one(cfg: Config, key: tuple, cores_cache: dict[tuple, Cores]) -> tuple[Config, Any]:
    """One run of an experiment, `key` its (scenario, controller, samples, seed): its
    configuration and its episode. The services' cores are kept in `cores_cache` per
    (scenario, controller, samples), at most 8 (the planner keeps 8 compiled solvers,
    mppi.solver)."""
    scenario, controller, k, seed = key
    run_cfg = cfg.replace(**{"episode.scenario": scenario, "planner.controller": controller,
                             "planner.samples": k, "episode.seed": seed})
    if key[:3] not in cores_cache:
        if len(cores_cache) >= 8:
            cores_cache.clear()
        cores_cache[key[:3]] = Cores.from_config(run_cfg)
    return run_cfg, run_episode(run_cfg, cores_cache[key[:3]])


def _records_serial(cfg: Config, todo: list[tuple]) -> Iterator[dict[str, Any]]:
    cores_cache: dict[tuple, Cores] = {}
    for key in todo:
        yield run_record(*run_one(cfg, key, cores_cache))


# a worker process's own state (`_worker_init`): the configuration and its cores cache
_WORKER: dict[str, Any] = {}


def cpu_shares(jobs: int) -> list[list[int]] | None:
    """The CPUs this process may run on, dealt into `jobs` disjoint shares; None where
    there are fewer CPUs than jobs or the platform cannot pin processes."""
    try:
        cpus = sorted(os.sched_getaffinity(0))
    except AttributeError:
        return None
    return [cpus[i::jobs] for i in range(jobs)] if jobs <= len(cpus) else None


def _worker_init(cfg: Config, shares: list[list[int]] | None, counter: Any, jobs: int
                 ) -> None:
    from common import compile_cache
    share_device(jobs)                       # before JAX starts: the workers share a GPU
    # Ctrl-C is the parent's to handle: it stops the workers (`_records_parallel`)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    when_orphaned(lambda: os._exit(1))         # the parent killed outright: nothing to keep
    with counter.get_lock():
        index = counter.value
        counter.value += 1
    if shares:
        # the native kernels' threads (planner.va_threads = 0) and XLA's follow the pinning
        os.sched_setaffinity(0, shares[index % len(shares)])
    compile_cache.enable()
    _WORKER.update(cfg=cfg, cores={})


def _worker_run(key: tuple) -> dict[str, Any]:
    return run_record(*run_one(_WORKER["cfg"], key, _WORKER["cores"]))


def _records_parallel(cfg: Config, todo: list[tuple], jobs: int) -> Iterator[dict[str, Any]]:
    """The records of `todo` as `jobs` worker processes finish them (each takes the next
    run in `todo`'s order). Stopped early (an interrupt, an error), the workers are
    killed: a run not finished has nothing to keep."""
    ctx = multiprocessing.get_context("spawn")       # a fresh JAX runtime per worker
    pool = ctx.Pool(jobs, _worker_init, (cfg, cpu_shares(jobs), ctx.Value("i", 0), jobs))
    try:
        yield from pool.imap_unordered(_worker_run, todo)
    finally:
        pool.terminate()
        pool.join()


# what runs a list of runs elsewhere, e.g. on a cluster: (cfg, todo) -> their records
Runner = Callable[[Config, list[tuple]], Iterator[dict[str, Any]]]


def experiment(cfg: Config, scenarios: list[str], controllers: list[str], samples: list[int],
               runs: int, seed: int, out: Path, progress: bool = True, jobs: int = 1,
               runner: Runner | None = None) -> list[dict[str, Any]]:
    """Run what is missing from `out/runs.jsonl` (in `jobs` worker processes when more
    than 1; by `runner` if given: deploy/sim/cluster.py's on a Ray cluster) and return
    every run there; deploy.analysis.summary writes what they show."""
    check_scenarios(cfg, scenarios)
    out.mkdir(parents=True, exist_ok=True)
    runs_path = out / "runs.jsonl"
    existing = read_runs(runs_path)
    digest = config_digest(cfg)
    other = {r["config_digest"] for r in existing if r.get("config_digest", digest) != digest}
    if other:
        raise ExperimentError(f"{runs_path} holds runs of another configuration (digest "
                              f"{', '.join(sorted(other))}, this one {digest}): resume with the "
                              "same --config/--set, or write to a new --out")
    if any("config_digest" not in r for r in existing):
        log.warning("%s: runs without a config digest (older records) are taken as this "
                    "configuration's", runs_path)
    for r in existing:
        want = resolve_layout(r["scenario"], cfg.episode.layout)
        if run_layout(r) != want:
            raise ExperimentError(
                f"{runs_path} holds {r['scenario']} runs on its layout {run_layout(r)}, this "
                f"experiment would run layout {want}: resume with --set "
                f"episode.layout={run_layout(r)}, or write to a new --out")
    # the configuration beside its runs: `--config DIR/config.toml` resumes it, and
    # `vamppi reveal DIR` reads it
    (out / "config.toml").write_text(config_toml(saved_config(cfg, scenarios)))
    done = {tuple(r[k] for k in KEY_FIELDS) for r in existing}
    # round robin: every combination gets its i-th run before any gets its (i+1)-th,
    # so an experiment stopped early is still balanced
    todo = [(s, c, k, seed + i) for i in range(runs) for s in scenarios for c in controllers
            for k in samples if (s, c, k, seed + i) not in done]
    log.info("%d run(s) to do, %d already in %s", len(todo), len(done), runs_path)
    if runner is not None and todo:
        records = runner(cfg, todo)
    elif jobs <= 1 or len(todo) <= 1:
        records = _records_serial(cfg, todo)
    else:
        records = _records_parallel(cfg, todo, jobs)
    with tqdm(total=len(todo), desc="experiment", unit="run", disable=not progress,
              dynamic_ncols=True) as bar:
        for rec in records:
            _append(runs_path, rec)
            bar.update()
            bar.set_postfix_str(f"{rec['scenario']}/{rec['controller']}/{rec['samples']}: "
                                f"{rec['outcome']}")
    return read_runs(runs_path)


def parse_list(text: str, kind=str) -> list:
    items = [kind(x) for x in text.split(",") if x.strip()]
    if not items:
        raise ValueError(f"empty list: {text!r}")
    return items

