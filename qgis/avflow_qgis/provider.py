"""The Processing provider "avflow" and the one setting it keeps: where avflow is."""

import os

from qgis.core import QgsProcessingProvider
from qgis.PyQt.QtGui import QIcon

#: The Processing setting (Settings > Options > Processing > Providers > avflow).
EXECUTABLE_SETTING = "AVFLOW_EXECUTABLE"

HERE = os.path.dirname(__file__)


class AvflowProvider(QgsProcessingProvider):
    def load(self):
        try:  # the Processing plugin's settings page; absent only in a bare PyQGIS script
            from processing.core.ProcessingConfig import ProcessingConfig, Setting

            ProcessingConfig.settingIcons[self.name()] = self.icon()
            ProcessingConfig.addSetting(Setting(
                self.name(), EXECUTABLE_SETTING,
                "avflow executable (empty: 'avflow' on the PATH)", "",
                valuetype=Setting.FILE))
            ProcessingConfig.readSettings()
        except ImportError:
            pass
        self.refreshAlgorithms()
        return True

    def unload(self):
        try:
            from processing.core.ProcessingConfig import ProcessingConfig

            ProcessingConfig.removeSetting(EXECUTABLE_SETTING)
        except ImportError:
            pass

    def loadAlgorithms(self):  # noqa: N802
        from .algorithms import ALGORITHMS

        for cls in ALGORITHMS:
            self.addAlgorithm(cls())

    def id(self):
        return "avflow"

    def name(self):
        return "avflow"

    def longName(self):  # noqa: N802
        return "avflow: avalanche runout (kinetic Saint-Venant scheme)"

    def icon(self):
        return QIcon(os.path.join(HERE, "icon.svg"))
