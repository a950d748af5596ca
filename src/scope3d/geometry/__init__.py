"""Pure geometry, the lowest layer: rotations, rigid poses (``cam_from_world``), similarity transforms,
planes, spheres (:mod:`.sphere`), triangles of vertex grids (:mod:`.grid`), points from rays
(:mod:`.triangulation`), poses sampled in time (:mod:`.trajectory`), ISO metric threads (:mod:`.iso_thread`).
No cameras, no files.
"""
from scope3d.geometry.plane import fit_plane, plane_residuals, plane_rms, principal_axes
from scope3d.geometry.pose import Pose
from scope3d.geometry.similarity import Similarity, fit_similarity

__all__ = ["Pose", "Similarity", "fit_plane", "fit_similarity", "plane_residuals", "plane_rms", "principal_axes"]
