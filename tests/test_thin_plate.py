"""The thin-plate spline of the map's surface: scipy's spline, and its tiled evaluation against the exact one."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import RBFInterpolator

from scope3d.scene.thin_plate import ThinPlateSpline


def _wavy_sheet(n, size_mm, seed):
    """Heights of a 0.5 mm-amplitude, 8 mm-wavelength wave with 0.03 mm noise (a printed sheet's relief
    seen through triangulation noise), at n random points of a size_mm square."""
    rng = np.random.default_rng(seed)
    st = rng.uniform(0.0, size_mm, (n, 2))
    h = 0.5 * np.sin(2 * np.pi * st[:, 0] / 8.0) * np.cos(2 * np.pi * st[:, 1] / 11.0) + rng.normal(0, 0.03, n)
    return st, h


def test_spline_is_scipys_thin_plate_spline():
    """Same system as RBFInterpolator(kernel="thin_plate_spline", smoothing): the two solutions differ only
    by the solvers' rounding (condition number ~1e8 here, times 1e-16: far below 1e-6 mm)."""
    st, h = _wavy_sheet(400, 30.0, 0)
    ours = ThinPlateSpline.fit(st, h, 0.5)
    scipys = RBFInterpolator(st, h, kernel="thin_plate_spline", smoothing=0.5)
    query = np.random.default_rng(1).uniform(-2.0, 32.0, (500, 2))
    np.testing.assert_allclose(ours(query), scipys(query), atol=1e-6)
    np.testing.assert_allclose(ours(st), scipys(st), atol=1e-6)
    # without smoothing it interpolates
    exact = ThinPlateSpline.fit(st[:50], h[:50], 0.0)
    np.testing.assert_allclose(exact(st[:50]), h[:50], atol=1e-8)


def test_tiled_evaluation_matches_the_exact_sum():
    """The far centres' sum on a 0.8 mm lattice, bicubic in between: within 1 um of the exact sum on a field
    several tiles wide (measured 0.1-0.2 um; the map's points scatter by tens of um, so 1 um is invisible
    in the surface), and closer on a finer lattice (the interpolation's error, ~lattice^4)."""
    st, h = _wavy_sheet(1500, 60.0, 2)
    spline = ThinPlateSpline.fit(st, h, 0.5)
    grid = np.stack(np.meshgrid(np.arange(0, 60, 0.2), np.arange(0, 45, 0.2)), axis=-1).reshape(-1, 2)
    exact = spline(grid)
    coarse = np.abs(spline.tiled(grid) - exact).max()
    fine = np.abs(spline.tiled(grid, lattice_mm=0.4) - exact).max()
    assert coarse < 1e-3 and fine < coarse / 4, (coarse, fine)
    # a single row of points (a tile one vertex high) still gets its four lattice nodes per axis
    row = np.abs(spline.tiled(grid[:300]) - exact[:300]).max()
    assert row < 1e-3, row
    # centres all within the margin of the points: no far sum, nothing interpolated
    near = ThinPlateSpline.fit(st[(st < 10).all(axis=1)], h[(st < 10).all(axis=1)], 0.5)
    inner = grid[(grid < 10).all(axis=1)]
    assert np.abs(near.tiled(inner) - near(inner)).max() < 1e-12


def test_bad_inputs():
    with pytest.raises(ValueError):
        ThinPlateSpline.fit(np.zeros((5, 3)), np.zeros(5))
    with pytest.raises(ValueError):
        ThinPlateSpline.fit(np.zeros((5, 2)), np.zeros(5), -1.0)
