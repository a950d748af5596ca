"""The phantom lab: image sequences of the reference's phantoms with exact ground truth, in millimetres.

Scenes (:mod:`.scenes`): ``dome`` (brain-tumour cavity with fluorescent targets), ``sheet`` (flat print),
``bladder`` (closed cavity with star markers), ``thread`` (ISO internal thread in a blind hole), ``cavity`` (a
resection cavity with an overhanging lip, issue 35).
Trajectories (:mod:`.trajectories`): ``grid5x6``, ``grid7x8``, ``axial``, ``quadrants``, ``spiral``, ``approach``.
Rendering (:mod:`.render`, compiled :mod:`.render_kernels`): Embree ray casting refined in double precision
(:mod:`.raycast`, :mod:`.raycast_kernels`), procedural textures (:mod:`.textures`), light at the scope tip,
Blinn-Phong specular, seeded sensor noise. :func:`generate` renders a sequence, :func:`write` saves it
as a :mod:`scope3d.io.dataset` folder with ground truth (:mod:`.lab`). Also: calibration boards
(:mod:`.boards`), synthetic bundle-adjustment scenes (:mod:`.bundle_scene`), a tool hiding part of the view
(:mod:`.tool`), a raw lab recording (:mod:`.recording`).
"""
from scope3d.phantoms.lab import (
    PhantomSequence,
    catalogue,
    contact_sheet,
    default_camera,
    generate,
    measure_poses,
    true_targets,
    write,
)
from scope3d.phantoms.raycast import Hits, RayCaster
from scope3d.phantoms.render import RenderedFrame, RenderOptions, render_frame, sequence_exposure
from scope3d.phantoms.scenes import (
    SCENE_TRAJECTORIES,
    SCENES,
    Material,
    Scene,
    TrueTarget,
    build_scene,
)
from scope3d.phantoms.trajectories import (
    TRAJECTORIES,
    Trajectory,
    axial_trajectory,
    build_trajectory,
    grid_trajectory,
    quadrant_trajectory,
    spiral_trajectory,
)

__all__ = [
    "Hits", "Material", "PhantomSequence", "RayCaster", "RenderOptions", "RenderedFrame", "SCENES",
    "SCENE_TRAJECTORIES", "Scene", "TRAJECTORIES", "Trajectory", "TrueTarget", "axial_trajectory",
    "build_scene", "build_trajectory", "catalogue", "contact_sheet", "default_camera", "generate",
    "grid_trajectory", "measure_poses", "quadrant_trajectory", "render_frame",
    "sequence_exposure", "spiral_trajectory", "true_targets", "write",
]
