"""A compiled kernel run over a frame by fixed blocks of rows, the blocks shared by the machine's cores.

The kernels this serves (``scope3d.mvs.refine_kernels``, ``scope3d.mvs.axial_kernels``) release the GIL and
take ``(*inputs, row_lo, row_hi, *outputs)``, writing only rows ``[row_lo, row_hi)`` of their outputs. The
cut into blocks is fixed (``block_rows``), never derived from the number of cores, so that a kernel whose
running sums restart at each block gives the same bits on any machine.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Sequence

from scope3d.utils.threads import resolve_threads

BLOCK_ROWS = 128  # rows per block: ~10 blocks for a 608 px axial grid, a tenth of a row-restart's overhead


def row_blocks(height: int, block_rows: int | None = None) -> list[tuple[int, int]]:
    """[(row_lo, row_hi), ...] covering ``range(height)`` in blocks of ``block_rows`` (default
    :data:`BLOCK_ROWS`; the last block shorter)."""
    block_rows = BLOCK_ROWS if block_rows is None else block_rows
    if block_rows < 1:
        raise ValueError(f"block_rows must be positive, got {block_rows}")
    return [(lo, min(lo + block_rows, height)) for lo in range(0, height, block_rows)]


def run_by_row_blocks(kernel: Callable, height: int, inputs: Sequence, outputs: Sequence,
                      block_rows: int | None = None) -> None:
    """Call ``kernel(*inputs, row_lo, row_hi, *outputs)`` for every block of ``height`` rows, on up to every
    available core (:func:`~scope3d.utils.threads.available_cores`; in the caller alone when there is one
    block or one core); raises what a call raised."""
    blocks = row_blocks(height, block_rows)
    threads = resolve_threads(0, len(blocks))
    if threads <= 1:
        for lo, hi in blocks:
            kernel(*inputs, lo, hi, *outputs)
        return
    with ThreadPoolExecutor(max_workers=threads) as pool:
        for done in [pool.submit(kernel, *inputs, lo, hi, *outputs) for lo, hi in blocks]:
            done.result()
