"""A synthetic ridge-and-valley region for ``avflow region``: a GeoTIFF DEM, a GeoPackage
of release polygons on slopes of 28-45 degrees, and the region file.

    python workflows/make_region.py OUTDIR --size 2000 --dx 10 --releases 15

The bed: valleys along y (a sinusoid across x, amplitude ``--relief``) draining north to
south at 3 degrees, with smaller waves for texture. Releases are squares (``--release-side``)
centred on cells whose slope is within [28, 45] degrees, at least one side apart, drawn with
a seeded generator: the same arguments make the same files.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

REGION_YAML = """\
name: {name}
description: synthetic ridge-and-valley region ({size:g} m x {size:g} m at {dx:g} m)
dem: dem.tif
releases:
  path: releases.gpkg
  thickness_field: thickness
  id_field: id
scenario:
  rheology: {{law: coulomb, delta_deg: {delta:g}}}
  time: {{end: {end:g}}}
  numerics: {{order: 1}}
window:
  runout_angle_deg: {angle:g}
merge:
  chunk: 256
"""


def ridge_valley(size: float, dx: float, relief: float = 300.0, wavelength: float = 1000.0,
                 seed: int = 1):
    """Elevation (rows north first), cell-centre x and y (y descending)."""
    n = int(round(size / dx))
    x = (np.arange(n) + 0.5) * dx
    y = (np.arange(n) + 0.5)[::-1] * dx
    xx, yy = np.meshgrid(x, y)
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0, 2 * np.pi, 3)
    z = (relief * 0.5 * (1 - np.cos(2 * np.pi * xx / wavelength + phase[0]))
         + math.tan(math.radians(3.0)) * yy
         + 0.08 * relief * np.sin(2 * np.pi * yy / (0.7 * wavelength) + phase[1])
         * np.sin(2 * np.pi * xx / (0.45 * wavelength) + phase[2]))
    return z, x, y


def slope_deg(z: np.ndarray, dx: float) -> np.ndarray:
    gy, gx = np.gradient(z, dx)
    return np.degrees(np.arctan(np.hypot(gx, gy)))


def make_region(folder, size: float = 2000.0, dx: float = 10.0, releases: int = 15,
                side: float = 60.0, relief: float = 300.0, seed: int = 1,
                delta_deg: float = 22.0, end: float = 120.0, angle: float = 22.0,
                name: str = "synthetic-region") -> Path:
    """Write dem.tif, releases.gpkg and region.yaml into ``folder``; return region.yaml."""
    import pyogrio.raw
    import rasterio
    import shapely
    from rasterio.transform import from_origin

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    z, x, y = ridge_valley(size, dx, relief, seed=seed)
    crs = "EPSG:2056"  # Swiss LV95: any projected CRS in metres
    with rasterio.open(folder / "dem.tif", "w", driver="GTiff", width=z.shape[1],
                       height=z.shape[0], count=1, dtype="float32", crs=crs,
                       transform=from_origin(2_600_000.0, 1_200_000.0 + size, dx, dx),
                       tiled=True, blockxsize=256, blockysize=256, compress="deflate") as dst:
        dst.write(z.astype(np.float32), 1)
    slope = slope_deg(z, dx)
    rng = np.random.default_rng(seed + 1)
    margin = int(math.ceil(side / dx)) + 2
    ok = np.argwhere((slope >= 28) & (slope <= 45))
    ok = ok[(ok[:, 0] > margin) & (ok[:, 0] < z.shape[0] - margin)
            & (ok[:, 1] > margin) & (ok[:, 1] < z.shape[1] - margin)]
    rng.shuffle(ok)
    centres: list[tuple[float, float]] = []
    for r, c in ok:
        cx, cy = 2_600_000.0 + x[c], 1_200_000.0 + y[r]
        if all(math.hypot(cx - a, cy - b) > 2 * side for a, b in centres):
            centres.append((cx, cy))
        if len(centres) == releases:
            break
    half = side / 2
    geoms = [shapely.box(cx - half, cy - half, cx + half, cy + half) for cx, cy in centres]
    thickness = rng.uniform(0.8, 2.0, len(geoms))
    pyogrio.raw.write(str(folder / "releases.gpkg"),
                      np.array([shapely.to_wkb(g) for g in geoms], dtype=object),
                      [np.arange(1, len(geoms) + 1, dtype=np.int32), thickness],
                      ["id", "thickness"], driver="GPKG", crs=crs, geometry_type="Polygon")
    path = folder / "region.yaml"
    path.write_text(REGION_YAML.format(name=name, size=size, dx=dx, delta=delta_deg, end=end,
                                       angle=angle))
    return path


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("outdir")
    p.add_argument("--size", type=float, default=2000.0, help="side of the square region, m")
    p.add_argument("--dx", type=float, default=10.0, help="DEM cell size, m")
    p.add_argument("--releases", type=int, default=15, help="number of release polygons")
    p.add_argument("--release-side", type=float, default=60.0, help="side of each, m")
    p.add_argument("--relief", type=float, default=300.0, help="ridge-to-valley height, m")
    p.add_argument("--seed", type=int, default=1)
    args = p.parse_args()
    path = make_region(args.outdir, args.size, args.dx, args.releases, args.release_side,
                       args.relief, args.seed)
    print(f"wrote {path} (dem.tif, releases.gpkg beside it)")


if __name__ == "__main__":
    main()
