"""Rasters in: DEMs and thickness grids from ESRI ASCII (.asc), GeoTIFF (.tif) and NetCDF (.nc).

Every reader returns a :class:`Raster`: values on ascending cell-centre coordinates ``x``,
``y`` (m, projected), NODATA as NaN, and the CRS as WKT when the file carries one (the
``.prj`` sidecar of an ESRI grid, the GeoTIFF's own CRS, the ``grid_mapping`` of a NetCDF).
The solver never sees NaN: :func:`avflow.terrain.bed.surface_terrain` leaves those cells out of
the mesh. :func:`resample` puts a raster on a coarser (or finer) grid by bilinear
interpolation; a cell with a NODATA corner stays NODATA. :func:`cf_grid_mapping` turns the
CRS into the attributes of a CF ``grid_mapping`` variable (CF-1.11 section 5.6).
"""

from __future__ import annotations

import contextlib
import functools
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from avflow.files import atomic_text, atomic_write

SUFFIXES = (".asc", ".tif", ".tiff", ".nc")

#: A DEM whose spacing is within this fraction of the requested ``dx`` is used as it is.
NATIVE_TOLERANCE = 0.01


class RasterError(ValueError):
    """A raster file that cannot be read or used; the message names the file."""


@dataclass(frozen=True)
class Raster:
    """Values (ny, nx) on ascending cell-centre coordinates; NaN where NODATA."""

    values: np.ndarray
    x: np.ndarray
    y: np.ndarray
    crs_wkt: str | None = None
    path: str | None = None

    @property
    def dx(self) -> float:
        return float(self.x[1] - self.x[0])

    @property
    def dy(self) -> float:
        return float(self.y[1] - self.y[0])

    def sample(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """Bilinear values at points (NaN outside the raster or next to a NODATA cell)."""
        fx = (np.asarray(xs, float) - self.x[0]) / self.dx
        fy = (np.asarray(ys, float) - self.y[0]) / self.dy
        ny, nx = self.values.shape
        inside = (fx >= -1e-9) & (fx <= nx - 1 + 1e-9) & (fy >= -1e-9) & (fy <= ny - 1 + 1e-9)
        fx = np.clip(fx, 0.0, nx - 1)
        fy = np.clip(fy, 0.0, ny - 1)
        i0 = np.minimum(np.floor(fx).astype(np.int64), max(nx - 2, 0))
        j0 = np.minimum(np.floor(fy).astype(np.int64), max(ny - 2, 0))
        i1 = np.minimum(i0 + 1, nx - 1)
        j1 = np.minimum(j0 + 1, ny - 1)
        wx, wy = fx - i0, fy - j0
        v = self.values
        out = ((1 - wx) * (1 - wy) * v[j0, i0] + wx * (1 - wy) * v[j0, i1]
               + (1 - wx) * wy * v[j1, i0] + wx * wy * v[j1, i1])
        return np.where(inside, out, np.nan)


def read_raster(path, what: str = "raster") -> Raster:
    """Read a raster by its suffix; any problem is a :class:`RasterError` naming the file.
    ``what`` names it in the messages (``"DEM"``). A raster in degrees (a geographic CRS)
    is refused: every cell size and distance here is in metres."""
    raster = _read_raster(path)
    degrees = geographic_crs(raster.crs_wkt)
    if degrees:
        raise RasterError(f"{path}: this {what} is in degrees ({degrees}): reproject it to a "
                          "projected CRS in metres (e.g. gdalwarp -t_srs EPSG:<UTM zone>)")
    return raster


def geographic_crs(wkt: str | None) -> str | None:
    """The name of ``wkt`` when it is a geographic CRS (longitude and latitude in degrees),
    else None (projected, or none given)."""
    if not wkt:
        return None
    try:
        from pyproj import CRS

        crs = CRS.from_user_input(wkt)
    except Exception:  # noqa: BLE001 - a CRS pyproj does not read is not judged here
        return None
    if not crs.is_geographic:
        return None
    epsg = crs.to_epsg()
    return f"EPSG:{epsg}" if epsg else crs.name


def _read_raster(path) -> Raster:
    path = Path(path)
    if not path.is_file():
        raise RasterError(f"{path}: no such raster file")
    suffix = path.suffix.lower()
    stat = path.stat()
    try:
        if suffix == ".asc":
            return _cached(str(path), stat.st_mtime_ns, stat.st_size, "asc")
        if suffix in (".tif", ".tiff"):
            return _cached(str(path), stat.st_mtime_ns, stat.st_size, "tif")
        if suffix == ".nc":
            return _cached(str(path), stat.st_mtime_ns, stat.st_size, "nc")
    except RasterError:
        raise
    except Exception as err:  # a reader library's own error: say which file
        detail = " ".join(str(err).split())[:120]  # one line, never the file's content
        raise RasterError(f"{path}: cannot be read as a raster ({type(err).__name__}: "
                          f"{detail})") from None
    raise RasterError(f"{path}: unknown raster format (use one of {', '.join(SUFFIXES)})")


@functools.lru_cache(maxsize=8)
def _cached(path: str, mtime_ns: int, size: int, kind: str) -> Raster:
    """Readers are cached per file version: an ensemble reads its DEM once per process."""
    raster = {"asc": _read_asc, "tif": _read_tif, "nc": _read_nc}[kind](Path(path))
    values = raster.values
    values.setflags(write=False)
    if values.ndim != 2 or min(values.shape) < 2:
        raise RasterError(f"{path}: {' x '.join(map(str, values.shape[::-1]))} cells; a DEM or "
                          "raster needs at least 2 x 2 (its cell size comes from them)")
    if not np.isfinite(values).any():
        raise RasterError(f"{path}: every cell is NODATA")
    return raster


#: Header keys of an ESRI ASCII grid (GDAL's AAIGrid driver reads the same ones).
_ASC_KEYS = {"ncols", "nrows", "xllcorner", "yllcorner", "xllcenter", "yllcenter", "cellsize",
             "dx", "dy", "nodata_value", "nodata"}


def _read_asc(path: Path) -> Raster:
    """ESRI ASCII grid through GDAL's AAIGrid driver (rasterio), in float64.

    GDAL parses the header (corner or centre origin, ``cellsize`` or ``dx``/``dy``), the
    values and ``NODATA_value``. Two things are added here, because GDAL does not do them:
    the number of values is checked against the header (GDAL fills a short last row with
    zeros, a pit in a DEM, and ignores extra values), and a header that GDAL does not
    recognise names its missing key. The CRS is the text of the ``.prj`` (GDAL's only
    source for it too), kept as written. Without ``DATATYPE=Float64`` GDAL would read a
    decimal grid as float32.
    """
    import rasterio

    with open(path, "rb") as fh:
        tokens = fh.read().split()
    k, header = 0, {}
    while k + 1 < len(tokens) and tokens[k].decode("ascii", "replace").lower() in _ASC_KEYS:
        header[tokens[k].decode().lower()] = tokens[k + 1]
        k += 2
    for need in ("ncols", "nrows"):
        if need not in header:
            raise RasterError(f"{path}: ESRI ASCII header lacks {need!r}")
    if "cellsize" not in header and not ("dx" in header and "dy" in header):
        raise RasterError(f"{path}: ESRI ASCII header lacks 'cellsize' (or 'dx' and 'dy')")
    for a, b in (("xllcorner", "xllcenter"), ("yllcorner", "yllcenter")):
        if a not in header and b not in header:
            raise RasterError(f"{path}: ESRI ASCII header lacks {a!r} (or {b!r})")
    try:
        nx, ny = int(header["ncols"]), int(header["nrows"])
    except ValueError as err:
        raise RasterError(f"{path}: ESRI ASCII header value is not a number ({err})") from None
    if len(tokens) - k != nx * ny:
        raise RasterError(f"{path}: header says {ny} x {nx} = {nx * ny} values, "
                          f"the file holds {len(tokens) - k}")
    del tokens
    with rasterio.open(path, driver="AAIGrid", DATATYPE="Float64") as src:
        t = src.transform
        values = src.read(1, masked=True).astype(float).filled(np.nan)[::-1]  # south first
    # The .prj as written: GDAL's WKT1 export of an ESRI .prj no longer matches its EPSG
    # code in pyproj (cf_grid_mapping), and a CRS that GDAL cannot parse still travels.
    prj = path.with_suffix(".prj")
    wkt = (prj.read_text().strip() or None) if prj.is_file() else None
    dx, dy = t.a, -t.e
    x0, y0 = t.c + 0.5 * dx, t.f - ny * dy + 0.5 * dy  # centres of the south-west cell
    return Raster(np.ascontiguousarray(values), x0 + dx * np.arange(nx),
                  y0 + dy * np.arange(ny), wkt, str(path))


def _read_tif(path: Path) -> Raster:
    import rasterio

    with rasterio.open(path) as src:
        t = src.transform
        if t.b != 0.0 or t.d != 0.0:
            raise RasterError(f"{path}: rotated GeoTIFFs are not supported")
        band = src.read(1, masked=True).astype(float)
        values = band.filled(np.nan)
        wkt = src.crs.to_wkt() if src.crs is not None else None
        nx, ny = src.width, src.height
    dx, dy = t.a, t.e  # dy < 0 for north-up rasters
    x = t.c + dx * (np.arange(nx) + 0.5)
    y = t.f + dy * (np.arange(ny) + 0.5)
    if dx < 0:
        x, values = x[::-1], values[:, ::-1]
    if dy < 0:
        y, values = y[::-1], values[::-1]
    return Raster(np.ascontiguousarray(values), x, y, wkt, str(path))


def _read_nc(path: Path) -> Raster:
    import xarray as xr

    with xr.open_dataset(path, decode_times=False) as ds:
        candidates = [n for n, v in ds.data_vars.items() if v.ndim == 2]
        preferred = [n for n in ("elevation", "z", "band_data", "bed_elevation",
                                 "thickness", "h") if n in candidates]
        if not candidates:
            raise RasterError(f"{path}: no 2D variable to read as a raster")
        name = (preferred or candidates)[0]
        var = ds[name]
        ydim, xdim = var.dims
        x = np.asarray(ds[xdim].values, dtype=float)
        y = np.asarray(ds[ydim].values, dtype=float)
        values = np.asarray(var.values, dtype=float)
        wkt = None
        gm = var.attrs.get("grid_mapping") or var.encoding.get("grid_mapping")
        if gm and gm in ds.variables:
            a = ds[gm].attrs
            wkt = a.get("crs_wkt") or a.get("spatial_ref")
    if x.size < 2 or y.size < 2:
        raise RasterError(f"{path}: variable {name!r} needs at least 2 x 2 cells")
    if x[1] < x[0]:
        x, values = x[::-1], values[:, ::-1]
    if y[1] < y[0]:
        y, values = y[::-1], values[::-1]
    for axis, c in (("x", x), ("y", y)):
        d = np.diff(c)
        if not np.allclose(d, d[0], rtol=1e-6):
            raise RasterError(f"{path}: {axis} coordinates are not evenly spaced")
    return Raster(np.ascontiguousarray(values), x, y, wkt, str(path))


def resample(raster: Raster, dx: float, dy: float | None = None) -> Raster:
    """The raster on a grid of spacing ``dx`` (``dy``) over the same extent, bilinear.

    Returned unchanged when the spacing is already within :data:`NATIVE_TOLERANCE`.
    """
    dy = dx if dy is None else dy
    if (abs(raster.dx - dx) <= NATIVE_TOLERANCE * dx
            and abs(raster.dy - dy) <= NATIVE_TOLERANCE * dy):
        return raster
    nx = int(np.floor((raster.x[-1] - raster.x[0]) / dx + 1e-9)) + 1
    ny = int(np.floor((raster.y[-1] - raster.y[0]) / dy + 1e-9)) + 1
    if nx < 2 or ny < 2:
        raise RasterError(f"{raster.path}: dx = {dx} m leaves fewer than 2 x 2 cells")
    x = raster.x[0] + dx * np.arange(nx)
    y = raster.y[0] + dy * np.arange(ny)
    xx, yy = np.meshgrid(x, y)
    values = raster.sample(xx, yy)
    return Raster(values, x, y, raster.crs_wkt, raster.path)


def cf_grid_mapping(wkt: str | None) -> dict | None:
    """Attributes of a CF grid_mapping variable for a CRS given as WKT (None: no CRS).

    pyproj writes the CF parameters (grid_mapping_name, standard parallels, ellipsoid...)
    and ``crs_wkt``; GDAL reads the latter. A CRS without a CF name keeps ``crs_wkt`` only.
    """
    if not wkt:
        return None
    try:
        from pyproj import CRS

        crs = CRS.from_user_input(wkt)
        code = crs.to_epsg(min_confidence=70)  # an ESRI .prj of an EPSG CRS: write EPSG's
        if code is not None:
            crs = CRS.from_epsg(code)
        with warnings.catch_warnings():
            # an oblique Mercator's (LV95) skew angle has no CF name; crs_wkt keeps it
            warnings.filterwarnings("ignore", "angle from rectified to skew grid",
                                    UserWarning)
            attrs = crs.to_cf()
        attrs["crs_wkt"] = crs.to_wkt()
    except Exception:  # an unknown or broken CRS still travels as text
        attrs = {"crs_wkt": wkt}
    attrs["spatial_ref"] = attrs["crs_wkt"]  # the name GDAL looks up first
    return {k: v for k, v in attrs.items() if v is not None}


def same_crs(a: str | None, b: str | None) -> bool:
    """True when two WKT strings name the same CRS (or either is absent)."""
    if not a or not b:
        return True
    try:
        from pyproj import CRS

        ca, cb = CRS.from_user_input(a), CRS.from_user_input(b)
        if ca.equals(cb, ignore_axis_order=True):
            return True
        # ESRI and EPSG spellings of one CRS (datum names, TOWGS84) compare unequal:
        # the same EPSG code, or the same projection parameters, is the same CRS.
        ea, eb = ca.to_epsg(min_confidence=70), cb.to_epsg(min_confidence=70)
        if ea is not None and ea == eb:
            return True
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return ca.to_proj4() == cb.to_proj4()
    except Exception:
        return a.strip() == b.strip()


def write_asc(path, values: np.ndarray, x: np.ndarray, y: np.ndarray, wkt: str | None = None,
              nodata: float = -9999.0) -> Path:
    """ESRI ASCII grid (rows north to south) and its .prj, each written atomically."""
    path = Path(path)
    dx = float(x[1] - x[0])
    if not np.isclose(float(y[1] - y[0]), dx, rtol=1e-6):
        raise RasterError(f"{path}: ESRI ASCII grids need square cells")
    v = np.where(np.isfinite(values), values, nodata)[::-1]
    header = (f"ncols {v.shape[1]}\nnrows {v.shape[0]}\n"
              f"xllcorner {x[0] - 0.5 * dx:.6f}\nyllcorner {y[0] - 0.5 * dx:.6f}\n"
              f"cellsize {dx:.6f}\nNODATA_value {nodata:g}\n")
    # %.9g round-trips float32 exactly
    atomic_text(path, header + "\n".join(" ".join(f"{a:.9g}" for a in row) for row in v) + "\n")
    if wkt:
        atomic_text(path.with_suffix(".prj"), _esri_wkt(wkt))
    return path


def write_tif(path, values: np.ndarray, x: np.ndarray, y: np.ndarray,
              wkt: str | None = None, *, dtype: str = "float32", nodata=np.nan,
              colormap: dict | None = None, description: str | None = None,
              tags: dict | None = None, units: str | None = None) -> Path:
    """Single-band GeoTIFF (north up), written atomically: float32 with NaN as nodata, or
    ``dtype`` with ``nodata`` for NaN; ``colormap`` (value -> RGBA) makes a byte raster
    paletted; ``description``, ``units`` and ``tags`` name the band in GIS programs.

    The file is read back before it is renamed into place: GDAL reports a full disk as a
    logged error, not an exception, and left 0-byte rasters that said "wrote"."""
    import rasterio
    from rasterio.transform import from_origin

    path = Path(path)
    dx, dy = float(x[1] - x[0]), float(y[1] - y[0])
    transform = from_origin(x[0] - 0.5 * dx, y[-1] + 0.5 * dy, dx, dy)
    values = np.asarray(values, dtype=float)[::-1]
    if np.dtype(dtype).kind != "f":
        values = np.where(np.isfinite(values), values, nodata)
    band = values.astype(dtype)

    def write(tmp: Path) -> None:
        with _c_stderr_kept(said), rasterio.open(tmp, "w", driver="GTiff", width=band.shape[1],
                           height=band.shape[0], count=1, dtype=dtype,
                           crs=wkt, transform=transform, nodata=nodata,
                           compress="deflate") as dst:
            dst.write(band, 1)
            if colormap:
                dst.write_colormap(1, colormap)
            if description:
                dst.set_band_description(1, description)
            if units:
                dst.set_band_unit(1, units)
            if tags:
                dst.update_tags(1, **tags)

    def verify(tmp: Path) -> None:
        why = said[0] if said else "is the disk full?"
        try:
            with _c_stderr_kept(said), rasterio.open(tmp) as src:
                back = src.read(1)
        except Exception as err:  # noqa: BLE001 - a truncated file: GDAL's own error
            raise OSError(f"the GeoTIFF reads back broken ({type(err).__name__}; {why})"
                          ) from None
        if not np.array_equal(back, band, equal_nan=band.dtype.kind == "f"):
            raise OSError(f"the GeoTIFF reads back different ({why})")

    said: list[str] = []  # what libtiff printed while writing: a full disk's "No space..."

    return atomic_write(path, write, verify)


@contextlib.contextmanager
def _c_stderr_kept(said: list):
    """libtiff prints a failed write on the process's stderr (fd 2, not Python's logging),
    once per block: kept here, so that the command says it once, in its own error line."""
    import sys
    import tempfile

    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as caught:
        os.dup2(caught.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            caught.seek(0)
            lines = caught.read(4096).decode(errors="replace").splitlines()
            said.extend(" ".join(line.split()) for line in lines if line.strip())


def _esri_wkt(wkt: str) -> str:
    """WKT1 in ESRI's dialect, the only one GDAL's ESRI ASCII driver reads from a .prj."""
    try:
        from pyproj import CRS

        return CRS.from_user_input(wkt).to_wkt("WKT1_ESRI")
    except Exception:
        return wkt
