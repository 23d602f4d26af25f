"""Potential release areas on AvaFrame's four real paths against their own release polygons.

For avaKot, avaHit, avaAlr and avaWog (DEMs and release polygons from the AvaFrame
repository, 5 m grids): the potential release areas with the default criteria
(avflow.terrain.release_areas: slope 28-60 degrees, Veitinger's roughness at a snow depth of
2.3 m, no wind shelter, no forest map, minimum area 4 cells), then

- the share of each path's own release polygon(s) covered by the PRA cells,
- the PRA's total area and number of single areas, and the path's release area.

The defaults are not tuned on these four paths. Run: ``python workflows/pra_avaframe.py
[DATA_DIR]`` (default: the repository's data/avaframe); writes
workflows/pra_avaframe_results.md.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PATHS = ("avaKot", "avaHit", "avaAlr", "avaWog")


def coverage(data: Path, name: str, settings=None) -> dict:
    import shapely

    from avflow.terrain.polygons import read_polygons
    from avflow.terrain.release_areas import PRASettings, potential_release_areas

    folder = data / name
    dem = next(p for p in folder.iterdir() if p.stem == name and p.suffix in (".asc", ".tif"))
    rel = folder / f"rel{name[3:]}.shp"
    started = time.perf_counter()
    result = potential_release_areas(dem, settings or PRASettings())
    seconds = time.perf_counter() - started
    areas, _ = read_polygons(rel, attribute=False)
    release = shapely.union_all([shapely.Polygon(a.rings[0], a.rings[1:]) for a in areas])
    pra = shapely.union_all([a["geometry"] for a in result.areas]) if result.areas else None
    covered = 0.0 if pra is None else shapely.intersection(release, pra).area
    dx = abs(result.x[1] - result.x[0])
    return {"path": name, "release_m2": release.area,
            "covered_share": covered / release.area,
            "pra_m2": float(sum(a["area_m2"] for a in result.areas)),
            "pra_areas": len(result.areas),
            "dem_m2": float(np.isfinite(result.index).sum() * dx * dx),
            "seconds": seconds}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    data = Path(argv[0]) if argv else ROOT / "data" / "avaframe"
    rows = [coverage(data, name) for name in PATHS]
    lines = ["| path | own release (m2) | share covered by the PRA | PRA total (m2) | "
             "PRA areas | DEM (m2) | PRA / DEM | time (s) |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['path']} | {r['release_m2']:.0f} | {100 * r['covered_share']:.1f}% "
                     f"| {r['pra_m2']:.0f} | {r['pra_areas']} | {r['dem_m2']:.0f} | "
                     f"{100 * r['pra_m2'] / r['dem_m2']:.1f}% | {r['seconds']:.1f} |")
    text = "\n".join(lines)
    print(text)
    out = ROOT / "workflows" / "pra_avaframe_results.md"
    out.write_text("# Potential release areas on AvaFrame's four paths\n\n"
                   "Default criteria (slope 28-60 deg, roughness at HS 2.3 m, no wind, no "
                   "forest, minimum 4 cells); `python workflows/pra_avaframe.py`.\n\n"
                   + text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
