"""Pipelines: the jobs, each a short script of stage calls, all called one way::

    result = run(options, inputs..., out_dir, *, progress=None)   # a <Job>Result dataclass
    print(result.summary())

* :mod:`.surgical_map` (``scope3d map``), :mod:`.axial`, :mod:`.localize`, :mod:`.track_markers`,
  :mod:`.calibrate`, :mod:`.hand_eye` (``calibrate-hand-eye``), :mod:`.thread_scan`, :mod:`.thread_batch`
  (``batch thread-scan``, on Dask), :mod:`.scan_plan` (``plan-scan``), :mod:`.mosaic`, :mod:`.panorama`
  (the 3-D panorama), :mod:`.video_import` and :mod:`.frames_import` (``import video``, ``import frames``).

Every result pickles (cluster workers send them back); ``tests/test_job_calls.py`` holds every job to this.
The package exports them as ``scope3d.map``, ``scope3d.localize``... (:data:`scope3d.JOBS`: the inputs first,
the options after them). A job whose dataset must meet static requirements has
``check_dataset(options, dataset)``, called first by its ``run`` and alone by ``scope3d check --for JOB``
(:mod:`.surgical_map`, :mod:`.axial`, :mod:`.panorama`, :mod:`.thread_scan`).
"""
