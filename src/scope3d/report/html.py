"""``RUN_DIR/report.html``: one self-contained page per run, opened from the file system with no network.

The page holds the figures of merit of report.json with their units, the job's PNG pictures (inlined as
data URIs), an interactive 3D view (WebGL, :mod:`scope3d.report.scene` gathers what it draws; the viewer's
JavaScript and the styles are this package's data files, inlined) and the fluorescent targets' table.
"""
from __future__ import annotations

import base64
import html
import json
import math
from importlib import resources
from pathlib import Path

from scope3d.errors import InputError
from scope3d.io.json_object import read_json_object
from scope3d.report.scene import ReportOptions, ViewScene, colour_stops, gather_scene, scene_payload
from scope3d.utils.atomic import atomic_file
from scope3d.utils.jsonio import MACHINE_FIELDS, TIMING_FIELD_SUFFIXES, json_default

# Key suffix -> unit shown beside the value (units live in the report's key names, see STYLE.md).
UNIT_SUFFIXES = (("_mm2", "mm²"), ("_mm", "mm"), ("_px2", "px²"), ("_px", "px"), ("_deg", "°"), ("_rad", "rad"),
                 ("_s", "s"), ("_mb", "MB"), ("_fraction", "%"))
# The headline cards: (dotted key in report.json, label), shown when present.
HEADLINES = (
    ("n_frames", "frames"), ("n_points", "points"), ("mean_reprojection_error_px", "mean reprojection error"),
    ("surface_error_mm.direct.mean", "mean distance to the true surface"),
    ("surface_error_mm.after_icp.mean", "mean distance after ICP"),
    ("surface_error_mm.mean", "mean distance to the true surface"),
    ("surface_error_mm.within_1mm_fraction", "points within 1 mm of the truth"),
    ("surface_error_mm.direct.within_1mm_fraction", "points within 1 mm of the truth"),
    ("pose_error.position_mm_mean", "mean camera position error"),
    ("initial_cost", "initial cost"), ("final_cost", "final cost"), ("iterations", "iterations"),
)
COLOURINGS = (("height", "height"), ("error", "error against ground truth"), ("texture", "texture"),
              ("multimodal", "texture + fluorescence"))


def write_report(run_dir: str | Path, options: ReportOptions = ReportOptions(), *, name: str | None = None) -> Path:
    """Write ``run_dir/report.html`` from the run folder's report.json, pictures and geometry; returns its
    path. name : the run's name in the page's title (default the folder's: give it when the folder is a
    temporary one, renamed into place afterwards). Raises InputError if the folder has no readable report.json."""
    run = Path(run_dir)
    page = build_page(run, options, name=name)
    out = run / "report.html"
    with atomic_file(out, encoding="utf-8") as handle:
        handle.write(page)
    return out


def read_report_json(run: Path) -> dict:
    path = run / "report.json"
    if not path.is_file():
        raise InputError(f"{path}: no report.json (is {run} a scope3d run folder?)")
    return read_json_object(path)


def build_page(run: Path, options: ReportOptions = ReportOptions(), *, name: str | None = None) -> str:
    """The whole page as one string (no external references except links to the run's own files); name: see
    :func:`write_report`."""
    report = read_report_json(run)
    scene = gather_scene(run, report, options)
    assets = resources.files("scope3d.report") / "assets"
    style = (assets / "style.css").read_text(encoding="utf-8")
    script = (assets / "viewer.js").read_text(encoding="utf-8")
    payload = json.dumps(scene_payload(scene), default=json_default).replace("</", "<\\/")
    title = f"scope3d {job_name(report)}: {name or run.name}"
    parts = [
        "<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
        # no network at view time, whatever the page holds
        "<meta http-equiv=\"Content-Security-Policy\" content=\"default-src 'none'; img-src data:; "
        "style-src 'unsafe-inline'; script-src 'unsafe-inline'\">",
        f"<title>{_e(title)}</title><style>{style}</style></head><body>",
        f"<header><h1>{_e(title)}</h1><p>{_e(str(report.get('dataset', '')))}</p></header><main>",
        _merit_section(report), _organ_map_section(run, report),
        _view_section(scene), _targets_section(scene, report), _pictures_section(run),
        _files_section(run, scene), _timings_section(report),
        f'</main><script type="application/json" id="scene-data">{payload}</script>',
        f"<script>{script}</script></body></html>",
    ]
    return "\n".join(parts)


def job_name(report: dict) -> str:
    """Which job wrote the report (its ``job`` entry, else its keys tell)."""
    if isinstance(report.get("job"), str):
        return report["job"]
    if "pose_mode" in report:
        return "map"
    if report.get("method") in ("sgm", "sad", "multiview"):
        return "axial"
    if "initial_cost" in report:
        return "bundle-adjust"
    return "run"


def _e(text) -> str:
    return html.escape(str(text), quote=True)


def flatten(report: dict, prefix: str = "") -> list[tuple[str, object]]:
    """(dotted key, value) of every scalar (and short list of numbers) in the report, in order; lists of
    records (bundle rounds, targets) are left to their own sections."""
    rows: list[tuple[str, object]] = []
    for key, value in report.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            rows.extend(flatten(value, name + "."))
        elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            for i, v in enumerate(value) if key == "bundle" else ():
                rows.extend(flatten(v, f"{name}[{i}]."))
        elif isinstance(value, list) and len(value) > 8:
            continue
        else:
            rows.append((name, value))
    return rows


def unit_of(key: str) -> str:
    """The unit a dotted key states in its name (the nearest part with a known suffix), or ''."""
    for part in reversed(key.replace("[", ".").split(".")):
        for suffix, unit in UNIT_SUFFIXES:
            if part.endswith(suffix) or f"{suffix}_" in part:  # position_mm_mean is in mm too
                return unit
    return ""


def format_value(key: str, value) -> str:
    """A value as shown: fractions in %, floats to 4 significant digits, lists joined."""
    if isinstance(value, bool) or value is None:
        return "—" if value is None else ("yes" if value else "no")
    if isinstance(value, float):
        if not math.isfinite(value):
            return str(value)
        if unit_of(key) == "%":
            return f"{100 * value:.4g}"
        return f"{value:.4g}"
    if isinstance(value, list):
        return ", ".join(format_value(key, v) for v in value)
    return str(value)


def _lookup(report: dict, dotted: str):
    value = report
    for part in dotted.split("."):
        if not isinstance(value, dict) or part not in value:
            return None
        value = value[part]
    return None if isinstance(value, (dict, list)) else value


def _merit_section(report: dict) -> str:
    cards, seen = [], set()
    for key, label in HEADLINES:
        value = _lookup(report, key)
        if value is None or label in seen:
            continue
        seen.add(label)
        cards.append(f'<div class="card"><div class="value">{_e(format_value(key, value))} {_e(unit_of(key))}</div>'
                     f'<div class="label">{_e(label)}</div></div>')
    rows = _rows((k, v) for k, v in flatten(report) if not is_timing(k))
    return (f'<section id="merit"><h2>Figures of merit</h2><div class="cards">{"".join(cards)}</div>'
            f'<details><summary>every figure in report.json</summary><table id="merit-table"><thead><tr><th>figure'
            f'</th><th>value</th><th>unit</th></tr></thead><tbody>{rows}</tbody></table></details></section>')


def is_timing(key: str) -> bool:
    """Whether a dotted key measures the machine (time, memory) rather than the data: the page keeps those
    apart, in its last section, so that the rest of it is a function of the input, options and seed."""
    parts = key.replace("[", ".").split(".")
    return any(p.endswith(TIMING_FIELD_SUFFIXES) or p in MACHINE_FIELDS for p in parts)


def _rows(items) -> str:
    return "".join(f'<tr><td>{_e(k)}</td><td class="num">{_e(format_value(k, v))}</td><td>{_e(unit_of(k))}</td></tr>'
                   for k, v in items)


def _timings_section(report: dict) -> str:
    rows = _rows((k, v) for k, v in flatten(report) if is_timing(k))
    if not rows:
        return ""
    return ('<section id="timings"><h2>Time and memory</h2><p>Measured on the machine that ran the job; the '
            'only part of this page that differs between runs of the same input.</p><table><thead><tr><th>figure'
            f'</th><th>value</th><th>unit</th></tr></thead><tbody>{rows}</tbody></table></section>')


def _view_section(scene: ViewScene) -> str:
    available = {mode for layer in scene.layers for mode in layer.colours} | \
        ({"texture"} if any(layer.textured for layer in scene.layers) else set())
    first = next((mode for mode, _ in COLOURINGS if mode in available), "height")
    if scene.inside and "texture" in available:  # a cavity seen from inside reads best as the scope saw it
        first = "texture"
    radios = "".join(
        f'<label><input type="radio" name="colouring" value="{mode}"{" checked" if mode == first else ""}'
        f'{"" if mode in available else " disabled"}> {_e(label)}</label>'
        for mode, label in COLOURINGS if mode in available or mode == "error")
    layers = "".join(f'<label><input type="checkbox" data-layer="{i}" checked> {_e(layer.name)} '
                     f'({len(layer.positions):,} {"vertices" if layer.faces is not None else "points"})</label>'
                     for i, layer in enumerate(scene.layers))
    gradient = ", ".join(colour_stops())
    scales = "".join(
        f'<div class="colour-scale" data-mode="{mode}" hidden><span>{low:.3g} {unit}</span>'
        f'<span class="bar" style="background: linear-gradient(to right, {gradient})"></span>'
        f'<span>{high:.3g} {unit}</span><span>({_e(dict(COLOURINGS)[mode])})</span></div>'
        for mode, (low, high, unit) in scene.scales.items())
    no_error = "" if "error" in available else \
        "<p class='notes'>No error colouring: the run's dataset has no ground-truth surface here.</p>"
    has_targets = bool(scene.targets or scene.true_targets)
    hide_targets = "" if has_targets else " hidden"
    legend = ('<span><span class="legend-key" style="background:#408cf2"></span>camera frusta</span> '
              '<span><span class="legend-key" style="background:#ff991a"></span>trajectory</span> '
              f'<span{hide_targets}><span class="legend-key" style="background:#ff1ae6"></span>targets found</span> '
              f'<span{hide_targets}><span class="legend-key" style="background:#1ad94d"></span>true targets</span>')
    notes = "".join(f"<li>{_e(n)}</li>" for n in scene.notes)
    # the panorama is a closed cavity: seen from outside, its wall hides what the scope saw
    inside = ('<label><input type="checkbox" id="inside-view" checked> view from inside (drag: look around, '
              'wheel: zoom)</label>') if scene.inside else ""
    alternate = ('<label><input type="checkbox" id="alternate-modes"> alternate texture and fluorescence '
                 '</label>') if {"texture", "multimodal"} <= available else ""
    explorer = ('<aside id="explorer"><p id="explorer-hint">Click a spot of the surface: the frames that saw it '
                'appear here, the spot circled.</p><div id="explorer-frames"></div></aside>') \
        if scene.camera is not None and scene.frames else ""
    return (
        '<section id="view-section"><h2>3D view</h2>'
        f'<div class="controls"><span>colour by: {radios}</span><span>{layers}</span>'
        '<label><input type="checkbox" id="show-frusta" checked> cameras</label>'
        f'<label{hide_targets}><input type="checkbox" id="show-targets" checked> targets</label>{inside}{alternate}'
        '<button id="reset-view" type="button">reset view</button></div>'
        '<div class="view-row"><div class="viewer"><canvas id="view"></canvas><canvas id="view-labels"></canvas>'
        f'<div id="view-message"></div></div>{explorer}</div>'
        f'<div class="controls">{scales}{legend}</div>'
        '<p style="font-size:12px;color:#5b6474">drag: orbit · shift-drag or right-drag: pan · wheel: zoom · '
        f'click: the frames that saw a spot; lengths in mm</p>{no_error}<ul class="notes">{notes}</ul></section>')


def _targets_section(scene: ViewScene, report: dict) -> str:
    if "targets" not in report and not scene.true_targets:
        return ""
    matched = {t.get("found_label"): t for t in scene.true_targets if t.get("found_label") is not None}
    rows = []
    for t in scene.targets:
        c = t.get("centroid_mm", [math.nan] * 3)
        truth = matched.get(t.get("label"), {})
        rows.append(
            f'<tr><td>{_e(t.get("label"))}</td><td>{_e(t.get("shape", ""))}</td>'
            + "".join(f'<td class="num">{v:.3f}</td>' for v in c)
            + "".join(f'<td class="num">{math.nan if t.get(k) is None else t[k]:.3f}</td>' for k in ("size_mm", "area_mm2"))
            + f'<td>{_e(truth.get("name", "—"))}</td>'
            f'<td class="num">{_e(format_value("x_mm", truth.get("centroid_error_mm")))}</td></tr>')
    table = ('<table id="targets"><thead><tr><th>label</th><th>shape</th><th>x (mm)</th><th>y (mm)</th><th>z (mm)</th>'
             '<th>size (mm)</th><th>area (mm²)</th><th>true target</th><th>centre error (mm)</th></tr></thead>'
             f'<tbody>{"".join(rows)}</tbody></table>')
    missed = [t["name"] for t in scene.true_targets if t.get("found_label") is None]
    missed_text = f"<p>True targets not found: {_e(', '.join(missed))}.</p>" if missed else ""
    return (f'<section id="targets-section"><h2>Fluorescent targets ({len(scene.targets)} found'
            + (f" of {len(scene.true_targets)} true" if scene.true_targets else "") + f")</h2>{table}{missed_text}</section>")


# The organ map's pictures: shown in their own section (the map) or listed as data (the coverage mask).
ORGAN_MAP_FILES = ("organ_map.png", "organ_coverage.png")


def _organ_map_section(run: Path, report: dict) -> str:
    """The panorama's 2-D map of the whole cavity (report.json ``organ_map``): the picture, coverage, the
    uncovered regions and, with ground truth, the alignment."""
    organ = report.get("organ_map")
    picture = run / ORGAN_MAP_FILES[0]
    if not isinstance(organ, dict) or not picture.is_file():
        return ""
    data = base64.b64encode(picture.read_bytes()).decode()
    surface = organ.get("surface", {})
    text = (f"{organ.get('coverage_fraction', math.nan):.1%} of the wall covered "
            f"({len(organ.get('uncovered_regions', []))} uncovered regions outlined in yellow, hatched blue; "
            f"{organ.get('n_small_uncovered_regions', 0)} smaller ones hatched only). Surface: "
            f"{surface.get('kind', '?')} ({surface.get('reason', '')}). Red: the scope's path (where each "
            "frame's optical axis meets the wall; further videos orange, magenta), green its start, every fifth "
            "frame numbered. "
            "Longitude left to right, latitude top (the first frame's side) to bottom; lines every 30°.")
    videos = organ.get("videos") or []
    if videos:
        text += " Videos: " + "; ".join(f"{Path(v['dataset']).name} alone {v['coverage_fraction']:.1%}"
                                        for v in videos) + "."
    alignment = organ.get("alignment")
    if alignment:
        text += (f" Against the truth: alignment {alignment['mean_px']:.2f} px mean, {alignment['p95_px']:.2f} px "
                 f"p95; true covered fraction {organ['true_coverage_fraction']:.1%}.")
    rows = "".join(
        f'<tr><td class="num">{i + 1}</td><td class="num">{r["area_mm2"]:.1f}</td><td class="num">'
        f'{r["fraction"]:.2%}</td><td class="num">{r["centre_lon_deg"]:.0f}</td><td class="num">'
        f'{r["centre_lat_deg"]:.0f}</td><td>{"yes" if r.get("touches_pole") else ""}</td></tr>'
        for i, r in enumerate(organ.get("uncovered_regions", [])))
    table = ('<table><thead><tr><th>uncovered region</th><th>area (mm²)</th><th>of the wall</th><th>longitude (°)'
             f'</th><th>latitude (°)</th><th>at a pole</th></tr></thead><tbody>{rows}</tbody></table>') if rows else ""
    check = report.get("self_check") if isinstance(report.get("self_check"), dict) else {}
    doubts = list(check.get("problems") or []) + list(check.get("warnings") or [])
    warning = (f'<p class="warning">This map is drawn from a 3-D map its self-check doubts, so frames may sit in '
               f'the wrong place on it: {_e("; ".join(doubts))}</p>') if doubts else ""
    return (f'<section id="organ-map"><h2>Map of the whole organ</h2>{warning}<figure><img alt="organ_map.png" '
            f'src="data:image/png;base64,{data}"><figcaption>{_e(text)}</figcaption></figure>{table}</section>')


def texture_files(run: Path) -> set[str]:
    """The images the run's .mtl files name as textures (``map_Kd``): data, not pictures to show."""
    names = set()
    for mtl in run.glob("*.mtl"):
        for line in mtl.read_text(encoding="utf-8", errors="replace").splitlines():
            if line.startswith("map_Kd") and len(line.split(None, 1)) == 2:
                names.add(line.split(None, 1)[1].strip())
    return names


def _pictures_section(run: Path) -> str:
    figures = []
    textures = texture_files(run)
    for png in sorted(p for p in run.glob("*.png") if p.name not in textures and p.name not in ORGAN_MAP_FILES):
        data = base64.b64encode(png.read_bytes()).decode()
        figures.append(f'<figure><img alt="{_e(png.name)}" src="data:image/png;base64,{data}">'
                       f"<figcaption>{_e(png.name)}</figcaption></figure>")
    if not figures:
        return ""
    return f'<section id="pictures"><h2>Pictures</h2>{"".join(figures)}</section>'


def _files_section(run: Path, scene: ViewScene) -> str:
    textures = texture_files(run)
    files = sorted(p for p in run.iterdir() if p.is_file() and not p.name.startswith(".") and
                   (p.suffix in (".ply", ".json", ".csv", ".obj", ".mtl") or p.name in textures
                    or p.name == ORGAN_MAP_FILES[1]))
    items = "".join(f'<li><a href="{_e(p.name)}">{_e(p.name)}</a> ({p.stat().st_size / 1e6:.2f} MB)</li>' for p in files)
    return f'<section id="files"><h2>Full data</h2><ul>{items}</ul></section>'
