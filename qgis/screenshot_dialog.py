"""Screenshot of the "Run a scenario" dialog for the docs (docs/img/qgis_dialog.png), from a
real, headless QGIS. Run with QGIS's Python (the system python3 on Debian):

    QT_QPA_PLATFORM=offscreen /usr/bin/python3 qgis/screenshot_dialog.py out/qgis_dialog.png

then make it small (a 128-colour palette) before committing it.
"""

import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
KOT = os.path.join(HERE, "..", "data", "avaframe", "avaKot")


def main(target):
    sys.path.insert(0, HERE)
    from qgis.core import (QgsApplication, QgsCoordinateReferenceSystem,
                           QgsProcessingContext, QgsProject, QgsRasterLayer, QgsVectorLayer)

    app = QgsApplication([], True)
    app.initQgis()
    sys.path.insert(0, os.path.join(QgsApplication.pkgDataPath(), "python", "plugins"))
    from processing.core.Processing import Processing

    Processing.initialize()
    from avflow_qgis.provider import AvflowProvider

    provider = AvflowProvider()
    QgsApplication.processingRegistry().addProvider(provider)
    dem = QgsRasterLayer(os.path.join(KOT, "avaKot.asc"), "avaKot DEM")
    dem.setCrs(QgsCoordinateReferenceSystem("EPSG:31287"))  # the .asc has no .prj
    release = QgsVectorLayer(os.path.join(KOT, "relKot.shp"), "release (drawn)", "ogr")
    QgsProject.instance().addMapLayers([dem, release])
    from processing.gui.AlgorithmDialog import AlgorithmDialog

    dialog = AlgorithmDialog(QgsApplication.processingRegistry()
                             .algorithmById("avflow:run_scenario").create())
    dialog.resize(1000, 720)
    dialog.show()
    context = QgsProcessingContext()
    wrappers = dialog.mainWidget().wrappers
    wrappers["THICKNESS_FIELD"].setParameterValue("thickness", context)
    wrappers["CELL_SIZE"].setParameterValue(20.0, context)
    wrappers["NAME"].setParameterValue("kontertal", context)
    for _ in range(20):
        app.processEvents()
    dialog.grab().save(target)
    print(f"wrote {target}", flush=True)
    os._exit(0)  # QGIS's exit can crash headless; the file is written


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "qgis_dialog.png")
