"""`vamppi bench startup`: how long a service's process takes to import its code, each in a
fresh interpreter, the cases interleaved rep by rep. A restart, a hot swap's new planner
and every process of `vamppi up` pay it before they load their solvers from the
compilation cache (docs/running.md). JAX's import is most of it; `ml_dtypes`, JAX's own
dependency and pinned for its import time (pyproject.toml), is timed alone, after numpy."""

from __future__ import annotations

import importlib.metadata
import statistics
import subprocess
import sys
from typing import Any

from deploy.bench.device import device_info, heading, markdown_table

# case: (what is imported before the clock starts, the module timed)
CASES = {**{s: ("", f"services.{s}.node") for s in ("sensor", "mapper", "planner", "plant")},
         "jax": ("", "jax"), "ml_dtypes": ("import numpy", "ml_dtypes")}
PROBE = ("{pre}\nimport time\nt = time.perf_counter()\nimport {module}\n"
         "print(time.perf_counter() - t)")


class ImportFailed(RuntimeError):
    """A timed import raised: its last line of stderr (`vamppi bench` prints it)."""


def import_s(pre: str, module: str) -> float:
    """Seconds to import `module` in a fresh interpreter, after `pre`."""
    r = subprocess.run([sys.executable, "-c", PROBE.format(pre=pre, module=module)],
                       capture_output=True, text=True, timeout=300)
    if r.returncode != 0:
        last = (r.stderr.strip().splitlines() or [f"exit {r.returncode}"])[-1]
        raise ImportFailed(f"importing {module} failed: {last}")
    return float(r.stdout.strip().splitlines()[-1])


def bench_startup(reps: int) -> dict[str, Any]:
    times: dict[str, list[float]] = {k: [] for k in CASES}
    for _ in range(reps):
        for k, (pre, module) in CASES.items():
            times[k].append(import_s(pre, module))
    cases = [{"case": k, "module": CASES[k][1], "after": CASES[k][0] or None, "reps": reps,
              "median_s": round(statistics.median(v), 3), "min_s": round(min(v), 3),
              "max_s": round(max(v), 3), "seconds": [round(x, 3) for x in v]}
             for k, v in times.items()]
    versions = {p: importlib.metadata.version(p) for p in ("jax", "jaxlib", "ml_dtypes",
                                                           "numpy")}
    return {"benchmark": "startup", **device_info(),
            "settings": {"reps": reps, "python": sys.version.split()[0], "versions": versions},
            "cases": cases}


def startup_table(result: dict[str, Any]) -> str:
    v = result["settings"]["versions"]
    rows = [[c["case"], c["module"] + (f" (after {c['after']})" if c["after"] else ""),
             c["reps"], c["median_s"], c["min_s"], c["max_s"]] for c in result["cases"]]
    return markdown_table(
        f"{heading(result)}; " + ", ".join(f"{p} {x}" for p, x in v.items()),
        ["case", "import", "reps", "median s", "min s", "max s"], rows)
