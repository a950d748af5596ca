"""Every job speaks the same command-line habits (issue 15 part 3): ``--json`` prints the report on stdout,
``--quiet`` silences progress, and ``--help`` states the exit codes."""
from __future__ import annotations

import argparse

import pytest

from scope3d.cli.job_output import EXIT_CODES
from scope3d.cli.main import build_parser

# The commands that do a job and write a report (not `check`, `report`, `phantom --list`...).
JOBS = ["map", "bundle-adjust", "axial", "localize", "track-markers", "calibrate", "calibrate-hand-eye",
        "thread-scan", "mosaic", "panorama"]


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


@pytest.mark.parametrize("job", JOBS)
def test_every_job_has_json_quiet_and_states_its_exit_codes(job):
    sub = _subparsers(build_parser())[job]
    options = {s for a in sub._actions for s in a.option_strings}
    assert {"--json", "--quiet"} <= options
    assert " ".join(EXIT_CODES.split()) in " ".join(sub.format_help().split())
