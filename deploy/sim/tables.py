"""The tables of record (docs/results.md): each one's grid of runs and configuration, in one
place, and whether its committed records are what today's program would run.

A table is an experiment (deploy/sim/experiment.py): scenarios x controllers x one sample
count x planner seeds `seed .. seed + runs - 1`, under the defaults with a preset and
`--set` overrides on top. `vamppi tables` says of each whether its directory under
docs/results holds that whole grid under the configuration the entry gives today
(`current`), runs of another configuration (`stale`: a default changed since it was made),
part of it, or nothing; `vamppi tables --run` makes the named, stale or all tables again
into another root, resumably, on `--jobs` processes or a Ray cluster, so that a change of
a default can be carried into every table and the docs' tables copied over in one step.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from common.config import Config, load_config, preset_overrides
from common.scenarios import resolve_layout
from deploy.sim.experiment import (
    KEY_FIELDS,
    Runner,
    config_digest,
    expand_scenarios,
    experiment,
    run_layout,
)

RESULTS_DIR = Path(__file__).resolve().parents[2] / "docs" / "results"
CONTROLLERS = ("va", "deterministic", "prescient")
HELDOUT = "common/scenarios/benchmark/heldout"
TUNE = "common/scenarios/benchmark/tune"
FRESH = "common/scenarios/fresh"
# the paper's method as its tables run it: the expectation of Eq. occupied in closed form,
# not by 1000 Monte-Carlo draws (the same expectation without the sampling noise, 8.5 s a
# K = 400 solve otherwise; docs/results.md "The paper's method on the held-out half")
PAPER = ("planner.surface_estimator=\"closed_form\"",)
# records made by an older program with the same arithmetic, and the digest today's
# program gives their configuration (docs/results.md "Reproducing")
SAME_ARITHMETIC = {"01a921557eea04ef": "781abd64bdcb87a0"}


@dataclass(frozen=True)
class Table:
    """One table of record: its directory's name and the experiment that makes it."""
    name: str
    scenarios: tuple[str, ...]
    samples: int
    runs: int
    seed: int = 0
    controllers: tuple[str, ...] = CONTROLLERS
    preset: str | None = None
    sets: tuple[str, ...] = ()

    def config(self) -> Config:
        """The defaults, the preset's parameters, then the overrides."""
        return load_config(overrides=[*(preset_overrides(self.preset) if self.preset else []),
                                      *self.sets])

    def keys(self) -> set[tuple[str, str, int, int]]:
        """Every run's (scenario, controller, samples, seed)."""
        return {(s, c, self.samples, self.seed + i) for s in expand_scenarios(
            list(self.scenarios)) for c in self.controllers for i in range(self.runs)}

    def command(self) -> str:
        """The `vamppi experiment` command that makes it into DIR."""
        words = ["vamppi experiment", f"--scenario {','.join(self.scenarios)}"]
        if self.controllers != CONTROLLERS:
            words.append(f"--controllers {','.join(self.controllers)}")
        words += [f"--samples {self.samples}", f"--runs {self.runs}"]
        if self.seed:
            words.append(f"--seed {self.seed}")
        if self.preset:
            words.append(f"--preset {self.preset}")
        words += [f"--set '{s}'" for s in self.sets]
        return " ".join([*words, "--jobs 2 --no-plots --out DIR"])


def _grid(prefix: str, scenarios: tuple[str, ...], runs: dict[int, int], **kw: Any
          ) -> list[Table]:
    """Ours and the paper's method at each sample count: `runs` {K: ours, ...}; the
    paper's method, where `kw` has no `paper_runs`, as many."""
    paper_runs = kw.pop("paper_runs", runs)
    return ([Table(f"{prefix}-{k}", scenarios, k, n, **kw) for k, n in runs.items()]
            + [Table(f"{prefix}-{k}-paper", scenarios, k, paper_runs[k], preset="paper",
                     sets=(*kw.get("sets", ()), *PAPER)) for k in paper_runs])


TABLES: tuple[Table, ...] = (
    *_grid("benchmark-heldout", (HELDOUT,), {400: 3, 1000: 3, 4000: 1}),
    Table("benchmark-tune-400", (TUNE,), 400, 3),
    Table("fresh-draw-400", (FRESH,), 400, 3),
    Table("fresh-draw-1000", (FRESH,), 1000, 3),
    *_grid("builtin", ("alleyway", "offroad"), {400: 20, 1000: 20, 4000: 10},
           paper_runs={400: 10, 1000: 10, 4000: 10}),
    *_grid("offroad-layout1", ("offroad",), {400: 20, 1000: 20, 4000: 10},
           paper_runs={400: 10, 1000: 10, 4000: 10}, sets=("episode.layout=1",)),
    *(Table(f"forms-alleyway-400-{form}", ("alleyway",), 400, 20, controllers=("va",),
            sets=(f"planner.va_kernel=\"{form}\"", f"planner.rollout_kernel=\"{form}\""))
      for form in ("native", "jax")),
)
BY_NAME = {t.name: t for t in TABLES}


@dataclass(frozen=True)
class TableState:
    """What a table's directory holds against its entry."""
    table: Table
    digest: str                 # the digest today's program gives the entry's configuration
    want: int                   # runs in the entry's grid
    found: int                  # records of the entry's grid
    digests: tuple[str, ...]    # the records' digests
    extra: int                  # records outside the grid
    wrong_layout: int           # records of the grid on another layout than the entry's
    wall_h: float               # the grid's records' wall time, summed: hours of one worker

    @property
    def state(self) -> str:
        """current | stale | incomplete | missing | mixed"""
        if not self.found:
            return "missing"
        same = {SAME_ARITHMETIC.get(d, d) for d in self.digests}
        if same != {self.digest}:
            return "stale" if self.digest not in same else "mixed"
        if self.wrong_layout or self.extra:
            return "mixed"
        return "current" if self.found == self.want else "incomplete"


def table_state(table: Table, records: Iterable[dict[str, Any]]) -> TableState:
    """A table's state from its directory's records (`experiment.read_runs`)."""
    cfg = table.config()
    keys = table.keys()
    found = extra = wrong = 0
    wall = 0.0
    digests = set()
    for r in records:
        key = tuple(r[k] for k in KEY_FIELDS)
        if key not in keys:
            extra += 1
            continue
        found += 1
        wall += float(r.get("wall_time_s") or 0.0)
        digests.add(r.get("config_digest", "none"))
        wrong += run_layout(r) != resolve_layout(r["scenario"], cfg.episode.layout)
    return TableState(table, config_digest(cfg), len(keys), found, tuple(sorted(digests)),
                      extra, wrong, wall / 3600.0)


def make_table(table: Table, root: Path, progress: bool = True, jobs: int = 1,
               runner: Runner | None = None, plots: bool = False) -> list[dict[str, Any]]:
    """Run what `root / table.name` lacks of the table (an experiment: resumable; a
    directory of another configuration is refused) and write its summary there."""
    from deploy.analysis.summary import write_summary
    cfg, out = table.config(), root / table.name
    runs = experiment(cfg, expand_scenarios(list(table.scenarios)), list(table.controllers),
                      [table.samples], table.runs, table.seed, out, progress=progress,
                      jobs=jobs, runner=runner)
    write_summary(cfg, runs, out, plots=plots)
    return runs


def select(names: Iterable[str]) -> list[Table]:
    """The named tables, in the manifest's order; an unknown name is a ValueError."""
    names = list(names)
    unknown = [n for n in names if n not in BY_NAME]
    if unknown:
        raise ValueError(f"unknown table(s) {', '.join(unknown)}; `vamppi tables` lists them")
    return [t for t in TABLES if t.name in names] if names else list(TABLES)


def status_markdown(states: list[TableState]) -> str:
    lines = ["| table | runs | records' digest | today's digest | state | worker-hours |",
             "|---|---|---|---|---|---|"]
    for s in states:
        lines.append(f"| {s.table.name} | {s.found} of {s.want} | "
                     f"{', '.join(s.digests) or '-'} | {s.digest} | {s.state} | "
                     f"{s.wall_h:.2f} |")
    return "\n".join(lines) + "\n"
