"""`make bench-gpu` (python -m deploy.bench.gpu): the GPU figures of docs/benchmarks.md in
one short run, for the few minutes a GPU machine is lent.

    planner.json   vamppi bench planner --forms jax (K = 400, 800, 1000, 4000)
    mapper.json    vamppi bench mapper
    table/         vamppi experiment: alleyway, VA-MPPI at K = 800, 20 seeds, the defaults
                   (on a GPU `auto` runs the JAX forms), its summary.md
    summary.md     the three tables, under the device that ran them

Each step is a `vamppi` command in its own process (so its JAX runtime starts fresh and
the GPU is shared as every vamppi process shares it: common.memory); a step that fails is
reported and the others still run. `--quick` runs every step small (a few reps, 2 seeds):
the check that the script runs, on the CPU backend where there is no GPU.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path


def steps(out: Path, quick: bool) -> list[tuple[str, list[str], Path | None]]:
    """(name, vamppi arguments, file its stdout goes to) of each step."""
    samples, reps, runs = ("800", "3", "2") if quick else ("400,800,1000,4000", "20", "20")
    return [
        ("planner", ["bench", "planner", "--samples", samples, "--forms", "jax", "--reps", reps,
                     "--json"], out / "planner.json"),
        ("mapper", ["bench", "mapper", "--reps", reps, "--json"], out / "mapper.json"),
        ("table", ["experiment", "--scenario", "alleyway", "--controllers", "va", "--samples",
                   "800", "--runs", runs, "--seed", "0", "--out", str(out / "table"),
                   "--quiet", "--no-plots"], None),
    ]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m deploy.bench.gpu", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="bench-gpu", help="output directory (default bench-gpu)")
    ap.add_argument("--quick", action="store_true", help="every step small: a check")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from deploy.bench.main import table
    # what runs it, from a process of its own: this one never starts JAX on the GPU
    device = subprocess.run([sys.executable, "-c", "import json; from deploy.bench.device "
                             "import device_info; print(json.dumps(device_info()))"],
                            capture_output=True, text=True)
    report = [f"# GPU figures: {device.stdout.strip() or device.stderr[-500:]}"]
    failed: list[str] = []
    for name, cmd, dest in steps(out, args.quick):
        t0 = time.monotonic()
        r = subprocess.run([sys.executable, "-m", "deploy", *cmd], capture_output=True,
                           text=True)
        took = time.monotonic() - t0
        print(f"{name}: exit {r.returncode} after {took:.0f} s", file=sys.stderr, flush=True)
        if r.returncode != 0:
            failed.append(name)
            report.append(f"## {name}: failed (exit {r.returncode})\n\n```\n"
                          f"{r.stderr[-3000:]}\n```")
            continue
        if dest is not None:
            dest.write_text(r.stdout)
            report.append(f"## {name} ({took:.0f} s)\n\n{table(json.loads(r.stdout))}")
        else:
            report.append(f"## {name} ({took:.0f} s)\n\n"
                          f"{(out / 'table' / 'summary.md').read_text()}")
    (out / "summary.md").write_text("\n\n".join(report) + "\n")
    print(f"{out / 'summary.md'}" + (f"; failed: {', '.join(failed)}" if failed else ""),
          flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
