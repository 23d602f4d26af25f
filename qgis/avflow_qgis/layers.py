"""Styled layers out of avflow's rasters: which QML, which name, the run's status."""

import os
import re
import shutil
import struct

from qgis.core import (QgsProcessingContext, QgsProcessingLayerPostProcessorInterface,
                       QgsProcessingUtils, QgsRasterLayer, QgsVectorLayer)

STYLES = os.path.join(os.path.dirname(__file__), "styles")

#: (what the file name holds, QML, what the layer name says), first match wins.
_KINDS = (
    ("exceedance_probability", "probability.qml", None),
    ("peak_pressure_class", "peak_pressure_class.qml", "peak pressure class (1 / 3 / 30 kPa)"),
    ("peak_pressure", "peak_pressure.qml", "peak pressure (kPa)"),
    ("peak_thickness", "thickness.qml", "peak flow thickness (m)"),
    ("deposit_thickness", "thickness.qml", "deposit thickness (m)"),
    ("peak_speed", "speed.qml", "peak speed (m/s)"),
    ("arrival_time", "time.qml", "arrival time (s)"),
    ("rest_time", "time.qml", "time of rest (s)"),
)

_STATUS = {"at_rest": "at rest", "stopped": "at rest", "not_stopped": "still moving at the end",
           "ended_by_rule": "ended by rule", "completed": "reached the end time",
           "max_steps": "stopped at the step limit", "failed": "failed"}


def _release_ids(name):
    """A region's maps of which release set each peak, and how many reached a cell."""
    stem = os.path.splitext(name)[0]
    return stem.endswith("_release") or stem.endswith("release_count")


def style_for(path):
    """The QML shipped for an avflow raster (by its file name), or None."""
    name = os.path.basename(path)
    if _release_ids(name):
        return None
    for key, qml, _ in _KINDS:
        if key in name:
            return os.path.join(STYLES, qml)
    return None


def describe(path):
    """What a raster holds, in words, from avflow's file name."""
    stem = os.path.splitext(os.path.basename(path))[0]
    match = re.search(r"(peak_\w+?|deposit_\w+?)_exceedance_probability_([0-9.]+)(\w*)$", stem)
    if match:
        what = match.group(1).replace("_", " ")
        unit = {"m_s": "m/s"}.get(match.group(3), match.group(3))
        return f"P({what} > {match.group(2)} {unit})".replace(" )", ")")
    if stem.endswith("release_count"):
        return "number of releases reaching each cell"
    if stem.endswith("_release"):
        return "release that set the " + describe(stem[:-len("_release")])
    for key, _, words in _KINDS:
        if words and stem.endswith(key):
            return words
    return stem


def add_sidecar_style(path):
    """Copy the raster's QML beside it (``x.tif`` -> ``x.qml``): QGIS applies it whenever
    the file is opened, also dragged in from a file manager."""
    qml = style_for(path)
    if qml:
        shutil.copyfile(qml, os.path.splitext(path)[0] + ".qml")
    return qml


def styled_raster(path, name):
    """A raster layer with its avflow style (tests and the report figure use it)."""
    layer = QgsRasterLayer(path, name, "gdal")
    qml = style_for(path)
    if layer.isValid() and qml:
        message, ok = layer.loadNamedStyle(qml)
        if not ok:
            raise RuntimeError(f"{qml}: {message}")
    return layer


class _Style(QgsProcessingLayerPostProcessorInterface):
    """Applies a QML and a name once Processing has loaded the layer into the project."""

    def __init__(self, qml, name):
        super().__init__()
        self.qml, self.name = qml, name

    def postProcessLayer(self, layer, context, feedback):  # noqa: N802
        if self.qml:
            layer.loadNamedStyle(self.qml)
        layer.setName(self.name)
        layer.triggerRepaint()


_KEEP = []  # post-processors must outlive the algorithm (Processing calls them afterwards)


def load_on_completion(context, path, name, qml=None, output="OUTPUT"):
    """Ask Processing to add ``path`` to the project when the algorithm ends, styled."""
    details = QgsProcessingContext.LayerDetails(name, context.project(), output)
    post = _Style(qml if qml is not None else style_for(path), name)
    _KEEP.append(post)
    details.setPostProcessor(post)
    context.addLayerToLoadOnCompletion(path, details)


# --- the run's status, from the NetCDF's attributes (GDAL, which QGIS has) -----------------


def run_status(nc_path):
    """``at rest`` or ``ended by rule, 64% still moving`` for an avflow NetCDF; "" when
    the file cannot say (an ensemble, a region, no GDAL netCDF driver)."""
    try:
        from osgeo import gdal
    except ImportError:
        return ""
    try:
        ds = gdal.Open(str(nc_path))
        meta = ds.GetMetadata() if ds is not None else {}
    except RuntimeError:
        return ""
    status = meta.get("NC_GLOBAL#status", "")
    if not status:
        return ""
    words = _STATUS.get(status, status.replace("_", " "))
    if status in ("ended_by_rule", "not_stopped"):
        moving = moving_percent(nc_path)
        if moving is not None:
            words += f", {_percent(moving)} still moving"
    if meta.get("NC_GLOBAL#runout_truncated", "0") not in ("0", ""):
        words += ", runout truncated by the map's edge"
    return words


def moving_percent(nc_path):
    """moving_volume_end over the volume there was (released + entrained + supplied), in
    percent, read with GDAL's multidimensional API (no numpy needed)."""
    try:
        from osgeo import gdal

        root = gdal.OpenEx(str(nc_path), gdal.OF_MULTIDIM_RASTER).GetRootGroup()

        def scalar(name):
            array = root.OpenMDArray(name)
            if array is None:
                return 0.0
            raw = array.Read(buffer_datatype=gdal.ExtendedDataType.Create(gdal.GDT_Float64))
            return struct.unpack("d", bytes(raw)[:8])[0]

        total = scalar("release_volume") + scalar("entrained_volume")
        try:
            total += scalar("supplied_volume")
        except Exception:
            pass
        return 100.0 * scalar("moving_volume_end") / total if total > 0 else None
    except Exception:
        return None


def _percent(share):
    if share != share:
        return "?"
    return "0%" if share == 0 else f"{share:.2g}%" if share < 10 else f"{share:.0f}%"


def status_from_summary(lines):
    """The status of ``avflow run``'s summary line, in the words of the layer names."""
    for line in lines:
        match = re.match(r"^[^:]+: (\w+)( \(([^)]*)\))?", line)
        if match and match.group(1) in _STATUS:
            words = _STATUS[match.group(1)]
            moving = re.search(r"([0-9.]+%) of the volume still moving", match.group(3) or "")
            if moving:
                words += f", {moving.group(1)} still moving"
            return words
    return ""


def temporary_folder(name):
    return QgsProcessingUtils.generateTempFilename(name)


def vector_layer(path, name, qml):
    layer = QgsVectorLayer(path, name, "ogr")
    if layer.isValid() and qml:
        layer.loadNamedStyle(os.path.join(STYLES, qml))
    return layer
