"""Command-line interface: a thin layer over the Python API (``scope3d <command> --help``)."""
