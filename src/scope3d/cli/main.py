"""Entry point of the ``scope3d`` command. Each sub-command lives in its own module with a ``register``."""
from __future__ import annotations

import argparse
import sys

from scope3d import __version__

# Each module defines ``register(subparsers)`` which adds one or more sub-commands whose handler is
# stored as ``func`` and returns an exit status.
from scope3d.cli import commands_axial, commands_bundle, commands_dataset, commands_map, commands_phantom
from scope3d.cli import (
    commands_calibrate,
    commands_live,
    commands_localize,
    commands_panorama,
    commands_report,
    commands_thread,
    commands_track_markers,
)
from scope3d.cli.job_output import EXIT_CODES
from scope3d.errors import InputError

COMMAND_MODULES = [commands_phantom, commands_dataset, commands_bundle, commands_axial, commands_map, commands_report,
                   commands_calibrate, commands_localize, commands_live, commands_track_markers, commands_thread, commands_panorama]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scope3d",
        description="Metric 3D models from a robot-held scope whose poses are known within a tolerance.",
        epilog=EXIT_CODES, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"scope3d {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in COMMAND_MODULES:
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except InputError as exc:
        print(f"scope3d {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except FileNotFoundError as exc:
        print(f"scope3d {args.command}: error: file not found: {exc.filename or exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a read-only or full output location, a path under a file: the user's to fix
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"scope3d {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"scope3d {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
