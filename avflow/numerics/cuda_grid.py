"""The square-grid kernel on a CUDA GPU: the CPU square-grid kernel's step at order 1 or 2,
one GPU thread per cell or face, with the whole state resident on the device for the run,
through numba-cuda (NVIDIA's CUDA target for Numba, which ``numba.cuda`` is once it is
installed; Numba's built-in target, deprecated since Numba 0.61, is refused:
:func:`unavailable`).

The physics is not written again here. The pointwise functions of
:mod:`avflow.numerics.kinetic`, :mod:`avflow.numerics.physics` and the friction laws of
:mod:`avflow.numerics.rheology` are compiled with ``numba.cuda.jit(device=True)`` by the
same :func:`avflow.numerics.cpu.compile_pointwise` that compiles them for the CPU; the
square-grid kernel's own per-face and per-cell helpers (its face flux, its order of a
cell's four faces, the per-cell friction parameters, order 2's reconstruction of a row,
``_recon_row``, and the pointwise pieces it is made of) are the same Python functions,
retargeted the same way (:func:`_retarget`). What is written here is only the traversal:
which thread computes which cell or face, and the sums over the grid.

One step is six or seven launches, every cell or face of the grid (no swept region, a
first version): what each cell emits (:func:`_emit`), the flux of every face
(:func:`_faces`), the trial momentum and Coulomb flag of each cell (:func:`_trial`), the
final update with Dirac faces, projection and film rule (:func:`_final`), the grid's sums
in one or two passes of a block reduction (:func:`_reduce`), and once the step is accepted
(and its sources added) the running maps of each cell (:func:`_observe`, the CPU kernels'
observer pass); order 2 adds a launch per stage and one for the merge (below). These
launches are the hooks of a region (:class:`CudaGrid`'s ``_start`` ..
``_end``) run by the CPU kernels' own time loop, :func:`avflow.numerics.loop.advance`,
executed as Python on the host: step size, retry by halving, the sources, the stop rules
and the statistics are one piece of code for every backend. The host reads eight numbers a
step (the sums; three times at order 2); it sees the state only when a call ends (an output time), and the state
stays on the device for the next call.

Compared with the CPU square-grid kernel: thickness, discharge, flags and observers are
the same arithmetic, the grid-wide sums (moving volume, film, kinetic energy, outflow) are
added in another order (a tree per block of threads, then over the blocks: the CPU kernel
adds the swept columns of each row in vector lanes, then the rows), so they differ by
round-off; the simulator (``NUMBA_ENABLE_CUDASIM=1``) gives the CPU kernel's fields bit
for bit. On a GPU
the multiply-adds are not fused (:func:`_no_fused_multiply_add`), so the same should hold
there for Coulomb and Voellmy (libdevice's ``exp`` and ``log`` of the other laws may differ
in the last bit); no GPU has run it yet.

Order 2 is the CPU kernel's order-2 step (square_grid's ``_order2_step``): two stages, each
the launches of an order-1 step with one more, the reconstructed sides of every cell
(:func:`_recon`, the CPU kernel's ``_recon_row`` on the cell's span of its row), which the
faces read instead of the cells' emitted values; stage 1 keeps its flags and each cell's
transport, stage 2 runs from its result; then Heun's merge (:func:`_heun`,
physics.heun_average) of the step's start and stage 2, and its sums. A stage that leaves a
cell below 0 fails the attempt (the loop halves the step), as on the CPU.

Entrainment is the CPU kernels' own source hook (:func:`_source`: numerics.sources' gain
per cell, after each accepted step, before the maps are observed), the registered sources
their pass (:func:`_supply`: numerics.supply's supply_at per cell), and a registered law
or map is built into the device copies as into the CPU kernels (:func:`_build`). Not served (refused
at load time, one line): meshes other than square grids. Cells with no wet cell
around them are computed too (all cells traversal): their update changes nothing, and they
are left out of the CFL limit, as the CPU kernel does by not sweeping them.
"""

from __future__ import annotations

import functools
import inspect
import math
import types
from collections import namedtuple

import numpy as np

from avflow.numerics import kinetic, physics, rheology, stepping
from avflow.numerics.physics import DRY
from avflow.numerics.physics import SOURCE_NONE
from avflow.numerics.sources import SRC_KIND, SRC_PARAMS, SRC_RATIO, SRC_UMIN
from avflow.numerics.stepping import ST_SOURCE, ST_TIME, record_end
from avflow.terrain.squaregrid import HIGH_OPEN, HIGH_WALL, INNER, KIND, LOW_OPEN, NO_FACE

#: Rows of the emitted values of each cell (those of the CPU kernel's ``E_*`` lines)
E_H, E_U1, E_U2, E_C, E_S, E_KH, E_K3, E_SPEED = range(8)
N_EMIT = 8
#: Per-cell terms of the step's sums, then per row, then for the grid
T_INV, T_KIN, T_MOV, T_FILM, T_OUT, T_CLAMPED, T_BAD, T_SOURCE = range(8)
N_TERMS = 8
#: Threads per block of the launches (the simulator runs a Python thread for each, even
#: those past the grid's end: :func:`_build` takes fewer there)
THREADS = 256
SIMULATOR_THREADS = 32
#: Threads per block of the sums (a power of 2), and their first pass's most blocks, whose
#: partial sums one block then adds (the simulator: a block of 8, whose barriers are slow)
RED_THREADS = 256
MAX_PARTIALS = 1024

#: What the kernels read of the grid (device arrays; those of
#: :data:`~avflow.numerics.stepping.GridMesh`, curvature ``(3, places)``; the faces'
#: offsets ``x_off``, ``y_off`` empty at order 1)
DeviceMesh = namedtuple("DeviceMesh", "valid x_code x_frame x_length y_code y_frame y_length "
                        "cell_area inv_area cfl_factor density gamma_x gamma_y gamma_z "
                        "curvature params x_off y_off")
#: One buffer of the conserved variables on the device
DeviceState = namedtuple("DeviceState", "h hu hv")
#: The running observers and the flags, on the device
DeviceObservers = namedtuple("DeviceObservers", "flag peak_h peak_speed arrival last_moved")
#: The work arrays of a step: emitted values, face fluxes, trial flags and momenta, terms
DeviceWork = namedtuple("DeviceWork", "emit xf yf trial_flag qx qy terms partials totals")
#: Order 2's arrays on the device: what each cell emits through each side ``(4, N_EMIT,
#: places)`` (SIDE_W, SIDE_E, SIDE_S, SIDE_N), the first stage's flags, the cells either
#: stage touched, each cell's transport for Heun's merge, the second stage's state
DeviceOrder2 = namedtuple("DeviceOrder2", "sides flag1 touched transport stage2")
#: The scalars of the physics a step reads
Scalars = namedtuple("Scalars", "law g dirac h_dry h_zero")


def unavailable() -> str | None:
    """Why the cuda backend cannot run here (a phrase), or None: numba-cuda missing (Numba's
    built-in ``numba.cuda``, deprecated since Numba 0.61, is not used: with numba-cuda
    installed, ``numba.cuda`` is numba-cuda's), or no GPU (the simulator,
    ``NUMBA_ENABLE_CUDASIM=1``, counts as one)."""
    import importlib.util

    missing = "numba-cuda is not installed (pip install 'avflow[cuda]')"
    try:
        if importlib.util.find_spec("numba_cuda") is None:
            return missing
        from numba import cuda
    except ImportError:
        return missing
    if getattr(cuda, "implementation", None) != "NVIDIA":  # Numba's own, deprecated target:
        # numba-cuda's redirection of numba.cuda did not take (another Numba found first)
        return ("numba.cuda is Numba's built-in CUDA target, not numba-cuda's "
                f"({cuda.__file__}): reinstall numba-cuda beside this Numba")
    try:
        if not cuda.is_available():
            return "no CUDA GPU or driver found (numba.cuda.is_available() is False)"
    except Exception as err:  # a broken driver: one line, not a traceback
        return f"the CUDA driver failed: {str(err).splitlines()[0] if str(err) else err}"
    return None


def _plain_rheology():
    """The friction laws as plain Python, in a module object of their own (rheology's are
    Numba CPU dispatchers): every compiled function of :mod:`~avflow.numerics.rheology` as
    its ``py_func``, every constant and module it reads as it is; a law's new helper comes
    with it, with no list here to keep."""
    plain = types.ModuleType(rheology.__name__)
    for name, value in vars(rheology).items():
        if name.startswith("__"):
            continue
        fn = getattr(value, "py_func", None)
        if fn is not None and fn.__module__ == rheology.__name__:
            setattr(plain, name, fn)
        elif isinstance(value, (int, float, types.ModuleType)):
            setattr(plain, name, value)
    return plain


def _retarget(fn, namespace: dict, decorate):
    """``fn`` (a Python function or a Numba dispatcher's) compiled by ``decorate``, its
    globals those of its module with ``namespace`` over them: the CPU kernel's helpers call
    the device copies of the pointwise functions."""
    py = getattr(fn, "py_func", fn)
    scope = dict(py.__globals__)
    scope.update(namespace)
    copy = types.FunctionType(py.__code__, scope, py.__name__, py.__defaults__, py.__closure__)
    copy.__qualname__, copy.__module__, copy.__doc__ = py.__qualname__, py.__module__, py.__doc__
    return decorate(copy)


# --- the traversal: one thread per cell (or face) ------------------------------------------
# Written against the names below, which :func:`_build` binds to the device copies.

emitted_state = speed_of = trial_momentum = cell_update = observe_cell = observe = None
dirac_face = take_back = outflow_volume = carries = cell_moves = None
step_terms = coded_flux = kind_of = in_face_order = cell_law = cuda = float64 = gain = None


def _emit(mesh, cur, emit, g, h_zero):
    """Per cell, what it emits through its faces at time n and its speed (physics'
    emitted_state and speed_of: the CPU kernel's emitted_cell, the same bits)."""
    i = cuda.grid(1)
    n = cur.h.size
    if i >= n:
        return
    h, q1, q2 = cur.h[i], cur.hu[i], cur.hv[i]
    e0, e1, e2, e3, e4, e5, e6 = emitted_state(h, q1, q2, h_zero, g * mesh.gamma_z[i],
                                               mesh.density[i])
    emit[E_H, i] = e0
    emit[E_U1, i] = e1
    emit[E_U2, i] = e2
    emit[E_C, i] = e3
    emit[E_S, i] = e4
    emit[E_KH, i] = e5
    emit[E_K3, i] = e6
    emit[E_SPEED, i] = speed_of(h, q1, q2)


def _faces(mesh, xa, xb, ya, yb, xf, yf):
    """Per face, its flux ``(fh, qix, qiy, qjx, qjy)``: the CPU kernel's face flux, the owner
    beyond a boundary face (HIGH_*: the east or north cell), zero on a NO_FACE. What the
    face's first cell emits through it is read in ``xa`` (x faces: the west cell) or ``ya``
    (y faces: the south cell), its second cell's in ``xb`` or ``yb`` (rows ``E_*`` of every
    cell): the emitted values of the cells at order 1 (all four the same array), the
    reconstructed sides at order 2 (the west cell's east side, the east cell's west side;
    the south cell's north side, the north cell's south side), as the CPU kernel feeds its
    face rows."""
    k = cuda.grid(1)
    ny, nx1 = mesh.x_code.shape
    nx = nx1 - 1
    n_x = ny * nx1
    if k < n_x:
        r = k // nx1
        c = k - r * nx1
        code = mesh.x_code[r, c]
        frame = mesh.x_frame
        length = mesh.x_length[r, c]
        out = xf
        first = xa
        second = xb
        a = r * nx + c - 1  # the first (west) cell, the second (east) one
        b = r * nx + c
    else:
        k -= n_x
        if k >= (ny + 1) * nx:
            return
        r = k // nx
        c = k - r * nx
        code = mesh.y_code[r, c]
        frame = mesh.y_frame
        length = mesh.y_length[r, c]
        out = yf
        first = ya
        second = yb
        a = (r - 1) * nx + c  # the south cell, the north one
        b = r * nx + c
    kind = code & KIND
    if kind == NO_FACE:
        for m in range(5):
            out[m, r, c] = 0.0
        return
    if kind == INNER:
        f0, f1, f2, f3, f4 = coded_flux(
            kind_of(code), code, first[E_H, a], first[E_U1, a], first[E_U2, a],
            first[E_C, a], first[E_S, a], first[E_KH, a], first[E_K3, a], second[E_H, b],
            second[E_U1, b], second[E_U2, b], second[E_C, b], second[E_S, b],
            second[E_KH, b], second[E_K3, b], frame[r, 0, c], frame[r, 1, c], frame[r, 2, c],
            frame[r, 3, c], length)
    else:
        high = kind >= HIGH_WALL
        o = b if high else a  # the face's owner, and what it emits through the face
        own = second if high else first
        f0, f1, f2, f3, f4 = coded_flux(
            kind_of(code), code, own[E_H, o], own[E_U1, o], own[E_U2, o], own[E_C, o],
            own[E_S, o], own[E_KH, o], own[E_K3, o], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
            frame[r, 0, c], frame[r, 1, c], frame[r, 2, c], frame[r, 3, c],
            length)
    out[0, r, c] = f0
    out[1, r, c] = f1
    out[2, r, c] = f2
    out[3, r, c] = f3
    out[4, r, c] = f4


def _recon(mesh, sc, cur, sides):
    """Order 2, per cell: what it emits through each of its sides from its limited linear
    reconstruction (``sides[SIDE_*, E_*, i]``), by the CPU kernel's own row pass
    (square_grid's _recon_row, on the one cell's span of its row: the same Green-Gauss
    gradients, Barth-Jespersen limiter and emitted states, so the same bits)."""
    i = cuda.grid(1)
    if i >= cur.h.size:
        return
    nx = mesh.x_code.shape[1] - 1
    r = i // nx
    recon_at(r, i - r * nx, nx, mesh, sc, cur, sides[:, :, r * nx:(r + 1) * nx])


def _recon_at(r, c, nx, mesh, sc, cur, out):
    """Cell c of row r through the row pass (its arguments as it takes them)."""
    recon_row(r, c, c, nx, mesh.x_code.shape[0], mesh.x_code[r], mesh.y_code[r],
              mesh.y_code[r + 1], mesh.x_frame[r], mesh.y_frame[r], mesh.y_frame[r + 1],
              mesh.x_length[r], mesh.y_length[r], mesh.y_length[r + 1], mesh.x_off[r],
              mesh.y_off[r], mesh.y_off[r + 1], mesh.cell_area, mesh.density, mesh.gamma_z,
              cur.h, cur.hu, cur.hv, sc.h_zero, sc.g, out)


def _recon_at_predicting(r, c, nx, mesh, sc, cur, out):
    """:func:`_recon_at` for a row pass that can also predict the sides half a step on (the
    CPU kernel's MUSCL-Hancock): Heun's stages predict nothing (a half step of 0)."""
    recon_row(r, c, c, nx, mesh.x_code.shape[0], mesh.x_code[r], mesh.y_code[r],
              mesh.y_code[r + 1], mesh.x_frame[r], mesh.y_frame[r], mesh.y_frame[r + 1],
              mesh.x_length[r], mesh.y_length[r], mesh.y_length[r + 1], mesh.x_off[r],
              mesh.y_off[r], mesh.y_off[r + 1], mesh.cell_area, mesh.density, mesh.gamma_z,
              cur.h, cur.hu, cur.hv, sc.h_zero, sc.g, 0.0, mesh.gamma_x, mesh.gamma_y, sc.law,
              mesh.params, out)


recon_row = recon_at = heun_average = None


def _side_terms(mesh, xf, yf, r, c):
    """A cell's four side terms (mass, x, y), W, E, S, N, as the CPU kernel's: a face brings
    +F_j to its second cell and -F_i to its first."""
    w_in = (mesh.x_code[r, c] & KIND) == INNER
    s_in = (mesh.y_code[r, c] & KIND) == INNER
    return ((xf[0, r, c] if w_in else -xf[0, r, c]), (xf[3, r, c] if w_in else -xf[1, r, c]),
            (xf[4, r, c] if w_in else -xf[2, r, c]),
            -xf[0, r, c + 1], -xf[1, r, c + 1], -xf[2, r, c + 1],
            (yf[0, r, c] if s_in else -yf[0, r, c]), (yf[3, r, c] if s_in else -yf[1, r, c]),
            (yf[4, r, c] if s_in else -yf[2, r, c]),
            -yf[0, r + 1, c], -yf[1, r + 1, c], -yf[2, r + 1, c])


side_terms = None


def _centripetal(mesh, i, u1, u2):
    """u.K.u of cell i (physics.centripetal_accel, from the emitted velocity)."""
    k = mesh.curvature
    return k[0, i] * u1 * u1 + 2.0 * k[1, i] * u1 * u2 + k[2, i] * u2 * u2


centripetal = None


def _trial(mesh, sc, cur, work, dt, dt_decide, explicit):
    """Per cell, the flux divergence, the trial momentum of eq. 47 and the flag of eq. 49
    (physics.trial_momentum); a dry cell keeps its momentum sum for the final update.
    ``explicit``: a stage of order 2 (gravity and friction explicit, as the CPU kernel's
    stages)."""
    i = cuda.grid(1)
    n = cur.h.size
    if i >= n:
        return
    nx = mesh.x_code.shape[1] - 1
    r = i // nx
    c = i - r * nx
    xf, yf, emit = work.xf, work.yf, work.emit
    wm, wx, wy, e_m, ex, ey, sm, sx, sy, nm, nx_, ny_ = side_terms(mesh, xf, yf, r, c)
    mx = in_face_order(0.0, wx, ex, sx, nx_)
    my = in_face_order(0.0, wy, ey, sy, ny_)
    mh = in_face_order(0.0, wm, e_m, sm, nm)
    ia = mesh.inv_area[i]
    u1 = emit[E_U1, i]
    u2 = emit[E_U2, i]
    p = mesh.params
    pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7 = cell_law(
        sc.law, p, i, p[0, 0], p[0, 1], p[0, 2], p[0, 3], p[0, 4], p[0, 5], p[0, 6], p[0, 7])
    h = cur.h[i]
    qx, qy, fi = trial_momentum(h, sc.h_zero, emit[E_SPEED, i], cur.hu[i], cur.hv[i],
                                mh * ia, mx * ia, my * ia, dt, dt_decide, mesh.gamma_x[i],
                                mesh.gamma_y[i], mesh.gamma_z[i], centripetal(mesh, i, u1, u2),
                                sc.law, pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7, sc.g, explicit)
    dry = h <= sc.h_zero
    work.qx[i] = mx if dry else qx
    work.qy[i] = my if dry else qy
    work.trial_flag[i] = DRY if (mesh.valid[i] == 0 or dry) else fi


def _final(mesh, sc, cur, nxt, flag, work, dt, stage, transport, touched_by):
    """Per cell, the final update (the CPU kernel's _final_cells, its two loops one after
    the other): mass through the faces that are not Dirac, the projection, the flags (into
    ``flag``: the run's, or order 2's first stage's), and the cell's terms of the step's sums
    (``work.terms``). ``stage``: 0 at order 1, else order 2's stage 1 or 2 (friction with
    the stage's own thickness, physics.final_momentum's ``explicit``), which also writes
    the cell's ``transport`` (the largest mass flux per metre through its faces that are not
    Dirac, where the stage touches it, as the CPU kernel's stages) and whether the stage
    touched it into ``touched_by`` (stage 1: set, stage 2: added), for Heun's merge."""
    i = cuda.grid(1)
    n = cur.h.size
    if i >= n:
        return
    nx = mesh.x_code.shape[1] - 1
    r = i // nx
    c = i - r * nx
    xf, yf, emit, fl = work.xf, work.yf, work.emit, work.trial_flag
    g, h_zero = sc.g, sc.h_zero
    inside = mesh.valid[i] != 0
    fi = fl[i]
    w_code, e_code = mesh.x_code[r, c], mesh.x_code[r, c + 1]
    s_code, n_code = mesh.y_code[r, c], mesh.y_code[r + 1, c]
    w_in = (w_code & KIND) == INNER
    e_in = (e_code & KIND) == INNER
    s_in = (s_code & KIND) == INNER
    n_in = (n_code & KIND) == INNER
    # a boundary ghost shares its cell's flag
    f_w = fl[i - 1] if w_in else fi
    f_e = fl[i + 1] if e_in else fi
    f_s = fl[i - nx] if s_in else fi
    f_n = fl[i + nx] if n_in else fi
    wm, wx, wy, e_m, ex, ey, sm, sx, sy, nm, nx_, ny_ = side_terms(mesh, xf, yf, r, c)
    area = mesh.cell_area[i]
    h_old = cur.h[i]
    qx = work.qx[i]
    qy = work.qy[i]
    gz = mesh.gamma_z[i]
    speed_n = emit[E_SPEED, i]
    u1 = emit[E_U1, i]
    u2 = emit[E_U2, i]
    # Dirac faces (eqs. 51-53): both sides at zero temperature
    d_w = dirac_face(sc.dirac, fi, f_w)
    d_e = dirac_face(sc.dirac, fi, f_e)
    d_s = dirac_face(sc.dirac, fi, f_s)
    d_n = dirac_face(sc.dirac, fi, f_n)
    acc = in_face_order(0.0, 0.0 if d_w else wm, 0.0 if d_e else e_m,
                        0.0 if d_s else sm, 0.0 if d_n else nm)
    if (d_w or d_e or d_s or d_n) and fi == DRY:  # what those faces brought to the trial's
        # sum, taken back in face order
        qx = take_back(take_back(take_back(take_back(qx, wx, d_w), ex, d_e), sx, d_s), nx_, d_n)
        qy = take_back(take_back(take_back(take_back(qy, wy, d_w), ey, d_e), sy, d_s), ny_, d_n)
    p = mesh.params
    pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7 = cell_law(
        sc.law, p, i, p[0, 0], p[0, 1], p[0, 2], p[0, 3], p[0, 4], p[0, 5], p[0, 6], p[0, 7])
    hn, qx, qy, cl = cell_update(fi == DRY, fi, h_old, acc, qx, qy, area, dt, mesh.gamma_x[i],
                                 mesh.gamma_y[i], gz, centripetal(mesh, i, u1, u2), speed_n,
                                 sc.law, pc0, pc1, pc2, pc3, pc4, pc5, pc6, pc7, g, h_zero,
                                 stage > 0, False)
    good = inside and (hn >= 0.0)
    bad = inside and (hn < 0.0)
    if inside:
        flag[i] = fi
    h_w = hn if good else h_old
    qx = qx if good else 0.0
    qy = qy if good else 0.0
    nxt.h[i] = h_w
    nxt.hu[i] = qx
    nxt.hv[i] = qy
    # the sums, from what was written
    speed, inv_i = observe_cell(h_w, math.sqrt(qx * qx + qy * qy), mesh.cfl_factor[i], gz, g)
    len_w, len_e = mesh.x_length[r, c], mesh.x_length[r, c + 1]
    len_s, len_n = mesh.y_length[r, c], mesh.y_length[r + 1, c]
    carried = (((not d_w) and carries(wm, h_w, speed_n, len_w))
               or ((not d_e) and carries(e_m, h_w, speed_n, len_e))
               or ((not d_s) and carries(sm, h_w, speed_n, len_s))
               or ((not d_n) and carries(nm, h_w, speed_n, len_n)))
    moves = good and cell_moves(speed, speed_n, carried)
    # the CFL limit counts the cells the CPU kernel sweeps: wet, or by a wet cell
    eh = emit[E_H]
    touched = ((eh[i] > 0.0) or (w_in and eh[i - 1] > 0.0) or (e_in and eh[i + 1] > 0.0)
               or (s_in and eh[i - nx] > 0.0) or (n_in and eh[i + nx] > 0.0))
    kin, mov, film = step_terms(h_w, area, speed, moves, sc.h_dry)
    open_w = ((w_code & KIND) == HIGH_OPEN) and (not d_w) and (wm < 0.0)
    open_e = ((e_code & KIND) == LOW_OPEN) and (not d_e) and (e_m < 0.0)
    open_s = ((s_code & KIND) == HIGH_OPEN) and (not d_s) and (sm < 0.0)
    open_n = ((n_code & KIND) == LOW_OPEN) and (not d_n) and (nm < 0.0)
    out_w = outflow_volume(-wm, dt) if open_w else 0.0
    out_e = outflow_volume(-e_m, dt) if open_e else 0.0
    out_s = outflow_volume(-sm, dt) if open_s else 0.0
    out_n = outflow_volume(-nm, dt) if open_n else 0.0
    terms = work.terms
    terms[T_INV, i] = inv_i if (good and touched) else 0.0
    terms[T_KIN, i] = kin if good else 0.0
    terms[T_MOV, i] = mov
    terms[T_FILM, i] = film
    terms[T_OUT, i] = ((out_w + out_e) + out_s) + out_n if good else 0.0
    terms[T_CLAMPED, i] = cl if good else 0
    terms[T_BAD, i] = 1.0 if bad else 0.0
    terms[T_SOURCE, i] = 0.0
    if stage > 0:  # the CPU kernel's stage: its transport, through faces that are not Dirac
        if touched:
            unit = max(max(max(0.0 if d_w else abs(wm) / len_w, 0.0 if d_e else abs(e_m) / len_e),
                           0.0 if d_s else abs(sm) / len_s), 0.0 if d_n else abs(nm) / len_n)
            transport[i] = unit
        touched_by[i] = 1 if (touched or (stage == 2 and touched_by[i] != 0)) else 0


def _heun(mesh, sc, start, stage2, new, flag1, transport, touched_by, terms):
    """Order 2, per cell: Heun's merge of the step's start and the second stage
    (physics.heun_average, as the CPU kernel's _heun_cells: the same bits) into ``new``,
    and the cell's terms of the step's sums: its inverse CFL limit where a stage touched it
    (the cells the CPU kernel merges), kinetic energy, moving and film volumes, and in the
    ``T_CLAMPED`` slot whether the merge fell back to q = 0 (eq. 56)."""
    i = cuda.grid(1)
    if i >= new.h.size:
        return
    a = start.h[i]
    qa = start.hu[i]
    qb = start.hv[i]
    hn, qx, qy, fell_back = heun_average(a, qa, qb, stage2.h[i], stage2.hu[i], stage2.hv[i],
                                         flag1[i], sc.h_zero)
    new.h[i] = hn
    new.hu[i] = qx
    new.hv[i] = qy
    speed, inv_i = observe_cell(hn, math.sqrt(qx * qx + qy * qy), mesh.cfl_factor[i],
                                mesh.gamma_z[i], sc.g)
    speed_n = speed_of(a, qa, qb)
    moves = cell_moves(speed, speed_n, carries(transport[i], hn, speed_n, 1.0))
    kin, mov, film = step_terms(hn, mesh.cell_area[i], speed, moves, sc.h_dry)
    terms[T_INV, i] = inv_i if touched_by[i] != 0 else 0.0
    terms[T_KIN, i] = kin
    terms[T_MOV, i] = mov
    terms[T_FILM, i] = film
    terms[T_OUT, i] = 0.0
    terms[T_CLAMPED, i] = fell_back
    terms[T_BAD, i] = 0.0
    terms[T_SOURCE, i] = 0.0


def _source(mesh, sc, nxt, erodible, terms, law_row, src, dt):
    """Per cell, after an accepted step, what it takes from its erodible layer
    (numerics.sources' gain: the CPU kernels' own, the same bits), its volume and the new
    inverse CFL limit into the cell's terms."""
    i = cuda.grid(1)
    if i >= nxt.h.size:
        return
    added, inv = gain(i, nxt.h, nxt.hu, nxt.hv, erodible, sc.law, mesh.params, law_row, src,
                      dt, mesh.cell_area, mesh.cfl_factor, mesh.gamma_z)
    old = terms[T_INV, i]
    terms[T_INV, i] = inv if inv > old else old
    terms[T_SOURCE, i] = added


def _observe(mesh, sc, nxt, obs, maps, t_new):
    """Per cell inside the DEM, once per accepted step (its sources added), the running maps
    from its new state: physics.observe and the registered maps (``more_maps``), the rule of
    the CPU kernels' observer pass (numerics.observers), so a step redone with half the step
    writes none."""
    i = cuda.grid(1)
    if i >= nxt.h.size:
        return
    h = nxt.h[i]
    hu = nxt.hu[i]
    hv = nxt.hv[i]
    speed = speed_of(h, hu, hv)
    inside = mesh.valid[i] != 0
    (obs.peak_h[i], obs.peak_speed[i], obs.arrival[i], obs.last_moved[i]) = observe(
        inside, h, speed, t_new, sc.h_dry, obs.peak_h[i], obs.peak_speed[i],
        obs.arrival[i], obs.last_moved[i])
    if inside:
        more_maps(maps, i, h, hu, hv, speed, t_new)


def _supply(cells, weights, params, h, hu, hv, supplied, cell_area, cfl_factor, gamma_z, g,
            dt, t_new, terms):
    """Per cell of the registered sources, what they add (numerics.supply's supply_at, the
    CPU kernels' own), its volume and new inverse CFL limit into the sources' terms."""
    c = cuda.grid(1)
    if c >= cells.size:
        return
    added, inv = supply_at(c, cells, weights, params, h, hu, hv, supplied, cell_area,
                           cfl_factor, gamma_z, g, dt, t_new)
    for k in range(N_TERMS):
        terms[k, c] = 0.0
    terms[T_INV, c] = inv
    terms[T_SOURCE, c] = added


more_maps = supply_at = None


def _reduce(src, dst, n):
    """Block b's sums of the terms ``src[:, 0..n)`` into ``dst[:, b]`` (the CFL inverse:
    the largest): each thread adds the cells ``b * RED_THREADS + t``, a grid's width apart,
    then the block adds its threads' sums in a tree in shared memory. The order is fixed by
    ``n`` and the launch: the same bits from run to run (not the CPU kernel's order)."""
    part = cuda.shared.array((N_TERMS, RED_THREADS), float64)
    t = cuda.threadIdx.x
    b = cuda.blockIdx.x
    stride = cuda.gridDim.x * RED_THREADS
    for k in range(N_TERMS):
        acc = 0.0
        i = b * RED_THREADS + t
        while i < n:
            v = src[k, i]
            if k == T_INV:
                acc = v if v > acc else acc
            else:
                acc += v
            i += stride
        part[k, t] = acc
    cuda.syncthreads()
    half = RED_THREADS // 2
    while half > 0:
        if t < half:
            for k in range(N_TERMS):
                a = part[k, t]
                v = part[k, t + half]
                if k == T_INV:
                    part[k, t] = v if v > a else a
                else:
                    part[k, t] = a + v
        cuda.syncthreads()
        half //= 2
    if t == 0:
        for k in range(N_TERMS):
            dst[k, b] = part[k, 0]


#: the kernels made in this process, by the registered law, maps and sources built in
_KERNELS: dict = {}


def _no_fused_multiply_add() -> None:
    """NVVM fuses ``a * b + c`` into one rounding by default (``-fma=1``); the CPU kernels
    never do. Without the fusion a GPU gives the CPU's bits (Coulomb, Voellmy; libdevice's
    ``exp`` and ``log`` of Pouliquen and samosAT may differ in the last bit). numba-cuda
    has no option for it: its ``compile_ir`` is given ``fma=0`` for the whole process,
    except where a kernel asks for fastmath."""
    from numba.cuda.cudadrv import nvvm

    if getattr(nvvm.compile_ir, "avflow_no_fma", False):
        return
    original = nvvm.compile_ir

    def compile_ir(llvmir, **options):
        if not options.get("fastmath"):
            options.setdefault("fma", False)
        return original(llvmir, **options)

    compile_ir.avflow_no_fma = True
    nvvm.compile_ir = compile_ir


def _build(law: int = 0, sources=()):
    """The device copies of the pointwise physics and the CPU kernel's helpers, and the
    kernels, with what the run uses of the registry (avflow.extend: a registered law, the
    maps, its sources) built in as on the CPU (numerics.variants); made once per process and
    registry, at the first cuda run (numba.cuda is imported then)."""
    global THREADS, RED_THREADS, MAX_PARTIALS
    from avflow.numerics import variants

    laws, maps, entries = variants.registered(law, sources)
    key = variants.tag_of(*laws, *maps, *entries) if (laws or maps or entries) else ""
    if key in _KERNELS:
        return _KERNELS[key]
    from numba import config, cuda, float64

    if config.ENABLE_CUDASIM:
        THREADS, RED_THREADS, MAX_PARTIALS = SIMULATOR_THREADS, 8, 1
    else:
        _no_fused_multiply_add()

    from avflow.numerics import observers, sources as entrainment, square_grid, supply
    from avflow.numerics import vectorize
    from avflow.numerics.cpu import compile_pointwise

    device = cuda.jit(device=True)

    def registered_law(compiled):  # the registered law's branch before the built-in ones
        return ({"law_friction": variants.law_friction_with(laws, compiled["law_friction"],
                                                            device)} if laws else {})

    names = compile_pointwise((kinetic, physics, _plain_rheology()), device, registered_law)
    names["coded_flux"] = _retarget(square_grid._coded_flux, names, device)
    names["kind_of"] = _retarget(square_grid._kind_of, names, device)
    names["in_face_order"] = _retarget(square_grid._in_face_order, names, device)
    names["cell_law"] = _retarget(vectorize.cell_law, names, device)
    names["cuda"] = cuda
    names["float64"] = float64
    names["side_terms"] = _retarget(_side_terms, names, device)
    names["centripetal"] = _retarget(_centripetal, names, device)
    names["gain"] = _retarget(entrainment._gain, names, device)
    names["more_maps"] = (variants.more_maps_with(maps, device) if maps
                          else _retarget(observers.more_maps, names, device))
    names["supply_rate"] = (variants.supply_rate_with(entries, device) if entries
                            else _retarget(supply.supply_rate, names, device))
    names["supply_at"] = _retarget(supply.supply_at, names, device)
    # order 2's reconstruction: the CPU kernel's row pass and the cell loop it calls, with
    # the pointwise pieces that loop is made of
    names["friction_law"] = _retarget(vectorize.friction_law, names, device)
    for name in ("_gg_face", "_range", "_bj_select", "emitted_cell", "_side", "_side_direct",
                 "_in_face_order", "_recon_cells"):
        if hasattr(square_grid, name):  # (_side_direct: the row pass's MUSCL-Hancock form)
            names[name] = _retarget(getattr(square_grid, name), names, device)
    names["recon_row"] = _retarget(square_grid._recon_row, names, device)
    predicting = "dt_half" in inspect.signature(square_grid._recon_row.py_func).parameters
    names["recon_at"] = _retarget(_recon_at_predicting if predicting else _recon_at, names,
                                  device)
    _KERNELS[key] = {name: _retarget(fn, names, cuda.jit)
                     for name, fn in (("emit", _emit), ("faces", _faces), ("trial", _trial),
                                      ("final", _final), ("reduce", _reduce),
                                      ("source", _source), ("observe", _observe),
                                      ("supply", _supply), ("recon", _recon),
                                      ("heun", _heun))}
    return _KERNELS[key]


def _blocks(n: int) -> int:
    return max(1, (n + THREADS - 1) // THREADS)


def _partials(n: int) -> int:
    """Blocks of the first pass of the sums over ``n`` cells."""
    return max(1, min((n + RED_THREADS - 1) // RED_THREADS, MAX_PARTIALS))


#: The spare buffer of the device state, as the time loop reads a kernel's work buffers
DeviceSpare = namedtuple("DeviceSpare", "h_work hu_work hv_work")
#: What a call of the time loop keeps: the physics' scalars, and the entrainment's
#: (``(law_row, src)``, None without entrainment)
DeviceCall = namedtuple("DeviceCall", "sc entrainment")


class CudaGrid:
    """A solver's grid on the device: the geometry uploaded once, the state uploaded at the
    first call and kept there from call to call (downloaded at the end of each call, which
    the runner makes at output times). :meth:`advance` runs the CPU kernels' own time loop
    (:func:`avflow.numerics.loop.advance`, as Python) with this backend's region: its
    hooks launch the kernels, so step size, retry by halving, the sources, the stop rules
    and the statistics are the same code on every backend."""

    def __init__(self, mesh: stepping.GridMesh, params: np.ndarray, law: int = 0,
                 sources=(), order: int = 1):
        from numba import cuda

        from avflow.numerics import square_grid
        from avflow.numerics.loop import advance

        self.k = _build(law, sources)
        self.cuda = cuda
        self.order = int(order)
        self.nx, self.ny = int(mesh.nx), int(mesh.ny)
        n = self.nx * self.ny
        self.n = n
        to = cuda.to_device
        self.mesh = DeviceMesh(
            to(np.ascontiguousarray(mesh.valid)), to(np.ascontiguousarray(mesh.x_code)),
            to(np.ascontiguousarray(mesh.x_frame)), to(np.ascontiguousarray(mesh.x_length)),
            to(np.ascontiguousarray(mesh.y_code)), to(np.ascontiguousarray(mesh.y_frame)),
            to(np.ascontiguousarray(mesh.y_length)), to(mesh.cell_area), to(mesh.inv_area),
            to(mesh.cfl_factor), to(mesh.density), to(mesh.gamma_x), to(mesh.gamma_y),
            to(mesh.gamma_z), to(np.ascontiguousarray(mesh.curvature)),
            to(np.ascontiguousarray(params, dtype=np.float64).reshape(-1, params.shape[-1])),
            to(np.ascontiguousarray(mesh.x_offset)), to(np.ascontiguousarray(mesh.y_offset)))
        z = cuda.device_array
        self.work = DeviceWork(z((N_EMIT, n)), z((5, self.ny, self.nx + 1)),
                               z((5, self.ny + 1, self.nx)), z(n, dtype=np.uint8), z(n), z(n),
                               z((N_TERMS, n)), z((N_TERMS, _partials(n))), z((N_TERMS, 1)))
        self.buffers = [DeviceState(z(n), z(n), z(n)), DeviceState(z(n), z(n), z(n))]
        self.obs = DeviceObservers(z(n, dtype=np.uint8), z(n), z(n), z(n), z(n))
        m2 = n if self.order == 2 else 0  # order 2's arrays (empty at order 1)
        sides = z((4, N_EMIT, m2))
        self.o2 = DeviceOrder2(sides, to(np.full(m2, DRY, dtype=np.uint8)),
                               to(np.zeros(m2, dtype=np.uint8)), to(np.zeros(m2)),
                               DeviceState(z(m2), z(m2), z(m2)))
        #: what the faces read of each side of a face at order 2 (:func:`_faces`)
        self.face_sides = (sides[square_grid.SIDE_E], sides[square_grid.SIDE_W],
                           sides[square_grid.SIDE_N], sides[square_grid.SIDE_S])
        self.erodible = z(n)  # the erodible layer (read and written where there is a source)
        self.maps = z((0, n))  # the registered maps, and the registered sources' book,
        self.supplied = z(n)  # sized at the first upload
        self.supply = None  # (the host's Supply, its device copy and the sources' terms)
        self.current = 0  # the buffer that holds the state
        self.held = None  # (owner, the fields' arrays, the stats) as last downloaded
        self.uploads = 0  # calls that copied the state to the device
        hooks = {"region_start": self._start, "region_before": self._before,
                 "region_step": self._step, "region_source": self._source,
                 "region_observe": self._observe, "region_after": self._after,
                 "region_end": self._end, "supply_cells": self._supply}
        scope = dict(advance.__globals__)
        scope.update(hooks)
        #: the CPU kernels' time loop, run as Python with this backend's hooks
        self.loop = types.FunctionType(advance.__code__, scope, "advance_cuda")

    def _pairs(self, fields: stepping.Fields):
        cur = self.buffers[self.current]
        return ((cur.h, fields.h), (cur.hu, fields.hu), (cur.hv, fields.hv),
                (self.obs.flag, fields.flag), (self.obs.peak_h, fields.peak_h),
                (self.obs.peak_speed, fields.peak_speed), (self.obs.arrival, fields.arrival),
                (self.obs.last_moved, fields.last_moved), (self.erodible, fields.erodible),
                (self.maps, fields.maps), (self.supplied, fields.supplied))

    def _upload(self, fields: stepping.Fields) -> None:
        self.uploads += 1
        if self.maps.shape != fields.maps.shape:
            self.maps = self.cuda.device_array(fields.maps.shape)
        for dev, host in self._pairs(fields):
            if host.size:  # (no erodible layer without a source, no book without sources)
                dev.copy_to_device(np.ascontiguousarray(host))

    def _download(self, fields: stepping.Fields) -> None:
        for dev, host in self._pairs(fields):
            if host.size:
                host[:] = dev.copy_to_host()

    def _is_held(self, fields: stepping.Fields, owner) -> bool:
        """Whether the device holds ``fields`` of ``owner`` (the caller's state) as the last
        call left them: the same owner, arrays and statistics. (A caller that writes into
        the state's arrays between calls must pass another owner.)"""
        if self.held is None:
            return False
        who, arrays, stats = self.held
        return (who is owner and all(a is b for a, b in zip(arrays, fields[:-1]))
                and np.array_equal(stats, fields.stats))

    def _device_supply(self, supply):
        """The registered sources' arrays on the device (uploaded once per ``supply``)."""
        if self.supply is None or self.supply[0] is not supply:
            from avflow.numerics.supply import Supply

            to = self.cuda.to_device
            on = Supply(*(to(np.ascontiguousarray(a)) for a in supply))
            m = max(int(supply.cells.size), 1)
            z = self.cuda.device_array
            self.supply = (supply, on, z((N_TERMS, m)), z((N_TERMS, _partials(m))))
        return self.supply[1]

    def advance(self, fields: stepping.Fields, physics: stepping.Physics,
                run: stepping.Control, owner=None, supply=None) -> int:
        """The time loop (the CPU kernels': same arguments where they mean the same, same
        status codes and ``stats`` slots, ``fields`` on the full ``ny x nx`` grid).
        ``owner``: the state the fields are of; None: uploaded at every call. ``supply``:
        the registered sources (numerics.supply; None: none)."""
        from avflow.numerics.supply import no_supply

        if owner is None or not self._is_held(fields, owner):
            self._upload(fields)
        cur, nxt, obs = self.buffers[self.current], self.buffers[1 - self.current], self.obs
        on_device = stepping.Fields(cur.h, cur.hu, cur.hv, obs.flag, obs.peak_h,
                                    obs.peak_speed, obs.arrival, obs.last_moved,
                                    self.erodible, self.maps, self.supplied, fields.stats)
        status = self.loop(self.mesh, on_device, DeviceSpare(nxt.h, nxt.hu, nxt.hv), physics,
                           run, None, self._device_supply(supply or no_supply()))
        self._download(fields)
        self.held = (owner, tuple(fields[:-1]), fields.stats.copy())
        return status

    # --- the region's hooks (numerics.loop): each launches the kernels of its part ---------

    def _start(self, loop):
        """The call's scalars; a call that takes no step (the runner's warm-up) compiles
        every kernel."""
        physics, source = loop.physics, loop.physics.source
        sc = Scalars(int(physics.law), float(physics.g), bool(physics.dirac),
                     float(physics.h_dry), float(physics.h_zero))
        entrainment = None
        if int(source[SRC_KIND]) != SOURCE_NONE:  # what every cell's gain reads
            p = physics.params
            entrainment = (tuple(float(p[0, j]) for j in range(8)),
                           (int(source[SRC_KIND]), float(source[SRC_RATIO]),
                            float(source[SRC_UMIN]), float(source[SRC_PARAMS]),
                            float(source[SRC_PARAMS + 1]), float(source[SRC_PARAMS + 2]),
                            float(source[SRC_PARAMS + 3]), sc.h_zero, sc.g))
        if not loop.fields.stats[ST_TIME] < loop.run.t_target:
            self._warm(sc, entrainment, loop.supply)
        return None, DeviceCall(sc, entrainment)

    def _before(self, region, ctx, loop, cur, nxt, steps):
        """What cells emit and the face fluxes depend on the state alone: once a step (order
        1; order 2's stages are launched by :meth:`_step`)."""
        if self.order == 1:
            self._fluxes(ctx.sc, cur, 0)
        return region

    def _fluxes(self, sc, state, stage):
        """What the cells of ``state`` emit, and every face's flux: fed the cells' emitted
        values (``stage`` 0, order 1) or their reconstructed sides (order 2's stages)."""
        k, m, work = self.k, self.mesh, self.work
        k["emit"][_blocks(self.n), THREADS](m, state, work.emit, sc.g, sc.h_zero)
        if stage:
            k["recon"][_blocks(self.n), THREADS](m, sc, state, self.o2.sides)
            xa, xb, ya, yb = self.face_sides
        else:
            xa = xb = ya = yb = work.emit
        k["faces"][_blocks(self._n_faces()), THREADS](m, xa, xb, ya, yb, work.xf, work.yf)

    def _update(self, sc, cur, nxt, flag, when, stage):
        """Trial momentum and final update from ``cur`` into ``nxt`` (flags into ``flag``),
        and the grid's sums of the cells' terms."""
        k, m, work, bc, o2 = self.k, self.mesh, self.work, _blocks(self.n), self.o2
        k["trial"][bc, THREADS](m, sc, cur, work, when.dt, when.dt_decide, stage > 0)
        k["final"][bc, THREADS](m, sc, cur, nxt, flag, work, when.dt, stage, o2.transport,
                                o2.touched)
        return self._sums(work.terms, work.partials, self.n)

    def _step(self, region, ctx, loop, cur, nxt, when, steps, attempt):
        """One attempt: trial momentum, final update, the grid's sums (the few numbers the
        host sees); order 2: Heun's two stages and merge, as the CPU kernel's order-2 step
        (square_grid's _order2_step): stage 1 from ``cur`` into ``nxt`` (its flags kept for
        the merge), stage 2 from ``nxt`` into the stage buffers (the run's flags), the merge
        of ``cur`` and stage 2 into ``nxt``; the outflow is the stages' mean, the clamped
        cells both stages', the other sums the merge's."""
        sc = ctx.sc
        if self.order == 1:
            sums = self._update(sc, cur, nxt, self.obs.flag, when, 0)
            return (sums[T_BAD] == 0.0, sums[T_OUT], physics_dt(sums[T_INV]), sums[T_MOV],
                    sums[T_FILM], int(sums[T_CLAMPED]), sums[T_KIN], 0, region)
        o2 = self.o2
        fail = (False, 0.0, physics_dt(0.0), 0.0, 0.0, 0, 0.0, 0, region)
        self._fluxes(sc, cur, 1)
        one = self._update(sc, cur, nxt, o2.flag1, when, 1)
        if one[T_BAD] != 0.0:  # (the CPU kernel runs no second stage either)
            return fail
        self._fluxes(sc, nxt, 2)
        two = self._update(sc, nxt, o2.stage2, self.obs.flag, when, 2)
        if two[T_BAD] != 0.0:
            return fail
        self.k["heun"][_blocks(self.n), THREADS](self.mesh, sc, cur, o2.stage2, nxt, o2.flag1,
                                                 o2.transport, o2.touched, self.work.terms)
        merged = self._sums(self.work.terms, self.work.partials, self.n)
        return (True, 0.5 * (one[T_OUT] + two[T_OUT]), physics_dt(merged[T_INV]),
                merged[T_MOV], merged[T_FILM], int(one[T_CLAMPED]) + int(two[T_CLAMPED]),
                merged[T_KIN], int(merged[T_CLAMPED]), region)

    def _source(self, region, ctx, loop, nxt, when):
        """The entrainment after the accepted step, on its new state."""
        law_row, src = ctx.entrainment
        work = self.work
        self.k["source"][_blocks(self.n), THREADS](self.mesh, ctx.sc, nxt, self.erodible,
                                                   work.terms, law_row, src, when.dt)
        sums = self._sums(work.terms, work.partials, self.n)
        loop.fields.stats[ST_SOURCE] += sums[T_SOURCE]
        return sums[T_INV]

    def _supply(self, cells, weights, params, h, hu, hv, supplied, cell_area, cfl_factor,
                gamma_z, g, dt, t_new):
        """The registered sources (the loop's call of numerics.supply.supply_cells, on the
        device): ``(volume added, the largest new inverse CFL limit)``."""
        _, _, terms, partials = self.supply
        self.k["supply"][_blocks(cells.size), THREADS](
            cells, weights, params, h, hu, hv, supplied, cell_area, cfl_factor, gamma_z, g,
            dt, t_new, terms)
        sums = self._sums(terms, partials, cells.size)
        return sums[T_SOURCE], sums[T_INV]

    def _observe(self, region, ctx, loop, nxt, when):
        self.k["observe"][_blocks(self.n), THREADS](self.mesh, ctx.sc, nxt, self.obs,
                                                    self.maps, when.t_new)

    def _after(self, region, ctx, loop, nxt):
        return region

    def _end(self, region, ctx, loop, cur, t, steps):
        """The call's time and steps into ``stats``; the buffer that holds the state."""
        record_end(loop.fields.stats, t, steps)
        self.current = 0 if cur.h is self.buffers[0].h else 1

    def _n_faces(self) -> int:
        return self.ny * (self.nx + 1) + (self.ny + 1) * self.nx

    def _warm(self, sc: Scalars, source=None, supply=None) -> None:
        """Every kernel launched once on the state, into scratch observers and the spare
        buffer, so that the first call of a run times no compilation (numba.cuda compiles a
        kernel at its first launch); the state and its observers are left as they are."""
        k, m, work, o2 = self.k, self.mesh, self.work, self.o2
        cur = self.buffers[self.current]
        nxt = self.buffers[1 - self.current]
        like = self.cuda.device_array_like
        scratch = DeviceObservers(*(like(a) for a in self.obs))
        bc = _blocks(self.n)
        stage = 0 if self.order == 1 else 1  # (the transport and merge's flags: scratch)
        transport, touched = like(o2.transport), like(o2.touched)
        self._fluxes(sc, cur, stage)
        k["trial"][bc, THREADS](m, sc, cur, work, 0.0, 0.0, stage > 0)
        k["final"][bc, THREADS](m, sc, cur, nxt, scratch.flag, work, 0.0, stage, transport,
                                touched)
        if stage:  # Heun's merge, into the spare buffer
            k["heun"][bc, THREADS](m, sc, cur, nxt, nxt, like(o2.flag1), transport, touched,
                                   work.terms)
        if source is not None:  # ``(law_row, src)``: on the spare buffer, a scratch layer
            k["source"][bc, THREADS](m, sc, nxt, like(self.erodible), work.terms, source[0],
                                     source[1], 0.0)
        if supply is not None and supply.cells.size:  # nothing falls in a step of 0 s
            self._supply(supply.cells, supply.weights, supply.params, nxt.h, nxt.hu, nxt.hv,
                         like(self.supplied), m.cell_area, m.cfl_factor, m.gamma_z, sc.g,
                         0.0, 0.0)
        k["observe"][bc, THREADS](m, sc, nxt, scratch, like(self.maps), 0.0)
        self._sums(work.terms, work.partials, self.n)
        self.cuda.synchronize()

    def _sums(self, terms, partials, n: int) -> np.ndarray:
        """The sums of the terms of ``n`` cells (two passes of a block reduction), copied to
        the host: the ``T_*`` slots."""
        k, totals = self.k, self.work.totals
        nb = min(partials.shape[1], _partials(n))
        if nb == 1:  # one block adds them all
            k["reduce"][1, RED_THREADS](terms, totals, n)
        else:
            k["reduce"][nb, RED_THREADS](terms, partials, n)
            k["reduce"][1, RED_THREADS](partials, totals, nb)
        return totals.copy_to_host()[:, 0]


def physics_dt(inv_lim: float) -> float:
    """The CFL limit of the step's largest inverse limit (physics.dt_from_inverse)."""
    return physics.dt_from_inverse(float(inv_lim))


def loop(structured, order, law, parallel):
    """The registry's ``loop`` of the cuda kernel: the class that runs it, at ``order``
    (there is no one compiled loop to hand out: the kernels compile at the first launch)."""
    return functools.partial(CudaGrid, order=order)
