"""The variance factor of the images' covariances: how much larger the images' errors are than their
residuals say, estimated from the frames' disagreements with their reports (a variance component, as in
geodesy), robust to wrong reports among them; the scale the per-frame check of reported poses
(:mod:`scope3d.sfm.pose_checks`) multiplies each frame's leave-one-out covariance by
(:func:`scale_of_images`; :func:`scale_terms` and :func:`scale_from_terms` serve many sets of frames from
one computation per frame).
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from scope3d.sensor.pose_tolerance import MeasuredPose
from scope3d.sfm.leave_one_out import FramePoseTest


def scale_of_images(tests: list[FramePoseTest], measured: list[MeasuredPose],
                    level: float) -> tuple[float, float, list[int]]:
    """How much larger the images' errors are than their residuals say (at least 1), from ``tests``' frames
    (the other frames than the one it will scale), the degrees of freedom of that estimate, and the frames
    left out of it as outliers.

    Each frame's estimate differs from its report by two independent errors, the images' (covariance
    ``f C_j``) and the report's (uniform in its box, variance ``B_j = half^2 / 3``): ``e_j ~ (0, f C_j +
    B_j)``. ``f`` is their maximum-likelihood scale, taken as Gaussian (a variance component, as in
    geodesy): in the box-whitened eigenbasis of ``C_j`` (eigenvalues ``l``, squared projections ``p``) it
    solves ``sum l / (f l + 1) (p / (f l + 1) - kappa) = 0``. Not ``median_j e_j^T (C_j + B_j)^-1 e_j /
    chi2.median(6)``, an earlier estimate: where a report's box outweighs the images' error that ratio
    hardly grows with ``f``, and on the dome it came out at 1.7-2.7 where the scale solved with the boxes
    is 2.5-6.9 (5 clean 12-frame maps): clean frames' statistics were 2x too large, which was most of the
    false alarms (docs/reliability.md section 5). Needed at all: with every other frame held at its true
    pose, dome frames' image-only estimates were off by 1.5-3x their covariance in sigma (keypoint errors
    of nearby views of one texture are not independent, and their tails are heavy: median 0.09 px, RMS
    0.32 px).

    Robust to wrong reports among the others: a mean of squares, which one wrong report inflates for every
    other frame's test (dome12, seed 22, a 3 mm glitch: 8.5-9.5 against 6.5). So a frame whose own
    disagreement ``q_j = e_j^T (f_j C_j + B_j)^-1 e_j`` is beyond ``c = chi2.isf(level, 6)``, at the scale
    ``f_j`` of all the other frames, is left out (``level`` is the test's per-frame level: a frame the test
    itself would reject does not set the scale); once, not iterated (see the code). Leaving out the tail
    of a right frame's ``q`` biases the mean square low; the score's ``kappa = E[z | q <= c] = F_8(c) /
    F_6(c)`` (each of the 6 whitened squares ``z`` of a chi-square(6) ``q`` truncated at ``c``, by symmetry)
    corrects that, with no threshold of its own.

    The degrees of freedom are ``2 f^2 / Var(f)``, ``Var(f)`` by the sandwich of that score under the
    truncated model (``E[z_i z_k | q <= c] = (1 + 2 delta_ik) F_10(c) / F_6(c)``, from ``z = q D`` with
    ``D`` Dirichlet(1/2, ..., 1/2) independent of ``q``); without truncation this is the Fisher information
    ``sum (f l / (f l + 1))^2``: a direction the images fix far better than the box (``f l << 1``) says
    nothing about ``f`` and counts for nothing, one they fix far worse counts 1. So ``d2 / f`` of the
    tested frame is about ``6 F(6, dof)``: 14-38 from 8-10 other dome frames, and the critical value at
    0.1 % 30-46 instead of 23. The tested frame's own disagreement is never in it.
    """
    if len(tests) < 3:  # too few frames to tell: the residuals' own scale, with their (large) redundancy
        return 1.0, float(min((t.dof for t in tests), default=1)), []
    return scale_from_terms([scale_terms(t, measured[t.frame], level) for t in tests], tests)


# every frame's score term on one grid of log f, 2.7 % apart in f (the smooth score interpolated linearly
# between them errs by ~1e-4 relatively, against the scale's own 4-25 % uncertainty), so that the scale of
# any set of frames is a sum and a root search
_SCALE_GRID = np.linspace(0.0, np.log(1e12), 1025)


@lru_cache(maxsize=64)
def _truncation(level: float) -> tuple[float, float, float]:
    """The cut ``c = chi2.isf(level, 6)`` and the truncated moments ``kappa = F_8(c) / F_6(c)`` and
    ``F_10(c) / F_6(c)`` (see :func:`scale_of_images`); scipy.special's functions, which scipy.stats's
    chi2 calls with milliseconds of checks around each (a map asks twice per frame)."""
    from scipy.special import chdtr, chdtri

    cut = float(chdtri(6, level))
    inside = chdtr(6, cut)
    return cut, float(chdtr(8, cut) / inside), float(chdtr(10, cut) / inside)


def scale_terms(t: FramePoseTest, m: MeasuredPose, level: float) -> tuple[np.ndarray, ...]:
    """One frame's share of :func:`scale_of_images`: its squared projections ``p`` and eigenvalues ``l`` (6,)
    in the box-whitened eigenbasis of its covariance, and its score terms on the grid, (grid,) each, with
    ``kappa`` 1 and the truncated one (computed once per test, whatever set of frames it then serves)."""
    half = np.maximum(np.r_[m.tolerance.orientation_rad, m.tolerance.position_mm], 1e-6)
    inv_sqrt_box = np.where(np.isfinite(half), np.sqrt(3.0) / half, 0.0)  # B^-1/2 (an unknown box: 0)
    # (f C + B)^-1 = D (f D C D + I)^-1 D with D = B^-1/2: one eigen-decomposition serves every f
    values, vectors = np.linalg.eigh(inv_sqrt_box[:, None] * t.covariance * inv_sqrt_box[None, :])
    p = (vectors.T @ (inv_sqrt_box * t.offset)) ** 2
    lam = np.maximum(values, 0.0)
    kappa = _truncation(level)[1]
    inverse = 1.0 / (np.exp(_SCALE_GRID)[:, None] * lam[None, :] + 1.0)  # (grid, 6)
    return (p, lam, *(np.sum(lam[None, :] * inverse * (p[None, :] * inverse - k), axis=1) for k in (1.0, kappa)),
            level)


def scale_from_terms(terms: list[tuple[np.ndarray, ...]],
                     tests: list[FramePoseTest]) -> tuple[float, float, list[int]]:
    """:func:`scale_of_images` from its frames' :func:`scale_terms`."""
    grid = _SCALE_GRID
    p, lam = np.array([t[0] for t in terms]), np.array([t[1] for t in terms])
    plain, truncated = np.array([t[2] for t in terms]), np.array([t[3] for t in terms])
    cut, kappa, second = _truncation(terms[0][4])

    def root(score: np.ndarray) -> np.ndarray:
        """The scale at which each row of ``score`` (m, grid: the score ``sum l / (f l + 1) (p / (f l + 1) -
        kappa)`` of some frames, which falls with f) crosses zero, interpolated on the grid; 1 where it is not
        positive at f = 1 (the residuals' own scale is not understated)."""
        last = np.sum(score > 0, axis=1) - 1  # the last grid point with a positive score
        i = np.clip(last, 0, len(grid) - 2)
        s0, s1 = score[np.arange(len(score)), i], score[np.arange(len(score)), i + 1]
        log_f = grid[i] + (grid[i + 1] - grid[i]) * s0 / np.where(s0 > s1, s0 - s1, 1.0)
        return np.where(last >= 0, np.exp(log_f), 1.0)

    # each frame judged at the scale of all the others, as the test judges the tested frame: judged at a scale
    # it raised itself, a wrong report can hide (seed 22, 3 mm: its q at 9 is within the cut, at the others'
    # 6.5 beyond it). Once, not iterated: trimming again at the scale the trimming lowered cascades where right
    # frames' errors have heavier tails than a Gaussian's (dome12, seed 21, a 3 mm glitch set aside: iterated,
    # a neighbour's factor fell to its floor of 1; once, it stays at 7)
    scales = root(np.ones(len(terms)) @ plain - plain)  # every frame's score, less each frame's own
    q = np.sum(p / (scales[:, None] * lam + 1.0), axis=1)
    # never fewer than 3 frames (a map of few frames and several wrong reports cannot be told apart)
    keep = q <= max(cut, float(np.sort(q)[2]))
    factor = float(root((keep @ truncated)[None])[0])
    a = lam[keep] / (factor * lam[keep] + 1.0)
    information = kappa * np.sum(a**2)
    score_variance = np.sum(second * (2.0 * np.sum(a**2, axis=1) + np.sum(a, axis=1) ** 2)
                            - kappa**2 * np.sum(a, axis=1) ** 2)
    dof = 2.0 * factor**2 * information**2 / max(score_variance, 1e-300)
    return factor, max(float(dof), 1.0), [t.frame for t, k in zip(tests, keep) if not k]
