"""The four AvaFrame paths of ``data/avaframe`` as small real regions for ``avflow region``:
each path's DEM and release polygon, plus extra release squares placed on its slopes.

    python workflows/avaframe_regions.py OUTDIR                 # writes the regions
    python workflows/avaframe_regions.py OUTDIR --run --workers 0   # and runs them, a table

For each path (avaAlr, avaHit, avaKot, avaWog) it writes ``OUTDIR/<path>/``:

- ``dem.vrt``: a GDAL VRT over the path's DEM, unchanged, with the CRS of its release
  shapefile (MGI / Austria Lambert, EPSG:31287): the ESRI ASCII grids carry none, and the
  inputs are never rewritten. The GeoTIFF of avaAlr has its own CRS and is named directly.
- ``releases.gpkg``: the path's release polygon(s) first (ids 1..n, their ``thickness``),
  then ``--extra`` squares of ``--side`` m on cells of 28-45 degrees inside the DEM's data,
  at least two sides from every other release and from the DEM's NODATA, 1 m thick, drawn
  with a seeded generator (the same arguments make the same files);
- ``region.yaml``: Coulomb 20 degrees with AvaFrame's snow density and its stop rule (the
  kinetic energy down to 1 % of its peak), as ``scenarios/avakot_coulomb.yaml``.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PATHS = {"avaAlr": "avaAlr.tif", "avaHit": "avaHit.asc", "avaKot": "avaKot.asc",
         "avaWog": "avaWog.asc"}

REGION_YAML = """\
name: {name}
description: AvaFrame's {path} ({source}) with its release and {extra} extra releases on its slopes
dem: {dem}
releases:
  path: releases.gpkg
  thickness_field: thickness
  id_field: id
scenario:
  rheology: {{law: coulomb, delta_deg: 20.0}}
  time: {{end: {end:g}, cfl: 0.5}}
  output: {{stop_rule: kinetic_energy}}
  physics: {{density: 200.0}}
window:
  runout_angle_deg: 20.0
merge:
  chunk: 128
"""


def _vrt(target: Path, source: Path, wkt: str) -> Path:
    """A VRT naming ``source`` unchanged, with the CRS ``wkt``."""
    import rasterio

    with rasterio.open(source) as src:
        t, nodata, dtype = src.transform, src.nodata, src.dtypes[0]
        width, height = src.width, src.height
    gdal_type = {"float32": "Float32", "float64": "Float64", "int16": "Int16",
                 "int32": "Int32"}[dtype]
    nodata_xml = f"    <NoDataValue>{nodata!r}</NoDataValue>\n" if nodata is not None else ""
    target.write_text(
        f'<VRTDataset rasterXSize="{width}" rasterYSize="{height}">\n'
        f"  <SRS>{escape(wkt)}</SRS>\n"
        f"  <GeoTransform>{t.c!r}, {t.a!r}, {t.b!r}, {t.f!r}, {t.d!r}, {t.e!r}</GeoTransform>\n"
        f'  <VRTRasterBand dataType="{gdal_type}" band="1">\n{nodata_xml}'
        f"    <SimpleSource>\n"
        f'      <SourceFilename relativeToVRT="0">{escape(str(source))}</SourceFilename>\n'
        f"      <SourceBand>1</SourceBand>\n"
        f"    </SimpleSource>\n"
        f"  </VRTRasterBand>\n"
        f"</VRTDataset>\n")
    return target


def make_path_region(outdir, path: str, extra: int = 3, side: float = 50.0, seed: int = 1,
                     end: float = 300.0) -> Path:
    """Write one path's region into ``outdir/path``; return its region.yaml."""
    import pyogrio
    import pyogrio.raw
    import rasterio
    import shapely
    from pyproj import CRS
    from scipy import ndimage

    folder = Path(outdir) / path
    folder.mkdir(parents=True, exist_ok=True)
    data = ROOT / "data" / "avaframe" / path
    dem_src = data / PATHS[path]
    shp = data / f"rel{path[3:]}.shp"
    meta, _, wkb, columns = pyogrio.raw.read(shp)
    crs_wkt = CRS.from_user_input(meta["crs"]).to_wkt()
    with rasterio.open(dem_src) as src:
        has_crs = src.crs is not None
        z = src.read(1, masked=True)
        t = src.transform
    dem = dem_src if has_crs else _vrt(folder / "dem.vrt", dem_src, crs_wkt)
    valid = ~np.ma.getmaskarray(z)
    zz = z.filled(np.nan).astype(float)
    dx = t.a
    gy, gx = np.gradient(zz, dx)
    slope = np.degrees(np.arctan(np.hypot(gx, gy)))
    own = [shapely.from_wkb(w) for w in wkb]
    thickness = list(columns[list(meta["fields"]).index("thickness")])
    # candidate centres: slope 28-45 degrees, two sides away from NODATA and the border
    margin = int(math.ceil(2 * side / dx))
    far = ndimage.binary_erosion(valid, iterations=margin)
    ok = np.argwhere(far & (slope >= 28.0) & (slope <= 45.0))
    rng = np.random.default_rng(seed)
    rng.shuffle(ok)
    geoms = list(own)
    half = side / 2
    for r, c in ok:
        if len(geoms) == len(own) + extra:
            break
        cx, cy = t.c + (c + 0.5) * dx, t.f + (r + 0.5) * t.e
        square = shapely.box(cx - half, cy - half, cx + half, cy + half)
        if all(square.distance(g) > 2 * side for g in geoms):
            geoms.append(square)
            thickness.append(1.0)
    target = folder / "releases.gpkg"
    target.unlink(missing_ok=True)
    pyogrio.raw.write(str(target), np.array([shapely.to_wkb(g) for g in geoms], dtype=object),
                      [np.arange(1, len(geoms) + 1, dtype=np.int32),
                       np.asarray(thickness, dtype=float)],
                      ["id", "thickness"], driver="GPKG", crs=crs_wkt, geometry_type="Polygon")
    region = folder / "region.yaml"
    region.write_text(REGION_YAML.format(name=f"{path}-region", path=path,
                                         source=PATHS[path], extra=len(geoms) - len(own),
                                         dem=dem if has_crs else "dem.vrt", end=end))
    return region


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("outdir")
    p.add_argument("--paths", default=",".join(PATHS), help="comma-separated (default: all)")
    p.add_argument("--extra", type=int, default=3, help="extra releases per path")
    p.add_argument("--side", type=float, default=50.0, help="side of each extra square, m")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--end", type=float, default=300.0, help="time.end, s")
    p.add_argument("--run", action="store_true", help="run each region into <path>/maps")
    p.add_argument("--workers", type=int, default=None, help="as avflow region --workers")
    args = p.parse_args()
    rows = []
    for path in args.paths.split(","):
        region_file = make_path_region(args.outdir, path, args.extra, args.side, args.seed,
                                       args.end)
        print(f"wrote {region_file}")
        if not args.run:
            continue
        import xarray as xr

        from avflow.region import load_region
        from avflow.region.orchestrate import run_region

        clock = time.perf_counter()
        out = run_region(load_region(region_file), region_file.parent / "maps",
                         workers=args.workers, quiet=True)
        wall = time.perf_counter() - clock
        t = out.table
        ds = xr.open_zarr(out.store)
        reached = int((ds.release_count.values > 0).sum())
        dx = float(ds.x[1] - ds.x[0])
        rows.append((path, len(t), int((t.status == "ok").sum()),
                     int((t.status == "dem_edge").sum()), int(t.retries.fillna(0).sum()),
                     ", ".join(f"{v:.0f}" for v in t.runout),
                     ", ".join(f"{v:.1f}" for v in t.travel_angle),
                     reached * dx * dx / 1e6, int(ds.release_count.max()), wall,
                     t.run_time.sum()))
    if rows:
        print("\n| path | releases | ok | dem_edge | retries | runout (m) | travel angle (deg) "
              "| area reached (km2) | most releases on a cell | wall (s) | runs (s) |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        for r in rows:
            print(f"| {r[0]} | {r[1]} | {r[2]} | {r[3]} | {r[4]} | {r[5]} | {r[6]} | "
                  f"{r[7]:.3f} | {r[8]} | {r[9]:.0f} | {r[10]:.0f} |")


if __name__ == "__main__":
    main()
