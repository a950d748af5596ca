"""The progress convention with tqdm itself, the bar the command line makes."""
import io

import tqdm

from scope3d.utils.progress import advance, stage


def test_a_stage_of_unknown_length_does_not_keep_the_last_stages_total():
    bar = tqdm.tqdm(total=36, file=io.StringIO())
    advance(bar, 36)
    stage(bar, "pairs", None)  # tqdm's own reset(total=None) would keep 36 and show "3/36"
    advance(bar, 3)
    assert (bar.total, bar.n, bar.desc.startswith("pairs")) == (None, 3, True)
    stage(bar, "features (pale wall)", 36)
    assert (bar.total, bar.n) == (36, 0)
    stage(None, "nothing to report to", None)  # no bar: a no-op
