"""The plugin object QGIS loads: it only registers the Processing provider."""

from qgis.core import QgsApplication


class AvflowPlugin:
    def __init__(self, iface=None):
        self.iface = iface
        self.provider = None

    def initProcessing(self):  # noqa: N802 (QGIS's name; qgis_process calls it too)
        from .provider import AvflowProvider

        if self.provider is None:
            self.provider = AvflowProvider()
            QgsApplication.processingRegistry().addProvider(self.provider)

    def initGui(self):  # noqa: N802
        self.initProcessing()

    def unload(self):
        if self.provider is not None:
            QgsApplication.processingRegistry().removeProvider(self.provider)
            self.provider = None
