"""The regional maps as Cloud-Optimized GeoTIFFs (``avflow export OUTDIR/region.zarr``).

Each 2D map of the store, and each threshold of an exceedance map, becomes one COG
(GDAL's COG driver: 512 x 512 tiles, DEFLATE, internal overviews, the CRS of the store's
grid mapping, NODATA NaN for floats and 0 for release ids; counts have none, 0 is a count;
peak pressure in kPa, as every avflow export).
The store is read by strips of its chunk rows, written into a tiled temporary GeoTIFF, then
copied by the COG driver (which streams): the map is never held whole in memory. Each file
is read back (layout COG, size, CRS) before it is renamed into place.

Overviews: the maxima and probabilities ask GDAL for ``MAX`` (a zoomed-out view that never
hides a hazard), which GDAL 3.10 refuses for overviews; they are then ``NEAREST`` (the
value of a pixel, never an average), as the ids and counts always are. Each band's tags
say which (``overview_resampling``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from avflow.errors import AvflowError

#: Names of the region's store (as :mod:`avflow.region.orchestrate` writes it).
STORE = "region.zarr"
#: COG creation options (GDAL's COG driver).
COG_OPTIONS = {"COMPRESS": "DEFLATE", "BLOCKSIZE": "512", "OVERVIEWS": "AUTO",
               "BIGTIFF": "IF_SAFER"}
_UNIT_SUFFIX = {"m": "m", "m s-1": "m_s", "kPa": "kPa", "Pa": "Pa"}


class RegionExportError(AvflowError):
    """A region store that cannot be exported (one line naming it); exit code 2."""


#: The list of the chunks avflow region wrote, beside the store's own metadata.
MANIFEST = ".avflow-chunks.json"


def damaged(store: Path, why: str) -> RegionExportError:
    return RegionExportError(f"{store}: the store is damaged ({why}); run avflow region "
                             "again to write it anew")


def find_store(path) -> Path | None:
    """The region store ``path`` names (the store, or the region's output folder), or
    None when it names no region store; a store whose metadata cannot be read (truncated)
    is said to be damaged."""
    path = Path(path)
    for store in (path, path / STORE):
        if not store.is_dir():
            continue
        if not (store / ".zmetadata").is_file():
            if (store / ".zgroup").is_file() and (store / MANIFEST).is_file():
                raise damaged(store, "its metadata .zmetadata is missing")
            continue
        try:
            meta = json.loads((store / ".zmetadata").read_text())
            attrs = meta["metadata"][".zattrs"]
        except (OSError, ValueError, KeyError, TypeError) as err:
            if store.name.endswith(".zarr") or (store / MANIFEST).is_file():
                raise damaged(store, f"its metadata .zmetadata cannot be read: "
                                     f"{type(err).__name__}") from None
            continue
        if isinstance(attrs, dict) and attrs.get("source") == "avflow region":
            return store
    return None


def write_manifest(store: Path) -> None:
    """Record every chunk file of every array of ``store`` (those never written are
    absent by design: no release reached them), so that a chunk lost later is found."""
    chunks = {}
    for zarray in sorted(Path(store).rglob(".zarray")):
        folder = zarray.parent
        chunks[folder.relative_to(store).as_posix()] = sorted(
            p.relative_to(folder).as_posix() for p in folder.rglob("*")
            if p.is_file() and not p.name.startswith("."))
    (Path(store) / MANIFEST).write_text(json.dumps(chunks))


def check_chunks(store: Path, names) -> None:
    """Every chunk the manifest lists for the arrays ``names`` is there (a store written
    before the manifest: not checked)."""
    try:
        listed = json.loads((store / MANIFEST).read_text())
    except FileNotFoundError:
        return
    except (OSError, ValueError) as err:
        raise damaged(store, f"{MANIFEST} cannot be read: {type(err).__name__}") from None
    for name in names:
        for key in listed.get(name, ()) if isinstance(listed, dict) else ():
            if not (store / name / key).is_file():
                raise damaged(store, f"chunk {name}/{key} is missing")


def region_rasters(ds, store: Path, variables=None) -> list[tuple]:
    """``(file stem suffix, 2D DataArray, options)`` of each raster to write: every 2D map
    (or those named), and each threshold of the exceedance probabilities (and counts, when
    named)."""
    maps = [n for n, v in ds.data_vars.items() if v.dims == ("y", "x")]
    stacked = [n for n, v in ds.data_vars.items() if v.dims[1:] == ("y", "x")
               and v.ndim == 3]
    default = maps + [n for n in stacked if n.endswith("_exceedance_probability")]
    names = list(variables or default)
    unknown = [n for n in names if n not in maps + stacked]
    if unknown:
        why = ("; exceedance maps need a scenarios: block or merge.thresholds in the region "
               "file" if not stacked and any("_exceedance_" in n for n in unknown) else "")
        raise RegionExportError(f"{store}: no map named {', '.join(map(repr, unknown))}; "
                                f"available: {', '.join(maps + stacked)}{why}")
    out = []
    for name in names:
        var = ds[name]
        if var.ndim == 2:
            out.append((name, var, _options(name, var, {})))
            continue
        coord = ds[var.dims[0]]
        units = coord.attrs.get("units", "")
        for t in coord.values:
            label = f"{float(t):g}{_UNIT_SUFFIX.get(units, units.replace(' ', '_'))}"
            what = name.removesuffix("_exceedance_probability").removesuffix(
                "_exceedance_count").replace("_", " ")
            kind = "P" if name.endswith("_probability") else "runs with"
            out.append((f"{name}_{label}", var.sel({coord.name: t}), _options(
                name, var, {"description": f"{kind}({what} > {float(t):g} {units})",
                            "tags": {"variable": name, "threshold": f"{float(t):g}",
                                     "threshold_units": units}})))
    return out


def _options(name: str, var, extra: dict) -> dict:
    integer = var.dtype.kind in "iu"
    ids = name.endswith("_release")
    units = var.attrs.get("units")
    pascal = name == "peak_pressure" and units == "Pa"  # kPa, as every avflow export says
    return {"dtype": "int32" if integer else "float32",
            "nodata": 0 if ids else None if integer else np.nan,
            "resampling": "NEAREST" if integer else "MAX",
            "scale": 1e-3 if pascal else None,
            "description": extra.get("description", var.attrs.get("long_name", name)),
            "units": "kPa" if pascal else units,
            "tags": {**extra.get("tags", {}),
                     **({"comment": var.attrs["comment"]} if "comment" in var.attrs else {})}}


def export_region(path, outdir=None, variables=None) -> list[Path]:
    """Write the maps of a region store as COGs named ``region_<variable>.tif`` (next to
    the store unless ``outdir``); returns the paths written."""
    import xarray as xr

    from avflow.files import check_folder, check_target, inputs_of

    store = find_store(path)
    if store is None:
        raise RegionExportError(f"{path}: not a region store (region.zarr of avflow region)")
    try:
        ds = xr.open_zarr(store, consolidated=True)
    except Exception as err:  # noqa: BLE001 - one line naming the store
        raise RegionExportError(f"{store}: cannot be read as Zarr ({type(err).__name__}: "
                                f"{' '.join(str(err).split())[:120]})") from None
    with ds:
        inputs = inputs_of(store, ds.attrs)
        rasters = region_rasters(ds, store, variables)
        check_chunks(store, dict.fromkeys(var.name for _, var, _ in rasters))
        outdir = check_folder(store.parent if outdir is None else Path(outdir))
        stem = store.name.removesuffix(".zarr")
        targets = [outdir / f"{stem}_{name}.tif" for name, _, _ in rasters]
        for target in targets:
            # every one before the first is written; none the region's DEM, releases, file
            check_target(target, inputs, what="raster")
        wkt = _crs_wkt(ds)
        x, y = ds["x"].values, ds["y"].values
        chunk = int(next(iter(ds.data_vars.values())).encoding.get("chunks", (256,))[-1])
        written = []
        for target, (_, var, options) in zip(targets, rasters):
            try:
                write_cog(target, var, x, y, wkt, chunk, **options)
            except AvflowError:
                raise
            except Unreadable as err:  # a chunk of the store that cannot be decoded
                raise damaged(store, f"{var.name} cannot be read: {err}") from None
            except Exception as err:  # noqa: BLE001 - the output's write: never the store's
                from avflow.files import OutputWriteError, write_error

                if isinstance(err, OSError):
                    raise
                raise (write_error(target, err) or OutputWriteError(
                    f"cannot write {target}: {type(err).__name__}: "
                    f"{' '.join(str(err).split())[:120]}")) from None
            written.append(target)
    return written


def _crs_wkt(ds) -> str | None:
    if "crs" in ds.variables:
        attrs = ds["crs"].attrs
        return attrs.get("crs_wkt") or attrs.get("spatial_ref") or None
    return None


class Unreadable(Exception):
    """A block of the store that cannot be read (raised while writing a COG: the store's
    fault, not the output's)."""


def _read_block(var, r0: int, r1: int) -> np.ndarray:
    try:
        return np.asarray(var[r0:r1].values)
    except Exception as err:  # noqa: BLE001 - a codec's or zarr's error, any type
        raise Unreadable(f"{type(err).__name__}: {' '.join(str(err).split())[:80]}") from None


def write_cog(path, var, x, y, wkt, strip: int, *, dtype, nodata, resampling, scale=None,
              description=None, units=None, tags=None) -> Path:
    """One 2D DataArray (north first) as a COG, by strips of ``strip`` rows; written to a
    temporary name, read back (LAYOUT=COG, shape, CRS), then renamed into place."""
    import tempfile

    import rasterio
    import rasterio.shutil
    from rasterio.transform import from_origin
    from rasterio.windows import Window

    from avflow.files import atomic_write

    path = Path(path)
    height, width = var.shape
    dx, dy = float(x[1] - x[0]), float(y[0] - y[1])
    transform = from_origin(float(x[0]) - 0.5 * dx, float(y[0]) + 0.5 * dy, dx, dy)
    used = {"resampling": resampling}

    def write(tmp: Path) -> None:
        with tempfile.TemporaryDirectory(prefix=".cog-", dir=path.parent) as folder:
            src = Path(folder) / "tiled.tif"
            with rasterio.open(src, "w", driver="GTiff", width=width, height=height, count=1,
                               dtype=dtype, crs=wkt, transform=transform, nodata=nodata,
                               tiled=True, blockxsize=512, blockysize=512, compress="deflate",
                               BIGTIFF="IF_SAFER") as dst:
                for r0 in range(0, height, strip):
                    r1 = min(r0 + strip, height)
                    block = _read_block(var, r0, r1)
                    if scale is not None:
                        block = block * np.float32(scale)
                    if nodata is not None and np.dtype(dtype).kind != "f":
                        block = np.where(np.isfinite(block), block, nodata)
                    dst.write(block.astype(dtype), 1, window=Window(0, r0, width, r1 - r0))
                if description:
                    dst.set_band_description(1, description)
                if units:
                    dst.set_band_unit(1, units)
            tmp.unlink(missing_ok=True)
            for method in dict.fromkeys((resampling, "NEAREST")):
                try:
                    _tag(src, method)
                    rasterio.shutil.copy(src, tmp, driver="COG", RESAMPLING=method,
                                         **COG_OPTIONS)
                    used["resampling"] = method
                    break
                except Exception as err:  # noqa: BLE001 - GDAL refuses MAX for overviews
                    tmp.unlink(missing_ok=True)
                    if method == "NEAREST" or "resampling" not in str(err).lower():
                        raise

    def _tag(src: Path, method: str) -> None:
        with rasterio.open(src, "r+") as dst:
            dst.update_tags(1, overview_resampling=method.lower(),
                            **{k: str(v) for k, v in (tags or {}).items()})

    def verify(tmp: Path) -> None:
        with rasterio.open(tmp) as src:
            layout = src.tags(ns="IMAGE_STRUCTURE").get("LAYOUT")
            if layout != "COG" or src.shape != (height, width) or not src.is_tiled:
                raise OSError(f"the COG reads back wrong (layout {layout}, shape "
                              f"{src.shape})")
            if wkt and src.crs is None:
                raise OSError("the COG reads back without its CRS")

    return atomic_write(path, write, verify)
