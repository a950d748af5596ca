"""Map cost against the number of frames (issue 17): ``scope3d map`` on surveys of 30, 56, 200 and 1,000
frames of one large printed sheet.

The survey is the reference's raster (5 mm spacing, looking straight down from 15 mm, serpentine rows) on a
215 mm sheet (``phantoms.scenes.build_sheet(size_mm=215)``), rendered at 304 x 304 px. Every survey is a
block of rows x columns of one 25 x 40 grid, centred on the sheet, so a frame common to two surveys is
the same picture; frames are rendered once and kept in a cache folder (default
``$TMPDIR/scope3d_map_scaling_cache``). Grids: 5 x 6 (30), 7 x 8 (56), 10 x 20 (200), 25 x 40 (1,000).
With a fixed spacing each frame overlaps a fixed number of neighbours, so the number of pairs grows like
the number of frames: a linear pipeline costs the same per frame at every size.

Each map runs in its own process through ``benchmarks/profile_map.py`` (the same call as ``scope3d map
DATASET --out DIR --no-progress``): CPU and wall seconds per stage, pairs matched, peak resident memory of
that process (the kernel's high-water mark ``VmHWM`` of its process image: exact, not sampled; the rendering
in this parent process does not count).
The exponent b of ``cost = a * n**b`` is a least-squares fit of log cost on log n, over frames and over
pairs, for the total and for every stage. A size whose map does not finish within ``--timeout`` seconds is
reported as such; nothing is extrapolated.

Writes benchmarks/results/map_scaling.json and map_scaling.png. Run (the machine's load is recorded):
    PYTHONPATH=src .venv/bin/python benchmarks/bench_map_scaling.py [--frames 30,56,200,1000] [--timeout 3600]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
sys.path.insert(0, str(ROOT / "src"))

FULL_GRID = (25, 40)  # rows, columns of the largest survey
SURVEYS = {30: (5, 6), 56: (7, 8), 200: (10, 20), 1000: (25, 40)}  # frames -> (rows, columns)
SPACING_MM = 5.0  # the reference's raster (Fig. 4.6(a)), as phantoms.trajectories.grid_trajectory
STANDOFF_MM = 15.0
# the full grid spans 39 x 5 = 195 mm; a 53° view from 15 mm sees 15 mm across, plus a 5 mm margin
SHEET_MM = 215.0
# 0.04 mm per texel: finer than a 304 px view of 15 mm (0.049 mm per pixel), so the texture is never
# magnified; the 60 mm sheet's 0.02 mm would take 8 GB of intermediate noise at this size
MM_PER_TEXEL = 0.04
IMAGE_PX = (304, 304)
SEED = 0


def _full_grid():
    from scope3d.phantoms.trajectories import grid_trajectory

    rows, cols = FULL_GRID
    traj = grid_trajectory(rows, cols, spacing_mm=SPACING_MM, standoff_mm=STANDOFF_MM)
    # grid_trajectory visits serpentine rows; index the poses by (row, column) instead
    index = {}
    k = 0
    for r in range(rows):
        for c in (range(cols) if r % 2 == 0 else range(cols - 1, -1, -1)):
            index[(r, c)] = traj.poses[k]
            k += 1
    return index


def survey_cells(n_frames: int) -> list[tuple[int, int]]:
    """(row, column) cells of the full grid in the survey's serpentine order, the block centred."""
    rows, cols = SURVEYS[n_frames]
    r0, c0 = (FULL_GRID[0] - rows) // 2, (FULL_GRID[1] - cols) // 2
    cells = []
    for r in range(rows):
        for c in (range(cols) if r % 2 == 0 else range(cols - 1, -1, -1)):
            cells.append((r0 + r, c0 + c))
    return cells


def render_survey(n_frames: int, cache: Path, work: Path) -> tuple[Path, float]:
    """The survey's dataset folder (frames from the cache, rendering the missing ones) and the CPU seconds
    spent rendering here."""
    from scope3d.io.dataset import write_dataset
    from scope3d.io.images import write_image
    from scope3d.phantoms.lab import default_camera, measure_poses
    from scope3d.phantoms.render import RenderOptions, render_frame, sequence_exposure
    from scope3d.phantoms.scenes import build_sheet

    poses = _full_grid()
    cells = survey_cells(n_frames)
    cache.mkdir(parents=True, exist_ok=True)
    paths = [cache / f"r{r:02d}_c{c:02d}.png" for r, c in cells]
    cpu0 = time.process_time()
    missing = [(cell, path) for cell, path in zip(cells, paths) if not path.exists()]
    # the texture takes ~10 s and ~1.7 GB to build; with every frame cached, only the sheet's mesh (which
    # does not depend on the texture) is needed, so a coarse texture stands in
    scene = build_sheet(size_mm=SHEET_MM, mm_per_texel=MM_PER_TEXEL if missing else 2.0, texture_seed=SEED)
    camera = default_camera(scene, "grid5x6", size=IMAGE_PX)
    options = RenderOptions()
    if missing:
        # one exposure for the whole sheet (a flat print under the same light: every view's gain is alike)
        exposure = sequence_exposure(scene, camera, [poses[c] for c in survey_cells(30)], options=options)
        for (r, c), path in missing:
            frame = render_frame(scene, camera, poses[(r, c)], seed=SEED, frame_index=r * FULL_GRID[1] + c,
                                 exposure=exposure, options=options)
            write_image(path, frame.image)  # atomic: a killed run leaves no half-written frame in the cache
    true_poses = [poses[c] for c in cells]
    info = dict(scene.info)
    info["texture"] = {**info["texture"], "mm_per_texel": MM_PER_TEXEL}  # what the cached frames were rendered with
    info["trajectory"] = {"name": f"grid{SURVEYS[n_frames][1]}x{SURVEYS[n_frames][0]}", "kind": "grid",
                          "rows": SURVEYS[n_frames][0], "cols": SURVEYS[n_frames][1], "spacing_mm": SPACING_MM,
                          "standoff_mm": STANDOFF_MM, "cells_of_full_grid": [list(c) for c in cells]}
    out = write_dataset(work / f"sheet_{n_frames}", camera, paths, measure_poses(true_poses, 0.0, seed=SEED),
                        names=[p.name for p in paths], true_poses=true_poses, true_surface=scene.mesh, scene=info,
                        metadata={"source": "benchmarks/bench_map_scaling.py", "scene_name": "sheet"})
    return out, time.process_time() - cpu0


def map_one(dataset: Path, work: Path, timeout_s: float) -> dict:
    """profile_map.py on ``dataset`` in a child process: its JSON, or a row saying it did not finish."""
    result = work / f"{dataset.name}_profile.json"
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    load = [round(v, 2) for v in os.getloadavg()]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "profile_map.py"), str(dataset),
                               "--out", str(work / f"{dataset.name}_map"), "--result", str(result)],
                              env=env, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return {"finished": False, "timeout_s": timeout_s, "load_average_at_start": load}
    if proc.returncode != 0:
        return {"finished": False, "returncode": proc.returncode, "stderr_tail": proc.stderr[-2000:],
                "load_average_at_start": load}
    row = json.loads(result.read_text())
    row.update(finished=True, wall_s_child=round(time.perf_counter() - t0, 2), load_average_at_start=load)
    return row


def fit_exponent(n, cost) -> float | None:
    """b of cost = a n^b by least squares on the logs (None with fewer than two sizes)."""
    n, cost = np.asarray(n, float), np.asarray(cost, float)
    ok = (n > 0) & (cost > 0)
    if ok.sum() < 2:
        return None
    return round(float(np.polyfit(np.log(n[ok]), np.log(cost[ok]), 1)[0]), 3)


def summarise(rows: list[dict]) -> dict:
    done = [r for r in rows if r["finished"]]
    stages = [s["stage"] for s in done[0]["stages"]] if done else []
    frames = [r["n_frames"] for r in done]
    pairs = [r["n_pairs"] for r in done]

    def cpu(r, stage):
        return next(s["cpu_s"] for s in r["stages"] if s["stage"] == stage)

    per_stage = {st: {"exponent_vs_frames": fit_exponent(frames, [cpu(r, st) for r in done]),
                      "exponent_vs_pairs": fit_exponent(pairs, [cpu(r, st) for r in done])}
                 for st in stages if st != "interpreter start-up"}
    return {"sizes_finished": frames, "exponent_pairs_vs_frames": fit_exponent(frames, pairs),
            "exponent_peak_rss_vs_frames": fit_exponent(frames, [r["peak_rss_mb"] for r in done]),
            "exponent_cpu_per_stage": per_stage}


def plot(rows: list[dict], path: Path) -> None:
    from scope3d.utils.figures import new_figure, save_figure

    done = [r for r in rows if r["finished"]]
    fig = new_figure((12.0, 4.2), dpi=100)
    ax1, ax2, ax3 = fig.subplots(1, 3)
    frames = np.array([r["n_frames"] for r in done], float)
    pairs = np.array([r["n_pairs"] for r in done], float)
    stages = [s["stage"] for s in done[0]["stages"] if s["stage"] not in ("interpreter start-up",
                                                                           "total from process start")]
    for st in stages:
        ax1.loglog(frames, [next(s["cpu_s"] for s in r["stages"] if s["stage"] == st) for r in done], "o-",
                   label=st.split(" (")[0], ms=4)
    total = np.array([r["stages"][-1]["cpu_s"] for r in done])
    ax1.loglog(frames, total, "k^-", lw=2, label="total")
    ax1.loglog(frames, total[0] * frames / frames[0], "k:", lw=1, label="linear from the smallest")
    ax1.set(xlabel="frames", ylabel="CPU s", title="CPU per stage vs frames")
    ax1.legend(fontsize=6)
    ax2.loglog(pairs, total, "k^-", lw=2, label="total CPU")
    ax2.loglog(pairs, total[0] * pairs / pairs[0], "k:", lw=1, label="linear from the smallest")
    for x, y, f in zip(pairs, total, frames):
        ax2.annotate(f"{int(f)} frames", (x, y), fontsize=7, xytext=(4, -10), textcoords="offset points")
    ax2.set(xlabel="pairs matched", ylabel="CPU s", title="total CPU vs pairs")
    ax2.legend(fontsize=7)
    ax3.plot(frames, [r["peak_rss_mb"] for r in done], "o-")
    ax3.axhline(2048, color="r", ls="--", lw=1, label="2 GB goal (issue 17)")
    ax3.set(xlabel="frames", ylabel="MB", title="peak resident memory of the map")
    ax3.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)


def write_results(rows: list[dict]) -> dict:
    """map_scaling.json (and .png) from the runs so far: rewritten after every size, so that a run
    stopped half-way keeps the sizes it finished."""
    result = {"benchmark": "scope3d map cost vs frames (issue 17)", "machine": "2 shared cores",
              "scene": {"name": "sheet", "size_mm": SHEET_MM, "mm_per_texel": MM_PER_TEXEL, "image_px": list(IMAGE_PX),
                        "grid_spacing_mm": SPACING_MM, "standoff_mm": STANDOFF_MM, "full_grid_rows_cols": list(FULL_GRID)},
              "peak_memory_method": "VmHWM (/proc/self/status) of the child process that runs the map",
              "runs": rows, "fit": summarise(rows), "load_average_at_end": [round(v, 2) for v in os.getloadavg()]}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "map_scaling.json").write_text(json.dumps(result, indent=2) + "\n")
    if any(r["finished"] for r in rows):
        plot(rows, RESULTS / "map_scaling.png")
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", default="30,56,200,1000", help="survey sizes, of " + ", ".join(map(str, SURVEYS)))
    parser.add_argument("--timeout", type=float, default=3600.0, help="seconds a map may take before it is given up")
    parser.add_argument("--cache", default=str(Path(tempfile.gettempdir()) / "scope3d_map_scaling_cache"))
    args = parser.parse_args()
    sizes = [int(v) for v in args.frames.split(",")]
    unknown = [n for n in sizes if n not in SURVEYS]
    if unknown:
        parser.error(f"unknown survey sizes {unknown}; use some of {list(SURVEYS)}")
    rows = []
    with tempfile.TemporaryDirectory(prefix="map_scaling_") as tmp:
        # numba compiles its kernels once per source path on first use (about a minute): pay that outside
        # the timed runs
        warm = map_one(render_survey(min(sizes), Path(args.cache), Path(tmp))[0], Path(tmp), args.timeout)
        if not warm["finished"]:
            raise SystemExit(f"the warm-up map failed: {warm}")
        for n in sizes:
            dataset, render_cpu = render_survey(n, Path(args.cache), Path(tmp))
            row = map_one(dataset, Path(tmp), args.timeout)
            row.update(frames_requested=n, grid_rows_cols=list(SURVEYS[n]), render_cpu_s_this_run=round(render_cpu, 1))
            rows.append(row)
            brief = {k: row.get(k) for k in ("frames_requested", "finished", "n_pairs", "n_points", "peak_rss_mb",
                                             "wall_s_child", "load_average_at_start")}
            if row["finished"]:
                brief["cpu_total_s"] = row["stages"][-1]["cpu_s"]
            print(brief, flush=True)
            result = write_results(rows)
    print(json.dumps(result["fit"], indent=1))


if __name__ == "__main__":
    main()
