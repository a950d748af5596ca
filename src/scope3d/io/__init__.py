"""Files: the dataset folder (:mod:`.dataset`) and what it holds (:mod:`.images`, :mod:`.poses_csv`,
:mod:`.camera_json`, :mod:`.hand_eye_json`, :mod:`.intrinsic_bounds`, :mod:`.quadrants`, :mod:`.scan_plan`),
outputs (:mod:`.ply`, :mod:`.obj`, :mod:`.map_points`), and other tools' formats, each importer turning a
foreign format into a dataset folder: COLMAP sparse text models (:mod:`.colmap`, also written so any
pipeline can hand its model to COLMAP, pycolmap or their viewers), Middlebury multi-view sets
(:mod:`.middlebury`), videos (:mod:`.video`), ROS bags (:mod:`.rosbag`), robot pose logs
(:mod:`.robot_log`), NDI Track exports (:mod:`.tracker`), Bundle Adjustment in the Large problems and
their bounds files (:mod:`.bal`, :mod:`.bal_bounds`); :mod:`.json_object` reads anyone's JSON object.
"""
from scope3d.io.colmap import SparseModel, import_colmap, read_colmap_text, write_colmap_text
from scope3d.io.middlebury import import_middlebury, read_middlebury_par

__all__ = [
    "SparseModel", "import_colmap", "import_middlebury", "read_colmap_text", "read_middlebury_par",
    "write_colmap_text",
]
