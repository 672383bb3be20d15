"""The viewer page as an animator sees it (issue 31): headless Chromium stills of 1, 3 and 16 motions, measured
from pixels -- each cell's figure (saturated pixels) spans at least 40 % of its cell's height, and the labels (the
only dark grey pixels) are as many separate blobs as there are motions, so none overprints another. Also time
sync (``?t=`` and ``?frame=`` of the first motion across 30 and 60 fps clips) and the 'ended' mark."""
from __future__ import annotations

import re
import shutil
import subprocess

import numpy as np
import pytest

from modi.data.procedural import generate_clip
from modi.viz.viewer import load_motion, page_html

CHROMIUM = shutil.which("chromium")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="headless browser test needs the Debian package "
                                                         "'chromium' (binary 'chromium' on PATH)")
WIDTH, HEIGHT = 1000, 700   # the window; the canvas is what the page reports (above its 40 px control bar)
KINDS = ("walk", "run", "jump", "wave", "squat", "idle")


_CMD = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--no-first-run", "--hide-scrollbars", f"--window-size={WIDTH},{HEIGHT}"]


def _dom(url: str) -> str:
    """The page's DOM once its script ran, which it did without an error."""
    dom = subprocess.run([CHROMIUM, *_CMD, "--dump-dom", url], capture_output=True, text=True, timeout=90).stdout
    body = re.search(r"<body([^>]*)>", dom).group(1)
    assert 'data-status="ready"' in body and "data-errors" not in body, body
    return dom


def _shot(url: str, png) -> tuple[np.ndarray, str]:
    """(the canvas's pixels, the DOM) of the page at ``url``."""
    from PIL import Image

    r = subprocess.run([CHROMIUM, *_CMD, f"--screenshot={png}", url], capture_output=True, text=True, timeout=90)
    assert png.is_file(), r.stderr[-1500:]
    dom = _dom(url)
    img = np.asarray(Image.open(png).convert("RGB")).astype(np.int16)
    return img[:img.shape[0] - 40], dom   # the canvas: all but the 40 px control bar


def _cells(n: int, W: int, H: int) -> list[tuple[int, int, int, int]]:
    """The tiling the page should use, recomputed here: the column count that gives each figure the most
    height (figures are taller than wide: a cell's width counts 1.6 x)."""
    best = max(range(1, n + 1), key=lambda c: (min(H / -(-n // c), 1.6 * W / c), -c))
    rows = -(-n // best)
    out = []
    for i in range(n):
        c, r = i % best, i // best
        x0, y0 = round(c * W / best), round(r * H / rows)
        out.append((x0, y0, round((c + 1) * W / best) - x0, round((r + 1) * H / rows) - y0))
    return out


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    d = tmp_path_factory.mktemp("looks")
    paths = []
    for i in range(16):
        p = d / f"{i:02d}_{KINDS[i % len(KINDS)]}.bvh"
        generate_clip(KINDS[i % len(KINDS)], 48, 30.0, rng=i).save(p)
        paths.append(p)
    return paths


@pytest.mark.parametrize("n", [1, 3, 16])
def test_every_cell_frames_its_figure_and_labels_never_overprint(clips, tmp_path, n):
    from scipy import ndimage

    page = tmp_path / "view.html"
    page.write_text(page_html([load_motion(p) for p in clips[:n]]), encoding="utf-8")
    img, dom = _shot(f"{page.as_uri()}?t=0.8&paused=1", tmp_path / "still.png")
    figure = (img.max(-1) - img.min(-1)) > 60                     # bones, joints, contacts: saturated colours
    text = ((img.max(-1) - img.min(-1)) < 16) & (img.max(-1) < 110)  # labels: dark grey; grid and borders are light
    for k, (x0, y0, w, h) in enumerate(_cells(n, img.shape[1], img.shape[0])):
        ys, _ = np.nonzero(figure[y0 + 20:y0 + h, x0:x0 + w])     # below the label line
        assert len(ys) > 50, f"cell {k}: no figure"
        span = ys.max() - ys.min() + 1
        assert span >= 0.4 * h, f"cell {k}: figure {span} px of a {h} px cell"
    # each label is one blob once its glyphs are joined (8 px sideways, 3 px down): overprinting merges two
    blobs, count = ndimage.label(ndimage.binary_dilation(text, np.ones((3, 9), bool)))
    boxes = [b for b in ndimage.find_objects(blobs) if text[b].sum() >= 8]  # not a stray pixel where bones cross
    count = len(boxes)
    assert count == n, f"{count} label blobs for {n} motions"
    for a in range(count):
        for b in range(a + 1, count):
            ya, xa = boxes[a]
            yb, xb = boxes[b]
            assert ya.stop <= yb.start or yb.stop <= ya.start or xa.stop <= xb.start or xb.stop <= xa.start


def test_time_sync_across_frame_rates_and_the_ended_mark(tmp_path):
    a, b = tmp_path / "a30.bvh", tmp_path / "b60.bvh"
    generate_clip("walk", 60, 30.0, rng=1).save(a)       # 2 s at 30 fps
    generate_clip("wave", 60, 60.0, rng=2).save(b)       # 1 s at 60 fps
    page = tmp_path / "view.html"
    page.write_text(page_html([load_motion(a), load_motion(b)]), encoding="utf-8")
    dom = _dom(f"{page.as_uri()}?frame=15&paused=1")
    assert re.search(r'id="frame"[^>]*>frame 15 / 59 \u00b7 0\.50 s', dom), "?frame=N is the first motion's"
    assert 'title="ended: holds its last pose"' not in dom
    dom = _dom(f"{page.as_uri()}?t=1.5&paused=1")
    assert re.search(r'id="frame"[^>]*>frame 45 / 59 \u00b7 1\.50 s', dom), "?t=SECONDS"
    ended = re.findall(r'<span class="motion"[^>]*title="ended: holds its last pose"[^>]*>.*?</i>([^<]*)</span>', dom)
    assert ended == ["b60"], ended   # the 1 s clip has ended at 1.5 s, the 2 s one has not
    # the same first-motion frame shows the same time whatever else is on the page
    page1 = tmp_path / "one.html"
    page1.write_text(page_html([load_motion(a)]), encoding="utf-8")
    dom1 = _dom(f"{page1.as_uri()}?frame=15&paused=1")
    assert re.search(r'id="frame"[^>]*>frame 15 / 59 \u00b7 0\.50 s', dom1)
