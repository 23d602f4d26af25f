"""The alpha-beta model on AvaFrame's four real paths (their own alpha-beta lines).

For avaKot, avaHit (two lines), avaAlr and avaWog: the bed along AvaFrame's ``pathAB``
line (data/avaframe/<path>/pathAB.shp, from AvaFrame's Inputs/LINES), sampled every 5 m
(bilinear) from its upper end, and avflow's alpha-beta model
(avflow.output.alphabeta) with the Norwegian regression (the default) and AvaFrame's
Austrian set: beta, alpha, alpha - 1 SD, alpha - 2 SD and where each meets the bed (s,
horizontal from the line's top). Beside them: the travel angle of avflow's Coulomb run of
the same path (workflows/compare_avaframe_results.md, delta as there).

Run: ``python workflows/alphabeta_avaframe.py``; writes workflows/alphabeta_avaframe_results.md.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PATHS = ("avaKot", "avaHit", "avaAlr", "avaWog")
#: avflow's Coulomb run of each path (travel angle, degrees), workflows/compare_avaframe_results.md
DYNAMIC = {"avaKot": 30.6, "avaHit": 28.1, "avaAlr": math.nan, "avaWog": math.nan}


def profiles(name: str, step: float = 5.0):
    import pyogrio
    import shapely

    from avflow.terrain.raster import read_raster

    folder = ROOT / "data" / "avaframe" / name
    dem = read_raster(next(p for p in folder.iterdir()
                           if p.stem == name and p.suffix in (".asc", ".tif")))
    _, _, wkb, _ = pyogrio.raw.read(folder / "pathAB.shp")
    for k, line in enumerate(shapely.from_wkb(wkb)):
        s = np.arange(0.0, line.length, step)
        pts = shapely.get_coordinates(shapely.line_interpolate_point(line, s))
        z = dem.sample(pts[:, 0], pts[:, 1])
        if np.nanmean(z[: z.size // 2]) < np.nanmean(z[z.size // 2:]):  # drawn uphill
            line = shapely.reverse(line)
            pts = shapely.get_coordinates(shapely.line_interpolate_point(line, s))
            z = dem.sample(pts[:, 0], pts[:, 1])
        yield f"{name}" + (f" line {k + 1}" if len(wkb) > 1 else ""), s, z


def main() -> int:
    from avflow.output.alphabeta import alpha_beta

    rows = []
    for name in PATHS:
        for label, s, z in profiles(name):
            for reg in ("norway", "austria"):
                ab = alpha_beta(s, z, reg)
                rows.append((label, reg, ab, DYNAMIC.get(name, math.nan), z[0]))
    head = ("| path | regression | top (m) | beta (deg) | beta point s (m) | alpha | s | "
            "alpha-1SD | s | alpha-2SD | s | avflow Coulomb travel angle |")
    lines = [head, "|" + "---|" * 12]

    def f(v, fmt):
        return "–" if not np.isfinite(v) else format(v, fmt)
    for label, reg, ab, dyn, top in rows:
        cells = [label, reg, f(top, ".0f"), f(ab.beta, ".1f"), f(ab.beta_s, ".0f")]
        for a, s_ in zip(ab.alphas, ab.points_s):
            cells += [f(a, ".1f"), f(s_, ".0f")]
        cells.append(f(dyn, ".1f"))
        lines.append("| " + " | ".join(cells) + " |")
    text = "\n".join(lines)
    print(text)
    (ROOT / "workflows" / "alphabeta_avaframe_results.md").write_text(
        "# Alpha-beta on AvaFrame's four paths\n\n`python workflows/alphabeta_avaframe.py`: "
        "the bed along AvaFrame's pathAB lines, every 5 m from the top; s is horizontal "
        "from the line's top.\n\n" + text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
