"""avflow for QGIS: a Processing provider that runs avflow as a separate process."""


def classFactory(iface):  # noqa: N802 (QGIS's name)
    from .plugin import AvflowPlugin

    return AvflowPlugin(iface)
