"""Every traversal against recorded states (``tests/data/reference_states.npz``, made by
``tests/reference_states.py``), not one kernel against another: the profile sweep at both
orders and the four friction laws, the square-grid kernel with each law, the face kernel on
a profile, a grid and triangles at both orders, and 2 threads on grids and triangles.

Bit for bit on a CPU of the recording's vector width. Elsewhere LLVM's reassociated row sums
add in another order (``vectorize.line_sum``), so the comparison is to 1e-12 of the largest
value of each field, far below any difference a change of the scheme makes (1e-3 and more).
The grid-wide sums of the statistics (moving volume, film, outflow, kinetic energy, sources)
are such reassociated sums everywhere: their order is LLVM's choice, and another LLVM
(llvmlite 0.50 with Numba 0.68 here) added a few of them in another order on the same
vector width, 1-2 units in the last place apart. They are compared to 1e-13 relative: a
hundred roundings of the sum, far below any change of the scheme.
"""

import numpy as np
import pytest

from reference_states import FIELDS, FILE, TIMES, cases, run, vector_width

from avflow.numerics import stepping as st

REFERENCE = np.load(FILE)
SAME_MACHINE = str(REFERENCE["vector_width"]) == vector_width()


#: the statistics' slots that are grid-wide sums (their order is LLVM's: see above)
SUMS = (st.ST_MOVING, st.ST_FILM, st.ST_OUTFLOW, st.ST_KINETIC, st.ST_KINETIC_PEAK,
        st.ST_SOURCE, st.ST_SUPPLY)


def _bits(a):
    a = np.ascontiguousarray(a)
    return a.view(np.int64) if a.dtype == np.float64 else a


@pytest.mark.parametrize("case", cases(), ids=[c[0] for c in cases()])
def test_the_kernels_give_the_recorded_states(case):
    states = run(case)
    name = case[0]
    for f in FIELDS:
        for k, got in enumerate(states[f]):
            want = REFERENCE[f"{name}/{f}/{k}"]
            where = f"{name}: {f} at t = {TIMES[case[1]][k]} s"
            if f == "stats":  # slots added since the recording are zero in these runs
                assert not np.any(got[want.size:]), where
                got = got[:want.size]
            if f == "stats":  # the reassociated sums: to their round-off (see above)
                sums = [k for k in SUMS if k < want.size]
                np.testing.assert_allclose(got[sums], want[sums], rtol=1e-13, atol=0.0,
                                           err_msg=where)
                got, want = np.delete(got, sums), np.delete(want, sums)
            if SAME_MACHINE or f == "flag":
                np.testing.assert_array_equal(_bits(got), _bits(want), err_msg=where)
            else:
                scale = np.nanmax(np.abs(want)) if np.any(np.isfinite(want)) else 1.0
                np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * max(scale, 1e-300),
                                           equal_nan=True, err_msg=where)


def test_the_reference_moves_stops_and_reaches_every_branch():
    """The recorded runs are worth comparing: every case moves, the 2D ones hold cells under
    the threshold (Dirac faces), the open side of the grid lets mass out."""
    for case in cases():
        name, kind = case[0], case[1]
        assert REFERENCE[f"{name}/peak_speed/1"].max() > 3.0, name
        assert REFERENCE[f"{name}/stats/1"][2] > 25, name  # steps
    for name in ("grid-coulomb-o1", "triangles-coulomb-o1", "triangles-coulomb-o2",
                 "grid-threads-coulomb-o2", "grid-pouliquen-o1", "triangles-hancock-coulomb-o2"):
        assert np.sum(REFERENCE[f"{name}/flag/1"] == 1) > 0, name
