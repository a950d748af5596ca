"""Same input and seed, same output files byte for byte: across runs and across 1 and 2 threads (numba,
OpenMP, OpenBLAS). report.json is compared without its timing fields (scope3d.utils.jsonio.without_timings),
every other file as bytes. The kill harness (tests/kill_harness.py) also checks run-to-run identity: its
last uninterrupted run must reproduce the first."""
import pytest

from kill_harness import environment, jobs, make_inputs, run_to_completion, snapshot


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    return make_inputs(tmp_path_factory.mktemp("determinism") / "in")


@pytest.mark.parametrize("name", ["phantom", "map", "bundle-adjust", "axial"])
def test_one_and_two_threads_write_identical_files(inputs, tmp_path, name):
    # the same folder name under two parents: dataset.json records the folder's name
    one = {j.name: j for j in jobs(inputs, tmp_path / "threads1")}[name]
    two = {j.name: j for j in jobs(inputs, tmp_path / "threads2")}[name]
    run_to_completion(one, environment(threads=1))
    run_to_completion(two, environment(threads=2))
    a, b = snapshot(one.out), snapshot(two.out)
    assert len(a) >= 3  # a dataset (phantom) or a result folder with its report
    differing = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
    assert not differing, differing
