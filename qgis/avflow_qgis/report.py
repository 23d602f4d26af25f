"""Report figure: a print layout of one run's map over the hillshade, with scale bar, north
arrow, legend, CRS and the run's parameters, exported to PDF and PNG."""

import os
import re

from qgis.core import (QgsApplication, QgsBilinearRasterResampler, QgsContrastEnhancement,
                       QgsSingleBandGrayRenderer, QgsLayoutExporter,
                       QgsLayoutItemLabel, QgsLayoutItemLegend, QgsLayoutItemMap,
                       QgsLayoutItemPicture, QgsLayoutItemScaleBar, QgsLayoutPoint,
                       QgsLayoutSize, QgsMapLayerLegendUtils, QgsPrintLayout, QgsProcessingAlgorithm,
                       QgsProcessingException, QgsProcessingOutputFile,
                       QgsProcessingParameterEnum, QgsProcessingParameterFile,
                       QgsProcessingParameterFileDestination, QgsProcessingParameterNumber,
                       QgsProcessingParameterString, QgsProject, QgsRasterLayer, QgsRectangle,
                       QgsUnitTypes, QgsVectorLayer)
from qgis.PyQt.QtCore import Qt
from qgis.PyQt.QtGui import QFont

from . import layers, process

MAPS = (("peak_pressure_class", "peak pressure classes"), ("peak_thickness", "peak thickness"),
        ("peak_speed", "peak speed"))


def _scenario_lines(nc):
    """The run's parameters from its NetCDF: name, law, cells, order, density."""
    try:
        from osgeo import gdal

        meta = gdal.Open(nc).GetMetadata()
    except Exception:
        return [], {}
    text = meta.get("NC_GLOBAL#scenario", "")
    blocks, key = {}, None
    for line in text.splitlines():  # the resolved scenario, as avflow wrote it (YAML)
        if line and not line[0].isspace() and ":" in line:
            key, _, rest = line.partition(":")
            blocks[key] = [rest.strip()] if rest.strip() else []
        elif key and line.startswith("  ") and not line.startswith("   ") and ":" in line:
            name, _, value = line.strip().partition(":")
            value = value.strip().strip('"\'')
            if value and value not in ("null", "{}", "[]"):
                blocks[key].append(f"{name} {os.path.basename(value) if name == 'path' else value}")
    picks = []
    for key in ("rheology", "release", "grid", "physics", "numerics", "time"):
        if blocks.get(key):
            picks.append(f"{key}: " + ", ".join(blocks[key]))
    return picks, meta


class ReportFigure(QgsProcessingAlgorithm):
    def createInstance(self):  # noqa: N802
        return ReportFigure()

    def name(self):
        return "report_figure"

    def displayName(self):  # noqa: N802
        return "Report figure (PDF and PNG)"

    def group(self):
        return "avflow"

    def groupId(self):  # noqa: N802
        return "avflow"

    def flags(self):
        # a layout renders on the main thread
        return super().flags() | QgsProcessingAlgorithm.FlagNoThreading

    def shortHelpString(self):  # noqa: N802
        return ("An A4 landscape figure of one run for a report: the chosen map (peak "
                "pressure in the 1 / 3 / 30 kPa classes by default) over the hillshade of "
                "the bed, the release outlined, with legend, scale bar, north arrow, the CRS "
                "and the run's status and parameters, exported to PDF and PNG.")

    def initAlgorithm(self, config=None):  # noqa: N802
        self.addParameter(QgsProcessingParameterFile(
            "INPUT", "avflow run (NetCDF)", behavior=QgsProcessingParameterFile.File,
            fileFilter="NetCDF (*.nc)"))
        self.addParameter(QgsProcessingParameterEnum("MAP", "Map", [m[1] for m in MAPS],
                                                     defaultValue=0))
        self.addParameter(QgsProcessingParameterString("TITLE", "Title (empty: the run's name)",
                                                       "", optional=True))
        self.addParameter(QgsProcessingParameterNumber(
            "DPI", "PNG resolution (dpi)", QgsProcessingParameterNumber.Integer, 150,
            minValue=30, maxValue=1200))
        self.addParameter(QgsProcessingParameterFileDestination("PDF", "PDF", "PDF (*.pdf)"))
        self.addParameter(QgsProcessingParameterFileDestination("PNG", "PNG", "PNG (*.png)"))
        self.addOutput(QgsProcessingOutputFile("PDF_FILE", "PDF"))
        self.addOutput(QgsProcessingOutputFile("PNG_FILE", "PNG"))

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802
        nc = self.parameterAsFile(parameters, "INPUT", context)
        if not os.path.isfile(nc):
            raise QgsProcessingException(f"{nc}: no such file")
        key, words = MAPS[self.parameterAsEnum(parameters, "MAP", context)]
        pdf = self.parameterAsFileOutput(parameters, "PDF", context)
        png = self.parameterAsFileOutput(parameters, "PNG", context)
        folder = os.path.join(os.path.dirname(pdf) or ".", "report_maps")
        os.makedirs(folder, exist_ok=True)
        lines = process.run(["export", nc, "--format", "tif", "-o", folder, "--variables",
                             f"{key},bed_elevation"], feedback)
        tifs = process.written(lines)
        map_tif = next(p for p in tifs if p.endswith(f"_{key}.tif"))
        bed_tif = next((p for p in tifs if p.endswith("_bed_elevation.tif")), None)
        params, meta = _scenario_lines(nc)
        name = meta.get("NC_GLOBAL#scenario_name", os.path.basename(nc))
        status = layers.run_status(nc)
        title = self.parameterAsString(parameters, "TITLE", context) or name

        project = QgsProject()  # a project of its own: the user's stays as it is
        shade = None
        if bed_tif:  # GDAL's hillshade (QGIS's own GDAL), drawn grey and bilinear
            from osgeo import gdal

            shade_tif = bed_tif[:-4] + "_hillshade.tif"
            gdal.DEMProcessing(shade_tif, bed_tif, "hillshade", azimuth=315, altitude=45,
                               zFactor=1.0, computeEdges=True)
            shade = QgsRasterLayer(shade_tif, "hillshade", "gdal")
            grey = QgsSingleBandGrayRenderer(shade.dataProvider(), 1)
            enhancement = QgsContrastEnhancement(shade.dataProvider().dataType(1))
            enhancement.setContrastEnhancementAlgorithm(
                QgsContrastEnhancement.StretchToMinimumMaximum)
            enhancement.setMinimumValue(60)
            enhancement.setMaximumValue(255)
            grey.setContrastEnhancement(enhancement)
            shade.setRenderer(grey)
            shade.resampleFilter().setZoomedInResampler(QgsBilinearRasterResampler())
            shade.resampleFilter().setZoomedOutResampler(QgsBilinearRasterResampler())
        layer = layers.styled_raster(map_tif, words)
        if not layer.isValid():
            raise QgsProcessingException(f"{map_tif}: not a raster QGIS reads")
        release = _release_layer(meta)
        for item in (shade, layer, release):
            if item is not None:
                project.addMapLayer(item, False)
        shown = [item for item in (release, layer, shade) if item is not None]
        crs = layer.crs()
        project.setCrs(crs)

        layout = QgsPrintLayout(project)
        layout.initializeDefaults()  # one A4 landscape page
        layout.setName(title)
        page = layout.pageCollection().page(0).pageSize()  # mm
        W, H = page.width(), page.height()
        mm = QgsUnitTypes.LayoutMillimeters

        themap = QgsLayoutItemMap(layout)
        themap.setLayers(shown)
        themap.setCrs(crs)
        extent = layer.extent()
        if release is not None:
            extent.combineExtentWith(release.extent())
        extent.scale(1.05)
        layout.addLayoutItem(themap)
        themap.attemptMove(QgsLayoutPoint(8, 20, mm))
        width, height = W * 0.66, H - 30
        themap.attemptResize(QgsLayoutSize(width, height, mm))
        # grow the extent to the item's shape: setExtent would otherwise resize the item
        cx, cy = extent.center().x(), extent.center().y()
        ew, eh = extent.width(), extent.height()
        if ew / eh < width / height:
            ew = eh * width / height
        else:
            eh = ew * height / width
        themap.setExtent(QgsRectangle(cx - ew / 2, cy - eh / 2, cx + ew / 2, cy + eh / 2))
        themap.setFrameEnabled(True)

        left = 8 + W * 0.66 + 6
        label = QgsLayoutItemLabel(layout)
        label.setText(title)
        label.setFont(QFont("DejaVu Sans", 16, QFont.Bold))
        label.attemptMove(QgsLayoutPoint(8, 6, mm))
        label.attemptResize(QgsLayoutSize(W - 16, 12, mm))
        layout.addLayoutItem(label)

        legend = QgsLayoutItemLegend(layout)
        legend.setTitle("Legend")
        legend.setLinkedMap(themap)
        legend.setAutoUpdateModel(False)
        root = legend.model().rootGroup()
        root.clear()
        for item in (layer, release):
            if item is not None:
                node = root.addLayer(item)
                nodes = legend.model().layerLegendNodes(node)
                keep = [i for i, n in enumerate(nodes)  # not the band's own line
                        if not str(n.data(Qt.DisplayRole) or "").startswith("Band ")]
                if len(keep) < len(nodes):
                    QgsMapLayerLegendUtils.setLegendNodeOrder(node, keep)
                    legend.model().refreshLayerLegend(node)
        legend.attemptMove(QgsLayoutPoint(left, 20, mm))
        layout.addLayoutItem(legend)

        scale = QgsLayoutItemScaleBar(layout)
        scale.setStyle("Single Box")
        scale.setLinkedMap(themap)
        scale.applyDefaultSize(QgsUnitTypes.DistanceMeters)
        scale.setUnitLabel("m")
        scale.attemptMove(QgsLayoutPoint(12, H - 24, mm))
        layout.addLayoutItem(scale)

        arrow = QgsLayoutItemPicture(layout)
        svg = _north_arrow()
        if svg:
            arrow.setPicturePath(svg)
        arrow.setLinkedMap(themap)
        arrow.attemptMove(QgsLayoutPoint(8 + W * 0.66 - 18, 24, mm))
        arrow.attemptResize(QgsLayoutSize(12, 16, mm))
        layout.addLayoutItem(arrow)

        text = [f"status: {status}" if status else "",
                f"CRS: {crs.authid() or ''} {crs.description()}".strip()] + params + [
            f"file: {os.path.basename(nc)}",
            f"avflow {meta.get('NC_GLOBAL#avflow_version', '')}"]
        info = QgsLayoutItemLabel(layout)
        info.setText("\n".join(t for t in text if t))
        info.setFont(QFont("DejaVu Sans", 8))
        info.attemptMove(QgsLayoutPoint(left, H * 0.52, mm))
        info.attemptResize(QgsLayoutSize(W - left - 6, H * 0.45, mm))
        layout.addLayoutItem(info)

        feedback.pushInfo(f"page {W:g} x {H:g} mm, map {themap.rect().width():.0f} x "
                          f"{themap.rect().height():.0f} mm at 1:{themap.scale():.0f}")
        exporter = QgsLayoutExporter(layout)
        for target, kind in ((pdf, "pdf"), (png, "png")):
            os.makedirs(os.path.dirname(target) or ".", exist_ok=True)
            tmp = f"{target}.tmp.{kind}"
            if kind == "pdf":
                result = exporter.exportToPdf(tmp, QgsLayoutExporter.PdfExportSettings())
            else:
                settings = QgsLayoutExporter.ImageExportSettings()
                settings.dpi = self.parameterAsInt(parameters, "DPI", context)
                settings.generateWorldFile = False
                result = exporter.exportToImage(tmp, settings)
            if result != QgsLayoutExporter.Success:
                raise QgsProcessingException(f"{target}: layout export failed ({result})")
            os.replace(tmp, target)
            feedback.pushInfo(f"wrote {target}")
        return {"PDF_FILE": pdf, "PNG_FILE": png, "PDF": pdf, "PNG": png}


def _release_layer(meta):
    """The run's release polygons (its input file, when it still exists), outlined."""
    for path in meta.get("NC_GLOBAL#input_files", "").splitlines():
        path = path.strip()
        if path.lower().endswith((".shp", ".gpkg", ".geojson", ".fgb")) and os.path.isfile(path):
            layer = QgsVectorLayer(path, "release", "ogr")
            if layer.isValid() and layer.geometryType() == 2:
                layer.loadNamedStyle(os.path.join(layers.STYLES, "release.qml"))
                return layer
    return None


def _north_arrow():
    for folder in QgsApplication.svgPaths():
        for name in ("arrows/NorthArrow_02.svg", "arrows/NorthArrow_01.svg"):
            path = os.path.join(folder, name)
            if os.path.isfile(path):
                return path
    return ""
