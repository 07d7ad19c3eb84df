"""`vamppi experiment --cluster ADDRESS`: the experiment's runs as tasks on a Ray cluster.

The same runs as the in-process runner (deploy/sim/experiment.py: `run_one`, `run_record`),
one Ray task each; this process alone writes runs.jsonl, a record as each task returns, so
resuming, the configuration digest and the summaries are the in-process runner's. A run's
record does not depend on where it ran, except its solve and wall times (tested).

- `--cluster local` starts a Ray instance on this machine with `--jobs` CPUs (stopped at
  the end); any other ADDRESS is `ray.init(address=...)`: `auto`, `HOST:6379`, or
  `ray://HOST:10001` (Ray Client).
- Every node must hold the same vamppi (its sources are digested: a worker whose digest
  differs refuses the run), and the scenario files at the same paths (each run's scenario
  digest is checked on the worker; a relative path is taken from the driver's directory
  where the node has one of that name).
- A worker that dies (killed, out of memory, its node lost) costs its run nothing: Ray
  runs the task again on another worker, up to `RETRIES` times; a run whose code raises is
  not retried (it would raise again) and stops the experiment, the finished runs kept.
- Each worker process keeps the services' cores of its last runs (`run_one`'s cache) and
  the JAX compilation cache, as a `--jobs` worker does. On a GPU node the workers share
  the GPU (common.memory.share_device).
"""

from __future__ import annotations

import hashlib
import logging
import os
import socket
from collections.abc import Iterator
from functools import cache
from pathlib import Path
from typing import Any

from common.config import Config
from deploy.sim.experiment import Runner, run_one, run_record

log = logging.getLogger(__name__)

RETRIES = 3             # times a task lost with its worker runs again
SOURCES = ("common", "services", "deploy")


class ClusterError(RuntimeError):
    """The cluster cannot run this experiment (no Ray, unreachable, another vamppi)."""


@cache
def source_digest() -> str:
    """Digest of this vamppi's Python and C++ sources and scenario files: what must be the
    same on every node for a run's record not to depend on where it ran."""
    root = Path(__file__).resolve().parents[2]
    h = hashlib.sha256()
    for top in SOURCES:
        for p in sorted((root / top).rglob("*")):
            if p.suffix in (".py", ".cc", ".h", ".toml") and "__pycache__" not in p.parts:
                h.update(str(p.relative_to(root)).encode())
                h.update(p.read_bytes())
    return h.hexdigest()[:16]


# a worker process's own, kept from task to task: its cores cache (`run_one`) and the
# worlds whose digest it has checked
_CORES: dict[tuple, Any] = {}
_CHECKED: set[str] = set()


def run_task(cfg: Config, key: tuple, digest: str, scenario_digest: str | None,
             cwd: str | None = None) -> dict[str, Any]:
    """One run on a Ray worker: its record (experiment.run_record). In the driver's
    directory `cwd` where the node has it, so that a scenario file named by a relative
    path is the same file."""
    from common.scenarios import build_scenario
    if cwd and os.path.isdir(cwd):
        os.chdir(cwd)
    if digest != source_digest():
        raise ClusterError(f"worker {os.uname().nodename}: its vamppi (sources {source_digest()}"
                           f") is not the driver's ({digest}): install the same commit on "
                           "every node")
    if scenario_digest is not None and scenario_digest not in _CHECKED:
        scn = build_scenario(key[0], cfg.episode.scenario_seed, cfg.mapper.resolution_m,
                             cfg.episode.layout)
        if scn.digest != scenario_digest:
            raise ClusterError(f"worker {os.uname().nodename}: scenario {key[0]} is another "
                               f"world there (digest {scn.digest}, the driver's "
                               f"{scenario_digest})")
        _CHECKED.add(scenario_digest)
    _worker_start()
    return run_record(*run_one(cfg, key, _CORES))


@cache
def _worker_start() -> None:
    """Once per worker process, before its first run: the JAX compilation cache."""
    from common import compile_cache
    compile_cache.enable()


def check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """A HOST:PORT or ray://HOST:PORT address answers on its port: Ray itself retries an
    address that does not for minutes before it gives up."""
    hostport = address.removeprefix("ray://")
    host, sep, port = hostport.rpartition(":")
    if not sep or not port.isdigit():
        return                                   # `auto` and the like: Ray's to resolve
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as exc:
        raise ClusterError(f"no Ray cluster at {address}: {exc}") from exc


def connect(address: str, jobs: int) -> bool:
    """Join the Ray cluster at `address` ("local": start one with `jobs` CPUs); returns
    whether this process started it (and so stops it)."""
    try:
        import ray
    except ImportError as exc:
        raise ClusterError("--cluster needs Ray: pip install -e '.[cluster]'") from exc
    from common.memory import share_device
    if ray.is_initialized():
        return False
    # the workers share a GPU, if their node has one; settings of the user's own win
    env = share_device(jobs, dict(os.environ))
    if address != "local":
        check_reachable(address)
    try:
        if address == "local":
            ray.init(num_cpus=jobs, include_dashboard=False, log_to_driver=False,
                     logging_level=logging.WARNING, runtime_env={"env_vars": env})
            return True
        ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING,
                 runtime_env={"env_vars": env})
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise ClusterError(f"no Ray cluster at {address}: {exc}") from exc
    return False


def records_on_cluster(cfg: Config, todo: list[tuple], address: str, jobs: int
                       ) -> Iterator[dict[str, Any]]:
    """The records of `todo` as the cluster's tasks finish them. Stopped early (an
    interrupt, an error), the tasks not finished are cancelled."""
    import ray
    from ray.exceptions import RayTaskError, WorkerCrashedError

    from common.scenarios import build_scenario
    started = connect(address, jobs)
    try:
        task = ray.remote(num_cpus=1, max_retries=RETRIES, retry_exceptions=False)(run_task)
        cfg_ref, digest = ray.put(cfg), source_digest()
        worlds = {s: build_scenario(s, cfg.episode.scenario_seed, cfg.mapper.resolution_m,
                                    cfg.episode.layout).digest for s in {k[0] for k in todo}}
        pending = {task.remote(cfg_ref, key, digest, worlds[key[0]], os.getcwd()): key
                   for key in todo}
        try:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    key = pending.pop(ref)
                    try:
                        yield ray.get(ref)
                    except RayTaskError as exc:
                        cause = exc.cause if isinstance(exc.cause, Exception) else exc
                        raise ClusterError(f"run {key}: {cause}") from exc
                    except WorkerCrashedError as exc:
                        raise ClusterError(f"run {key}: its worker died {RETRIES + 1} times "
                                           f"({exc})") from exc
        finally:
            for ref in pending:
                ray.cancel(ref, force=True)
    finally:
        if started:
            ray.shutdown()


def on_cluster(address: str, jobs: int) -> Runner:
    """experiment()'s runner for the Ray cluster at `address` (`records_on_cluster`)."""
    return lambda cfg, todo: records_on_cluster(cfg, todo, address, jobs)
