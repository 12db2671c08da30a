"""The rasterstereograph simulator: the project's test bench, demo data and ground truth.

A :class:`~rasterserver.simulator.scene.Scene` (meshes in world millimetres with an albedo each)
is rendered by :mod:`rasterserver.simulator.render` as the station's camera sees it under the
projector's line raster; every image comes with its exact ground truth.
"""
