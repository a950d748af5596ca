"""Which frames lost more of their matched observations to the map's reprojection gate than chance allows:
the screen's gate-loss test of the per-frame check of reported poses (:mod:`scope3d.sfm.pose_checks`).

Each frame's count of lost observations is beta-binomial (its rate beta-distributed about a mean whose logit
is linear in the log of the frame's observations), fitted by maximum likelihood on a grid to the *other*
frames of the map (:func:`gate_loss_p_values`); :func:`lost_to_the_gate` names the frames beyond a level.
"""
from __future__ import annotations

import numpy as np

from scope3d.sfm.leave_one_out import FramePoseTest


# the gate-loss test's beta-binomial on one grid (it decides only which frames the exact test sees, and a
# grid makes every frame's leave-one-out likelihood a sum): the logit of the mean lost fraction every 0.1
# (10 % in the odds), its slope in log(observations) every 0.2, log10 of the intra-frame correlation every
# 0.1 (26 %), from nearly binomial (1e-5) to losses almost shared by a frame's observations (0.9)
_GATE_LOGIT = np.arange(-9.0, 3.0 + 1e-9, 0.1)
_GATE_SLOPE = np.arange(-2.0, 1.0 + 1e-9, 0.2)
_GATE_RHO = 10.0 ** np.arange(-5.0, np.log10(0.9) + 1e-9, 0.1)


def _beta_shapes(mean, rho):
    """The beta's shapes ``a, b`` of mean ``mean`` and intra-frame correlation ``rho = 1 / (a + b + 1)``."""
    concentration = 1.0 / rho - 1.0
    return mean * concentration, (1.0 - mean) * concentration


def _beta_binomial_sf(lost: int, total: int, mean: float, rho: float) -> float:
    """P(``lost`` or more of ``total``) under the beta-binomial of ``mean`` and ``rho``, as 1 - P(fewer): a
    frame loses few, so that sum is short (its round-off, ~1e-16, is far below any level it is held to)."""
    from scipy.special import betaln, gammaln

    a, b = _beta_shapes(mean, rho)
    count = np.arange(lost)
    log_pmf = (gammaln(total + 1) - gammaln(count + 1) - gammaln(total - count + 1)
               + betaln(count + a, total - count + b) - betaln(a, b))
    return float(np.clip(1.0 - np.exp(log_pmf).sum(), 0.0, 1.0))


def gate_loss_p_values(total: np.ndarray, lost: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Each frame's p-value of losing ``lost`` of its ``total`` observations under the beta-binomial fitted
    (maximum likelihood on the grid) to the frames of ``keep`` other than itself (see :func:`lost_to_the_gate`)."""
    from scipy.special import betaln, expit

    size = np.log(total) - np.median(np.log(total))  # the covariate, centred: intercept and slope apart
    a, b = _beta_shapes(expit(_GATE_LOGIT)[:, None], _GATE_RHO[None, :])
    table = betaln(lost[:, None, None] + a, (total - lost)[:, None, None] + b) - betaln(a, b)  # (frames, logit, rho)
    frames, logits = len(total), len(_GATE_LOGIT)
    best, argbest = np.full(frames, -np.inf), np.zeros((frames, 3), int)
    for s, slope in enumerate(_GATE_SLOPE):
        # a slope shifts each frame's logit axis by slope * size (rounded to the grid)
        shifted = np.clip(np.arange(logits)[None, :] + np.rint(slope * size / 0.1).astype(int)[:, None], 0, logits - 1)
        terms = table[np.arange(frames)[:, None], shifted]
        others = (terms[keep].sum(axis=0)[None] - keep[:, None, None] * terms).reshape(frames, -1)
        at = others.argmax(axis=1)
        value = others[np.arange(frames), at]
        better = value > best
        best[better] = value[better]
        where = np.column_stack(np.unravel_index(at[better], table.shape[1:]))  # (logit, rho) indices
        argbest[better] = np.c_[np.full(better.sum(), s), where]
    mean = expit(_GATE_LOGIT[argbest[:, 1]] + _GATE_SLOPE[argbest[:, 0]] * size)
    return np.array([_beta_binomial_sf(lost[i], total[i], mean[i], _GATE_RHO[argbest[i, 2]]) if lost[i] > 0 else 1.0
                     for i in range(frames)])


def lost_to_the_gate(screened: dict[int, FramePoseTest], level: float) -> set[int]:
    """Frames that lost more of their matched observations to the map's reprojection gate than the other
    frames of the map do, beyond chance at ``level``: a wrong report's frame sits on its box's edge, where its
    right observations no longer fit and the gate drops them, so the screen, linearised at the bounded map,
    sees only those that fit the wrong pose (dome12, seed 21, frame 6 3 mm off: 84 of 154 kept, screen d2
    0.6; its exact test 123 against 30).

    A frame's losses are not independent draws: a two-view track dropped takes one observation from each of
    its frames (a survey's first two frames often share tracks only with each other and lose the same
    count), and a frame on its box's edge loses a patch of its image at once; and frames with few matched
    observations (the survey's edge: short, two-view tracks, dropped whole) lose a larger fraction (clean
    dome30: 8-22 % of 36-76 observations against 1-3 % of 200-450). The binomial at the median lost fraction
    tested before fired on clean frames far above its level for both reasons (dome30: 2-5 frames of every
    clean map, docs/reliability.md section 5). So the count is beta-binomial: each frame binomial at its own
    rate, the rates beta-distributed with intra-frame correlation ``rho`` (variance ``n mu (1 - mu) (1 + (n -
    1) rho)``) about a mean whose logit is linear in the log of the frame's observations; the three fitted
    (maximum likelihood) to the *other* frames of the map, as the variance factor is estimated without the
    tested frame (:func:`gate_loss_p_values`). Robust as that factor is: a frame
    beyond ``level`` at the fit of all the others is left out of every other frame's fit (once, never leaving
    fewer than 4 frames: a wrong report's neighbours lose observations too, and would otherwise raise
    ``rho`` for its own test). With fewer than 5 frames there is nothing to fit: every frame that lost an
    observation is sent on (the exact test of so few frames is cheap). No threshold of its own.

    Measured (docs/reliability.md section 5): on 19 clean maps (14 of 12 frames, 5 of 30) it sent 5 of 300
    frames on at a level of 1 %, where the binomial sent 16. Its tail is the fit's, not a predictive one:
    a dispersion fitted to about ten frames is mostly too small, and on synthetic maps drawn from the model
    itself (12 frames, rho 0.01) it fires at 3-6x its level (docs/reliability.md section 5); averaging the
    tail over the grid's parameters by their likelihood fired at 0.8-2x, but the check then found 4 of 34
    glitches of 2-5 mm fewer (dome12 and dome30). A frame sent on wrongly costs an exact test, not a false
    alarm.
    """
    # (a screen that could not place any frame lists frames without observations too: nothing to count)
    rows = [(k, t.observations, t.observations - t.inliers) for k, t in screened.items()
            if t.status != "unseen" and t.observations > 0]
    if len(rows) < 5:
        return {k for k, _, lost in rows if lost > 0}
    frames, total, lost = (np.array(column) for column in zip(*rows))
    first = gate_loss_p_values(total, lost, np.ones(len(rows), bool))
    keep = first >= level
    if keep.sum() < 4:
        keep = first >= np.sort(first)[-4]
    return set(frames[gate_loss_p_values(total, lost, keep) < level].tolist())
