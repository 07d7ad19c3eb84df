"""Examples in the docs are what the code prints: checked here, so they cannot drift."""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from deploy.launch.cli import build_parser, config_from_args
from deploy.launch.up import summary_template

ROOT = Path(__file__).resolve().parents[1]


def _example(text: str, command: str) -> tuple[list[str], dict]:
    """The first ```sh block running `vamppi COMMAND` and the JSON line of the ```json block
    after it."""
    m = re.search(r"```sh\n\.venv/bin/vamppi (" + command + r" [^\n]*)\n```.*?```json\n(.*?)\n```",
                  text, re.S)
    assert m, f"no `vamppi {command}` example with its output"
    return shlex.split(m.group(1)), json.loads(m.group(2))


@pytest.mark.integration
def test_readme_up_example_is_what_up_prints():
    """The README's `vamppi up` line, run: the keys it prints, the episode's outcome and
    times, no restart, its router on a TLS endpoint it names, exit status 0."""
    argv, shown = _example((ROOT / "README.md").read_text(), "up")
    cfg = config_from_args(build_parser().parse_args(argv))
    assert set(shown) == set(summary_template(cfg))
    r = subprocess.run([sys.executable, "-m", "deploy", *argv], capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert set(got) == set(shown)
    same = ("scenario", "controller", "samples", "seed", "outcome", "time_to_goal_s",
            "sim_time_s", "restarts", "failure")
    assert {k: got[k] for k in same} == {k: shown[k] for k in same}
    assert (got["scenario"], got["controller"], got["samples"], got["seed"]) == (
        cfg.episode.scenario, cfg.planner.controller, cfg.planner.samples, cfg.episode.seed)
    assert got["outcome"] == "success" and got["restarts"] == {} and got["failure"] is None
    assert got["router"].startswith("tls/localhost:") and f"router on {got['router']}" in \
        r.stderr


def test_make_demo_is_the_episode_the_docs_and_bench_view_name():
    """`make demo`'s command, quoted in docs/running.md and run by `vamppi bench view`."""
    from deploy.bench.view import DEMO
    recipe = re.search(r"^demo:.*\n\t\$\(BIN\)/vamppi (up .*)$",
                       (ROOT / "Makefile").read_text(), re.M)
    assert recipe, "no demo recipe"
    assert recipe.group(1) == "up " + " ".join(DEMO)
    assert f"make demo  {' ' * 35}# = vamppi {recipe.group(1)}" in (
        ROOT / "docs" / "running.md").read_text()
