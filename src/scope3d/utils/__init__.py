"""Helpers every layer may use: atomic outputs (:mod:`.atomic`), JSON with numpy values (:mod:`.jsonio`),
figures on an Agg canvas without pyplot (:mod:`.figures`), robust scales and Huber weights (:mod:`.robust`),
the machine's cores (:mod:`.threads`) and BLAS threads (:mod:`.blas`), the progress convention
(:mod:`.progress`), figures drawn in a child process (:mod:`.background`), numba kernels compiled at
install (:mod:`.aot`) and run over a frame's rows on every core (:mod:`.row_blocks`).
"""
