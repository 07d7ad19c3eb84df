"""The suite's own machinery: what `make test` relies on to keep tests apart."""

from __future__ import annotations

import subprocess
import sys
import textwrap


def test_tests_of_one_xdist_group_run_on_one_worker(tmp_path):
    """`make test` runs two pytest-xdist workers with `--dist loadgroup`; the tests that
    make network namespaces on fixed subnets share one `xdist_group` so that they never
    overlap (conftest.py). pytest 9.2 ignores the group suffix pytest-xdist 3.8 gives a
    test's node id, which spread such tests over both workers: pyproject.toml pins a
    pytest that honours it, and this checks it on a throwaway suite."""
    (tmp_path / "test_grouped.py").write_text(textwrap.dedent("""
        import os, time, pytest
        @pytest.mark.parametrize("i", range(4))
        @pytest.mark.xdist_group("apart")
        def test_grouped(i):
            time.sleep(0.2)
            with open("workers.txt", "a") as f:
                f.write(os.environ["PYTEST_XDIST_WORKER"] + "\\n")
        @pytest.mark.parametrize("i", range(4))
        def test_free(i):
            time.sleep(0.2)
    """))
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-n", "2", "--dist",
                        "loadgroup", "-p", "no:cacheprovider", "test_grouped.py"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    workers = (tmp_path / "workers.txt").read_text().split()
    assert len(workers) == 4 and len(set(workers)) == 1, workers
