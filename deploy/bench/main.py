"""`vamppi bench WHAT`: speed measured, never asserted (the machines are shared and noisy).
Each benchmark prints a markdown table, or with `--json` its result (the machine that ran it
in `device`, deploy.bench.device): planner and mapper (deploy.bench.kernels); bus, pipeline,
security and record (deploy.bench.bus); peer (deploy.bench.peer, the extra `.[peer]`);
faults (deploy.bench.faults); swaps (deploy.bench.swaps); view (deploy.bench.view);
startup (deploy.bench.startup).
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

from common.config import Config
from deploy.bench import bus, faults, kernels, peer, startup, swaps, view

TABLES = {"planner": kernels.planner_table, "mapper": kernels.mapper_table,
          "bus": bus.bus_table, "pipeline": bus.pipeline_table,
          "security": bus.security_table, "record": bus.record_table,
          "faults": faults.faults_table, "swaps": swaps.swaps_table,
          "peer": peer.peer_table, "view": view.view_table,
          "startup": startup.startup_table}


def table(result: dict[str, Any]) -> str:
    """A markdown table of any benchmark's result."""
    kind = result["benchmark"]
    return TABLES[kind](result)


def main(cfg: Config, what: str, samples: list[int], controllers: list[str], reps: int,
         as_json: bool, overrides: list[str] = (), duration_s: float = 30.0,
         config_path: str | None = None, record: str | None = None,
         forms: list[str] | None = None) -> int:
    if what == "pipeline":
        result = bus.bench_pipeline(cfg, list(overrides), samples, controllers, duration_s,
                                config_path, record)
    elif what == "security":
        result = bus.bench_security(cfg, list(overrides), duration_s, reps, config_path)
    elif what == "record":
        result = bus.bench_record(cfg, duration_s, [1.0, 0.0])
    elif what == "peer":
        result = peer.bench_peer(cfg, samples, reps)
    elif what == "planner":
        result = kernels.bench_planner(cfg, samples, controllers, reps, forms)
    elif what == "mapper":
        result = kernels.bench_mapper(cfg, reps)
    elif what == "bus":
        result = bus.bench_bus(cfg, reps)
    elif what == "faults":
        with tempfile.TemporaryDirectory(prefix="vamppi-faults-") as tmp:
            result = faults.bench_faults(cfg, Path(tmp))
    elif what == "swaps":
        with tempfile.TemporaryDirectory(prefix="vamppi-swaps-") as tmp:
            result = swaps.bench_swaps(cfg, Path(tmp))
    elif what == "view":
        result = view.bench_view(cfg, reps)
    elif what == "startup":
        result = startup.bench_startup(reps)
    else:
        raise ValueError(f"unknown benchmark {what!r}")
    print(json.dumps(result) if as_json else table(result), flush=True)
    return 0
