"""Command-line interface: a thin layer over the Python API (``scope3d <command> --help``): :mod:`.main` builds
the parser from one ``commands_*`` module per command; :mod:`.job_output` is what every job does around
its work, :mod:`.progress` the bars, :mod:`.lazy` the choices imported only when a parser needs them."""
