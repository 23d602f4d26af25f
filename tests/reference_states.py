"""Recorded states that the kernels are compared against (issue 27): every traversal, both
orders, the four friction laws, 1 and 2 threads, on small scenes with walls, an open side, a
NODATA hole, curvature and a deposit at rest.

    python tests/reference_states.py      # record tests/data/reference_states.npz anew
    python tests/reference_states.py --missing  # add the cases it lacks, keep the others

Record only from a commit whose answers are the reference (the tests then compare every
later kernel with these states, not one kernel with another). The file notes the machine's
vector width: LLVM's reassociated row sums (``vectorize.line_sum``) add in another order
where it differs, so there the comparison is to round-off instead of bit for bit.
"""

from __future__ import annotations

import math
import platform
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
FILE = HERE / "data" / "reference_states.npz"
FIELDS = ("h", "hu", "hv", "peak_h", "peak_speed", "arrival", "last_moved", "flag", "stats")
#: output times (s) at which the state is recorded: mid-flow and later
TIMES = {"profile": (6.0, 14.0), "grid": (4.0, 9.0), "triangles": (4.0, 9.0)}

PARAMS = {
    "coulomb": ("COULOMB", [math.tan(math.radians(24.0))]),
    "pouliquen": ("POULIQUEN", [math.tan(math.radians(21.0)), math.tan(math.radians(31.0)),
                                0.5, 0.136]),
    "voellmy": ("VOELLMY", [0.3, 1000.0]),
    "samosat": ("SAMOSAT", [0.155, 0.0, 0.222, 0.001 / 200.0, 0.43, 0.05, 4.13]),
}


def cases():
    """``(name, terrain kind, mesh kind, law, order, kernel, threads)`` of every recorded run."""
    out = []
    for law in PARAMS:
        for order in (1, 2):
            out.append((f"profile-{law}-o{order}", "profile", "profile", law, order, "auto", 1))
        out.append((f"grid-{law}-o1", "grid", "grid", law, 1, "auto", 1))
    # the generic face kernel on a profile (order 1 only: order 2 there needs cell centres)
    out.append(("profile-faces-coulomb-o1", "profile", "faces", "coulomb", 1, "faces", 1))
    for order in (1, 2):
        out.append((f"grid-faces-voellmy-o{order}", "grid", "grid", "voellmy", order, "faces", 1))
        out.append((f"triangles-coulomb-o{order}", "triangles", "triangles", "coulomb", order,
                    "auto", 1))
        for kind in ("grid", "triangles"):  # (order 2 on a grid: recorded on the face kernel)
            out.append((f"{kind}-threads-coulomb-o{order}", kind, kind, "coulomb", order,
                        "faces" if order == 2 else "auto", 2))
    # order 2 on the square-grid kernel, 1 and 2 threads: Heun's stages (the face kernel's
    # bits), and MUSCL-Hancock (its default; "hancock" in the name), recorded 2026-12-05
    out.append(("grid-coulomb-o2", "grid", "grid", "coulomb", 2, "grid", 1))
    out.append(("grid-kernel-threads-coulomb-o2", "grid", "grid", "coulomb", 2, "grid", 2))
    for law in PARAMS:
        out.append((f"grid-hancock-{law}-o2", "grid", "grid", law, 2, "grid", 1))
    out.append(("grid-kernel-threads-hancock-o2", "grid", "grid", "coulomb", 2, "grid", 2))
    # MUSCL-Hancock on the face kernel (its default at order 2), triangles on 1 and 2
    # threads and a grid, recorded 2026-12-05 (night)
    out.append(("triangles-hancock-coulomb-o2", "triangles", "triangles", "coulomb", 2, "auto", 1))
    out.append(("triangles-threads-hancock-o2", "triangles", "triangles", "coulomb", 2, "faces",
                2))
    out.append(("grid-faces-hancock-voellmy-o2", "grid", "grid", "voellmy", 2, "faces", 1))
    return out


def _terrain(kind, mesh):
    sys.path.insert(0, str(HERE))
    from conftest import bump_on_a_slope, slope_profile

    if kind == "profile":
        ter = slope_profile(400.0, 2.0, 32.0, x_max="outflow")
        if mesh == "faces":  # the same profile through the generic face kernel
            import dataclasses

            ter = dataclasses.replace(ter, mesh=dataclasses.replace(ter.mesh,
                                                                    structured_1d=False))
        return ter
    return bump_on_a_slope("triangles" if kind == "triangles" else "grid")


def _release(ter, kind):
    if kind == "profile":  # a pile, and a deposit that stays at rest under friction
        x = ter.x
        return np.where((x > 40.0) & (x < 80.0), 6.0, 0.0) + np.where(x > 300.0, 0.2, 0.0)
    xx, yy = ter.cell_xy()
    return np.where((xx - 80.0) ** 2 + (yy - 100.0) ** 2 <= 40.0**2, 5.0, 0.0)


def run(case):
    """The states of one case at its output times: ``{field: [array per time]}``."""
    from avflow.numerics.rheology import Law
    from avflow.numerics.solver import Solver

    name, kind, mesh, law, order, kernel, threads = case
    ter = _terrain(kind, mesh)
    law_name, params = PARAMS[law]
    solver = Solver(ter, Law[law_name], np.array(params), order=order, kernel=kernel,
                    threads=threads, h_dry=1e-3, h_zero=1e-9,
                    time_scheme="hancock" if "hancock" in name else "heun")
    if threads > 1:  # every step on threads, however few its cells (the thresholds' point)
        if solver.kernel_used == "grid":
            solver._parallel_from = (0, 2)
        else:  # as tests/test_face_sweep.py: pieces of a few cells, so that there are two
            from avflow.numerics import face_sweep

            solver._gather_from = 1
            if order == 1:
                m = ter.mesh
                solver._sweep = solver._sweep._replace(work=face_sweep.work(
                    m.n_cells, m.n_faces, 2, min_piece=8, max_pieces=32, face_pieces=8))
    state = solver.new_state(_release(ter, kind))
    out = {f: [] for f in FIELDS}
    for t in TIMES[kind]:
        status = solver.advance(state, t)
        assert status == "running", (name, status)
        for f in FIELDS:
            out[f].append(np.array(getattr(state, f), copy=True))
    return out


def vector_width() -> str:
    """The widest vector unit of this CPU that LLVM uses: what fixes a reassociated sum."""
    try:
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.machine()
    return "avx512" if "avx512f" in flags else ("avx2" if "avx2" in flags else platform.machine())


def record(missing_only: bool = False) -> None:
    """Record every case (``missing_only``: only the cases the file lacks, the others kept
    as recorded; the file's vector width must be this machine's)."""
    data = {"vector_width": np.array(vector_width())}
    if missing_only:
        with np.load(FILE) as old:
            assert str(old["vector_width"]) == vector_width(), "recorded on another CPU"
            data = {k: old[k] for k in old.files}
    for case in cases():
        if missing_only and f"{case[0]}/h/0" in data:
            continue
        states = run(case)
        for f, arrays in states.items():
            for k, a in enumerate(arrays):
                data[f"{case[0]}/{f}/{k}"] = a
        print(case[0], "recorded", flush=True)
    FILE.parent.mkdir(exist_ok=True)
    np.savez_compressed(FILE, **data)
    print(f"{FILE}: {FILE.stat().st_size / 1e3:.0f} kB")


if __name__ == "__main__":
    sys.path.insert(0, str(HERE.parent))
    record(missing_only="--missing" in sys.argv)
