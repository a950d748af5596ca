"""One self-contained HTML page per run (``RUN_DIR/report.html``): figures of merit, pictures, an
interactive 3D view (clouds, meshes, camera frusta, fluorescent targets) and the targets' table.
:mod:`.html` writes the page, :mod:`.scene` what its 3D view draws. See docs/report.md."""
from scope3d.report.html import build_page, write_report
from scope3d.report.scene import ReportOptions

__all__ = ["ReportOptions", "build_page", "write_report"]
