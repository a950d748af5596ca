"""Does the per-frame pose check (scope3d.sfm.pose_checks) hold its stated false-alarm rate? (issue 16 section 5)

For each case (survey, seed, glitch) the map's stages run up to the bounded adjustment, then the check
alone (cheaper than two whole maps, which benchmarks/bench_pose_outliers.py runs), twice on the same map:
the default (``screened``: the screen, then the local exact test where it points) and the reference, every
frame's full leave-one-out (``--no-reference`` skips it: 30-60 s of CPU on a 30-frame map). Recorded per frame:
the statistic d2, its critical value, the p-value, and d2 against the *true* pose (what the test assumes is
about 6 F(6, nu)); per case: flagged frames, hits (glitched frames found), false alarms, the variance
factor, CPU time. A glitch moves frame n // 2's reported centre along x by G mm (``dome12:21:3``) or turns
its reported orientation about x by G degrees (``dome12:21:2deg``); ``dome12:22:3@5`` glitches frame 5
instead. Surveys: ``dome12`` (12 frames of the
5x6 grid), ``dome30`` (the whole 5x6 grid), ``dome56`` (the 7x8 grid); 320 x 240, reports +-0.5 mm /
+-0.25 deg.

    PYTHONPATH=src python benchmarks/bench_pose_check_rate.py --cases dome12:21:0,dome12:21:3,dome12:21:2deg
    PYTHONPATH=src python benchmarks/bench_pose_check_rate.py --sweep 21,22,23,24,25   # the detection curve

The detection power the noise model predicts: under it a frame's estimate is ``N(truth, f C)`` (its scaled
covariance), so for a glitch ``g`` the statistic is the box distance of ``offset_clean - g`` with
``offset_clean ~ N(truth - report, f C)``; its chance of exceeding the frame's critical value is drawn
(``POWER_DRAWS``) for every glitched frame (``predicted_power``) and, over a range of glitch sizes, for
every tested frame of the clean maps (``predicted_curve``: what that geometry can detect at all).
``--sweep`` runs the glitch sizes 0.5, 1, 2, 3, 5 mm and 1, 2, 5 deg on each seed's frame n // 2 and
draws results/pose_check_detection.png: found / runs against the predicted power.

Results: results/pose_check_rate.json (merged with the cases already there), with a summary per survey:
clean maps with a false alarm and the 95 % upper confidence bound on that rate (Clopper-Pearson), and
how many clean frames' statistic against the *true* pose exceeded their critical value (the model says a
fraction ``false_alarm_rate / frames`` of them).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from scope3d import phantoms  # noqa: E402
from scope3d.feature.tracks import build_tracks  # noqa: E402
from scope3d.geometry.pose import Pose  # noqa: E402
from scope3d.geometry.rotation import matrix_to_rotvec, rotvec_to_matrix  # noqa: E402
from scope3d.io.dataset import Dataset, load_dataset  # noqa: E402
from scope3d.pipelines import surgical_map as sm  # noqa: E402
from scope3d.sensor.pose_tolerance import MeasuredPose  # noqa: E402
from scope3d.sfm.leave_one_out import (LeaveOneOutOptions, box_mahalanobis, linearise,  # noqa: E402
                                       screen_reported_poses)
from scope3d.sfm.pose_checks import PoseCheckOptions, check_pose_reports  # noqa: E402
from scope3d.sfm.variance_factor import scale_of_images  # noqa: E402
from scope3d.utils.jsonio import write_json  # noqa: E402

SURVEYS = {"dome12": ("grid5x6", 12), "dome30": ("grid5x6", 30), "dome56": ("grid7x8", 56)}


SWEEP_MM, SWEEP_DEG = (0.5, 1.0, 2.0, 3.0, 5.0), (1.0, 2.0, 5.0)
CURVE_MM, CURVE_DEG = np.linspace(0.0, 6.0, 13), np.linspace(0.0, 8.0, 9)
POWER_DRAWS = 200  # Monte Carlo draws per frame and glitch size: a power's standard error <= 3.5 %


def predicted_power(offset: np.ndarray, covariance: np.ndarray, half: np.ndarray, critical: float,
                    rng: np.random.Generator, draws: int = POWER_DRAWS) -> float:
    """P(box distance of N(offset, covariance) > critical): the test's power under the noise model when the
    truth lies ``offset`` (w rad, centre mm) from the report."""
    samples = rng.multivariate_normal(offset, covariance, size=draws, method="eigh")
    return float(np.mean([box_mahalanobis(x, covariance, half)[0] > critical for x in samples]))


def glitch_vector(kind: str, size: float) -> np.ndarray:
    """The offset a glitch adds to the report: a centre moved along x (mm) or a turn about x (deg)."""
    return np.r_[0.0, 0.0, 0.0, size, 0.0, 0.0] if kind == "mm" else np.r_[np.deg2rad(size), 0.0, 0.0, 0.0, 0.0, 0.0]


def glitched_dataset(survey: str, seed: int, shift_mm: float, tmp: Path, turn_deg: float = 0.0,
                     frame: int | None = None) -> tuple[Dataset, list[int]]:
    """The survey's dome phantom (320 x 240, reports within 0.5 mm) written under ``tmp``, one frame's report
    (``frame``, default the middle one) moved ``shift_mm`` along x and turned ``turn_deg`` about x; -> (the
    dataset, the glitched frames: none without a glitch)."""
    trajectory, n = SURVEYS[survey]
    seq = phantoms.generate("dome", trajectory, size=(320, 240), seed=seed, n_frames=n, pose_noise_mm=0.5)
    dataset = load_dataset(phantoms.write(seq, tmp / f"{survey}_{seed}"))
    glitched = [n // 2 if frame is None else frame] if shift_mm or turn_deg else []
    poses = list(dataset.poses)
    for k in glitched:
        m = poses[k]
        rotation = rotvec_to_matrix(np.deg2rad([turn_deg, 0.0, 0.0])) @ m.pose.rotation
        poses[k] = MeasuredPose(Pose.from_centre(rotation, m.pose.centre + [shift_mm, 0.0, 0.0]), m.tolerance)
    return replace(dataset, poses=poses), glitched


def one_case(survey: str, seed: int, shift_mm: float, tmp: Path, turn_deg: float = 0.0, frame: int | None = None,
             reference: bool = True) -> dict:
    """One case: the reference (every frame's full leave-one-out, ``PoseCheckOptions(screen=False, local=False)``)
    unless ``reference`` is False, and the default (``"screened"``: the screen, then the local exact test where it
    points); the per-frame rows are the reference's, or the default's without it."""
    dataset, glitched = glitched_dataset(survey, seed, shift_mm, tmp, turn_deg, frame)
    options = replace(sm.MapOptions(), figures=False, fluorescence=None,
                      pose_check=PoseCheckOptions(screen=False, local=False))
    t0 = time.process_time()
    frames = [dataset.frame(k) for k in range(len(dataset))]
    features = sm.detect_features(options, dataset, frames)
    matching = sm.match_frames(options, dataset, features)
    sparse = sm.reconstruct(options, dataset, features, matching)
    tracks = build_tracks(features, matching.matches, min_track_length=options.tracks.min_track_length)
    stages_cpu = time.process_time() - t0
    args = (sparse.camera, dataset.poses, tracks, sparse.poses, options.tracks)
    t0 = time.process_time()
    screened_check = check_pose_reports(*args, PoseCheckOptions())  # the default: the screen, then local exact tests
    screened_cpu = time.process_time() - t0
    t0 = time.process_time()
    check = check_pose_reports(*args, options.pose_check) if reference else screened_check  # every frame's full one
    cpu = time.process_time() - t0 if reference else float("nan")
    screen = screen_statistics(*args, check.false_alarm_rate)
    truth = dataset.ground_truth.poses
    rng = np.random.default_rng(seed)
    frames_out = []
    curve = {"mm": np.zeros(len(CURVE_MM)), "deg": np.zeros(len(CURVE_DEG)), "frames": 0}
    for t in check.tests:
        row = {"frame": t.frame, "status": t.status}
        if t.status != "ok":
            row.update(observations=t.observations, fitted=t.inliers, why=t.why)
        else:
            report = dataset.poses[t.frame].pose
            true_offset = np.r_[matrix_to_rotvec(truth[t.frame].rotation @ report.rotation.T),
                                truth[t.frame].centre - report.centre]
            e = t.offset - true_offset
            if t.frame in screen and "offset" not in screen[t.frame]:
                row.update(screen[t.frame])
            if t.frame in screen and "offset" in screen[t.frame]:
                row.update(screen[t.frame], screen_d2_vs_truth=round(float(
                    (screen[t.frame]["offset"] - true_offset) @ np.linalg.solve(screen[t.frame]["covariance"],
                                                                                screen[t.frame]["offset"] - true_offset)), 3))
                del row["offset"], row["covariance"]
            row.update(d2=round(t.statistic, 3), critical=round(t.critical_value, 2), p_value=t.p_value,
                       variance_factor=round(t.variance_factor, 3), factor_dof=round(t.factor_dof, 1),
                       d2_vs_truth=round(float(e @ np.linalg.solve(t.covariance, e)), 3), flagged=t.flagged,
                       error_vs_truth_mm=round(float(np.linalg.norm(e[3:])), 3))
            half = np.r_[dataset.poses[t.frame].tolerance.orientation_rad, dataset.poses[t.frame].tolerance.position_mm]
            if t.frame in glitched:
                row["predicted_power"] = predicted_power(true_offset, t.covariance, half, t.critical_value, rng)
            elif not glitched and not t.flagged and reference:  # what this frame's geometry could detect, were it glitched
                curve["frames"] += 1
                for kind, sizes in (("mm", CURVE_MM), ("deg", CURVE_DEG)):
                    curve[kind] += [predicted_power(true_offset - glitch_vector(kind, g), t.covariance, half,
                                                    t.critical_value, rng, POWER_DRAWS // 8) for g in sizes]
        frames_out.append(row)
    flagged = check.flagged
    return {"survey": survey, "seed": seed, "shift_mm": shift_mm, "turn_deg": turn_deg, "glitched": glitched,
            "flagged": flagged,
            "hits": len(set(flagged) & set(glitched)), "false_alarms": sorted(set(flagged) - set(glitched)),
            "variance_factor": check.variance_factor, "frames_tested": sum(r["status"] == "ok" for r in frames_out),
            "check_cpu_s": round(cpu, 2), "stages_cpu_s": round(stages_cpu, 2), "reference": reference,
            "screened": {"flagged": [int(k) for k in screened_check.flagged], "hits": len(set(screened_check.flagged) & set(glitched)),
                         "false_alarms": sorted(int(k) for k in set(screened_check.flagged) - set(glitched)),
                         "frames_tested_exactly": int(sum(t.exact and np.isfinite(t.statistic) for t in screened_check.tests)),
                         "check_cpu_s": round(screened_cpu, 2)},
            "load_average": list(os.getloadavg()), "frames": frames_out,
            **({"predicted_curve": {"frames": curve["frames"], "mm": CURVE_MM.tolist(), "deg": CURVE_DEG.tolist(),
                                    "power_mm": (curve["mm"] / max(curve["frames"], 1)).round(3).tolist(),
                                    "power_deg": (curve["deg"] / max(curve["frames"], 1)).round(3).tolist()}}
               if curve["frames"] else {})}


def screen_statistics(camera, measured, tracks, poses, track_options, rate: float) -> dict[int, dict]:
    """Every frame's linearised leave-one-out (the screen), scaled and judged as its exact test is (the
    other screened frames' variance factor, the test's per-frame level): for the scatter against the exact
    statistic."""
    from scipy.stats import f as f_dist

    testable = [k for k in range(len(measured)) if not measured[k].tolerance.is_exact]
    model = linearise(camera, measured, tracks, poses, track_options, LeaveOneOutOptions())
    screened = screen_reported_poses(model, measured, testable, tracks, LeaveOneOutOptions())
    alpha = rate / max(len(testable), 1)
    out = {}
    for k, t in screened.items():
        if t.status != "ok":
            out[k] = {"screen_status": t.status}
            continue
        factor, dof, _ = scale_of_images([s for j, s in screened.items() if j != k and s.status == "ok"], measured, alpha)
        half = np.r_[measured[k].tolerance.orientation_rad, measured[k].tolerance.position_mm]
        out[k] = {"screen_status": "ok", "screen_d2": round(box_mahalanobis(t.offset, factor * t.covariance, half)[0], 3),
                  "screen_critical": round(6.0 * float(f_dist.isf(alpha, 6, dof)), 2),
                  "screen_kept": int(t.inliers), "offset": t.offset, "covariance": factor * t.covariance}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="", help="comma-separated survey:seed:shift_mm or survey:seed:Gdeg, "
                                                 "optionally @frame (default n // 2)")
    ap.add_argument("--sweep", default="", help="comma-separated dome12 seeds: each clean and glitched by "
                                                 "0.5, 1, 2, 3, 5 mm and 1, 2, 5 deg; then the detection curve")
    ap.add_argument("--map-dome", action="store_true",
                    help="also map benchmarks/bench_map_dome.py's bounded tracker and robot cases (608 x 608, 30 "
                         "frames) with the check and without: would turning it on by default change them?")
    ap.add_argument("--no-reference", action="store_true",
                    help="skip the reference (every frame's full leave-one-out: a bounded adjustment of the whole map "
                         "per frame, 30-60 s on dome30): the default check alone")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "pose_check_rate.json"))
    args = ap.parse_args(argv)
    out = Path(args.out)
    previous = json.loads(out.read_text()) if out.is_file() else {}
    runs, default = previous.get("runs", []), previous.get("map_dome_with_and_without", {})
    tmp = Path(tempfile.mkdtemp(prefix="pose_check_rate_"))
    out.parent.mkdir(parents=True, exist_ok=True)

    def save() -> None:  # after every case: a long sweep stopped half-way keeps what it measured
        write_json(out, {"summary": summary(runs), "map_dome_with_and_without": default, "runs": runs})

    if args.map_dome:
        default = map_dome_with_and_without(tmp)
        print(json.dumps(default, indent=1), flush=True)
        save()
    cases = [c for c in args.cases.split(",") if c]
    cases += [f"dome12:{seed}:{g:g}" for seed in args.sweep.split(",") if seed for g in (0, *SWEEP_MM)]
    cases += [f"dome12:{seed}:{g:g}deg" for seed in args.sweep.split(",") if seed for g in SWEEP_DEG]
    for case in cases:
        survey, seed, size = case.split(":")
        size, frame = size.split("@") if "@" in size else (size, None)
        shift, turn = (0.0, float(size[:-3])) if size.endswith("deg") else (float(size), 0.0)
        row = one_case(survey, int(seed), shift, tmp, turn, None if frame is None else int(frame), not args.no_reference)
        print(json.dumps({k: v for k, v in row.items() if k != "frames"}), flush=True)
        runs = [r for r in runs if _key(r) != _key(row)] + [row]
        save()
    print(json.dumps(summary(runs), indent=1))
    plot_detection(runs, out.with_name("pose_check_detection.png"))
    plot_screen(runs, out.with_name("pose_check_screen.png"))
    return 0


def map_dome_with_and_without(tmp: Path) -> dict:
    """bench_map_dome.py's dome (5x6 grid, 608 x 608, seed 0) with its tracker and robot reports, mapped in
    bounded mode with the pose check and without, in this process: surface error, frames flagged, CPU."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_map_dome import POSE_SOURCES, measured_poses

    seq = phantoms.generate("dome", "grid5x6", seed=0)
    rows = {"load_average_before": list(os.getloadavg())}
    for source in ("tracker", "robot"):
        seq.measured_poses = measured_poses(source, seq.true_poses)
        dataset = load_dataset(phantoms.write(seq, tmp / f"dome_{source}"))
        rows[source] = {"description": POSE_SOURCES[source]}
        for name, check in (("without", None), ("with", PoseCheckOptions())):
            options = replace(sm.MapOptions(pose_mode="bounded"), figures=False, pose_check=check)
            t0 = time.process_time()
            report = sm.run(options, dataset, tmp / f"out_{source}_{name}").report
            test = report["model_checks"].get("reported_pose_test")
            rows[source][name] = {
                "cpu_s": round(time.process_time() - t0, 2), "pose_check_wall_s": report["timings_s"].get("pose check"),
                "direct_mean_mm": report["surface_error_mm"]["direct"]["mean"],
                "after_icp_mean_mm": report["surface_error_mm"]["after_icp"]["mean"],
                "flagged": [f["frame"] for f in test["flagged"]] if test else None,
                "variance_factor": test["variance_factor"] if test else None}
    rows["load_average_after"] = list(os.getloadavg())
    return rows


def _key(row: dict) -> tuple:
    return row["survey"], row["seed"], row["shift_mm"], row.get("turn_deg", 0.0), tuple(row["glitched"])


def plot_screen(runs: list[dict], path: Path) -> None:
    """The screen's statistic against the exact test's, each over its frame's critical value (log-log; 1 is
    the line each test draws), clean and glitched frames apart."""
    from scope3d.utils.figures import new_figure, save_figure

    points = {"clean frame": [], "glitched frame": []}
    for r in runs:
        for f in r["frames"]:
            if f["status"] == "ok" and f.get("screen_status") == "ok":
                kind = "glitched frame" if f["frame"] in r["glitched"] else "clean frame"
                points[kind].append((f["d2"] / f["critical"], f["screen_d2"] / f["screen_critical"]))
    if not points["clean frame"]:
        return
    fig = new_figure(figsize=(5.5, 5))
    ax = fig.add_subplot(1, 1, 1)
    for (kind, xy), colour in zip(points.items(), ("tab:blue", "tab:red")):
        if xy:
            x, y = np.maximum(np.array(xy), 1e-4).T
            ax.scatter(x, y, s=10, color=colour, alpha=0.6, label=f"{kind} ({len(xy)})")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.axvline(1.0, color="gray", lw=0.8)
    ax.axhline(1.0, color="gray", lw=0.8)
    ax.plot([1e-4, 1e2], [1e-4, 1e2], color="gray", lw=0.5, ls=":")
    ax.set_xlabel("exact leave-one-out: d2 / critical value")
    ax.set_ylabel("linearised screen: d2 / critical value")
    ax.set_title("dome, 320 x 240: the screen against the exact test", fontsize=9)
    ax.legend(fontsize=7, loc="upper left")
    save_figure(fig, path)


def plot_detection(runs: list[dict], path: Path) -> None:
    """dome12, frame n // 2 glitched: the fraction found per glitch size (with its runs), each glitched frame's
    predicted power, and the power the clean maps' frames predict on average (what that geometry detects)."""
    from scope3d.utils.figures import new_figure, save_figure

    rows = [r for r in runs if r["survey"] == "dome12"]
    clean = [r["predicted_curve"] for r in rows if not r["glitched"] and "predicted_curve" in r]
    if not clean:
        return
    fig = new_figure(figsize=(10, 4))
    for a, (kind, field, unit) in enumerate((("mm", "shift_mm", "centre moved along x (mm)"),
                                            ("deg", "turn_deg", "orientation turned about x (deg)"))):
        ax = fig.add_subplot(1, 2, a + 1)
        weights = np.array([c["frames"] for c in clean], float)
        mean = np.average([c[f"power_{kind}"] for c in clean], axis=0, weights=weights)
        ax.plot(clean[0][kind], mean, color="tab:blue", label=f"predicted, mean over {int(weights.sum())} clean frames")
        glitched = [r for r in rows if r["glitched"] and r.get(field) and r["glitched"] == [SURVEYS["dome12"][1] // 2]]
        sizes = sorted({r[field] for r in glitched})
        found = [np.mean([r["hits"] for r in glitched if r[field] == g]) for g in sizes]
        runs_at = [sum(r[field] == g for r in glitched) for g in sizes]
        ax.plot(sizes, found, "o", color="tab:red", label="found (fraction of seeds)")
        for g, f, m in zip(sizes, found, runs_at):
            ax.annotate(f"{round(f * m)}/{m}", (g, f), textcoords="offset points", xytext=(4, -10), fontsize=7)
        for r in glitched:
            frame = next((f for f in r["frames"] if f["frame"] == r["glitched"][0]), {})
            if "predicted_power" in frame:
                ax.plot(r[field], frame["predicted_power"], "x", color="tab:gray", alpha=0.7)
        ax.plot([], [], "x", color="tab:gray", label="predicted for each glitched frame")
        ax.set_ylim(-0.03, 1.03)
        ax.set_xlabel(f"glitch: {unit}")
        ax.set_ylabel("detection power")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    fig.suptitle("dome12, 320 x 240, reports within +-0.5 mm / +-0.25 deg, false-alarm rate 0.01 per map")
    save_figure(fig, path)


def summary(runs: list[dict]) -> dict:
    """Per survey: clean maps with any frame flagged (stated: the false-alarm rate) with the one-sided 95 %
    Clopper-Pearson upper bound on that rate, and clean frames whose statistic against the true pose
    exceeded their critical value; per glitch: found / runs."""
    from scipy.stats import beta

    out = {}
    for survey in sorted({r["survey"] for r in runs}):
        clean = [r for r in runs if r["survey"] == survey and not r["glitched"]]
        alarms = sum(bool(r["false_alarms"]) for r in clean)
        frames = [f for r in clean for f in r["frames"] if f["status"] == "ok"]
        entry = {"clean_maps": len(clean), "clean_maps_with_a_false_alarm": alarms,
                 "false_alarm_rate_upper_95": round(float(beta.ppf(0.95, alarms + 1, len(clean) - alarms)), 3)
                 if clean else None,
                 "clean_frames_tested": len(frames),
                 "clean_frames_beyond_critical_against_truth": sum(f["d2_vs_truth"] > f["critical"] for f in frames),
                 "screened_clean_maps_with_a_false_alarm": sum(bool(r["screened"]["false_alarms"]) for r in clean
                                                               if "screened" in r),
                 "screened_clean_maps": sum("screened" in r for r in clean),
                 "screened_clean_frames_tested_exactly": sum(r["screened"]["frames_tested_exactly"] for r in clean
                                                             if "screened" in r),
                 "check_cpu_over_stages_cpu": {
                     mode: [round(float(np.percentile([(r["screened"] if mode == "screened" else r)["check_cpu_s"]
                                                       / r["stages_cpu_s"] for r in clean if "screened" in r
                                                       and (mode == "screened" or r.get("reference", True))], q)), 3)
                            for q in (0, 50, 100)] if any("screened" in r and (mode == "screened" or r.get("reference", True))
                                                          for r in clean) else None
                     for mode in ("exact", "screened")},
                 "glitches": {}}
        for r in runs:
            if r["survey"] == survey and r["glitched"]:
                name = f"{r['turn_deg']:g} deg" if r.get("turn_deg") else f"{r['shift_mm']:g} mm"
                g = entry["glitches"].setdefault(name, {"runs": 0, "found": 0, "clean_frames_flagged": 0,
                                                        "found_screened": 0, "clean_frames_flagged_screened": 0})
                g["runs"] += 1
                g["found"] += r["hits"]
                g["clean_frames_flagged"] += len(r["false_alarms"])
                g["found_screened"] += r.get("screened", {}).get("hits", 0)
                g["clean_frames_flagged_screened"] += len(r.get("screened", {}).get("false_alarms", []))
        out[survey] = entry
    return out


if __name__ == "__main__":
    raise SystemExit(main())
