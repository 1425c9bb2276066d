"""Headless Chromium (Debian's `chromium`) for the tests that look at a report as a person does."""
from __future__ import annotations

import re
import shutil
import subprocess

from matplotlib.image import imread

CHROMIUM = shutil.which("chromium")

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


def images_loaded(tmp_path, page) -> tuple[int, int]:
    """(decoded, total) images of an HTML page, as Chromium loads it."""
    probe = page.with_name("probe.html")      # the page plus a script that counts decoded images
    probe.write_text(page.read_text().replace("</body>", COUNT_LOADED_IMAGES + "</body>"))
    dom = chromium(tmp_path, "--virtual-time-budget=10000", "--dump-dom", probe.as_uri())
    loaded = re.search(r'data-images-loaded="(\d+)/(\d+)"', dom.stdout)
    assert loaded, f"no load report in the DOM; stderr: {dom.stderr[-500:]}"
    return int(loaded.group(1)), int(loaded.group(2))
