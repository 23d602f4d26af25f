"""The avflow Processing algorithms. Each writes the files avflow reads (a scenario,
ensemble or region YAML beside the outputs, the layers as GeoPackage/GeoTIFF), runs the
avflow command line as a separate process (:mod:`.process`) and returns its maps as styled
layers (:mod:`.layers`). The YAML stays in the output folder: ``avflow run FOLDER/NAME.yaml``
repeats the run from a terminal."""

import json
import math
import os
import re

from qgis.core import (QgsCoordinateTransform, QgsFeature, QgsField, QgsFields,
                       QgsProcessing, QgsProcessingAlgorithm, QgsProcessingException,
                       QgsProcessingOutputFile, QgsProcessingOutputFolder,
                       QgsProcessingOutputMultipleLayers, QgsProcessingOutputString,
                       QgsProcessingParameterBoolean, QgsProcessingParameterEnum,
                       QgsProcessingParameterField, QgsProcessingParameterFile,
                       QgsProcessingParameterFileDestination,
                       QgsProcessingParameterFolderDestination, QgsProcessingParameterNumber,
                       QgsProcessingParameterRasterLayer, QgsProcessingParameterString,
                       QgsProcessingParameterVectorLayer, QgsProject, QgsVectorFileWriter,
                       QgsWkbTypes)
from qgis.PyQt.QtCore import QVariant

from . import layers, process

#: Friction laws offered, with the scenario's law name.
LAWS = ("samosat", "voellmy", "coulomb", "pouliquen")
LAW_LABELS = ("samosAT (AvaFrame's snow law): mu", "Voellmy: mu and xi",
              "Coulomb: friction angle delta", "Pouliquen: delta1, delta2 and d")
#: Material: the density (kg/m^3) it sets, AvaFrame's snow and avflow's debris default.
MATERIALS = (("snow (200 kg/m³)", 200.0), ("debris (2000 kg/m³)", 2000.0))
DATA_SUFFIXES = (".asc", ".tif", ".tiff", ".nc")


# --- YAML out of plain values (PyYAML is not needed; YAML 1.1 traps avoided) -------------


def _scalar(value):
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise QgsProcessingException(f"not a finite number: {value}")
        text = repr(value)
        if "e" in text or "E" in text:  # PyYAML reads 1e-3 as a string: write it out
            text = f"{value:.12f}".rstrip("0")
            text = text + "0" if text.endswith(".") else text
        return text
    return json.dumps(str(value), ensure_ascii=False)  # a double-quoted YAML string


def to_yaml(value, indent=0):
    pad = " " * indent
    if isinstance(value, dict):
        lines = []
        for key, item in value.items():
            if isinstance(item, dict) and item:
                lines.append(f"{pad}{key}:\n{to_yaml(item, indent + 2)}")
            elif isinstance(item, (list, tuple)) and any(isinstance(i, dict) for i in item):
                lines.append(f"{pad}{key}:")
                for entry in item:
                    body = to_yaml(entry, indent + 4).lstrip()
                    lines.append(f"{pad}  - {body}")
            elif isinstance(item, (list, tuple)):
                lines.append(f"{pad}{key}: [{', '.join(_scalar(i) for i in item)}]")
            else:
                lines.append(f"{pad}{key}: {_scalar(item)}")
        return "\n".join(lines)
    return pad + _scalar(value)


def write_text(path, text):
    """Write to a temporary name and rename: never a half-written file."""
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(text)
    os.replace(tmp, path)


def _safe_name(text):
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", text.strip()).strip("._")
    return name or "run"


# --- layers to files avflow reads ---------------------------------------------------------


def dem_file(layer, folder, cell_size, feedback):
    """A DEM file avflow reads: the layer's own file where it is one, else a GeoTIFF copy;
    resampled (average) when ``cell_size`` is coarser than the DEM's cells."""
    source = layer.source().split("|")[0]
    res = max(layer.rasterUnitsPerPixelX(), layer.rasterUnitsPerPixelY())
    usable = os.path.isfile(source) and source.lower().endswith(DATA_SUFFIXES)
    if usable and not (cell_size and cell_size > res * 1.0001):
        return source
    from osgeo import gdal  # QGIS's own GDAL

    target = os.path.join(folder, "dem.tif")
    options = dict(format="GTiff", creationOptions=["COMPRESS=DEFLATE", "TILED=YES"])
    tmp = target + ".tmp.tif"
    if cell_size and cell_size > res * 1.0001:
        feedback.pushInfo(f"DEM resampled from {res:g} m to {cell_size:g} m cells (average)")
        out = gdal.Warp(tmp, source, xRes=cell_size, yRes=cell_size, resampleAlg="average",
                        **options)
    else:
        out = gdal.Translate(tmp, source, **options)
    if out is None:
        raise QgsProcessingException(f"{source}: GDAL could not copy the DEM")
    out = None  # noqa: F841 (closes the file)
    os.replace(tmp, target)
    return target


def vector_file(layer, path, crs, context, feedback, thickness_field=None, geometry=None):
    """The features of ``layer`` (a Processing feature source: safe to read off the main
    thread) in ``crs`` as a GeoPackage avflow reads; with ``thickness_field`` its values go
    to the ``thickness`` attribute avflow looks for."""
    layer = _Source(layer)
    fields = QgsFields()
    if thickness_field:
        fields.append(QgsField("thickness", QVariant.Double))
    options = QgsVectorFileWriter.SaveVectorOptions()
    options.driverName = "GPKG"
    options.layerName = os.path.splitext(os.path.basename(path))[0]
    tmp = path + ".tmp.gpkg"
    if os.path.exists(tmp):
        os.remove(tmp)
    target_crs = crs if crs.isValid() else layer.crs()
    writer = QgsVectorFileWriter.create(tmp, fields, layer.wkbType(), target_crs,
                                        context.transformContext(), options)
    if writer.hasError():
        raise QgsProcessingException(f"{path}: {writer.errorMessage()}")
    transform = None
    if crs.isValid() and layer.crs().isValid() and layer.crs() != crs:
        transform = QgsCoordinateTransform(layer.crs(), crs, context.transformContext())
        feedback.pushInfo(f"{layer.name()}: reprojected from {layer.crs().authid()} to "
                          f"{crs.authid() or crs.description()}")
    count = 0
    for feature in layer.getFeatures():
        geom = feature.geometry()
        if geom.isNull() or geom.isEmpty():
            continue
        if geometry is not None and QgsWkbTypes.geometryType(geom.wkbType()) != geometry:
            continue
        if transform is not None:
            geom.transform(transform)
        out = QgsFeature(fields)
        out.setGeometry(geom)
        if thickness_field:
            value = feature[thickness_field]
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise QgsProcessingException(
                    f"{layer.name()}: feature {feature.id()}: field {thickness_field!r} is "
                    f"not a number ({value!r})")
            out.setAttribute(0, value)
        writer.addFeature(out)
        count += 1
    del writer
    if not count:
        os.remove(tmp)
        raise QgsProcessingException(f"{layer.name()}: no features to use")
    os.replace(tmp, path)
    return path


class _Source:
    """One interface over a feature source and a vector layer (name, CRS, features)."""

    def __init__(self, source):
        self.source = source

    def name(self):
        s = self.source
        return s.sourceName() if hasattr(s, "sourceName") else s.name()

    def crs(self):
        s = self.source
        return s.sourceCrs() if hasattr(s, "sourceCrs") else s.crs()

    def wkbType(self):  # noqa: N802
        return self.source.wkbType()

    def getFeatures(self):  # noqa: N802
        return self.source.getFeatures()


def _relative(path, folder):
    """Inside the output folder: relative (the folder can move); else absolute."""
    path, folder = os.path.abspath(path), os.path.abspath(folder)
    if os.path.commonpath([path, folder]) == folder:
        return os.path.relpath(path, folder)
    return path


# --- the algorithms -----------------------------------------------------------------------


class _Base(QgsProcessingAlgorithm):
    NAME = ""
    LABEL = ""
    HELP = ""

    def createInstance(self):  # noqa: N802
        return type(self)()

    def name(self):
        return self.NAME

    def displayName(self):  # noqa: N802
        return self.LABEL

    def group(self):
        return "avflow"

    def groupId(self):  # noqa: N802
        return "avflow"

    def shortHelpString(self):  # noqa: N802
        return self.HELP

    def _folder(self, parameters, context):
        folder = self.parameterAsString(parameters, "OUTPUT_FOLDER", context)
        os.makedirs(folder, exist_ok=True)
        return folder

    def _export_and_load(self, target, folder, context, feedback, prefix, status=""):
        """``avflow export TARGET`` to GeoTIFFs in ``folder`` with their QML beside them;
        every map queued to load, styled; returns the GeoTIFF paths."""
        lines = process.run(["export", target, "--format", "tif", "-o", folder], feedback)
        tifs = [p for p in process.written(lines) if p.lower().endswith((".tif", ".tiff"))]
        for path in tifs:
            layers.add_sidecar_style(path)
            name = f"{prefix}: {layers.describe(path)}" + (f" [{status}]" if status else "")
            layers.load_on_completion(context, path, name)
        return tifs


class _ScenarioInputs(_Base):
    """The inputs a scenario needs, shared by Run a scenario and Ensemble."""

    def _scenario_parameters(self):
        self.addParameter(QgsProcessingParameterRasterLayer("DEM", "DEM (elevation, m)"))
        self.addParameter(QgsProcessingParameterVectorLayer(
            "RELEASE", "Release areas (polygons)", [QgsProcessing.TypeVectorPolygon]))
        self.addParameter(QgsProcessingParameterField(
            "THICKNESS_FIELD", "Release thickness field (m, normal to the slope)",
            parentLayerParameterName="RELEASE", type=QgsProcessingParameterField.Numeric,
            optional=True))
        self.addParameter(QgsProcessingParameterNumber(
            "THICKNESS", "Release thickness where no field is chosen (m)",
            QgsProcessingParameterNumber.Double, 1.0, minValue=0.001))
        self.addParameter(QgsProcessingParameterEnum("LAW", "Friction law", LAW_LABELS,
                                                     defaultValue=0))
        number = QgsProcessingParameterNumber.Double
        self.addParameter(QgsProcessingParameterNumber(
            "MU", "mu (samosAT, Voellmy)", number, 0.22, minValue=0.0))
        self.addParameter(QgsProcessingParameterNumber(
            "XI", "xi (Voellmy, m/s²)", number, 1000.0, minValue=1e-6))
        self.addParameter(QgsProcessingParameterNumber(
            "DELTA", "delta (Coulomb) or delta1 (Pouliquen), degrees", number, 20.0,
            minValue=0.0, maxValue=89.9))
        self.addParameter(QgsProcessingParameterNumber(
            "DELTA2", "delta2 (Pouliquen), degrees", number, 30.0, minValue=0.0,
            maxValue=89.9))
        self.addParameter(QgsProcessingParameterNumber(
            "POULIQUEN_D", "d (Pouliquen, m)", number, 1.0, minValue=1e-6))
        self.addParameter(QgsProcessingParameterEnum(
            "MATERIAL", "Material", [m[0] for m in MATERIALS], defaultValue=0))
        self.addParameter(QgsProcessingParameterNumber(
            "CELL_SIZE", "Cell size (m)", number, 10.0, minValue=0.01))
        self.addParameter(QgsProcessingParameterEnum(
            "ORDER", "Order of the scheme", ["1 (the seed's scheme)", "2 (sharper fronts)"],
            defaultValue=0))
        self.addParameter(QgsProcessingParameterNumber(
            "END_TIME", "End time (s)", number, 400.0, minValue=0.1))
        self.addParameter(QgsProcessingParameterBoolean(
            "STOP_RULE", "End when the kinetic energy falls to 1% of its peak (AvaFrame's rule)",
            True))
        self.addParameter(QgsProcessingParameterVectorLayer(
            "FOREST", "Forest (polygons, optional)", [QgsProcessing.TypeVectorPolygon],
            optional=True))
        self.addParameter(QgsProcessingParameterNumber(
            "FOREST_CF", "Forest resistance coefficient c_f", number, 0.01, minValue=0.0))
        self.addParameter(QgsProcessingParameterVectorLayer(
            "STRUCTURES", "Dams or walls (lines, optional)", [QgsProcessing.TypeVectorLine],
            optional=True))
        self.addParameter(QgsProcessingParameterEnum(
            "STRUCTURE_KIND", "Structure kind", ["dam", "wall"], defaultValue=0))
        self.addParameter(QgsProcessingParameterNumber(
            "STRUCTURE_HEIGHT", "Structure height (m)", number, 5.0, minValue=0.01))
        self.addParameter(QgsProcessingParameterNumber(
            "STRUCTURE_SLOPE", "Dam side slope (degrees)", number, 40.0, minValue=1.0,
            maxValue=89.9))
        self.addParameter(QgsProcessingParameterString("NAME", "Run name", "avflow-run"))

    def _rheology(self, parameters, context):
        law = LAWS[self.parameterAsEnum(parameters, "LAW", context)]
        value = lambda key: self.parameterAsDouble(parameters, key, context)  # noqa: E731
        if law == "samosat":
            return {"law": law, "mu": value("MU")}
        if law == "voellmy":
            return {"law": law, "mu": value("MU"), "xi": value("XI")}
        if law == "coulomb":
            return {"law": law, "delta_deg": value("DELTA")}
        return {"law": law, "delta1_deg": value("DELTA"), "delta2_deg": value("DELTA2"),
                "d": value("POULIQUEN_D")}

    def _write_scenario(self, parameters, context, feedback, folder):
        """The scenario YAML in ``folder`` (inputs in ``folder/inputs``); returns its path
        and the run's name."""
        name = self.parameterAsString(parameters, "NAME", context) or "avflow-run"
        stem = _safe_name(name)
        inputs = os.path.join(folder, "inputs")
        os.makedirs(inputs, exist_ok=True)
        dem_layer = self.parameterAsRasterLayer(parameters, "DEM", context)
        dx = self.parameterAsDouble(parameters, "CELL_SIZE", context)
        dem = dem_file(dem_layer, inputs, None, feedback)
        crs = dem_layer.crs()
        release_layer = self.parameterAsSource(parameters, "RELEASE", context)
        field = self.parameterAsString(parameters, "THICKNESS_FIELD", context) or None
        release = vector_file(release_layer, os.path.join(inputs, f"{stem}_release.gpkg"), crs,
                              context, feedback, thickness_field=field)
        spec = {"name": name,
                "description": "written by the avflow QGIS plugin",
                "terrain": {"kind": "dem", "path": _relative(dem, folder)},
                "grid": {"dx": dx},
                "release": {"kind": "polygon", "path": _relative(release, folder)}}
        if not field:
            spec["release"]["thickness"] = self.parameterAsDouble(parameters, "THICKNESS",
                                                                  context)
        spec["rheology"] = self._rheology(parameters, context)
        forest = self.parameterAsSource(parameters, "FOREST", context)
        if forest is not None:
            path = vector_file(forest, os.path.join(inputs, f"{stem}_forest.gpkg"), crs,
                               context, feedback)
            spec["forest"] = {"polygon": _relative(path, folder),
                              "c_f": self.parameterAsDouble(parameters, "FOREST_CF", context)}
        lines = self.parameterAsSource(parameters, "STRUCTURES", context)
        if lines is not None:
            path = vector_file(lines, os.path.join(inputs, f"{stem}_structures.gpkg"), crs,
                               context, feedback)
            kind = ("dam", "wall")[self.parameterAsEnum(parameters, "STRUCTURE_KIND", context)]
            structure = {"line": _relative(path, folder), "kind": kind,
                         "height": self.parameterAsDouble(parameters, "STRUCTURE_HEIGHT",
                                                          context)}
            if kind == "dam":
                structure["side_slope_deg"] = self.parameterAsDouble(
                    parameters, "STRUCTURE_SLOPE", context)
            spec["structures"] = [structure]
        spec["time"] = {"end": self.parameterAsDouble(parameters, "END_TIME", context)}
        if self.parameterAsBool(parameters, "STOP_RULE", context):
            spec["output"] = {"stop_rule": "kinetic_energy"}
        density = MATERIALS[self.parameterAsEnum(parameters, "MATERIAL", context)][1]
        spec["physics"] = {"density": density}
        spec["numerics"] = {"order": 1 + self.parameterAsEnum(parameters, "ORDER", context)}
        path = os.path.join(folder, f"{stem}.yaml")
        header = ("# avflow scenario written by the avflow QGIS plugin; repeat the run with\n"
                  f"#   avflow run {os.path.basename(path)} -o {stem}.nc\n")
        write_text(path, header + to_yaml(spec) + "\n")
        feedback.pushInfo(f"scenario: {path}")
        return path, stem, name


class RunScenario(_ScenarioInputs):
    NAME, LABEL = "run_scenario", "Run a scenario"
    HELP = ("Runs avflow on a DEM and release polygons: writes NAME.yaml (the scenario; "
            "'avflow run NAME.yaml' repeats the run), NAME.nc (CF NetCDF) and the maps as "
            "GeoTIFFs, each with its QGIS style beside it, into the output folder, and adds "
            "the peak pressure (1 / 3 / 30 kPa classes), thickness, speed and deposit maps "
            "to the project. Layer names carry the run's status (at rest, or ended by rule "
            "with the share still moving). Cancel stops avflow and leaves no half-written "
            "file.")

    def initAlgorithm(self, config=None):  # noqa: N802
        self._scenario_parameters()
        self.addParameter(QgsProcessingParameterFolderDestination("OUTPUT_FOLDER",
                                                                  "Output folder"))
        self.addOutput(QgsProcessingOutputFile("NETCDF", "Run file (NetCDF)"))
        self.addOutput(QgsProcessingOutputFile("SCENARIO", "Scenario file (YAML)"))
        self.addOutput(QgsProcessingOutputMultipleLayers("LAYERS", "Maps"))
        self.addOutput(QgsProcessingOutputString("STATUS", "Status"))
        self.addOutput(QgsProcessingOutputString("SUMMARY", "Summary line"))

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802
        folder = self._folder(parameters, context)
        scenario, stem, name = self._write_scenario(parameters, context, feedback, folder)
        nc = os.path.join(folder, f"{stem}.nc")
        lines = process.run(["run", scenario, "-o", nc], feedback)
        summary = next((l for l in lines if not l.startswith("wrote ")), "")
        status = layers.status_from_summary(lines) or layers.run_status(nc)
        feedback.pushInfo(f"status: {status}")
        tifs = self._export_and_load(nc, folder, context, feedback, name, status)
        release = os.path.join(folder, "inputs", f"{stem}_release.gpkg")
        layers.load_on_completion(context, release, f"{name}: release",
                                  os.path.join(layers.STYLES, "release.qml"))
        return {"NETCDF": nc, "SCENARIO": scenario, "LAYERS": tifs, "STATUS": status,
                "SUMMARY": summary, "OUTPUT_FOLDER": folder}


class Ensemble(_ScenarioInputs):
    NAME, LABEL = "ensemble", "Ensemble (friction and release thickness ranges)"
    HELP = ("Runs an ensemble over a range of the friction law's main parameter (mu for "
            "samosAT and Voellmy, delta for Coulomb and Pouliquen) and of the release "
            "thickness (a factor on it), sampled by a seeded Latin hypercube: writes the base "
            "scenario and the ensemble YAML ('avflow ensemble NAME_ensemble.yaml -o ...' "
            "repeats it) and adds the exceedance-probability maps (0-1) of peak pressure "
            "(1, 3, 30 kPa), thickness and speed.")

    def initAlgorithm(self, config=None):  # noqa: N802
        self._scenario_parameters()
        number = QgsProcessingParameterNumber.Double
        self.addParameter(QgsProcessingParameterNumber(
            "PARAM_MIN", "Friction parameter: lowest (mu, or delta in degrees)", number, 0.18))
        self.addParameter(QgsProcessingParameterNumber(
            "PARAM_MAX", "Friction parameter: highest", number, 0.26))
        self.addParameter(QgsProcessingParameterNumber(
            "FACTOR_MIN", "Release thickness factor: lowest", number, 0.75, minValue=0.001))
        self.addParameter(QgsProcessingParameterNumber(
            "FACTOR_MAX", "Release thickness factor: highest", number, 1.25, minValue=0.001))
        self.addParameter(QgsProcessingParameterNumber(
            "MEMBERS", "Members", QgsProcessingParameterNumber.Integer, 8, minValue=1))
        self.addParameter(QgsProcessingParameterNumber(
            "SEED", "Seed", QgsProcessingParameterNumber.Integer, 1, minValue=0))
        self.addParameter(QgsProcessingParameterNumber(
            "WORKERS", "Worker processes (0: one, no dask)",
            QgsProcessingParameterNumber.Integer, 0, minValue=0))
        self.addParameter(QgsProcessingParameterFolderDestination("OUTPUT_FOLDER",
                                                                  "Output folder"))
        self.addOutput(QgsProcessingOutputFile("ENSEMBLE", "ensemble.nc"))
        self.addOutput(QgsProcessingOutputFile("SCENARIO", "Ensemble file (YAML)"))
        self.addOutput(QgsProcessingOutputMultipleLayers("LAYERS", "Probability maps"))

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802
        folder = self._folder(parameters, context)
        base, stem, name = self._write_scenario(parameters, context, feedback, folder)
        law = LAWS[self.parameterAsEnum(parameters, "LAW", context)]
        key = {"samosat": "mu", "voellmy": "mu", "coulomb": "delta_deg",
               "pouliquen": "delta1_deg"}[law]
        value = lambda k: self.parameterAsDouble(parameters, k, context)  # noqa: E731
        ranges = {}
        if value("PARAM_MAX") > value("PARAM_MIN"):
            ranges[f"rheology.{key}"] = [value("PARAM_MIN"), value("PARAM_MAX")]
        if value("FACTOR_MAX") > value("FACTOR_MIN"):
            ranges["release.volume_factor"] = [value("FACTOR_MIN"), value("FACTOR_MAX")]
        if not ranges:
            raise QgsProcessingException("give a range (lowest < highest) of the friction "
                                         "parameter or of the release thickness factor")
        spec = {"name": f"{name}-ensemble", "base": os.path.basename(base),
                "sample": {"n": self.parameterAsInt(parameters, "MEMBERS", context),
                           "seed": self.parameterAsInt(parameters, "SEED", context),
                           "ranges": ranges},
                "thresholds": {"peak_pressure": [1.0, 3.0, 30.0],
                               "peak_thickness": [0.1, 0.5, 1.0],
                               "peak_speed": [5.0, 10.0, 20.0]}}
        path = os.path.join(folder, f"{stem}_ensemble.yaml")
        write_text(path, "# avflow ensemble written by the avflow QGIS plugin; repeat with\n"
                         f"#   avflow ensemble {os.path.basename(path)} -o {stem}_ensemble\n"
                   + to_yaml(spec) + "\n")
        out = os.path.join(folder, f"{stem}_ensemble")
        workers = self.parameterAsInt(parameters, "WORKERS", context)
        process.run(["ensemble", path, "-o", out, "--workers", workers], feedback)
        ensemble_nc = os.path.join(out, "ensemble.nc")
        tifs = self._export_and_load(ensemble_nc, os.path.join(out, "maps"), context,
                                     feedback, f"{name} ensemble")
        return {"ENSEMBLE": ensemble_nc, "SCENARIO": path, "LAYERS": tifs,
                "OUTPUT_FOLDER": folder}


class LoadRun(_Base):
    NAME, LABEL = "load_run", "Load a run"
    HELP = ("Adds the maps of an existing avflow result to the project, styled: a run's "
            "NetCDF, an ensemble's ensemble.nc (exceedance probabilities) or a region's "
            "output folder. The maps are exported as GeoTIFFs (avflow export) into the "
            "output folder, each with its QGIS style beside it.")

    def initAlgorithm(self, config=None):  # noqa: N802
        self.addParameter(QgsProcessingParameterFile(
            "INPUT", "avflow result (run NetCDF, ensemble.nc, or a region's folder)",
            behavior=QgsProcessingParameterFile.File, fileFilter="NetCDF (*.nc);;All (*)"))
        self.addParameter(QgsProcessingParameterFolderDestination("OUTPUT_FOLDER",
                                                                  "Output folder for the maps"))
        self.addOutput(QgsProcessingOutputMultipleLayers("LAYERS", "Maps"))
        self.addOutput(QgsProcessingOutputString("STATUS", "Status"))

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802
        target = self.parameterAsFile(parameters, "INPUT", context)
        if not os.path.exists(target):
            raise QgsProcessingException(f"{target}: no such file or folder")
        folder = self._folder(parameters, context)
        status = layers.run_status(target) if os.path.isfile(target) else ""
        name = os.path.splitext(os.path.basename(target.rstrip("/\\")))[0]
        tifs = self._export_and_load(target, folder, context, feedback, name, status)
        return {"LAYERS": tifs, "STATUS": status, "OUTPUT_FOLDER": folder}


class ReleaseAreas(_Base):
    NAME, LABEL = "release_areas", "Release areas from a DEM"
    HELP = ("Potential release areas of a DEM (slope band, roughness, minimum area), as "
            "polygons with their area and release thickness, ready for Run a scenario.")

    def initAlgorithm(self, config=None):  # noqa: N802
        number = QgsProcessingParameterNumber.Double
        self.addParameter(QgsProcessingParameterRasterLayer("DEM", "DEM (elevation, m)"))
        self.addParameter(QgsProcessingParameterNumber("SLOPE_MIN", "Lowest slope (degrees)",
                                                       number, 28.0, minValue=0.0))
        self.addParameter(QgsProcessingParameterNumber("SLOPE_MAX", "Steepest slope (degrees)",
                                                       number, 60.0, maxValue=90.0))
        self.addParameter(QgsProcessingParameterNumber("SNOW_DEPTH", "Snow depth (m)",
                                                       number, 2.3, minValue=0.0))
        self.addParameter(QgsProcessingParameterNumber(
            "MIN_AREA", "Smallest area (m², 0: avflow's default)", number, 0.0, minValue=0.0))
        self.addParameter(QgsProcessingParameterFileDestination(
            "OUTPUT", "Release areas", "GeoPackage (*.gpkg)"))

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802
        dem_layer = self.parameterAsRasterLayer(parameters, "DEM", context)
        out = self.parameterAsFileOutput(parameters, "OUTPUT", context)
        os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
        dem = dem_file(dem_layer, os.path.dirname(out) or ".", None, feedback)
        args = ["release-areas", dem, "-o", out,
                "--slope-min", self.parameterAsDouble(parameters, "SLOPE_MIN", context),
                "--slope-max", self.parameterAsDouble(parameters, "SLOPE_MAX", context),
                "--snow-depth", self.parameterAsDouble(parameters, "SNOW_DEPTH", context)]
        if self.parameterAsDouble(parameters, "MIN_AREA", context) > 0:
            args += ["--min-area", self.parameterAsDouble(parameters, "MIN_AREA", context)]
        lines = process.run(args, feedback)
        count = next((l.split()[0] for l in lines if "potential release areas" in l), "?")
        layers.load_on_completion(context, out, f"release areas ({count})",
                                  os.path.join(layers.STYLES, "release_areas.qml"), "OUTPUT")
        return {"OUTPUT": out}


class PathAnalysis(_Base):
    NAME, LABEL = "path_analysis", "Path analysis (runout, alpha-beta)"
    HELP = ("Runout along an avalanche path (AvaFrame's AIMEC): where the peak pressure (or "
            "thickness) last exceeds the threshold along the line, the runout angle, and the "
            "alpha-beta points of the chosen regression. Writes a table (CSV, Markdown) and a "
            "PNG beside the output stem; the line is added, outlined.")

    REGRESSIONS = ("norway", "austria", "austria_small")

    def initAlgorithm(self, config=None):  # noqa: N802
        self.addParameter(QgsProcessingParameterFile(
            "INPUT", "avflow run (NetCDF) or ensemble folder",
            behavior=QgsProcessingParameterFile.File, fileFilter="NetCDF (*.nc);;All (*)"))
        self.addParameter(QgsProcessingParameterVectorLayer(
            "LINE", "Path line (optional: the flow's centre-of-mass track)",
            [QgsProcessing.TypeVectorLine], optional=True))
        self.addParameter(QgsProcessingParameterEnum(
            "FIELD", "Runout by", ["peak pressure", "peak thickness"], defaultValue=0))
        self.addParameter(QgsProcessingParameterNumber(
            "THRESHOLD", "Threshold (kPa, or m; 0: the default)",
            QgsProcessingParameterNumber.Double, 0.0, minValue=0.0))
        self.addParameter(QgsProcessingParameterEnum(
            "ALPHA_BETA", "Alpha-beta regression", list(self.REGRESSIONS), defaultValue=0))
        self.addParameter(QgsProcessingParameterFolderDestination("OUTPUT_FOLDER",
                                                                  "Output folder"))
        self.addOutput(QgsProcessingOutputString("SUMMARY", "Runout"))
        self.addOutput(QgsProcessingOutputFile("TABLE", "Table (CSV)"))
        self.addOutput(QgsProcessingOutputFile("POINTS", "Runout and alpha-beta points"))

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802
        target = self.parameterAsFile(parameters, "INPUT", context)
        folder = self._folder(parameters, context)
        stem = os.path.join(folder, os.path.splitext(os.path.basename(target))[0] + "_path")
        args = ["path", target, "-o", stem, "--alpha-beta",
                self.REGRESSIONS[self.parameterAsEnum(parameters, "ALPHA_BETA", context)],
                "--field", ("pressure", "thickness")[self.parameterAsEnum(parameters, "FIELD",
                                                                          context)]]
        threshold = self.parameterAsDouble(parameters, "THRESHOLD", context)
        if threshold > 0:
            args += ["--threshold", threshold]
        line = self.parameterAsSource(parameters, "LINE", context)
        if line is not None:
            crs = _netcdf_crs(target)
            path = vector_file(line, os.path.join(folder, "path_line.gpkg"), crs, context,
                               feedback, geometry=QgsWkbTypes.LineGeometry)
            # avflow path reads .shp/.geojson/.json/.csv lines: GeoJSON beside the GeoPackage
            from osgeo import gdal

            geojson = os.path.join(folder, "path_line.geojson")
            tmp = geojson + ".tmp.geojson"
            gdal.VectorTranslate(tmp, path, format="GeoJSON")
            os.replace(tmp, geojson)
            args += ["--line", geojson]
            layers.load_on_completion(context, path, "path line",
                                      os.path.join(layers.STYLES, "path.qml"), "LINE")
        lines = process.run(args, feedback)
        out = process.written(lines)
        table = next((p for p in out if p.endswith("_path.csv")), "")
        profile = next((p for p in out if p.endswith("_profile.csv")), "")
        summary = " ".join(l for l in lines if not l.startswith("wrote "))
        points = ""
        if table and profile:
            points = path_points(table, profile, os.path.join(folder, "path_points.gpkg"),
                                 _netcdf_crs(target), context)
            layers.load_on_completion(context, points, "runout and alpha-beta points",
                                      os.path.join(layers.STYLES, "path_points.qml"), "POINTS")
        return {"SUMMARY": summary, "TABLE": table, "POINTS": points, "OUTPUT_FOLDER": folder}


class RegionalMap(_Base):
    NAME, LABEL = "regional_map", "Regional map (every release of a layer)"
    HELP = ("Runs every release polygon of a layer in its own window of the DEM and merges "
            "the peak maps into one regional map (avflow region). Writes the region YAML "
            "('avflow region NAME_region.yaml -o ...' repeats it) and adds the merged maps, "
            "styled.")

    def initAlgorithm(self, config=None):  # noqa: N802
        number = QgsProcessingParameterNumber.Double
        self.addParameter(QgsProcessingParameterRasterLayer("DEM", "DEM (elevation, m)"))
        self.addParameter(QgsProcessingParameterVectorLayer(
            "RELEASE", "Release areas (polygons)", [QgsProcessing.TypeVectorPolygon]))
        self.addParameter(QgsProcessingParameterField(
            "THICKNESS_FIELD", "Release thickness field (m)", parentLayerParameterName="RELEASE",
            type=QgsProcessingParameterField.Numeric, optional=True))
        self.addParameter(QgsProcessingParameterNumber(
            "THICKNESS", "Release thickness where no field is chosen (m)", number, 1.0,
            minValue=0.001))
        self.addParameter(QgsProcessingParameterEnum("LAW", "Friction law", LAW_LABELS,
                                                     defaultValue=0))
        self.addParameter(QgsProcessingParameterNumber("MU", "mu (samosAT, Voellmy)", number,
                                                       0.22, minValue=0.0))
        self.addParameter(QgsProcessingParameterNumber("XI", "xi (Voellmy, m/s²)", number,
                                                       1000.0, minValue=1e-6))
        self.addParameter(QgsProcessingParameterNumber(
            "DELTA", "delta (Coulomb) or delta1 (Pouliquen), degrees", number, 20.0))
        self.addParameter(QgsProcessingParameterNumber("DELTA2", "delta2 (Pouliquen), degrees",
                                                       number, 30.0))
        self.addParameter(QgsProcessingParameterNumber("POULIQUEN_D", "d (Pouliquen, m)",
                                                       number, 1.0, minValue=1e-6))
        self.addParameter(QgsProcessingParameterEnum(
            "MATERIAL", "Material", [m[0] for m in MATERIALS], defaultValue=0))
        self.addParameter(QgsProcessingParameterNumber(
            "CELL_SIZE", "Cell size (m; coarser than the DEM resamples it)", number, 10.0,
            minValue=0.01))
        self.addParameter(QgsProcessingParameterNumber("END_TIME", "End time (s)", number,
                                                       400.0, minValue=0.1))
        self.addParameter(QgsProcessingParameterNumber(
            "WORKERS", "Worker processes (0: one, no dask)",
            QgsProcessingParameterNumber.Integer, 0, minValue=0))
        self.addParameter(QgsProcessingParameterString("NAME", "Region name", "region"))
        self.addParameter(QgsProcessingParameterFolderDestination("OUTPUT_FOLDER",
                                                                  "Output folder"))
        self.addOutput(QgsProcessingOutputFolder("REGION", "Region output folder"))
        self.addOutput(QgsProcessingOutputFile("SCENARIO", "Region file (YAML)"))
        self.addOutput(QgsProcessingOutputMultipleLayers("LAYERS", "Maps"))

    _rheology = _ScenarioInputs._rheology

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802
        folder = self._folder(parameters, context)
        name = self.parameterAsString(parameters, "NAME", context) or "region"
        stem = _safe_name(name)
        inputs = os.path.join(folder, "inputs")
        os.makedirs(inputs, exist_ok=True)
        dem_layer = self.parameterAsRasterLayer(parameters, "DEM", context)
        dem = dem_file(dem_layer, inputs, self.parameterAsDouble(parameters, "CELL_SIZE",
                                                                 context), feedback)
        field = self.parameterAsString(parameters, "THICKNESS_FIELD", context) or None
        release = vector_file(self.parameterAsSource(parameters, "RELEASE", context),
                              os.path.join(inputs, f"{stem}_releases.gpkg"), dem_layer.crs(),
                              context, feedback, thickness_field=field)
        releases = {"path": _relative(release, folder)}
        if field:
            releases["thickness_field"] = "thickness"
        else:
            releases["thickness"] = self.parameterAsDouble(parameters, "THICKNESS", context)
        density = MATERIALS[self.parameterAsEnum(parameters, "MATERIAL", context)][1]
        spec = {"name": name, "dem": _relative(dem, folder), "releases": releases,
                "scenario": {"rheology": self._rheology(parameters, context),
                             "time": {"end": self.parameterAsDouble(parameters, "END_TIME",
                                                                    context)},
                             "output": {"stop_rule": "kinetic_energy"},
                             "physics": {"density": density}}}
        path = os.path.join(folder, f"{stem}_region.yaml")
        write_text(path, "# avflow region written by the avflow QGIS plugin; repeat with\n"
                         f"#   avflow region {os.path.basename(path)} -o {stem}_region\n"
                   + to_yaml(spec) + "\n")
        out = os.path.join(folder, f"{stem}_region")
        workers = self.parameterAsInt(parameters, "WORKERS", context)
        process.run(["region", path, "-o", out, "--workers", workers], feedback)
        tifs = self._export_and_load(out, os.path.join(out, "maps"), context, feedback, name)
        return {"REGION": out, "SCENARIO": path, "LAYERS": tifs, "OUTPUT_FOLDER": folder}


#: The points of avflow path's table: (column of s along the path, label).
PATH_POINTS = (("runout_s", "runout"), ("ab_beta_s", "beta point"), ("ab_alpha_s", "alpha"),
               ("ab_alpha_m1sd_s", "alpha - 1 SD"), ("ab_alpha_m2sd_s", "alpha - 2 SD"))


def path_points(table, profile, target, crs, context):
    """The runout and alpha-beta points of ``avflow path``'s table as a point GeoPackage,
    placed along the path by its profile (s, x, y; linear between the profile's points)."""
    import csv

    from qgis.core import QgsGeometry, QgsPointXY

    with open(profile, newline="", encoding="utf-8") as f:
        rows = [(float(r["s"]), float(r["x"]), float(r["y"])) for r in csv.DictReader(f)]
    with open(table, newline="", encoding="utf-8") as f:
        runs = list(csv.DictReader(f))
    fields = QgsFields()
    for name, kind in (("run", QVariant.String), ("point", QgsField), ("s", QVariant.Double),
                       ("angle_deg", QVariant.Double)):
        fields.append(QgsField(name, QVariant.String if kind is QgsField else kind))
    options = QgsVectorFileWriter.SaveVectorOptions()
    options.driverName = "GPKG"
    tmp = target + ".tmp.gpkg"
    writer = QgsVectorFileWriter.create(tmp, fields, QgsWkbTypes.Point, crs,
                                        context.transformContext(), options)
    for run in runs:
        for column, label in PATH_POINTS:
            run = {k.removeprefix("path_"): v for k, v in run.items()}  # the CSV's prefix
            try:
                s = float(run.get(column) or "nan")
            except ValueError:
                continue
            if not math.isfinite(s) or not rows or not rows[0][0] <= s <= rows[-1][0]:
                continue
            k = max(i for i, r in enumerate(rows) if r[0] <= s)
            a, b = rows[k], rows[min(k + 1, len(rows) - 1)]
            w = 0.0 if b[0] == a[0] else (s - a[0]) / (b[0] - a[0])
            x, y = a[1] + w * (b[1] - a[1]), a[2] + w * (b[2] - a[2])
            if column == "runout_s" and run.get("runout_x") and run.get("runout_y"):
                x, y = float(run["runout_x"]), float(run["runout_y"])  # the cell, off the line
            feature = QgsFeature(fields)
            feature.setGeometry(QgsGeometry.fromPointXY(QgsPointXY(x, y)))
            angle = run.get(column[:-2] if column != "runout_s" else "runout_angle", "")
            try:
                angle = float(angle)
            except ValueError:
                angle = None
            feature.setAttributes([run.get("run", ""), label, s, angle])
            writer.addFeature(feature)
    del writer
    os.replace(tmp, target)
    return target


def _netcdf_crs(path):
    """The CRS of an avflow NetCDF (its grid mapping's WKT), through GDAL."""
    from qgis.core import QgsCoordinateReferenceSystem

    try:
        from osgeo import gdal

        ds = gdal.Open(f'NETCDF:"{path}":peak_thickness')
        wkt = ds.GetProjection() if ds is not None else ""
    except Exception:
        wkt = ""
    return QgsCoordinateReferenceSystem.fromWkt(wkt) if wkt else QgsCoordinateReferenceSystem()


from .report import ReportFigure  # noqa: E402

ALGORITHMS = (RunScenario, LoadRun, Ensemble, PathAnalysis, ReleaseAreas, RegionalMap,
              ReportFigure)
