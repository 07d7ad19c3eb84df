"""What ran a benchmark, named in every benchmark's JSON."""

from __future__ import annotations

import platform
from typing import Any

import jax

from common.memory import keep_large_buffers


def device_info() -> dict[str, Any]:
    """What ran the benchmark: CPU model or GPU name, JAX backend and version, and
    whether the allocator keeps large freed buffers (common.memory; set here too)."""
    dev = jax.devices()[0]
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            names = [ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")]
        cpu = f"{names[0]} ({len(names)} logical cores)" if names else cpu
    except OSError:
        pass
    return {"backend": jax.default_backend(), "device": dev.device_kind if dev.platform != "cpu"
            else cpu, "cpu": cpu, "jax": jax.__version__, "malloc_tuned": keep_large_buffers()}


def heading(result: dict[str, Any]) -> str:
    """A benchmark table's first line: what ran it."""
    return f"{result['benchmark']}: {result['device']} ({result['backend']}, jax {result['jax']})"


def markdown_table(title: str, columns: list[str], rows: list[list[Any]]) -> str:
    """`title`, a blank line, then a markdown table of `rows` (each cell as str() gives it)."""
    lines = [title, "", "| " + " | ".join(columns) + " |", "|---" * len(columns) + "|"]
    lines += ["| " + " | ".join(str(x) for x in row) + " |" for row in rows]
    return "\n".join(lines)
