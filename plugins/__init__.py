"""The built-in pipeline stages, installed as the package ``rasterserver_plugins``.

One module per stage plugin (``peaks_first_moment.py`` and so on), each defining a
:class:`rasterserver.stage.Stage` subclass. They get no privileged path: like a third-party
package's stages, each is registered in the ``rasterserver.stages`` entry-point group of
``pyproject.toml`` (``"peaks.first-moment" =
"rasterserver_plugins.peaks_first_moment:FirstMomentPeaks"``) and found by
:mod:`rasterserver.registry` through :mod:`importlib.metadata`. Nothing in the core imports
this package or knows the plugins' names.
"""
