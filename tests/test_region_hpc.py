"""The dask-jobqueue set-ups of docs/guide/region.md ("Where they run") make valid job
scripts: each documented block is run up to its ``scale`` call (nothing is submitted:
there is no batch system here), and its SLURM / PBS script is checked and parsed by
``bash -n``. Skipped, with the reason, where dask-jobqueue is not installed."""

from __future__ import annotations

import ast
import re
import subprocess
from pathlib import Path

import pytest

GUIDE = Path(__file__).resolve().parents[1] / "docs" / "guide" / "region.md"
FENCE = re.compile(r"^```python\n(.*?)^```", re.M | re.S)

pytest.importorskip("dask_jobqueue", reason="dask-jobqueue is not installed (pip install "
                                            "'avflow[hpc]'): its job scripts are not checked")


def _blocks() -> dict[str, str]:
    """The guide's python blocks that build a jobqueue cluster, by class name."""
    out = {}
    for block in FENCE.findall(GUIDE.read_text()):
        m = re.search(r"\b(SLURMCluster|PBSCluster)\(", block)
        if m:
            out[m.group(1)] = block
    return out


def _up_to_scale(code: str) -> str:
    """The block's statements before the first ``.scale(...)``: the cluster, built."""
    tree = ast.parse(code)
    kept = []
    for node in tree.body:
        if any(isinstance(n, ast.Attribute) and n.attr == "scale" for n in ast.walk(node)):
            break
        if isinstance(node, ast.Expr) and "job_script" in ast.unparse(node):
            continue  # the print: read below instead
        kept.append(node)
    return ast.unparse(ast.Module(body=kept, type_ignores=[]))


def test_the_guide_documents_both():
    assert set(_blocks()) == {"SLURMCluster", "PBSCluster"}


@pytest.mark.parametrize("kind, directive", [("SLURMCluster", "#SBATCH"),
                                             ("PBSCluster", "#PBS")])
def test_documented_cluster_makes_a_valid_job_script(kind, directive, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # a scheduler may write its files here
    code = _up_to_scale(_blocks()[kind])
    scope: dict = {}
    exec(compile(code, f"{GUIDE.name}:{kind}", "exec"), scope)  # noqa: S102 - the docs' own
    cluster = scope["cluster"]
    try:
        script = cluster.job_script()
        assert scope["cluster"].scheduler_address.startswith("tcp://")
    finally:
        cluster.close()
    lines = script.splitlines()
    assert lines[0].startswith("#!") and "bash" in lines[0]
    heads = [line for line in lines if line.startswith(directive)]
    assert heads, script
    if kind == "SLURMCluster":
        assert any(re.search(r"--cpus-per-task=1\b|-n 1\b", h) for h in heads), heads
        assert any("--mem=" in h for h in heads) and any("-t 02:00:00" in h for h in heads)
        assert any("-p normal" in h for h in heads)
    else:
        assert any("ncpus=1" in h for h in heads) and any("mem=" in h for h in heads)
        assert any("walltime=02:00:00" in h for h in heads) and any("-q normal" in h
                                                                     for h in heads)
    assert "export NUMBA_NUM_THREADS=1" in script
    assert "export AVFLOW_CACHE_DIR=" in script
    # one worker process a job, one thread, under 4 GB, pointed at this scheduler
    worker = [line for line in lines if not line.startswith("#") and (
        "distributed.cli.dask_worker" in line or "dask worker" in line)]
    assert len(worker) == 1, script
    assert "--nthreads 1" in worker[0]
    assert "--nworkers" not in worker[0] or "--nworkers 1" in worker[0]
    assert re.search(r"--memory-limit (3\.7[0-9]GiB|4\.00GB|4GB|3\.73GiB)", worker[0]), worker
    assert "tcp://" in worker[0]
    path = tmp_path / "job.sh"
    path.write_text(script)
    done = subprocess.run(["bash", "-n", str(path)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
