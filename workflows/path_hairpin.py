"""Runout along the path on a hairpin valley: where the farthest cell misleads.

A DEM is built around an analytic thalweg (an arm east, a half circle of radius 200 m, an
arm west; slope 32 deg, 18 deg in the bend, 4 deg after), a Coulomb 20 deg avalanche runs
down it, and ``avflow path`` measures its runout along the thalweg (a CSV line) and along
its own centre-of-mass track. Writes OUT/hairpin.nc, OUT/hairpin_path.* (table, profiles,
AIMEC figure) and OUT/hairpin_com_path.*; tests/test_path.py uses the same valley.

    .venv/bin/python workflows/path_hairpin.py -o out/hairpin
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

R, ARM = 200.0, 300.0  # the hairpin: bend radius, length of the upper arm (m)

SCENARIO = """\
name: hairpin
terrain: {{kind: dem, path: valley.asc}}
grid: {{dx: 10.0}}
release: {{kind: cylinder, center: [-290.0, -200.0], radius: 40.0, thickness: 8.0}}
rheology: {{law: coulomb, delta_deg: 20.0}}
time: {{end: {end}, cfl: 0.5}}
output: {{every: 5.0, path: {{line: thalweg.csv}}}}
"""


def hairpin_sl(x, y):
    """Analytic (s, l) of the thalweg: an arm east along y = -R from x = -ARM, a half circle
    around the origin, an arm west along y = +R; l > 0 on the left (inside the bend)."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    s, l = np.empty_like(x), np.empty_like(x)
    a, b, c = (x <= 0) & (y < 0), (x <= 0) & (y >= 0), x > 0
    s[a], l[a] = x[a] + ARM, y[a] + R
    s[c] = ARM + R * (np.arctan2(y[c], x[c]) + np.pi / 2)
    l[c] = R - np.hypot(x[c], y[c])
    s[b], l[b] = ARM + np.pi * R - x[b], R - y[b]
    return s, l


def write_case(folder, end: float = 70.0, dx: float = 10.0) -> Path:
    """valley.asc (z = thalweg(s) + 0.015 l^2), thalweg.csv (37 vertices on the half
    circle) and hairpin.yaml in ``folder``; returns the scenario file."""
    from scipy.ndimage import uniform_filter1d

    from avflow.terrain.raster import write_asc

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    sg = np.arange(-400.0, 3000.0)
    beta = np.where(sg < ARM, 32.0, np.where(sg < ARM + np.pi * R, 18.0, 4.0))
    zt = 1000.0 - np.cumsum(np.tan(np.radians(uniform_filter1d(beta, 60))))
    x = np.arange(-ARM - 80 + dx / 2, R + 180, dx)
    y = np.arange(-R - 150 + dx / 2, R + 180, dx)
    X, Y = np.meshgrid(x, y)
    s, l = hairpin_sl(X, Y)
    write_asc(folder / "valley.asc", np.interp(s, sg, zt) + 0.015 * l**2, x, y)
    phi = np.linspace(-np.pi / 2, np.pi / 2, 37)
    thalweg = [(-ARM, -R)] + [(R * np.cos(p), R * np.sin(p)) for p in phi] + [(-ARM, R)]
    (folder / "thalweg.csv").write_text("x,y\n" + "".join(f"{a:.4f},{b:.4f}\n"
                                                          for a, b in thalweg))
    scenario = folder / "hairpin.yaml"
    scenario.write_text(SCENARIO.format(end=end))
    return scenario


def main() -> None:
    from avflow.cli import main as avflow

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("-o", "--output", default="out/hairpin", help="output folder")
    args = p.parse_args()
    scenario = write_case(args.output)
    out = Path(args.output) / "hairpin.nc"
    assert avflow(["run", str(scenario), "-o", str(out)]) == 0  # + hairpin_path.*
    assert avflow(["path", str(out), "--line", "com", "-o",
                   str(out.with_name("hairpin_com_path"))]) == 0


if __name__ == "__main__":
    main()
