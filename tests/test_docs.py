"""Examples in the docs are what the code prints: checked here, so they cannot drift."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

from deploy.launch.cli import build_parser, config_from_args
from deploy.launch.up import summary_template
from deploy.sim.runner import run_episode

ROOT = Path(__file__).resolve().parents[1]


def _example(text: str, command: str) -> tuple[list[str], dict]:
    """The first ```sh block running `vamppi COMMAND` and the JSON line of the ```json block
    after it."""
    m = re.search(r"```sh\n\.venv/bin/vamppi (" + command + r" [^\n]*)\n```.*?```json\n(.*?)\n```",
                  text, re.S)
    assert m, f"no `vamppi {command}` example with its output"
    return shlex.split(m.group(1)), json.loads(m.group(2))


def test_readme_up_example_is_what_up_prints():
    """The README's `vamppi up` line: the keys `up` prints, and the episode's outcome and
    times as the in-process reference gives them (the bus pipeline in lockstep gives the
    same trajectory bit for bit: test_pipeline)."""
    argv, shown = _example((ROOT / "README.md").read_text(), "up")
    args = build_parser().parse_args(argv)
    cfg = config_from_args(args)
    assert set(shown) == set(summary_template(cfg))
    assert {k: shown[k] for k in ("scenario", "controller", "samples", "seed")} == {
        "scenario": cfg.episode.scenario, "controller": cfg.planner.controller,
        "samples": cfg.planner.samples, "seed": cfg.episode.seed}
    result = run_episode(cfg).summary(cfg)
    assert (shown["outcome"], shown["time_to_goal_s"], shown["sim_time_s"]) == (
        result["outcome"], result["time_to_goal_s"], result["sim_time_s"])
    assert shown["restarts"] == {} and shown["failure"] is None


def test_make_demo_is_the_episode_the_docs_and_bench_view_name():
    """`make demo`'s command, quoted in docs/running.md and run by `vamppi bench view`."""
    from deploy.bench.view import DEMO
    recipe = re.search(r"^demo:.*\n\t\$\(BIN\)/vamppi (up .*)$",
                       (ROOT / "Makefile").read_text(), re.M)
    assert recipe, "no demo recipe"
    assert recipe.group(1) == "up " + " ".join(DEMO)
    assert f"make demo  {' ' * 35}# = vamppi {recipe.group(1)}" in (
        ROOT / "docs" / "running.md").read_text()
