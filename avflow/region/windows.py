"""Releases of a region and the window of the DEM each runs in.

Windows are in the DEM's pixel rows and columns (row 0 at the north edge, as GDAL stores
them): ``(r0, r1, c0, c1)``, end exclusive. The DEM is only ever read by windows
(``rasterio`` ``window=``); a release's run gets its window as a GeoTIFF of its own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from avflow.terrain.raster import same_crs


@dataclass(frozen=True)
class DemInfo:
    """What the region needs of its DEM: size, georeferencing, CRS (no values)."""

    path: str
    width: int
    height: int
    x0: float  #: west edge, m
    y0: float  #: north edge, m
    dx: float  #: column spacing, m (> 0)
    dy: float  #: row spacing, m (> 0, rows go south)
    crs_wkt: str | None
    dtype: str

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        return (self.x0, self.y0 - self.height * self.dy, self.x0 + self.width * self.dx,
                self.y0)

    def x(self, c0: int = 0, c1: int | None = None) -> np.ndarray:
        """Cell-centre x of columns c0..c1."""
        c1 = self.width if c1 is None else c1
        return self.x0 + self.dx * (np.arange(c0, c1) + 0.5)

    def y(self, r0: int = 0, r1: int | None = None) -> np.ndarray:
        """Cell-centre y of rows r0..r1 (descending: north first)."""
        r1 = self.height if r1 is None else r1
        return self.y0 - self.dy * (np.arange(r0, r1) + 0.5)

    @property
    def whole(self) -> tuple[int, int, int, int]:
        return (0, self.height, 0, self.width)


def dem_info(path: str) -> DemInfo:
    import rasterio

    with rasterio.open(path) as src:
        t = src.transform
        if t.a < 0 or t.e > 0:
            raise ValueError(f"{path}: only north-up rasters with columns going east are "
                             "supported; warp it first (gdalwarp)")
        return DemInfo(str(path), src.width, src.height, t.c, t.f, t.a, -t.e,
                       src.crs.to_wkt() if src.crs is not None else None, src.dtypes[0])


def read_window(dem: DemInfo, window) -> np.ndarray:
    """The DEM's values in a window (north first), NODATA as NaN, float64."""
    import rasterio
    from rasterio.windows import Window

    r0, r1, c0, c1 = window
    with rasterio.open(dem.path) as src:
        band = src.read(1, window=Window(c0, r0, c1 - c0, r1 - r0), masked=True)
    return band.astype(float).filled(np.nan)


def write_window(dem: DemInfo, window, path) -> None:
    """The DEM's window as a GeoTIFF (its own dtype when it is a float: the values the
    region's run reads are then those of the DEM to the bit)."""
    from avflow.terrain.raster import write_tif

    r0, r1, c0, c1 = window
    values = read_window(dem, window)
    dtype = dem.dtype if dem.dtype in ("float32", "float64") else "float64"
    write_tif(path, values[::-1], dem.x(c0, c1), dem.y(r0, r1)[::-1], dem.crs_wkt,
              dtype=dtype)


@dataclass(frozen=True)
class ReleaseArea:
    """One release polygon: its id, geometry (WKB), thickness, area, box; ``problem`` says
    why it cannot run ("" when it can)."""

    id: int
    index: int  #: feature order in the layer, from 0
    wkb: bytes
    thickness: float | None
    area: float  #: m^2, of the polygon
    bbox: tuple  #: (xmin, ymin, xmax, ymax), m
    problem: str = ""
    #: values of the attributes that ``scenarios.return_periods`` names (m)
    attributes: dict | None = None
    #: a patch of a release raster: :class:`Patch` (None: a polygon)
    patch: "Patch | None" = None
    #: what the result depends on besides the polygon and thickness (a patch's values)
    fingerprint: str = ""
    #: m^2 of the polygon outside the DEM's box: not released (``area`` is the rest)
    area_outside: float = 0.0


@dataclass(frozen=True)
class Patch:
    """One connected patch of a release raster, found again on a worker from a window of
    the raster: the component with the ``seed`` cell (rows, columns in the DEM's pixels)."""

    raster: str
    box: tuple  #: (r0, r1, c0, c1), DEM pixels, end exclusive: the patch's cells
    seed: tuple  #: (row, col), DEM pixels: its first cell in scan order
    offset: tuple  #: (rows, cols) of the raster's first pixel in the DEM's pixels
    connectivity: int
    mean: float = math.nan  #: m, the mean thickness of its cells

    def values(self, dem: "DemInfo", window) -> np.ndarray:
        """The patch's thickness on a DEM window (north first, 0 outside the patch)."""
        import rasterio
        from rasterio.windows import Window
        from scipy import ndimage

        r0, r1, c0, c1 = self.box
        orow, ocol = self.offset
        with rasterio.open(self.raster) as src:
            band = src.read(1, window=Window(c0 - ocol, r0 - orow, c1 - c0, r1 - r0),
                            masked=True)
        h = band.astype(float).filled(0.0)
        h = np.where(np.isfinite(h) & (h > 0), h, 0.0)
        labels, _ = ndimage.label(h > 0, structure=_structure(self.connectivity))
        mine = labels == labels[self.seed[0] - r0, self.seed[1] - c0]
        w0, w1, v0, v1 = window
        out = np.zeros((w1 - w0, v1 - v0))
        out[r0 - w0:r1 - w0, c0 - v0:c1 - v0] = np.where(mine, h, 0.0)
        return out


def _structure(connectivity: int) -> np.ndarray:
    return np.ones((3, 3), bool) if connectivity == 8 else np.array(
        [[0, 1, 0], [1, 1, 1], [0, 1, 0]], bool)


def read_raster_releases(region, dem: DemInfo) -> list[ReleaseArea]:
    """Every connected patch of cells above 0 of the region's release raster, one release
    each (ids 1, 2... in scan order of their first cell). The raster is read whole (its
    labels: 4 bytes a cell); each release keeps only its box and first cell."""
    import hashlib

    import rasterio
    import shapely
    from rasterio.features import shapes
    from rasterio.transform import from_origin
    from scipy import ndimage

    from avflow.region.spec import RegionError

    spec = region.releases
    with rasterio.open(spec.raster) as src:
        t = src.transform
        _check_raster_fits(region, src.width, src.height)
        h = src.read(1, masked=True).astype(float).filled(0.0)
    orow, ocol = round((t.f - dem.y0) / -dem.dy), round((t.c - dem.x0) / dem.dx)
    h = np.where(np.isfinite(h) & (h > 0), h, 0.0)
    labels, n = ndimage.label(h > 0, structure=_structure(spec.connectivity))
    if n == 0:
        raise RegionError(f"{spec.raster}: holds no cell above 0 (no release)", region.path,
                          "releases.raster")
    out = []
    xmin, ymin, xmax, ymax = dem.bounds
    for k, sl in enumerate(ndimage.find_objects(labels)):
        rid = k + 1
        mine = labels[sl] == rid
        rows, cols = np.nonzero(mine)
        first = (int(rows[0]) + sl[0].start + orow, int(cols[0]) + sl[1].start + ocol)
        r0, r1 = sl[0].start + orow, sl[0].stop + orow
        c0, c1 = sl[1].start + ocol, sl[1].stop + ocol
        transform = from_origin(dem.x0 + c0 * dem.dx, dem.y0 - r0 * dem.dy, dem.dx, dem.dy)
        geom = shapely.union_all([shapely.geometry.shape(g) for g, _ in shapes(
            mine.astype(np.uint8), mask=mine, transform=transform, connectivity=8)])
        values = np.where(mine, h[sl], 0.0)
        thick = float(values[mine].mean())
        box = tuple(float(v) for v in geom.bounds)
        problem = ""
        if r0 < 0 or c0 < 0 or r1 > dem.height or c1 > dem.width:
            problem = (f"outside the DEM (its box {_box(box)} against the DEM's "
                       f"{_box((xmin, ymin, xmax, ymax))})")
        digest = hashlib.sha256(np.ascontiguousarray(values).tobytes()
                                + repr(values.shape).encode()).hexdigest()[:16]
        thickness = spec.thickness  # None: the raster's values
        out.append(ReleaseArea(rid, k, shapely.to_wkb(geom), thickness,
                               float(mine.sum()) * dem.dx * dem.dy, box, problem, None,
                               Patch(spec.raster, (r0, r1, c0, c1), first, (orow, ocol),
                                     spec.connectivity, thick), f"raster:{digest}"))
    return out


def read_dem_releases(region) -> list[ReleaseArea]:
    """The potential release areas of the region's DEM (``releases.from_dem``), numbered as
    ``avflow release-areas`` numbers them; each area's thickness is ``releases.thickness``,
    else its Swiss-rule thickness (with ``d0``), else its return periods'."""
    import shapely

    from avflow.terrain.release_areas import PRAError, PRASettings, potential_release_areas
    from avflow.region.spec import RegionError

    spec = region.releases
    options = {k: v for k, v in spec.from_dem.items() if k != "forest"}
    try:
        result = potential_release_areas(region.dem, PRASettings(**options),
                                         forest=spec.from_dem.get("forest"))
    except PRAError as err:
        raise RegionError(str(err), region.path, "releases.from_dem") from None
    if not result.areas:
        raise RegionError(f"{region.dem}: no potential release area (slope band, roughness, "
                          "forest, minimum area)", region.path, "releases.from_dem")
    periods = any(rs.return_period is not None for rs in region.scenarios)
    out = []
    for k, a in enumerate(result.areas):
        thickness = spec.thickness if spec.thickness is not None else a.get("thickness")
        problem = "" if thickness is not None or periods else (
            "no thickness: give releases.thickness, from_dem.d0 or "
            "scenarios.return_periods")
        geom = a["geometry"]
        out.append(ReleaseArea(int(a["id"]), k, shapely.to_wkb(geom), thickness,
                               float(geom.area), tuple(float(v) for v in geom.bounds),
                               problem))
    return out


#: Bytes a cell of a release raster takes while it is read whole: the values, their mask,
#: as floats, the connected-component labels.
RASTER_BYTES_PER_CELL = 22


def _check_raster_fits(region, width: int, height: int) -> None:
    """A release raster too large to be read whole is refused before it is read (a
    100,000 x 100,000 raster ran out of memory), with the advice that applies to it."""
    from avflow.region.spec import RegionError
    from avflow.simulation.resources import default_max_memory, human

    limit, source = default_max_memory()
    need = float(width) * float(height) * RASTER_BYTES_PER_CELL
    if limit is not None and need > limit:
        raise RegionError(f"{region.releases.raster}: {width:,} x {height:,} cells; reading "
                          f"it whole needs about {human(need)}, more than the memory limit "
                          f"of {human(limit)} ({source}): crop the raster to the release "
                          "areas, coarsen it, or give them as polygons (releases.path)",
                          region.path, "releases.raster")


def read_releases(region, dem: DemInfo) -> list[ReleaseArea]:
    """Every feature of the release layer; features that cannot run carry their problem
    (outside the DEM, zero area, another CRS, no thickness...) and are reported, not run."""
    import pyogrio
    import shapely

    from avflow.region.spec import RegionError

    spec = region.releases
    if spec.raster is not None:
        return read_raster_releases(region, dem)
    if spec.from_dem is not None:
        return read_dem_releases(region)
    try:
        meta, _, wkb, columns = pyogrio.raw.read(spec.path)
    except Exception as err:  # noqa: BLE001 - GDAL's error: one line naming the file
        raise RegionError(f"{spec.path}: cannot be read as a vector file "
                          f"({type(err).__name__}: {' '.join(str(err).split())})",
                          region.path, "releases.path") from None
    fields = {str(n): c for n, c in zip(meta["fields"], columns)}
    lower = {k.lower(): k for k in fields}
    ids = None
    if spec.id_field is not None:
        if spec.id_field.lower() not in lower:
            raise RegionError(f"{spec.path} has no attribute {spec.id_field!r} (it has: "
                              f"{', '.join(fields) or 'none'})", region.path,
                              "releases.id_field")
        ids = fields[lower[spec.id_field.lower()]]
    by_period = {rs.thickness for rs in region.scenarios if isinstance(rs.thickness, str)}
    periods = any(rs.return_period is not None for rs in region.scenarios)
    thick_name = spec.thickness_field or ("thickness" if spec.thickness is None
                                          and not periods else None)
    named = {}
    for name in sorted(by_period):
        if name.lower() not in lower:
            rp = next(rs.return_period for rs in region.scenarios if rs.thickness == name)
            raise RegionError(f"{spec.path} has no attribute {name!r} (it has: "
                              f"{', '.join(fields) or 'none'}); the thickness of "
                              f"{rp} years", region.path, "scenarios.return_periods")
        named[name] = fields[lower[name.lower()]]
    thicknesses = None
    if thick_name is not None:
        if thick_name.lower() not in lower:
            raise RegionError(f"{spec.path} has no attribute {thick_name!r} (it has: "
                              f"{', '.join(fields) or 'none'}); give releases.thickness or "
                              "releases.thickness_field", region.path,
                              "releases.thickness_field")
        thicknesses = fields[lower[thick_name.lower()]]
    layer_crs = meta.get("crs")
    crs_problem = ""
    if layer_crs and dem.crs_wkt and not same_crs(_wkt(layer_crs), dem.crs_wkt):
        crs_problem = (f"its CRS ({layer_crs}) differs from the DEM's; reproject the layer "
                       "(ogr2ogr -t_srs)")
    geometries = shapely.from_wkb(wkb)
    xmin, ymin, xmax, ymax = dem.bounds
    out, seen = [], {}
    for k, geom in enumerate(geometries):
        rid = k + 1
        problem = ""
        if ids is not None:
            try:
                value = ids[k]
                rid = int(value)
                if rid != value or rid < 1:
                    raise ValueError
            except (TypeError, ValueError, OverflowError):
                raise RegionError(f"{spec.path}: feature {k} has {spec.id_field} "
                                  f"{ids[k]!r}; ids must be positive integers", region.path,
                                  "releases.id_field") from None
        if rid in seen:
            raise RegionError(f"{spec.path}: features {seen[rid]} and {k} have the same id "
                              f"{rid}; ids must be unique", region.path, "releases.id_field")
        seen[rid] = k
        thickness = spec.thickness
        if thicknesses is not None:
            thickness = _number(thicknesses[k])
            if thickness is None or not thickness > 0:
                problem = f"thickness {thicknesses[k]!r} is not a positive number of metres"
        attributes = {name: _number(values[k]) for name, values in named.items()}
        for name, value in attributes.items():
            if value is None or not value > 0:
                problem = (f"{name} {named[name][k]!r} is not a positive number of metres "
                           "(scenarios.return_periods)")
        if geom is None or geom.is_empty:
            problem, area, box = "empty geometry", 0.0, (math.nan,) * 4
        else:
            area, box = float(geom.area), tuple(float(v) for v in geom.bounds)
            if geom.geom_type not in ("Polygon", "MultiPolygon"):
                problem = f"a {geom.geom_type}, not a polygon"
            elif not area > 0:
                problem = "zero area"
            elif box[0] >= xmax or box[2] <= xmin or box[1] >= ymax or box[3] <= ymin:
                problem = (f"outside the DEM (its box {_box(box)} against the DEM's "
                           f"{_box(dem.bounds)})")
        outside = 0.0
        if not problem and geom is not None and not (
                box[0] >= xmin and box[2] <= xmax and box[1] >= ymin and box[3] <= ymax):
            # the run releases only the cells on the DEM: the area says what is released
            inside = float(shapely.intersection(geom, shapely.box(*dem.bounds)).area)
            outside, area = area - inside, inside
        out.append(ReleaseArea(rid, k, b"" if geom is None else shapely.to_wkb(geom), thickness,
                               area, box, crs_problem or problem, attributes or None,
                               area_outside=outside))
    if not out:
        raise RegionError(f"{spec.path}: holds no feature", region.path, "releases.path")
    return out


def _wkt(crs) -> str:
    try:
        from pyproj import CRS

        return CRS.from_user_input(crs).to_wkt()
    except Exception:  # noqa: BLE001 - compared as text then
        return str(crs)


def _number(value) -> float | None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _box(box) -> str:
    return "[" + ", ".join(f"{v:.6g}" for v in box) + "]"


def pixel_box(dem: DemInfo, bbox) -> tuple[int, int, int, int]:
    """The pixels a map box touches, clipped to the DEM."""
    xmin, ymin, xmax, ymax = bbox
    c0 = math.floor((xmin - dem.x0) / dem.dx)
    c1 = math.ceil((xmax - dem.x0) / dem.dx)
    r0 = math.floor((dem.y0 - ymax) / dem.dy)
    r1 = math.ceil((dem.y0 - ymin) / dem.dy)
    return (max(r0, 0), min(max(r1, r0 + 1), dem.height), max(c0, 0),
            min(max(c1, c0 + 1), dem.width))


def window_for(dem: DemInfo, bbox, buffer: float) -> tuple[int, int, int, int]:
    """The release's pixel box grown by ``buffer`` metres on every side, clipped."""
    r0, r1, c0, c1 = pixel_box(dem, bbox)
    nr, nc = math.ceil(buffer / dem.dy), math.ceil(buffer / dem.dx)
    return (max(r0 - nr, 0), min(r1 + nr, dem.height), max(c0 - nc, 0),
            min(c1 + nc, dem.width))


def estimate_buffer(dem: DemInfo, bbox, rules) -> float:
    """Buffer (m) from the drop below the release: ``(z_top - z_low) / tan(angle)``, with
    z_top the highest DEM cell of the release's box and z_low the lowest within
    ``search_radius`` of it, clipped to ``[min_buffer, search_radius]``."""
    if rules.buffer is not None:
        return float(rules.buffer)
    import warnings

    box = pixel_box(dem, bbox)
    around = window_for(dem, bbox, rules.search_radius)
    with warnings.catch_warnings():  # a box of NODATA only: NaN, the largest buffer below
        warnings.simplefilter("ignore", RuntimeWarning)
        top = np.nanmax(read_window(dem, box)) if _has_data(dem, box) else math.nan
        low = np.nanmin(read_window(dem, around)) if _has_data(dem, around) else math.nan
    drop = top - low
    if not math.isfinite(drop):
        return float(rules.search_radius)
    buffer = drop / math.tan(math.radians(rules.runout_angle_deg))
    return float(min(max(buffer, rules.min_buffer), rules.search_radius))


def _has_data(dem: DemInfo, box) -> bool:
    return box[1] > box[0] and box[3] > box[2]


def rule_thickness(dem: DemInfo, wkb: bytes, rule) -> tuple[float, float, float]:
    """``(thickness, mean elevation, mean slope in degrees)`` of a release by a
    :class:`~avflow.region.spec.ThicknessRule`, over the DEM cells whose centres lie in
    the polygon (those a run releases), slopes by central differences."""
    import shapely
    from rasterio.features import rasterize
    from rasterio.transform import from_origin

    geom = shapely.from_wkb(wkb)
    r0, r1, c0, c1 = pixel_box(dem, geom.bounds)
    r0, r1, c0, c1 = max(r0 - 1, 0), min(r1 + 1, dem.height), max(c0 - 1, 0), \
        min(c1 + 1, dem.width)
    z = read_window(dem, (r0, r1, c0, c1))
    inside = rasterize([(geom, 1)], out_shape=z.shape, fill=0, dtype="uint8",
                       transform=from_origin(dem.x0 + c0 * dem.dx, dem.y0 - r0 * dem.dy,
                                             dem.dx, dem.dy)).astype(bool)
    inside &= np.isfinite(z)
    if not inside.any():
        raise ValueError("no DEM cell centre with data inside the polygon (for the "
                         "thickness rule)")
    gy, gx = np.gradient(z, dem.dy, dem.dx) if min(z.shape) > 1 else (z * 0, z * 0)
    slope = np.degrees(np.arctan(np.hypot(gx, gy)))
    elevation = float(np.mean(z[inside]))
    psi = float(np.nanmean(slope[inside]))
    d = rule.d0 + rule.gradient * (elevation - rule.reference_elevation) / 100.0
    if rule.slope_correction:
        s, c = math.sin(math.radians(psi)), math.cos(math.radians(psi))
        if not s - 0.202 * c > 0.05:
            raise ValueError(f"mean slope {psi:.1f} degrees: too gentle for the slope "
                             "correction of the thickness rule (f(psi) needs psi > 14 deg)")
        d *= 0.291 / (s - 0.202 * c)
    if not d > 0:
        raise ValueError(f"the thickness rule gives {d:.3g} m at a mean elevation of "
                         f"{elevation:.0f} m")
    return float(d), elevation, psi
