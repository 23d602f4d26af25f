"""Potential release areas (PRA) from a DEM: cells, single release areas, their thickness.

The cell criteria follow Veitinger, Purves and Sovilla (2016, NHESS 16, 2211), with the
membership functions and their parameters as the authors' public implementation gives them
(J. Veitinger's ``PRA_R.r``, github.com/jocha81/Avalanche-release; the paper itself was not
read here):

- **slope** ``psi`` of the winter terrain (the plane fitted over the coarsest roughness
  window): membership ``1 / (1 + ((psi - 43) / 11)^8)``, zero outside the band
  ``slope_min``..``slope_max`` (28-60 degrees);
- **roughness**: the vector ruggedness measure (Sappington et al. 2007, J. Wildl. Manage.
  71, 1419) ``1 - |sum n| / 9`` of the unit normals over 3 x 3 cells, the normals of planes
  fitted over windows of ``2 i + 1`` cells, ``i = 1 .. i_max``, ``i_max = ceil(3 HS cv -
  0.1)`` with the snow depth ``HS`` and ``cv = 0.35``; the scale used in a cell falls from
  ``i_max`` on slopes of 30 degrees and less to 1 on slopes of 60 degrees and more (snow
  smooths gentle terrain more); membership ``1 / (1 + ((r + 0.007) / 0.01)^10)``, zero above
  0.01;
- **wind shelter** (optional, with a wind direction): the median, over the cells within 5
  cells of a DEM aggregated by 5 (by ``2 i_max`` when ``i_max > 2``) whose direction lies
  within ``wind_tolerance`` of the direction the wind comes from, of ``atan(dz / distance)``
  (radians; Plattner et al. 2004); membership ``1 / (1 + ((w - 2) / 2)^10)``;
- the **fuzzy operator** ``m (1 - m) + m mean(mu)``, ``m = min(mu)``, over the memberships
  used.

A cell is a potential release cell where that index exceeds ``threshold`` (default 0: the
crisp criteria, slope in the band and roughness at most 0.01; the wind shelter changes the
index, so it acts through a threshold above 0, the user's choice), whose coarsest window
lies inside the DEM (cells nearer its edge or NODATA are not classified), outside forest (a
raster, > 0 is forest, or polygons) and, when ``max_curvature`` is given, where the
terrain is not more convex than that (the mean curvature of the DEM, 1/m; off by default:
no published value is adopted here).

**Single release areas**: connected cells (sharing a side); with ``split_aspect_deg`` each
is split where the downslope direction changes sector (sectors of that width, centred on
north), fragments
smaller than the minimum area joining the neighbour they share the longest border with (an
object-based split in the spirit of Bühler et al. 2018, NHESS 18, 3235; not their
algorithm). Areas smaller than ``min_area`` (horizontal, m^2; default 4 cells: a release a
simulation resolves) are dropped.

**Thickness** (with a reference depth ``d0``): the Swiss guideline's rule (Salm, Burkard
and Gubler 1990, as RAMMS uses it and as ``avflow region``'s ``return_periods`` apply it):
``d = (d0 + gradient (z - reference_elevation) / 100) f(psi)``, ``f(psi) = 0.291 / (sin psi
- 0.202 cos psi)`` (1 at 28 degrees), ``z`` and ``psi`` the area's mean elevation and slope.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from avflow.errors import AvflowError

__all__ = ["PRAError", "PRASettings", "PRAResult", "potential_release_areas",
           "swiss_thickness", "write_release_areas"]


class PRAError(AvflowError, ValueError):
    """Bad input to the release-area analysis; one line naming the option and the file
    (exit 2)."""


@dataclass(frozen=True)
class PRASettings:
    """The criteria (see the module); lengths in m, angles in degrees."""

    slope_min: float = 28.0
    slope_max: float = 60.0
    snow_depth: float = 2.3         #: HS (m), the scale of the roughness; 2.3 in the authors' example
    roughness: bool = True
    wind_direction: float | None = None  #: where the wind comes from, degrees from north
    wind_tolerance: float = 30.0    #: half-width of the upwind sector (authors' example)
    threshold: float = 0.0          #: fuzzy index above which a cell is a release cell
    max_curvature: float | None = None
    min_area: float | None = None   #: m^2, horizontal; None: 4 cells
    split_aspect_deg: float | None = None
    d0: float | None = None         #: m, reference depth of the thickness rule
    reference_elevation: float = 2000.0
    gradient: float = 0.05          #: m per 100 m
    slope_correction: bool = True

    def __post_init__(self):
        """Every number typed, finite and in its physical range, naming the option: a NaN
        or 1e308 would otherwise reach the layer as a thickness, an unbounded snow depth
        would make the roughness windows without end."""
        for name in ("roughness", "slope_correction"):
            if not isinstance(getattr(self, name), bool):
                raise PRAError(f"{name} must be true or false, got {getattr(self, name)!r}")
        for name, (low, high, rule) in NUMBER_RANGES.items():
            v = getattr(self, name)
            if v is None and name in OPTIONAL:
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise PRAError(f"{name} must be a number, got {v!r}")
            if not (math.isfinite(v) and low(v) and high(v)):
                raise PRAError(f"{name} must be {rule}, got {v!r}")
        if not self.slope_min < self.slope_max:
            raise PRAError(f"slope_min must be below slope_max, got {self.slope_min!r} and "
                           f"{self.slope_max!r}")
        if self.d0 is not None and self.slope_correction and self.slope_min <= SLOPE_FACTOR_MIN:
            raise PRAError(f"slope_min must be above {SLOPE_FACTOR_MIN:.2f} degrees with d0: "
                           "the slope factor 0.291 / (sin psi - 0.202 cos psi) of the "
                           "thickness rule is negative below (or leave out the slope "
                           "correction)")


#: Below this slope (degrees, atan 0.202) the Swiss slope factor's denominator is <= 0.
SLOPE_FACTOR_MIN = math.degrees(math.atan(0.202))

#: The options that may be left out (None).
OPTIONAL = ("wind_direction", "max_curvature", "min_area", "split_aspect_deg", "d0")

#: m, the thinnest release the thickness rule may give
MIN_THICKNESS = 1e-3

#: Each number's range: a test of its low end, one of its high end, the rule in words. The
#: high ends are physical: a snow depth over 20 m or a d0* over 10 m (or under 1 cm) is a
#: typo (the Swiss guideline's d0* is 0.5 to 3 m), an elevation outside -500..9000 m is no mountain's.
NUMBER_RANGES = {
    "slope_min": (lambda v: v >= 0, lambda v: v <= 90, "in [0, 90] degrees"),
    "slope_max": (lambda v: v > 0, lambda v: v <= 90, "in (0, 90] degrees"),
    "snow_depth": (lambda v: v > 0, lambda v: v <= 20, "in (0, 20] m"),
    "wind_direction": (lambda v: v >= 0, lambda v: v < 360, "in [0, 360) degrees"),
    "wind_tolerance": (lambda v: v > 0, lambda v: v <= 180, "in (0, 180] degrees"),
    "threshold": (lambda v: v >= 0, lambda v: v < 1, "in [0, 1)"),
    "max_curvature": (lambda v: v > 0, lambda v: True, "a number > 0 (1/m)"),
    "min_area": (lambda v: v > 0, lambda v: True, "a number > 0 (m2)"),
    "split_aspect_deg": (lambda v: v >= 1, lambda v: v <= 180, "in [1, 180] degrees"),
    "d0": (lambda v: v >= 0.01, lambda v: v <= 10, "in [0.01, 10] m"),
    "reference_elevation": (lambda v: v >= -500, lambda v: v <= 9000, "in [-500, 9000] m"),
    "gradient": (lambda v: v >= -1, lambda v: v <= 1, "in [-1, 1] m per 100 m"),
}


@dataclass
class PRAResult:
    """The index and cell maps (ny, nx, rows from south to north as ``y``) and the areas."""

    x: np.ndarray
    y: np.ndarray
    index: np.ndarray             #: fuzzy release index, 0..1 (NaN off the DEM)
    cells: np.ndarray             #: bool: release cells kept
    labels: np.ndarray            #: int: area id of each cell, 0 none
    areas: list = field(default_factory=list)   #: dicts: id, geometry (shapely), attributes
    crs_wkt: str | None = None
    slope: np.ndarray | None = None


# ---------------------------------------------------------------------------------------
# terrain measures
# ---------------------------------------------------------------------------------------


def _plane_gradient(z, dx, dy, i):
    """Gradient of the least-squares plane over a (2i+1) x (2i+1) window (the linear terms
    of SAGA's quadratic fit); NaN cells are filled with the nearest value first."""
    from scipy.ndimage import correlate

    k = np.arange(-i, i + 1, dtype=float)
    kx = np.tile(k, (k.size, 1))
    ky = kx.T
    gx = correlate(z, kx / (kx**2).sum() / dx, mode="nearest")
    gy = correlate(z, ky / (ky**2).sum() / dy, mode="nearest")
    return gx, gy


def _filled(z):
    """NaN cells take their nearest valid cell's value (for the window filters)."""
    bad = ~np.isfinite(z)
    if not bad.any():
        return z
    from scipy.ndimage import distance_transform_edt

    _, (r, c) = distance_transform_edt(bad, return_indices=True)
    return z[r, c]


def _normal_sum_ruggedness(gx, gy):
    from scipy.ndimage import uniform_filter

    n = np.stack([-gx, -gy, np.ones_like(gx)])
    n /= np.linalg.norm(n, axis=0)
    s = [uniform_filter(c, size=3, mode="nearest") * 9.0 for c in n]
    return 1.0 - np.sqrt(s[0] ** 2 + s[1] ** 2 + s[2] ** 2) / 9.0


def roughness_and_slope(z, dx, dy, snow_depth):
    """Veitinger's multi-scale roughness and the slope (degrees) of the coarsest scale."""
    i_max = max(1, math.ceil(3.0 * snow_depth * 0.35 - 0.1))
    rugg = []
    for i in range(1, i_max + 1):
        gx, gy = _plane_gradient(z, dx, dy, i)
        rugg.append(_normal_sum_ruggedness(gx, gy))
    slope = np.degrees(np.arctan(np.hypot(gx, gy)))
    coef = np.clip(1.0 - (slope - 30.0) / 30.0, 0.0, 1.0)
    scale = np.rint(1.0 + coef * (i_max - 1)).astype(int)
    out = rugg[-1].copy()
    for i in range(1, i_max):
        out = np.where(scale == i, rugg[i - 1], out)
    return out, slope, i_max


def wind_shelter(z, dx, dy, direction, tolerance, i_max, north_up_rows: bool):
    """Plattner's wind-shelter index (radians) on the DEM aggregated by 5 (``2 i_max``
    when ``i_max > 2``), radius 5 aggregated cells, bilinear back onto the grid."""
    from scipy.ndimage import zoom

    f = 2 * i_max if i_max > 2 else 5
    ny, nx = z.shape
    py, px = (-ny) % f, (-nx) % f
    zp = np.pad(z, ((0, py), (0, px)), mode="edge")
    agg = zp.reshape(zp.shape[0] // f, f, zp.shape[1] // f, f).mean(axis=(1, 3))
    ax, ay = dx * f, dy * f
    radius = 5
    angles = []
    upwind = math.radians(direction)
    tol = math.radians(tolerance)
    for r in range(-radius, radius + 1):
        for c in range(-radius, radius + 1):
            if (r, c) == (0, 0) or r * r + c * c > radius * radius:
                continue
            north = r * ay if north_up_rows else -r * ay  # rows go north when y rises
            east = c * ax
            bearing = math.atan2(east, north)  # from north, clockwise
            off = (bearing - upwind + math.pi) % (2 * math.pi) - math.pi
            if abs(off) > tol:
                continue
            shifted = np.full(agg.shape, np.nan)
            rs = slice(max(r, 0), agg.shape[0] + min(r, 0))
            rd = slice(max(-r, 0), agg.shape[0] + min(-r, 0))
            cs = slice(max(c, 0), agg.shape[1] + min(c, 0))
            cd = slice(max(-c, 0), agg.shape[1] + min(-c, 0))
            shifted[rd, cd] = agg[rs, cs]
            angles.append(np.arctan((shifted - agg) / math.hypot(north, east)))
    if not angles:
        return np.zeros_like(z)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN sectors at the edges
            ws = np.nanmedian(np.stack(angles), axis=0)
    ws = np.nan_to_num(ws, nan=0.0)
    full = zoom(ws, (zp.shape[0] / ws.shape[0], zp.shape[1] / ws.shape[1]), order=1,
                mode="nearest")
    return full[:ny, :nx]


def _bell(x, a, b, c):
    with np.errstate(over="ignore", invalid="ignore"):
        return 1.0 / (1.0 + np.abs((x - c) / a) ** (2 * b))


def swiss_thickness(d0, slope_deg, elevation, reference_elevation=2000.0, gradient=0.05,
                    slope_correction=True):
    """The Swiss guideline's release thickness (see the module)."""
    d = d0 + gradient * (np.asarray(elevation, float) - reference_elevation) / 100.0
    if slope_correction:
        psi = np.radians(np.asarray(slope_deg, float))
        d = d * 0.291 / (np.sin(psi) - 0.202 * np.cos(psi))
    return d


# ---------------------------------------------------------------------------------------
# cells -> areas
# ---------------------------------------------------------------------------------------


def _split_by_aspect(cells, gx, gy, sector_deg, min_cells):
    """Label connected cells, split by aspect sector, small fragments joined to the
    neighbour sharing the longest border."""
    from scipy.ndimage import label

    aspect = (np.degrees(np.arctan2(-gx, -gy)) + 360.0) % 360.0
    # sectors centred on north (north, east, south, west are no boundaries at 90 degrees)
    sector = np.floor(((aspect + 0.5 * sector_deg) % 360.0) / sector_deg).astype(int)
    labels = np.zeros(cells.shape, int)
    n = 0
    for s in np.unique(sector[cells]):
        lab, k = label(cells & (sector == s))
        labels[lab > 0] = lab[lab > 0] + n
        n += k
    from scipy.ndimage import binary_dilation, find_objects

    cross = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], bool)
    for _ in range(50):  # join fragments until none is left or none can be joined
        sizes = np.bincount(labels.ravel(), minlength=n + 1)
        small = [k for k in range(1, n + 1) if 0 < sizes[k] < min_cells]
        if not small:
            break
        boxes = find_objects(labels)
        changed = False
        for k in small:
            box = boxes[k - 1]
            if box is None:
                continue
            # the fragment's box grown by one cell: its border cells, locally
            sl = tuple(slice(max(s.start - 1, 0), s.stop + 1) for s in box)
            local = labels[sl]
            mask = local == k
            ring = binary_dilation(mask, structure=cross) & ~mask
            neighbours = local[ring & (local > 0)]
            if neighbours.size:
                values, counts = np.unique(neighbours, return_counts=True)
                local[mask] = values[np.argmax(counts)]
                changed = True
        if not changed:
            break
    return labels


def potential_release_areas(dem_path, settings: PRASettings | None = None, forest=None
                            ) -> PRAResult:
    """The potential release areas of a DEM file (see the module). ``forest``: a raster
    (> 0: forest) or a polygon file, excluded."""
    from scipy.ndimage import label

    from avflow.terrain.raster import RasterError, read_raster

    settings = settings or PRASettings()
    try:
        raster = read_raster(dem_path)
    except RasterError as err:
        raise PRAError(str(err)) from None
    z = np.asarray(raster.values, float)
    x, y = np.asarray(raster.x, float), np.asarray(raster.y, float)
    dx, dy = abs(x[1] - x[0]), abs(y[1] - y[0])
    valid = np.isfinite(z)
    zf = _filled(z)
    north_up = y[1] > y[0]
    # gradients in map axes: rows run along y, whatever their order
    sign_y = 1.0 if north_up else -1.0
    i_max = max(1, math.ceil(3.0 * settings.snow_depth * 0.35 - 0.1))
    if min(z.shape) < 2 * i_max + 1:  # the planes of the slope and roughness need the window
        raise PRAError(f"{dem_path}: the DEM ({z.shape[1]} x {z.shape[0]} cells) is smaller "
                       f"than the slope and roughness window ({2 * i_max + 1} x "
                       f"{2 * i_max + 1} cells for a snow depth of {settings.snow_depth:g} m); "
                       "use a larger DEM or a smaller --snow-depth")
    rugg, slope, i_max = roughness_and_slope(zf, dx, dy, settings.snow_depth)
    gx1, gy1 = _plane_gradient(zf, dx, dy, i_max)
    memberships = [np.where((slope >= settings.slope_min) & (slope <= settings.slope_max),
                            _bell(slope, 11.0, 4, 43.0), 0.0)]
    if settings.roughness:
        memberships.append(np.where(rugg > 0.01, 0.0, _bell(rugg, 0.01, 5, -0.007)))
    if settings.wind_direction is not None:
        ws = wind_shelter(zf, dx, dy, settings.wind_direction, settings.wind_tolerance,
                          i_max, north_up)
        memberships.append(_bell(ws, 2.0, 5, 2.0))
    mu = np.stack(memberships)
    m = mu.min(axis=0)
    index = (1.0 - m) * m + m * mu.mean(axis=0)
    index = np.where(valid, index, np.nan)
    # a cell whose coarsest window (and its 3 x 3 sum) leaves the DEM is not classified
    from scipy.ndimage import binary_erosion

    whole = binary_erosion(valid, iterations=i_max + 1, border_value=0)
    cells = whole & (index > settings.threshold)
    if settings.max_curvature is not None:
        from scipy.ndimage import laplace

        mean_curvature = -laplace(zf) / (dx * dy) / 2.0  # > 0 convex (a ridge)
        cells &= mean_curvature <= settings.max_curvature
    if forest is not None:
        cells &= ~_forest_mask(forest, x, y, raster.crs_wkt)
    min_area = settings.min_area if settings.min_area is not None else 4 * dx * dy
    min_cells = max(1, math.ceil(min_area / (dx * dy) - 1e-9))
    if settings.split_aspect_deg is not None:
        labels = _split_by_aspect(cells, gx1, sign_y * gy1, settings.split_aspect_deg,
                                  min_cells)
    else:
        labels, _ = label(cells)
    sizes = np.bincount(labels.ravel())
    small = sizes < min_cells
    small[0] = True
    labels = np.where(small[labels], 0, labels)
    # renumber 1..n in scan order from the north-west
    order = labels[::-1] if north_up else labels
    firsts = [v for v in dict.fromkeys(order.ravel()) if v > 0]
    remap = np.zeros(labels.max() + 1, int)
    remap[firsts] = np.arange(1, len(firsts) + 1)
    labels = remap[labels]
    result = PRAResult(x, y, index, labels > 0, labels, [], raster.crs_wkt, slope)
    result.areas = _polygons(result, zf, slope, settings)
    return result


def _forest_mask(forest, x, y, dem_wkt):
    path = Path(forest)
    from avflow.terrain.polygons import (VECTOR_SUFFIXES, PolygonError, rasterize,
                                         read_polygons, warn_no_crs)

    if path.suffix.lower() in VECTOR_SUFFIXES:
        try:
            areas, wkt = read_polygons(path, attribute=False)
        except PolygonError as err:
            raise PRAError(str(err)) from None
        _same_crs(path, wkt, dem_wkt)
        warn_no_crs(path, wkt, dem_wkt)
        X, Y = np.meshgrid(x, y)
        return rasterize(areas, X, Y, thickness=1.0) > 0
    from avflow.terrain.raster import RasterError, read_raster

    try:
        f = read_raster(path)
    except RasterError as err:
        raise PRAError(str(err)) from None
    _same_crs(path, f.crs_wkt, dem_wkt)
    X, Y = np.meshgrid(x, y)
    values = f.sample(X.ravel(), Y.ravel()).reshape(X.shape)
    return np.nan_to_num(values) > 0


def _same_crs(path, wkt, dem_wkt) -> None:
    """A forest layer in another CRS than the DEM's would be read as the DEM's coordinates
    (matching nowhere, or removing everything): refused, naming both."""
    from avflow.terrain.raster import same_crs

    if wkt and dem_wkt and not same_crs(wkt, dem_wkt):
        from pyproj import CRS

        def name(w):
            try:
                return CRS.from_user_input(w).name
            except Exception:  # noqa: BLE001 - any unreadable WKT
                return "another CRS"
        raise PRAError(f"--forest {path}: the layer is in {name(wkt)}, the DEM in "
                       f"{name(dem_wkt)}; reproject it to the DEM's CRS")


def _polygons(result: PRAResult, z, slope, settings: PRASettings) -> list:
    import shapely
    from rasterio.features import shapes
    from rasterio.transform import from_origin

    x, y, labels = result.x, result.y, result.labels
    dx, dy = abs(x[1] - x[0]), abs(y[1] - y[0])
    north_up = y[1] > y[0]
    grid = labels[::-1] if north_up else labels  # rows from the north for the transform
    transform = from_origin(x.min() - dx / 2, y.max() + dy / 2, dx, dy)
    parts: dict[int, list] = {}
    for geom, value in shapes(grid.astype(np.int32), mask=grid > 0, transform=transform,
                              connectivity=4):
        parts.setdefault(int(value), []).append(shapely.geometry.shape(geom))
    areas = []
    for k in sorted(parts):
        geom = shapely.union_all(parts[k])
        inside = labels == k
        psi = float(slope[inside].mean())
        elevation = float(z[inside].mean())
        row = {"id": k, "geometry": geom, "area_m2": float(inside.sum() * dx * dy),
               "mean_slope_deg": psi, "mean_elevation_m": elevation,
               "max_elevation_m": float(z[inside].max()),
               "index_mean": float(np.nanmean(result.index[inside]))}
        if settings.d0 is not None:
            row["thickness"] = float(swiss_thickness(
                settings.d0, psi, elevation, settings.reference_elevation, settings.gradient,
                settings.slope_correction))
            # under a millimetre is no release (and a file's field may round it to 0)
            if not (math.isfinite(row["thickness"]) and row["thickness"] >= MIN_THICKNESS):
                raise PRAError(f"d0: the thickness rule gives {row['thickness']:.3g} m for the "
                               f"area at {elevation:.0f} m, {psi:.1f} degrees (d0 "
                               f"{settings.d0:g} m, gradient {settings.gradient:g} m per 100 m "
                               f"from {settings.reference_elevation:g} m): not a thickness")
        areas.append(row)
    return areas


def write_release_areas(result: PRAResult, target, index_raster=None) -> list[Path]:
    """The areas as a polygon layer (GeoPackage or any vector format by suffix; attributes
    id, area_m2, mean_slope_deg, mean_elevation_m, max_elevation_m, index_mean, thickness
    when a d0 was given), and optionally the index as a GeoTIFF."""
    import warnings

    import pyogrio.raw

    from avflow.files import OutputWriteError, atomic_write, fsync, write_error

    target = Path(target)
    if not result.areas:
        raise PRAError("no potential release area: no cell meets the criteria (slope band, "
                       "roughness, forest, minimum area)")
    names = [k for k in result.areas[0] if k != "geometry"]
    wkb = np.array([a["geometry"].wkb for a in result.areas], dtype=object)
    columns = [np.array([a[k] for a in result.areas]) for k in names]
    driver = {".gpkg": "GPKG", ".shp": "ESRI Shapefile", ".geojson": "GeoJSON",
              ".json": "GeoJSON", ".fgb": "FlatGeobuf"}.get(target.suffix.lower())
    if driver is None:
        raise PRAError(f"{target}: write a .gpkg, .shp, .geojson or .fgb file")

    def write(tmp: Path) -> None:
        tmp.unlink()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            warnings.simplefilter("ignore", UserWarning)  # no CRS: said by the caller
            pyogrio.raw.write(str(tmp), wkb, columns, names, layer="release_areas",
                              driver=driver, crs=result.crs_wkt, geometry_type="Unknown")

    def verify(tmp: Path) -> None:
        """Read back: GDAL reports some failed writes (a full disk) as log messages only,
        leaving an empty or cut layer."""
        try:
            with warnings.catch_warnings():  # the temporary's name is no GeoPackage's
                warnings.simplefilter("ignore", RuntimeWarning)
                count = pyogrio.read_info(str(tmp))["features"]
        except Exception:  # noqa: BLE001 - any reader's error: the file is not readable
            count = -1
        if count != len(result.areas):
            raise OutputWriteError(f"cannot write {target}: the layer reads back "
                                   f"{'unreadable' if count < 0 else f'with {count} of {len(result.areas)} areas'}"
                                   " (is the disk full?)")

    written = []
    if driver == "ESRI Shapefile":  # several files: written in a folder beside, then moved
        import os
        import shutil
        import tempfile

        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            folder = Path(tempfile.mkdtemp(prefix=f".{target.stem}-", dir=target.parent))
        except OSError as err:
            raise write_error(target, err) from None
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                warnings.simplefilter("ignore", UserWarning)
                pyogrio.raw.write(str(folder / target.name), wkb, columns, names,
                                  driver=driver, crs=result.crs_wkt, geometry_type="Polygon")
            parts = sorted(folder.iterdir())
            for part in parts:
                fsync(part)
            verify(folder / target.name)
            for part in parts:  # the .shp last: a reader sees the new layer whole, or none
                if part.suffix.lower() != ".shp":
                    os.replace(part, target.with_suffix(part.suffix))
            os.replace(folder / target.name, target)
        except BaseException as err:
            error = write_error(target, err)
            if error is not None:
                raise error from None
            raise
        finally:
            shutil.rmtree(folder, ignore_errors=True)
        written.append(target)
    else:
        written.append(atomic_write(target, write, verify))
    if index_raster is not None:
        from avflow.terrain.raster import write_tif

        written.append(write_tif(index_raster, result.index, result.x, result.y,
                                 result.crs_wkt, description="potential release index"))
    return written
