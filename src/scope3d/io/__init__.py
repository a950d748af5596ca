"""Other tools' file formats: COLMAP sparse text models and Middlebury multi-view ``*_par.txt`` sets.

Each importer turns a foreign format into a scope3d dataset folder (see :mod:`scope3d.io.dataset`); the
COLMAP writer lets any pipeline hand its sparse reconstruction to COLMAP, pycolmap or their viewers.
(Bundle Adjustment in the Large problems and their bounds files: :mod:`.bal`, :mod:`.bal_bounds`.)
"""
from scope3d.io.colmap import SparseModel, import_colmap, read_colmap_text, write_colmap_text
from scope3d.io.middlebury import import_middlebury, read_middlebury_par

__all__ = [
    "SparseModel", "import_colmap", "import_middlebury", "read_colmap_text", "read_middlebury_par",
    "write_colmap_text",
]
