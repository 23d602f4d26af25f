"""What a registered friction law, map or source costs to compile, the built-in kernels cached.

Each line runs `avflow run` in a fresh process on one kernel cache (a new folder, unless
--cache is given): first the built-in kernels of the scene (their cost is the first line),
then a law, a map, a source, the law and the map together after the law, and each of them
again (a cache load). Prints a table of the seconds the summary line reports as compiling.

    python workflows/extension_compile.py [--kernel grid|profile|faces] [--cache DIR]
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

LAW = '''
from avflow import extend

@extend.friction_law("bench_law", parameters=("mu", "k"), reference="mu + k |u|")
def bench_law(mu, k, h, speed, normal_accel, g):
    return (mu + k * speed) * h * normal_accel, 0.0
'''
MAP = '''
from avflow import extend

@extend.output_map("bench_map", units="m2 s-1", long_name="maximum |h u|")
def bench_map(old, h, hu, hv, speed, t):
    m = h * speed
    return m if m > old else old
'''
SOURCE = '''
from avflow import extend

@extend.source("bench_source", parameters=("rate",), reference="constant snowfall")
def bench_source(rate, h, speed, t):
    return rate
'''
PLANE = """
name: bench-extension
terrain: {kind: plane, slope_deg: 30.0, azimuth_deg: 90.0,
          extent: {x: [0.0, 400.0], y: [0.0, 240.0]}}
rheology: RHEOLOGY
grid: {dx: 20.0}
numerics: {kernel: KERNEL, threads: 1}
release: {kind: cylinder, center: [100.0, 120.0], radius: 50.0, thickness: 8.0}
time: {end: 6.0, cfl: 0.5}
output: {every: 6.0}
SOURCES
"""
PROFILE = """
name: bench-extension
terrain: {kind: profile, length: 600.0, slope: {kind: constant, theta_deg: 30.0}}
rheology: RHEOLOGY
grid: {dx: 10.0}
numerics: {threads: 1}
release: {kind: parabola, center: 150.0, half_length: 60.0, max_thickness: 8.0}
time: {end: 6.0, cfl: 0.5}
output: {every: 6.0}
SOURCES
"""
COULOMB = "{law: coulomb, delta_deg: 20.0}"
REGISTERED = "{law: bench_law, mu: 0.36, k: 0.002}"
SNOW = "sources: [{law: bench_source, rate: 0.001, x: [200.0, 300.0], y: [60.0, 180.0]}]"
SNOW_PROFILE = "sources: [{law: bench_source, rate: 0.001, x: [300.0, 450.0]}]"


def scene(kernel: str, rheology: str, source: bool) -> str:
    text = PROFILE if kernel == "profile" else PLANE.replace("KERNEL", kernel)
    snow = (SNOW_PROFILE if kernel == "profile" else SNOW) if source else ""
    return text.replace("RHEOLOGY", rheology).replace("SOURCES", snow)


def compiling(folder: Path, cache: Path, scene_text: str, files: list[str]) -> float:
    (folder / "s.yaml").write_text(scene_text)
    out = folder / "out.nc"
    out.unlink(missing_ok=True)
    args = [sys.executable, "-m", "avflow", "run", "s.yaml", "-o", str(out)]
    for name in files:
        args += ["--extensions", name]
    env = {**os.environ, "AVFLOW_CACHE_DIR": str(cache)}
    env.pop("AVFLOW_EXTENSIONS", None)
    done = subprocess.run(args, cwd=folder, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        sys.exit(f"avflow run failed: {done.stderr.strip()}")
    found = re.search(r"\(\+ ([0-9.]+) s compiling\)", done.stdout + done.stderr)
    return float(found.group(1)) if found else 0.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kernel", default="grid", choices=("grid", "profile", "faces"))
    parser.add_argument("--cache", type=Path, default=None,
                        help="kernel cache folder (default: a new, empty one)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        cache = args.cache or folder / "cache"
        for name, text in (("law.py", LAW), ("map.py", MAP), ("source.py", SOURCE)):
            (folder / name).write_text(textwrap.dedent(text))
        k = args.kernel
        rows = [
            ("built-in kernels (Coulomb)", scene(k, COULOMB, False), []),
            ("a registered law", scene(k, REGISTERED, False), ["law.py"]),
            ("  again", scene(k, REGISTERED, False), ["law.py"]),
            ("a registered map", scene(k, COULOMB, False), ["map.py"]),
            ("  again", scene(k, COULOMB, False), ["map.py"]),
            ("a registered source", scene(k, COULOMB, True), ["source.py"]),
            ("  again", scene(k, COULOMB, True), ["source.py"]),
            ("the law and the map, after the law", scene(k, REGISTERED, False),
             ["law.py", "map.py"]),
        ]
        print(f"| {k} kernel, order 1, one thread | compiling (s) |")
        print("|---|---:|")
        for label, text, files in rows:
            print(f"| {label} | {compiling(folder, cache, text, files):.1f} |", flush=True)


if __name__ == "__main__":
    main()
