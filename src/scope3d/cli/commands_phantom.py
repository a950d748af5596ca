"""``scope3d phantom``: render a phantom scene with exact ground truth (being written)."""


def register(subparsers) -> None:
    pass
