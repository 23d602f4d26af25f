"""The similarity solution of an avalanche on an inclined plane against avflow's orders.

    python workflows/similarity.py                  # the table at 10 / 5 / 2.5 m, t = 20 s
    python workflows/similarity.py --sizes 5 --times 5,10,20 --figure docs/img/similarity.png

A parabolic cap (80 m in radius, 4 m thick) released on a 35 degree plane with Coulomb
friction 25 degrees (AvaFrame's ana1Tests settings, earth-pressure coefficient 1) against
Hutter et al.'s (1993) similarity solution (``avflow.numerics.analytic.similarity``), the
slope turned by 0, 22.5 and 45 degrees on the grid, each order (and both time schemes of
order 2). Prints a markdown table: relative L2 of the thickness, the front against the
analytic contour at 1% of the release thickness, the lateral spread and the area above it,
the time loop's wall time (one thread). The runs are those of tests/test_similarity.py.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="10,5,2.5", help="cell sizes (m)")
    ap.add_argument("--times", default="20", help="times (s)")
    ap.add_argument("--turns", default="0,22.5,45", help="the slope turned on the grid (deg)")
    ap.add_argument("--figure", help="PNG of profiles along and across the slope (5 m, t = 20 s)")
    args = ap.parse_args(argv)
    import test_similarity as ts

    schemes = ((1, "auto", "order 1"), (2, "auto", "order 2 (MUSCL-Hancock)"),
               (2, "heun", "order 2 (Heun)"))
    print("| scheme | t (s) | dx (m) | turn (deg) | L2 | front (m) | spread | area | loop (s) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for t in (float(v) for v in args.times.split(",")):
        for order, scheme, label in schemes:
            for dx in (float(v) for v in args.sizes.split(",")):
                for turn in (float(v) for v in args.turns.split(",")):
                    ts.run(dx, order, turn, scheme, t=t)  # compiled and warm
                    started = time.perf_counter()
                    l2, front, spread, area, *_ = ts.run(dx, order, turn, scheme, t=t)
                    wall = time.perf_counter() - started
                    print(f"| {label} | {t:g} | {dx:g} | {turn:g} | {l2:.4f} | {front:+.1f} "
                          f"| {spread:+.1%} | {area:+.1%} | {wall:.2f} |", flush=True)
    if args.figure:
        figure(ts, Path(args.figure), 20.0)
    return 0


def figure(ts, path: Path, t: float) -> None:
    """Thickness along the slope's centre line and across the cap's centre, 5 m cells,
    the slope along the grid and at 45 degrees, both orders against the analytic cap."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from avflow.numerics.analytic import similarity, similarity_thickness

    cap = similarity(t, ts.THETA, ts.DELTA, ts.H0, ts.RADIUS, ts.RADIUS)
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6), constrained_layout=True)
    s = np.linspace(cap.travel - 1.15 * cap.a, cap.travel + 1.15 * cap.a, 400)
    n = np.linspace(-1.3 * cap.b, 1.3 * cap.b, 300)
    axes[0].plot(s, similarity_thickness(cap, s, 0 * s), "k-", lw=2, label="analytic")
    axes[1].plot(n, similarity_thickness(cap, cap.travel + 0 * n, n), "k-", lw=2)
    styles = {(1, 0.0): ("tab:red", "-"), (1, 45.0): ("tab:red", "--"),
              (2, 0.0): ("tab:blue", "-"), (2, 45.0): ("tab:blue", "--")}
    for (order, turn), (colour, dash) in styles.items():
        *_, state, terrain, (xi, eta) = ts.run(5.0, order, turn, t=t)
        band = 5.0
        along = np.abs(eta) < band / 2
        across = np.abs(xi - cap.travel) < band / 2 / math.cos(math.radians(ts.THETA))
        label = f"order {order}, slope {'along the grid' if turn == 0 else 'at 45 deg'}"
        order_a, order_c = np.argsort(xi[along]), np.argsort(eta[across])
        axes[0].plot(xi[along][order_a], state.h[along][order_a], color=colour, ls=dash,
                     lw=1.2, label=label)
        axes[1].plot(eta[across][order_c], state.h[across][order_c], color=colour, ls=dash,
                     lw=1.2)
    axes[0].set_xlabel("distance along the slope from the release centre (m)")
    axes[1].set_xlabel("distance across the slope (m)")
    for ax in axes:
        ax.set_ylabel("thickness (m)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="upper left")
    fig.suptitle(f"Similarity solution, 35 deg plane, Coulomb 25 deg, t = {t:g} s, 5 m cells",
                 fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


if __name__ == "__main__":
    raise SystemExit(main())
