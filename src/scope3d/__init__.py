"""scope3d: metric 3D models from a robot-held scope whose poses are known within a tolerance.

Layers, lowest first (a layer imports only its own and lower ones; docs/architecture.md names every module):
:mod:`.errors`, :mod:`.utils` -> :mod:`.geometry` -> :mod:`.sensor` -> :mod:`.scene` -> :mod:`.io` ->
:mod:`.phantoms` -> :mod:`.feature` -> :mod:`.estimators` -> :mod:`.sfm`, :mod:`.mvs`, :mod:`.registration`,
:mod:`.metrology` -> :mod:`.pipelines` -> :mod:`.report` -> :mod:`.cli`.

The jobs, as the command line runs them, are functions of the package (as pycolmap exposes its pipelines)::

    import scope3d
    result = scope3d.map("my_dataset", "my_map")              # options=scope3d.MapOptions() by default
    result.points, result.cam_from_world, result.mesh          # the model as arrays
    scope3d.localize("my_map", "approach_dataset", "out", scope3d.LocalizeOptions(use_reported_poses=False))

Each takes the inputs and the output folder of its pipeline's ``run`` (:mod:`scope3d.pipelines`) in the same
order, then its options (default: the options class's defaults; ``calibrate`` and ``calibrate_hand_eye``
need theirs, they name the board), then ``run``'s keywords (``progress=`` and the job's own); a dataset may
be given as its folder. ``scope3d.<job>.__wrapped__`` is the pipeline's ``run`` itself.
"""
from scope3d.errors import InputError

__version__ = "0.1.0"

# Everything below loads on first use (PEP 562), so that ``import scope3d``, ``scope3d --version`` and
# ``--help`` start without importing NumPy or SciPy (tests/test_cli_startup.py).
_LAZY = {"Camera": "scope3d.sensor.camera", "MeasuredPose": "scope3d.sensor.pose_tolerance",
         "Pose": "scope3d.geometry.pose", "PoseTolerance": "scope3d.sensor.pose_tolerance",
         "Dataset": "scope3d.io.dataset", "load_dataset": "scope3d.io.dataset",
         "MapOptions": "scope3d.pipelines.surgical_map", "MapResult": "scope3d.pipelines.surgical_map",
         "AxialOptions": "scope3d.pipelines.axial", "LocalizeOptions": "scope3d.pipelines.localize",
         "ThreadScanOptions": "scope3d.pipelines.thread_scan", "Panorama3dOptions": "scope3d.pipelines.panorama",
         "MosaicOptions": "scope3d.pipelines.mosaic", "CalibrateOptions": "scope3d.pipelines.calibrate",
         "HandEyeRunOptions": "scope3d.pipelines.hand_eye", "FramesImportOptions": "scope3d.pipelines.frames_import",
         "VideoImportOptions": "scope3d.pipelines.video_import", "TrackMarkersOptions": "scope3d.pipelines.track_markers",
         "ScanPlanOptions": "scope3d.pipelines.scan_plan"}

#: The jobs: the function's name -> (its pipeline, the options class of that pipeline).
JOBS = {"map": ("surgical_map", "MapOptions"), "axial": ("axial", "AxialOptions"),
        "localize": ("localize", "LocalizeOptions"), "thread_scan": ("thread_scan", "ThreadScanOptions"),
        "panorama": ("panorama", "Panorama3dOptions"), "mosaic": ("mosaic", "MosaicOptions"),
        "calibrate": ("calibrate", "CalibrateOptions"), "calibrate_hand_eye": ("hand_eye", "HandEyeRunOptions"),
        "import_frames": ("frames_import", "FramesImportOptions"), "import_video": ("video_import", "VideoImportOptions"),
        "track_markers": ("track_markers", "TrackMarkersOptions"), "plan_scan": ("scan_plan", "ScanPlanOptions")}


def _job(name: str):
    """The package-level function of job ``name``: its pipeline's ``run`` with the options moved after the
    inputs (defaulted) and dataset folders loaded."""
    import functools
    import importlib
    import inspect

    module = importlib.import_module(f"scope3d.pipelines.{JOBS[name][0]}")
    options_class = getattr(module, JOBS[name][1])
    run = module.run
    inputs = [p for p in inspect.signature(run).parameters.values() if p.kind is p.POSITIONAL_OR_KEYWORD][1:]

    @functools.wraps(run)
    def job(*args, options=None, **keywords):
        if len(args) == len(inputs) + 1 and options is None:
            *args, options = args
        if len(args) != len(inputs):
            raise TypeError(f"scope3d.{name}() takes {', '.join(p.name for p in inputs)}[, options], "
                            f"got {len(args)} positional argument(s)")
        args = [_loaded(p.annotation, a) for p, a in zip(inputs, args)]
        return run(options_class() if options is None else options, *args, **keywords)

    job.__name__ = job.__qualname__ = name
    return job


def _loaded(annotation, value):
    """A dataset folder given for a ``Dataset`` (or ``list[Dataset]``) input, loaded."""
    import os

    text = annotation if isinstance(annotation, str) else getattr(annotation, "__name__", "")
    if not text.startswith(("Dataset", "list[Dataset]")):
        return value
    from scope3d.io.dataset import load_dataset

    if text.startswith("list["):
        return [load_dataset(v) if isinstance(v, (str, os.PathLike)) else v for v in value]
    return load_dataset(value) if isinstance(value, (str, os.PathLike)) else value


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
    elif name in JOBS:
        value = _job(name)
    else:
        raise AttributeError(f"module 'scope3d' has no attribute {name!r}")
    globals()[name] = value  # looked up once
    return value


__all__ = ["InputError", "JOBS", "__version__", *sorted(_LAZY), *sorted(JOBS)]
