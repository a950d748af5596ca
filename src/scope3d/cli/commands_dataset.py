"""``scope3d check`` and ``scope3d import``: validate datasets and convert other formats (being written)."""


def register(subparsers) -> None:
    pass
