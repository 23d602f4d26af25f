"""Nothing lost, nothing invented: outputs never replace an input or a file that belongs to
one (a DEM's .prj, an extension file), a full disk is one line and leaves nothing, every
number a command takes is checked, and results the data cannot give are refused.

Hand-made DEMs (a slope of three planes, as in test_release_areas) keep each case quick.
"""

from __future__ import annotations

import math
import os
import resource
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from avflow.cli import main

ROOT = Path(__file__).resolve().parents[1]
DX = 5.0


def one_line(err: str) -> str:
    assert "Traceback" not in err, err
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert len(lines) == 1, err
    return lines[0]


def cli(argv, capsys):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def child(*argv, cwd=None, limit=None, env=None, timeout=300):
    """``python -m avflow ARGS`` in a child; ``limit``: files larger than that many bytes
    cannot be written (EFBIG, as on a full disk)."""
    pre = (lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))) if limit else None
    full_env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT),
                                                            os.environ.get("PYTHONPATH", "")])}
    full_env.pop("AVFLOW_EXTENSIONS", None)
    full_env.update(env or {})
    return subprocess.run([sys.executable, "-m", "avflow", *map(str, argv)], cwd=cwd,
                          env=full_env, capture_output=True, text=True, timeout=timeout,
                          preexec_fn=pre)


def steps_dem(folder: Path, name: str = "d3.asc", crs: str | None = "EPSG:2056") -> Path:
    """Three planes (20, 40, 65 degrees) falling east, 600 x 300 m at 5 m; an ASCII grid
    has its CRS in a .prj beside it."""
    import rasterio
    from rasterio.transform import from_origin

    x = np.arange(DX / 2, 600.0, DX)
    y = np.arange(DX / 2, 300.0, DX)
    t = [math.tan(math.radians(a)) for a in (20.0, 40.0, 65.0)]
    drop = np.where(x < 200, t[0] * x, np.where(x < 400, t[0] * 200 + t[1] * (x - 200),
                                                t[0] * 200 + t[1] * 200 + t[2] * (x - 400)))
    z = 3000.0 - np.tile(drop, (y.size, 1))
    path = folder / name
    driver = "AAIGrid" if name.endswith(".asc") else "GTiff"
    with rasterio.open(path, "w", driver=driver, width=x.size, height=y.size, count=1,
                       dtype="float64", crs=crs, transform=from_origin(0, 300, DX, DX)) as ds:
        ds.write(z[::-1], 1)
    return path


def digests(folder: Path) -> dict:
    import hashlib

    return {p.name: (p.stat().st_ino, hashlib.sha256(p.read_bytes()).hexdigest())
            for p in sorted(folder.iterdir()) if p.is_file()}


# --- 1. no output replaces an input, nor a file that belongs to one --------------------------


def test_a_shapefile_never_replaces_the_dems_projection(tmp_path, capsys):
    dem = steps_dem(tmp_path)
    assert (tmp_path / "d3.prj").exists()
    before = digests(tmp_path)
    code, out, err = cli(["release-areas", dem, "-o", tmp_path / "d3.shp"], capsys)
    assert code == 2 and "wrote" not in out
    line = one_line(err)
    assert "d3.prj" in line and "input" in line
    assert digests(tmp_path) == before  # the .prj is the DEM's own, same file, same bytes


def test_an_extension_file_is_an_input(tmp_path):
    (tmp_path / "law.py").write_text("from avflow import extend\n")
    (tmp_path / "s.yaml").write_text((ROOT / "scenarios" / "seed_dambreak_flat_dx20.yaml")
                                     .read_text())
    before = (tmp_path / "law.py").read_text()
    done = child("run", "--extensions", "law.py", "s.yaml", "-o", "law.py", cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert "law.py" in one_line(done.stderr) and "input" in done.stderr
    done = child("run", "s.yaml", "-o", "law.py", cwd=tmp_path,
                 env={"AVFLOW_EXTENSIONS": str(tmp_path / "law.py")})
    assert done.returncode == 2 and "input" in one_line(done.stderr)
    assert (tmp_path / "law.py").read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["law.py", "s.yaml"]


@pytest.mark.parametrize("target", ["X.shp", "X.gpkg"])
def test_release_areas_on_a_full_disk_is_one_line_and_leaves_nothing(tmp_path, target):
    dem = steps_dem(tmp_path)
    out = tmp_path / "out"
    done = child("release-areas", dem, "-o", out / target, limit=100)
    assert done.returncode == 1, done.stderr
    line = one_line(done.stderr)
    assert f"cannot write {out / target}" in line and len(line) < 300
    assert "wrote" not in done.stdout
    assert not out.exists() or list(out.iterdir()) == []


def test_a_full_disk_keeps_the_previous_shapefile_whole(tmp_path):
    dem = steps_dem(tmp_path)
    target = tmp_path / "out" / "X.shp"
    assert child("release-areas", dem, "-o", target).returncode == 0
    before = digests(target.parent)
    assert set(before) == {"X.shp", "X.shx", "X.dbf", "X.prj", "X.cpg"}
    done = child("release-areas", dem, "--slope-min", "35", "-o", target, limit=100)
    assert done.returncode == 1 and "cannot write" in one_line(done.stderr)
    assert digests(target.parent) == before


@pytest.mark.parametrize("kind", ["device", "fifo", "huge"])
def test_an_extension_file_that_is_no_file_is_refused_at_once(tmp_path, kind):
    if kind == "device":
        path = Path("/dev/zero")
    elif kind == "fifo":
        path = tmp_path / "law.py"
        os.mkfifo(path)
    else:
        path = tmp_path / "law.py"
        with open(path, "wb") as f:
            f.truncate(64 << 20)  # sparse: nothing written
    done = child("run", "--extensions", path, "nothere.yaml", timeout=60)
    assert done.returncode == 2
    assert str(path) in one_line(done.stderr)
