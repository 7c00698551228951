"""usdview plugin: menu "Skin -> Plot profile" for the selected SkinDiffusionProfile.

Enable it with the line ``skinpipe env`` prints (PXR_PLUGINPATH_NAME must list this
folder). It is a thin layer: the plot is skinpipe.usd.inspection.plot_profile, the same
code as ``skinpipe inspect --plot``. usdview itself is not installable from PyPI, so
this module only imports its Qt and plugin API when usdview loads it.
"""

from __future__ import annotations

import tempfile
from typing import Any

try:  # only inside usdview
    from pxr import Tf
    from pxr.Usdviewq.plugin import PluginContainer
except ImportError:  # pragma: no cover - usdview is not installed here
    PluginContainer = object
    Tf = None


def plot_selected_profiles(usdview_api: Any) -> list[str]:
    """Plot every selected profile (or a selected mesh's profiles) and show the images."""
    from skinpipe.usd.inspection import plot_profile, profiles_on_stage

    shown = []
    for prim in usdview_api.selectedPrims:
        for path, (fit, measured) in profiles_on_stage(usdview_api.stage,
                                                       str(prim.GetPath())).items():
            out = tempfile.NamedTemporaryFile(prefix="skinpipe-", suffix=".png", delete=False)
            out.close()
            plot_profile(fit, measured, out.name, title=f"{path} ({fit.name})")
            _show(usdview_api, out.name, path)
            shown.append(out.name)
    if not shown:
        usdview_api.PrintStatus("Select a SkinDiffusionProfile or a mesh with skin regions.")
    return shown


def _show(usdview_api: Any, png: str, title: str) -> None:  # pragma: no cover - needs Qt
    from pxr.Usdviewq.qt import QtGui, QtWidgets

    label = QtWidgets.QLabel()
    label.setPixmap(QtGui.QPixmap(png))
    label.setWindowTitle(f"skinpipe: {title}")
    label.show()
    usdview_api.qMainWindow._skinpipe_windows = [
        *getattr(usdview_api.qMainWindow, "_skinpipe_windows", []), label]


class SkinPluginContainer(PluginContainer):  # type: ignore[misc,valid-type]
    """Registers the "Skin" menu with usdview."""

    def registerPlugins(self, plugRegistry: Any, usdviewApi: Any) -> None:
        self._plot = plugRegistry.registerCommandPlugin(
            "SkinPluginContainer.plotProfile", "Plot profile", plot_selected_profiles)

    def configureView(self, plugRegistry: Any, plugUIBuilder: Any) -> None:
        plugUIBuilder.findOrCreateMenu("Skin").addItem(self._plot)


if Tf is not None:  # pragma: no cover
    Tf.Type.Define(SkinPluginContainer)
