"""One ``threads`` convention (scope3d.utils.threads): 0 is every core the process may run on, n >= 1 at
most n, never more threads than tasks; every options class with ``threads`` takes it."""
from __future__ import annotations

import os

import pytest

from scope3d.feature.matching import MatchOptions
from scope3d.metrology.evaluation import EvaluationOptions
from scope3d.pipelines.surgical_map import MapOptions
from scope3d.pipelines.thread_scan import ThreadScanOptions
from scope3d.sfm.cavity_mapping import CavityOptions
from scope3d.sfm.coarse_poses import CoarseOptions
from scope3d.utils.threads import available_cores, check_threads, resolve_threads


def test_zero_is_every_core_the_process_may_use():
    expected = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assert available_cores() == expected
    assert resolve_threads(0) == expected
    assert resolve_threads(3) == 3
    assert resolve_threads(0, tasks=1) == resolve_threads(5, tasks=1) == 1  # no thread without work
    assert resolve_threads(0, tasks=0) == 1


@pytest.mark.parametrize("options", [MatchOptions, EvaluationOptions, MapOptions, ThreadScanOptions, CoarseOptions,
                                     CavityOptions])
def test_every_threads_option_defaults_to_every_core_and_refuses_a_negative_count(options):
    assert options().threads == 0
    assert options(threads=1).threads == 1
    with pytest.raises(ValueError, match="threads"):
        options(threads=-1)
    with pytest.raises(ValueError, match="threads"):
        check_threads(True)
