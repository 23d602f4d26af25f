"""The cuda backend (avflow.numerics.cuda_grid) against the CPU square-grid kernel, under
numba-cuda's simulator: no GPU needed.

The simulator is switched on by ``NUMBA_ENABLE_CUDASIM=1``, read when Numba is first
imported: the cases run in a child process (this file run as a script), so the rest of the
suite keeps its Numba as it is. Each case runs the same solver on ``backend="cpu"`` and
``"cuda"`` on about 12 x 10 cells for a few steps, at order 1 and at order 2 (Heun's two
stages on the reconstructed sides). The simulator runs the kernels' Python
with Python floats, so the fields agree bit for bit (on a GPU, to round-off: NVVM fuses
multiply-adds); the grid-wide sums are added in another order (round-off).
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
FIELDS = ("h", "hu", "hv", "flag", "peak_h", "peak_speed", "arrival", "last_moved")
SUMS = ("moving", "film", "kinetic", "outflow")

pytestmark = pytest.mark.skipif(importlib.util.find_spec("numba_cuda") is None,
                                reason="numba-cuda is not installed (pip install "
                                "'avflow[cuda]'); the cuda backend's tests need its simulator")


def _child_env(simulate: bool) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(HERE)]
                                                      + sys.path))
    if simulate:
        env["NUMBA_ENABLE_CUDASIM"] = "1"
    else:
        env.pop("NUMBA_ENABLE_CUDASIM", None)
    return env


@pytest.fixture(scope="module")
def cases():
    """Every case's report (run once, in one child process under the simulator)."""
    done = subprocess.run([sys.executable, __file__], capture_output=True, text=True,
                          env=_child_env(True), timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def _assert_same(report):
    assert report["status_cpu"] == report["status_cuda"]
    assert report["steps_cpu"] == report["steps_cuda"] > 0
    assert report["t_cpu"] == report["t_cuda"]
    assert report["rel_h"] <= 1e-10  # where h is above the dry threshold
    for name in FIELDS:
        assert report["equal"][name], name  # the simulator: bit for bit
    for name in SUMS:
        a, b = report["sums_cpu"][name], report["sums_cuda"][name]
        assert b == pytest.approx(a, rel=1e-12, abs=1e-9), name


def test_plane_with_an_open_side_gives_the_cpu_answer(cases):
    report = cases["plane"]
    _assert_same(report)
    assert report["moved"]


def test_bumpy_dem_with_a_hole_gives_the_cpu_answer(cases):
    """Bed-linked frames, curvature, a NODATA hole, an open lower side, Voellmy friction."""
    report = cases["dem"]
    _assert_same(report)
    assert report["moved"]


def test_friction_map_per_cell_gives_the_cpu_answer(cases):
    _assert_same(cases["per_cell"])


def test_pile_at_rest_stays_at_rest_bit_for_bit(cases):
    report = cases["rest"]
    assert report["at_rest"] and report["steps_cuda"] > 0


def test_a_step_redone_writes_no_map(cases):
    """A step whose first attempts empty a cell (its CFL limit set far above its own) and
    are redone with half the step: the running maps are those of the accepted state, as
    on the CPU kernel, the retries the same."""
    report = cases["retry"]
    _assert_same(report)
    assert report["retries_cpu"] == report["retries_cuda"] > 0


def test_state_stays_on_the_device_between_calls(cases):
    """A second call on the same state uploads nothing (the device holds it)."""
    assert cases["plane"]["uploads"] == 1


def test_entrainment_gives_the_cpu_answer(cases):
    """AvaFrame's erosion energy over an erodible layer: the source hook (the CPU kernels'
    own gain per cell) after each accepted step; the layer left, bit for bit."""
    report = cases["entrainment"]
    _assert_same(report)
    assert report["equal_erodible"] and report["entrained_cpu"] > 0.0
    assert report["entrained_cuda"] == pytest.approx(report["entrained_cpu"], rel=1e-12)


def _assert_order2(report):
    """Order 2: the CPU kernel's fields bit for bit, its steps, retries and fallbacks to
    q = 0 (eq. 56) the same; mass to round-off, h >= 0."""
    _assert_same(report)
    assert report["fallbacks_cpu"] == report["fallbacks_cuda"]
    assert report["h_min"] >= 0.0
    assert report["mass_cuda"] == pytest.approx(report["mass_start"], rel=1e-12)


def test_order2_plane_gives_the_cpu_answer(cases):
    """Heun's two stages on the reconstructed sides, an open side, Coulomb friction; some
    cells fall back to q = 0 at the merge."""
    report = cases["plane2"]
    _assert_order2(report)
    assert report["moved"] and report["fallbacks_cpu"] > 0


def test_order2_bumpy_dem_with_a_hole_gives_the_cpu_answer(cases):
    """Order 2 with bed-linked frames (the reconstruction turns velocities across faces),
    curvature, a NODATA hole, an open lower side, Voellmy friction."""
    report = cases["dem2"]
    _assert_order2(report)
    assert report["moved"]


def test_order2_step_redone_gives_the_cpu_answer(cases):
    """Order 2 with first attempts that empty a cell (a stage fails): the same retries, the
    same fields."""
    report = cases["retry2"]
    _assert_order2(report)
    assert report["retries_cpu"] == report["retries_cuda"] > 0


def test_order2_pile_at_rest_stays_at_rest_bit_for_bit(cases):
    report = cases["rest2"]
    assert report["at_rest"] and report["steps_cuda"] > 0


def test_order2_entrainment_gives_the_cpu_answer(cases):
    report = cases["entrainment2"]
    _assert_same(report)
    assert report["equal_erodible"] and report["entrained_cpu"] > 0.0


@pytest.mark.parametrize("case,words", [
    ("profile", "the mesh is not a square grid"),
])
def test_what_it_does_not_serve_is_refused_in_one_line(cases, case, words):
    message = cases["refused"][case]
    assert words in message and "\n" not in message
    assert "available: grid (square grids" in message


def test_cli_refuses_a_profile_on_cuda_with_exit_2(tmp_path):
    scenario = tmp_path / "profile.yaml"
    scenario.write_text(textwrap.dedent("""\
        name: profile
        terrain:
          kind: profile
          length: 200.0
          slope: {kind: constant, theta_deg: 30.0}
        grid: {dx: 10.0}
        release: {kind: dam, position: 60.0, thickness: 2.0}
        rheology: {law: coulomb, delta_deg: 20.0}
        time: {end: 5.0}
        output: {every: 5.0}
        """))
    done = subprocess.run([sys.executable, "-m", "avflow", "run", str(scenario), "--backend",
                           "cuda", "-o", str(tmp_path / "out.nc")], capture_output=True,
                          text=True, env=_child_env(True), timeout=300)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "numerics.backend" in lines[0], done.stderr
    assert "not a square grid" in lines[0]


def test_missing_numba_cuda_or_gpu_is_one_line(tmp_path):
    """Without numba-cuda (Numba's built-in numba.cuda present or not), with Numba's
    built-in target in its place, and (on this machine) without a GPU: one line each, no
    traceback."""
    code = textwrap.dedent("""\
        import sys, types
        if sys.argv[1] == "missing":
            sys.modules["numba.cuda"] = None
            sys.modules["numba_cuda"] = None
        if sys.argv[1] == "builtin_only":  # Numba's own numba.cuda, no numba-cuda
            sys.modules["numba_cuda"] = None
        if sys.argv[1] == "builtin":  # numba.cuda not redirected to numba-cuda
            import numba
            fake = types.ModuleType("numba.cuda")
            fake.implementation, fake.__file__ = "Built-in", "numba/cuda/__init__.py"
            sys.modules["numba.cuda"] = numba.cuda = fake
        from avflow.numerics.cuda_grid import unavailable
        print(unavailable())
        """)
    for case, words in (("missing", "numba-cuda is not installed"),
                        ("builtin_only", "numba-cuda is not installed"),
                        ("builtin", "Numba's built-in CUDA target, not numba-cuda's")):
        done = subprocess.run([sys.executable, "-c", code, case], capture_output=True,
                              text=True, env=_child_env(False), timeout=120)
        assert done.returncode == 0, done.stderr
        assert words in done.stdout and len(done.stdout.strip().splitlines()) == 1, case
    real = subprocess.run([sys.executable, "-c", code, "real"], capture_output=True,
                          text=True, env=_child_env(False), timeout=120)
    assert real.returncode == 0, real.stderr
    if real.stdout.strip() == "None":
        pytest.skip("this machine has a GPU")
    assert len(real.stdout.strip().splitlines()) == 1 and "GPU" in real.stdout


def test_no_deprecation_warning_from_numbas_cuda_target():
    """The backend imports numba-cuda's numba.cuda, not Numba's deprecated built-in target:
    importing it and building its kernels (under the simulator, as on a machine without a
    GPU) warns of nothing about CUDA."""
    code = textwrap.dedent("""\
        import warnings
        warnings.simplefilter("always")
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            from avflow.numerics import cuda_grid
            cuda_grid._build()
            from numba import cuda
        print(cuda.implementation)
        print([f"{w.category.__name__}: {w.message}" for w in seen
               if "cuda" in str(w.message).lower() or "Deprecat" in w.category.__name__])
        """)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=_child_env(True), timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == ["NVIDIA", "[]"], done.stdout


PTX_CHECK = """\
import sys
from types import SimpleNamespace
import numpy as np
from numba import typeof
import numba.cuda.dispatcher as dispatcher
# no driver here: the device functions ask for the GPU's compute capability
dispatcher.get_current_device = lambda: SimpleNamespace(compute_capability=(9, 0))
from numba import cuda
from avflow.numerics import cuda_grid as cg
try:
    k = cg._build()
    nx, ny = 6, 5
    n = nx * ny
    f = lambda *shape: np.zeros(shape)
    u8, i8 = (lambda *shape: np.zeros(shape, np.uint8)), (lambda *shape: np.zeros(shape, np.int8))
    mesh = cg.DeviceMesh(u8(n), i8(ny, nx + 1), f(ny, 4, nx + 1), f(ny, nx + 1), i8(ny + 1, nx),
                         f(ny + 1, 4, nx), f(ny + 1, nx), f(n), f(n), f(n), f(n), f(n), f(n),
                         f(n), f(3, n), f(1, 8), f(ny, 4, nx + 1), f(ny + 1, 4, nx))
    st = cg.DeviceState(f(n), f(n), f(n))
    obs = cg.DeviceObservers(u8(n), f(n), f(n), f(n), f(n))
    t = cg.N_TERMS
    work = cg.DeviceWork(f(8, n), f(5, ny, nx + 1), f(5, ny + 1, nx), u8(n), f(n), f(n),
                         f(t, n), f(t, 1), f(t, 1))
    sc = cg.Scalars(1, 9.81, True, 1e-3, 1e-3)
    sides = f(4, 8, n)
    launches = {"emit": (mesh, st, work.emit, 9.81, 1e-3),
                "faces": (mesh, sides[1], sides[0], sides[3], sides[2], work.xf, work.yf),
                "recon": (mesh, sc, st, sides),
                "trial": (mesh, sc, st, work, 0.1, 0.1, True),
                "final": (mesh, sc, st, st, obs.flag, work, 0.1, 1, f(n), u8(n)),
                "heun": (mesh, sc, st, st, st, u8(n), f(n), u8(n), work.terms),
                "reduce": (work.terms, work.partials, n),
                "source": (mesh, sc, st, f(n), work.terms, (0.0,) * 8,
                           (3, 0.5, 0.0, 5000.0, 0.0, 0.0, 0.0, 1e-3, 9.81), 0.1),
                "observe": (mesh, sc, st, obs, f(0, n), 0.2),
                "supply": (np.zeros(2, np.int64), f(1, 2), f(1, 4), f(n), f(n), f(n), f(n),
                           f(n), f(n), f(n), 9.81, 0.1, 0.2, f(t, 2))}
    fused = {}
    for name, args in launches.items():
        ptx, _ = cuda.compile_ptx(k[name].py_func, tuple(typeof(a) for a in args), cc=(9, 0))
        fused[name] = ptx.count("fma.rn.f64")
except Exception as err:  # no NVVM or NVRTC on this machine
    if type(err).__name__ in ("NvvmSupportError", "DynamicLibNotFoundError", "CudaSupportError"):
        print("SKIP", type(err).__name__)
        sys.exit(0)
    raise
print("OK", fused)
"""


def test_kernels_compile_for_a_gpu():
    """Every kernel typed and compiled to PTX for sm_90 by the real CUDA target (no GPU
    needed, but NVVM and NVRTC: the CUDA toolkit's wheels, ``avflow[cuda]``). Emit, faces,
    order 2's reconstruction and merge, the sums and the running maps fuse no multiply-add
    (the CPU's bits); trial and final only inside libdevice's exp and log (trial, final and
    the source read the friction laws)."""
    done = subprocess.run([sys.executable, "-c", PTX_CHECK], capture_output=True, text=True,
                          env=_child_env(False), timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    if done.stdout.startswith("SKIP"):
        pytest.skip(f"no NVVM / NVRTC here ({done.stdout.split()[1]}): pip install "
                    "'avflow[cuda]'")
    fused = eval(done.stdout.split("OK", 1)[1])
    assert fused["emit"] == fused["faces"] == fused["reduce"] == fused["observe"] == 0
    assert fused["recon"] == fused["heun"] == 0


# --- the child process ----------------------------------------------------------------------

def _compare(terrain, h0, law, params, targets, max_steps, limit_times=None, **kw):
    """The same solver on both backends over ``targets``: a report of their differences.
    ``limit_times``: before the last call, the state's CFL limit is set that many times
    its own (its next step's first attempts then fail and are redone)."""
    import numpy as np

    from avflow.numerics.solver import Solver
    from avflow.numerics.stepping import ST_DT_LIMIT, ST_FALLBACK, ST_OUTFLOW, ST_RETRIES

    states, statuses = [], []
    uploads = []
    if kw.get("order") == 2 and "time_scheme" in Solver.__dataclass_fields__:
        kw["time_scheme"] = "heun"  # the GPU's order 2: the CPU kernel's Heun stages
    for backend in ("cpu", "cuda"):
        solver = Solver(terrain, law, np.asarray(params, dtype=float), kernel="grid",
                        threads=1, backend=backend, **kw)
        state = solver.new_state(h0)
        status = []
        for k, t in enumerate(targets):
            if limit_times is not None and k == len(targets) - 1:
                state.stats[ST_DT_LIMIT] *= limit_times
            status.append(solver.advance(state, t, max_steps=max_steps))
            if backend == "cuda":
                uploads.append(solver._cuda.uploads)
        states.append(state)
        statuses.append(status)
    a, b = states
    h_dry = kw.get("h_dry", 0.0)
    wet = a.h > h_dry
    rel = np.abs(a.h - b.h)[wet] / a.h[wet]
    stats = {"moving": 5, "film": 6, "outflow": 7, "kinetic": 10}
    return {
        "status_cpu": statuses[0], "status_cuda": statuses[1],
        "steps_cpu": a.steps, "steps_cuda": b.steps, "t_cpu": a.t, "t_cuda": b.t,
        "rel_h": float(rel.max()) if rel.size else 0.0,
        "equal": {name: bool(np.array_equal(getattr(a, name), getattr(b, name),
                                            equal_nan=name not in ("flag",)))
                  for name in FIELDS},
        "sums_cpu": {k: float(a.stats[v]) for k, v in stats.items()},
        "sums_cuda": {k: float(b.stats[v]) for k, v in stats.items()},
        "moved": bool(np.any(a.peak_speed > 0.0)),
        "at_rest": bool(np.array_equal(b.h, h0) and not b.hu.any() and not b.hv.any()
                        and np.array_equal(a.h, b.h)),
        "uploads": uploads[-1] if uploads else 0,
        "equal_erodible": bool(np.array_equal(a.erodible, b.erodible)),
        "entrained_cpu": float(a.stats[13]), "entrained_cuda": float(b.stats[13]),
        "retries_cpu": float(a.stats[ST_RETRIES]), "retries_cuda": float(b.stats[ST_RETRIES]),
        "fallbacks_cpu": float(a.stats[ST_FALLBACK]),
        "fallbacks_cuda": float(b.stats[ST_FALLBACK]),
        "mass_start": float(np.sum(h0 * terrain.mesh.cell_area)),
        "mass_cuda": float(np.sum(b.h * terrain.mesh.cell_area) + b.stats[ST_OUTFLOW]
                           - b.stats[13]),
        "h_min": float(b.h.min()),
    }


def _bumpy(nx=12, ny=10, dx=5.0):
    """A tilted valley with a bump and a NODATA hole (test_square_grid's valley, small)."""
    import numpy as np

    x = np.arange(nx) * dx + 2.5
    y = np.arange(ny) * dx + 2.5
    xx, yy = np.meshgrid(x, y)
    z = (100.0 - 0.7 * xx + 0.02 * (yy - y.mean()) ** 2
         + 2.0 * np.exp(-((xx - 35.0) ** 2 + (yy - 25.0) ** 2) / 60.0))
    z[4:6, 7:9] = np.nan
    return z, x, y


def _cases() -> dict:
    from types import SimpleNamespace as NS

    import numpy as np

    from avflow.numerics.physics import SOURCE_EROSION_ENERGY
    from avflow.numerics.registry import KernelUnavailable
    from avflow.numerics.rheology import Law
    from avflow.numerics.solver import Solver
    from avflow.numerics.sources import MassSource
    from avflow.terrain.bed import plane_terrain, surface_terrain

    from conftest import cylinder, slope_profile, walls

    tan20 = math.tan(math.radians(20.0))
    out = {}
    plane = NS(slope_deg=30.0, azimuth_deg=100.0, extent=NS(x=[0.0, 120.0], y=[0.0, 100.0]),
               elevation_at_center=0.0)
    ter = plane_terrain(plane, 10.0, 10.0, walls(x_max="outflow", y_min="outflow"))
    h0 = cylinder(ter, (70.0, 50.0), radius=30.0, thickness=4.0)
    out["plane"] = _compare(ter, h0, Law.COULOMB, (tan20,), (2.0, 6.0), 8, h_zero=1e-3,
                            h_dry=1e-3)
    out["retry"] = _compare(ter, h0, Law.COULOMB, (tan20,), (2.0, 6.0), 4, limit_times=64.0,
                            h_zero=1e-3, h_dry=1e-3)
    out["plane2"] = _compare(ter, h0, Law.COULOMB, (tan20,), (2.0, 6.0), 8, h_zero=1e-3,
                             h_dry=1e-3, order=2)
    out["retry2"] = _compare(ter, h0, Law.COULOMB, (tan20,), (2.0, 6.0), 4, limit_times=64.0,
                             h_zero=1e-3, h_dry=1e-3, order=2)
    z, x, y = _bumpy()
    dem = surface_terrain(z, x, y, walls(x_max="outflow"), nodata="outflow")
    xx, yy = dem.cell_xy()
    h0 = np.where((xx - 15.0) ** 2 + (yy - 25.0) ** 2 < 12.0**2, 3.0, 0.0)
    out["dem"] = _compare(dem, h0, Law.VOELLMY, (0.15, 500.0), (1.0, 4.0), 8, h_zero=1e-3,
                          h_dry=1e-3)
    out["dem2"] = _compare(dem, h0, Law.VOELLMY, (0.15, 500.0), (1.0, 4.0), 8, h_zero=1e-3,
                           h_dry=1e-3, order=2)
    rows = np.tile([tan20, 0.0], (dem.n_cells, 1))
    rows[: dem.n_cells // 2, 0] = math.tan(math.radians(15.0))
    out["per_cell"] = _compare(dem, h0, Law.COULOMB, rows, (3.0,), 5, h_zero=1e-3)
    layer = MassSource(SOURCE_EROSION_ENERGY, np.full(dem.n_cells, 0.5), (5000.0,),
                       density_ratio=0.5)
    out["entrainment"] = _compare(dem, h0, Law.COULOMB, (tan20,), (1.0, 3.0), 6, h_zero=1e-3,
                                  h_dry=1e-3, source=layer)
    out["entrainment2"] = _compare(dem, h0, Law.COULOMB, (tan20,), (1.0, 3.0), 4,
                                   h_zero=1e-3, h_dry=1e-3, source=layer, order=2)
    bowl_x = np.arange(12) * 5.0 + 2.5
    bowl_y = np.arange(10) * 5.0 + 2.5
    bx, by = np.meshgrid(bowl_x, bowl_y)
    bowl = surface_terrain(0.01 * ((bx - 30.0) ** 2 + (by - 25.0) ** 2), bowl_x, bowl_y,
                           walls())
    cx, cy = bowl.cell_xy()
    pile = np.where((cx - 30.0) ** 2 + (cy - 25.0) ** 2 < 15.0**2, 1.0, 0.0)
    out["rest"] = _compare(bowl, pile, Law.COULOMB, (math.tan(math.radians(35.0)),),
                           (30.0,), 4, h_zero=1e-3)
    out["rest2"] = _compare(bowl, pile, Law.COULOMB, (math.tan(math.radians(35.0)),),
                            (30.0,), 4, h_zero=1e-3, order=2)
    refused = {}
    attempts = {
        "profile": lambda: Solver(slope_profile(200.0, 10.0, 30.0), Law.COULOMB,
                                  np.array([tan20]), backend="cuda"),
    }
    for name, attempt in attempts.items():
        try:
            attempt()
            refused[name] = "accepted"
        except KernelUnavailable as err:
            refused[name] = str(err)
    out["refused"] = refused
    return out


if __name__ == "__main__":
    assert os.environ.get("NUMBA_ENABLE_CUDASIM") == "1"
    print(json.dumps(_cases()))
