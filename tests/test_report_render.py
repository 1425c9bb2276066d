"""The HTML report renders in headless Chromium with every plot loaded (Debian's `chromium`)."""
from __future__ import annotations

import numpy as np
import pytest
from matplotlib.image import imread

from bench.report.build import write_report
from tests.browser import CHROMIUM, chromium, colourful_fraction, images_loaded
from test_report import make_run

pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (tools/install-system-deps.sh)")


def test_report_renders_with_all_plots(tmp_path):
    run_dir = make_run(tmp_path / "run")
    _, page = write_report(run_dir)
    n_figures = page.read_text().count("<img ")
    assert n_figures >= 6

    assert images_loaded(tmp_path, page) == (n_figures, n_figures)

    shot = tmp_path / "shot.png"
    result = chromium(tmp_path, "--window-size=1300,2600", f"--screenshot={shot}", page.as_uri())
    assert shot.is_file(), result.stderr[-500:]
    assert colourful_fraction(shot) > 0.002     # a blank or text-only page has none
    assert np.std(imread(shot)[..., :3]) > 0.05
