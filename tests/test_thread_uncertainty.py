"""The gauge's systematic term from the registration's uncertainty, and the pass / fail / indeterminate
verdict on the combined uncertainty (issue 13), on clouds sampled from the phantom's true M8 mesh split
into twelve 30° quadrants, with a registration covariance chosen so its effect is known in closed form."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from scope3d.geometry.pose import Pose
from scope3d.metrology.thread_gauge import GaugeOptions, gauge_thread, profile_parts
from scope3d.metrology.thread_uncertainty import profile_bias_systematic, registration_systematic, with_systematic
from scope3d.phantoms.scenes import build_thread
from scope3d.registration.panorama import PanoramaResult, StagePoseModel

NOISE_MM = 0.01  # a sparse reconstruction's point noise
MOUNT_SHIFT_SIGMA_MM = 0.005  # the mount offset's 1-sigma, the size the joint solve states on the 90° scans
DRAWS = 16
MC_DRAWS = 60  # repeated measurements in the Monte Carlo below: its spread is good to 1 / sqrt(118) = 9 %


def _panorama(mount_shift_sigma_mm: float = MOUNT_SHIFT_SIGMA_MM) -> PanoramaResult:
    """A registered panorama of 12 quadrants at 30° steps, estimate = truth, whose only uncertainty is the
    camera's offset along quadrant 0's +x (the stage model's mount shift): each draw moves quadrant q by
    that shift turned by its stage angle, i.e. radially for the sector it faces, so every diameter moves
    by twice the draw."""
    angles = np.deg2rad(30.0 * np.arange(12))
    n = 4 + 2 * 11
    cov = np.diag(np.full(n, 1e-14))
    cov[2, 2] = mount_shift_sigma_mm**2
    return PanoramaResult([Pose.identity()] * 12, [], None, None, [], 30.0, True, [], np.zeros(n), cov,
                          StagePoseModel(angles))


@pytest.fixture(scope="module")
def scene():
    return build_thread("M8x1.25", minor_diameter_offset_mm=0.132, pitch_diameter_offset_mm=0.08,
                        major_diameter_offset_mm=0.05)


def _scanned(scene) -> tuple[np.ndarray, np.ndarray]:
    """Points on the true wall where a 4.5 mm 90° scan sees it (no noise yet), and each point's quadrant
    (the 30° sector it faces)."""
    surface, _ = trimesh.sample.sample_surface(scene.mesh.to_trimesh(), 24000, seed=1)
    surface = surface[(surface[:, 2] < -1.5) & (surface[:, 2] > -7.5)]
    angle = np.mod(np.arctan2(surface[:, 1], surface[:, 0]), 2 * np.pi)
    return surface, np.round(angle / np.deg2rad(30.0)).astype(int) % 12


def _moved(points, quadrant_of, panorama, world_from_stacked) -> np.ndarray:
    """Every quadrant's points moved by one draw of the registration, as registration_systematic does."""
    moved = points.copy()
    for q, (g_draw, g_est) in enumerate(zip(world_from_stacked, panorama.world_from_stacked)):
        moved[quadrant_of == q] = (g_draw @ g_est.inverse()).transform(points[quadrant_of == q])
    return moved


def test_registration_uncertainty_gives_the_verdict_its_guard_band(scene):
    made = scene.info["thread"]["as_made"]
    surface, quadrant_of = _scanned(scene)
    surface = surface + np.random.default_rng(1).normal(0.0, NOISE_MM, surface.shape)
    options = GaugeOptions(designation="M8x1.25", axis_hint=(0.0, 0.0, 1.0))
    d2_max = 7.348  # ISO 965-2, M8x1.25-6H

    verdicts = {}
    # Pushing the surface out radially by s makes every diameter 2 s larger: a conforming mid-class hole,
    # one with its pitch diameter 0.004 mm inside the no-go limit, and one 0.04 mm beyond it.
    for name, d2 in (("mid", made["pitch_diameter_mm"]), ("near", d2_max - 0.004), ("out", d2_max + 0.04)):
        s = (d2 - made["pitch_diameter_mm"]) / 2
        points = surface * np.array([1 + s / np.hypot(*surface[:, :2].T)] * 2 + [np.ones(len(surface))]).T
        alone = gauge_thread(points, options=options)
        # statistical alone: the fit's uncertainty from 0.01 mm independent noise over thousands of points
        assert alone.pitch_diameter_mm.uncertainty < 0.0015
        assert abs(alone.pitch_diameter_mm.value - d2) < 0.005  # sampling + tessellation, as the gauge tests
        panorama = _panorama()
        systematic = registration_systematic(alone, panorama.sample_world_from_stacked(DRAWS, 3),
                                             panorama.world_from_stacked, points, quadrant_of, options.noise_mm)
        # each diameter moves by twice the mount shift; the spread of 16 draws is good to 1/sqrt(30) = 18 %
        # (1 sigma): within 3 sigma
        for key in ("minor_diameter", "pitch_diameter", "major_diameter"):
            assert abs(systematic[key] / (2 * MOUNT_SHIFT_SIGMA_MM) - 1) < 0.55, (key, systematic)
        assert systematic["pitch"] < 2e-4  # a radial shift does not change the pitch
        combined = with_systematic(alone, systematic, options=options)  # the combination: see the Monte Carlo below
        assert combined.pitch_diameter_mm.systematic == systematic["pitch_diameter"]
        verdicts[name] = (alone.verdict, combined.verdict)
    assert verdicts["mid"] == ("pass", "pass")
    # 0.004 mm inside the limit: proven by the fit's own ~0.001 mm, not by a 0.01 mm registration term
    assert verdicts["near"] == ("pass", "indeterminate")
    assert verdicts["out"] == ("fail", "fail")


def test_profile_bias_term_matches_the_closed_form_of_each_part(scene):
    """A part's points moved by b along the surface normal: the crest moves D1 by 2 b, the root D by 2 b, and
    each flank the pitch radius by b (the symmetric tooth, half a pitch wide at D2, narrows by the flank's
    axial shift b / cos 30° shared between its sides, tan 30° per unit of radius): D2 by 2 b per flank, 2 sqrt(2) b
    for the two in quadrature."""
    surface, _ = trimesh.sample.sample_surface(scene.mesh.to_trimesh(), 24000, seed=2)
    surface = surface[(surface[:, 2] < -1.5) & (surface[:, 2] > -7.5)]
    surface += np.random.default_rng(2).normal(0.0, NOISE_MM, surface.shape)
    options = GaugeOptions(designation="M8x1.25", axis_hint=(0.0, 0.0, 1.0))
    result = gauge_thread(surface, options=options)
    part, normal = profile_parts(result, surface)
    assert set(np.unique(part)) == {0, 1, 2, 3}
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0)
    bias = 0.004
    sigma = profile_bias_systematic(result, surface, bias, options.noise_mm)
    # closed forms; 15 % for the fit's coupling of the parts (a moved crest also pulls the flanks' ends)
    assert abs(sigma["minor_diameter"] / (2 * bias) - 1) < 0.15, sigma
    assert abs(sigma["major_diameter"] / (2 * bias) - 1) < 0.15, sigma
    assert abs(sigma["pitch_diameter"] / (2 * np.sqrt(2) * bias) - 1) < 0.15, sigma
    assert sigma["pitch"] < 1e-4  # a profile offset leaves the helix' pitch alone


def test_combined_uncertainty_is_the_spread_of_repeated_measurements_under_both_errors(scene):
    """The budget against an independent truth, not against its own formula: the pitch diameter measured
    MC_DRAWS times, each with new point noise and a new draw of the registration (the mount shift), by the
    whole gauge; the spread of those measurements is what the combined uncertainty must state. The mount's
    sigma is chosen so that both terms are alike (~0.001 mm each): there, adding them linearly or dropping
    one is 30-40 % off the quadrature sum, beyond the sampling tolerance below."""
    surface, quadrant_of = _scanned(scene)
    options = GaugeOptions(designation="M8x1.25", axis_hint=(0.0, 0.0, 1.0))
    rng = np.random.default_rng(4)
    panorama = _panorama(mount_shift_sigma_mm=0.0005)
    noisy = surface + rng.normal(0.0, NOISE_MM, surface.shape)
    alone = gauge_thread(noisy, options=options)
    systematic = registration_systematic(alone, panorama.sample_world_from_stacked(MC_DRAWS, 3),
                                         panorama.world_from_stacked, noisy, quadrant_of, options.noise_mm)
    stated = with_systematic(alone, systematic, options=options).pitch_diameter_mm.uncertainty
    measured = [gauge_thread(_moved(surface, quadrant_of, panorama, draw) + rng.normal(0.0, NOISE_MM, surface.shape),
                             options=options).pitch_diameter_mm.value
                for draw in panorama.sample_world_from_stacked(MC_DRAWS, 5)]
    spread = np.std(measured, ddof=1)
    # a standard deviation from n draws is good to 1 / sqrt(2 (n - 1)) (1 sigma): the Monte Carlo's, and the
    # budget's systematic term (from as many draws), which weighs (u_sys / u)^2 in the stated u; within 3 sigma
    weight = (systematic["pitch_diameter"] / stated) ** 2
    tolerance = 3.0 * np.hypot(1.0, weight) / np.sqrt(2 * (MC_DRAWS - 1))
    assert abs(spread / stated - 1) < tolerance, (spread, stated, alone.pitch_diameter_mm.uncertainty, systematic)
