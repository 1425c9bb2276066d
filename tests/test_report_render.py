"""The HTML report renders in headless Chromium with every plot loaded (Debian's `chromium`)."""
from __future__ import annotations

import re
import shutil
import subprocess

import numpy as np
import pytest
from matplotlib.image import imread

from bench.report.build import write_report
from test_report import make_run

CHROMIUM = shutil.which("chromium")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (tools/install-system-deps.sh)")

# Closed network: without these Chromium waits on updates, sync and QUIC probes and hangs.
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--hide-scrollbars", "--allow-file-access-from-files"]
COUNT_LOADED_IMAGES = """<script>
window.addEventListener('load', () => document.body.setAttribute('data-images-loaded',
  [...document.images].filter(i => i.complete && i.naturalWidth > 0).length + '/' + document.images.length));
</script>"""


def chromium(tmp_path, *args: str) -> subprocess.CompletedProcess:
    profile = tmp_path / "chromium-profile"
    return subprocess.run([CHROMIUM, *FLAGS, f"--user-data-dir={profile}", *args],
                          capture_output=True, text=True, timeout=90)


def colourful_fraction(png_path) -> float:
    """Share of pixels with clearly coloured content (plot lines and fills; text is grey)."""
    rgb = imread(png_path)[..., :3]
    saturation = rgb.max(axis=-1) - rgb.min(axis=-1)
    return float((saturation > 0.25).mean())


def test_report_renders_with_all_plots(tmp_path):
    run_dir = make_run(tmp_path / "run")
    _, page = write_report(run_dir)
    n_figures = page.read_text().count("<img ")
    assert n_figures >= 6

    probe = run_dir / "probe.html"      # the report plus a script that counts decoded images
    probe.write_text(page.read_text().replace("</body>", COUNT_LOADED_IMAGES + "</body>"))
    dom = chromium(tmp_path, "--virtual-time-budget=10000", "--dump-dom", probe.as_uri())
    loaded = re.search(r'data-images-loaded="(\d+)/(\d+)"', dom.stdout)
    assert loaded, f"no load report in the DOM; stderr: {dom.stderr[-500:]}"
    assert loaded.groups() == (str(n_figures), str(n_figures))

    shot = tmp_path / "shot.png"
    result = chromium(tmp_path, "--window-size=1300,2600", f"--screenshot={shot}", page.as_uri())
    assert shot.is_file(), result.stderr[-500:]
    assert colourful_fraction(shot) > 0.002     # a blank or text-only page has none
    assert np.std(imread(shot)[..., :3]) > 0.05
