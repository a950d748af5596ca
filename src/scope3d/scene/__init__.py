"""The in-memory model of what is reconstructed: point clouds and meshes (:mod:`.mesh`), tracks
(:mod:`.tracks`), smooth surfaces with texture and depth maps (:mod:`.surface`, a thin-plate spline:
:mod:`.thin_plate`). Files are :mod:`scope3d.io`.
"""
from scope3d.scene.mesh import Mesh, PointCloud, SampledSurface
from scope3d.scene.tracks import Tracks

__all__ = ["Mesh", "PointCloud", "SampledSurface", "Tracks"]
