"""One contact labelling (issue 31): the viewer page, the glTF export of a BVH and the GIF show the same labels on
every frame; contacts are measured from the floor (a raised foot is never in contact) and do not blink."""
from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from modi.cli import main
from modi.core.contacts import feet_of
from modi.core.kinematics import bvh_positions
from modi.data.procedural import generate_clip
from modi.io import bvh as bvh_io
from modi.io import gltf
from modi.viz import render as R
from modi.viz import view_pages
from modi.viz.viewer import load_motion

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _clips(shared: bool, tmp_path, request):
    run = tmp_path / "run.bvh"   # a run: frames with and frames without contact, so the GIF check can fail
    generate_clip("run", 64, 30.0, rng=3).save(run)
    out = [run]
    if shared:
        data = request.getfixturevalue("shared_data")   # skips with a reason when ../shared is absent
        bandai = data / "bvh" / "bandai-namco-1" / "data" / "dataset-1_run_normal_001.bvh"
        if bandai.is_file():
            out.append(bandai)
    return out


@pytest.mark.parametrize("shared", [False, True])
def test_page_gltf_and_gif_agree_on_every_frame(tmp_path, shared, request):
    clips = _clips(shared, tmp_path, request)
    if shared and len(clips) < 2:
        pytest.skip("../shared/data Bandai clip absent")
    src = clips[-1]
    b = bvh_io.load(src)
    page = load_motion(src).contacts                                  # (T, J) as the page shows them
    assert page is not None and page.any()
    glb = tmp_path / "c.glb"
    assert main(["export", "gltf", str(src), str(glb)]) == 0
    _, _, _, _, from_glb = gltf.load_positions(glb)
    assert from_glb is not None and from_glb.shape == page.shape
    assert (from_glb == page).all(), f"glTF and page disagree on {(from_glb != page).mean():.1%} of labels"
    # the GIF at the clip's own rate: a frame shows contact red exactly when the page has a contact there
    gif = tmp_path / "c.gif"
    with view_pages(False):
        R.render_bvh([src], gif, fps=b.fps, size=(96, 96), contacts=True)
    im = Image.open(gif)
    assert im.n_frames == b.n_frames
    red = []
    for k in range(im.n_frames):
        im.seek(k)
        rgb = np.asarray(im.convert("RGB")).astype(int)[:-16]        # not the legend line (it says "contact")
        red.append(bool((np.abs(rgb - R._BASE_COLORS[R._CONTACT]).max(-1) < 8).any()))
    shown = page.any(axis=1)
    assert 0 < shown.sum() < len(shown), "the clip needs frames with and without contact"
    assert (np.array(red) == shown).all(), f"GIF red on {np.mean(np.array(red) != shown):.1%} frames not as the page"


def test_contacts_do_not_blink_and_need_the_floor(shared_data):
    from modi.core.contacts import preview_contacts

    names = ["bandai-namco-1/data/dataset-1_walk_normal_001.bvh", "bandai-namco-1/data/dataset-1_run_normal_001.bvh",
             "ganimator/Elephant/idle1.bvh"]
    for rel in names:
        p = shared_data / "bvh" / rel
        if not p.is_file():
            pytest.skip(f"{p} absent")
        b = bvh_io.load(p)
        pos = bvh_positions(b)
        feet = feet_of(b)
        lab = preview_contacts(pos, feet, b.fps, b.parents, b.names)[:, feet]
        for f in range(lab.shape[1]):   # runs inside the clip (not touching its ends) last >= 0.1 s
            d = np.diff(np.r_[0, lab[:, f].astype(int), 0])
            starts, ends = np.nonzero(d == 1)[0], np.nonzero(d == -1)[0]
            inner = [(s, e) for s, e in zip(starts, ends) if s > 0 and e < len(lab)]
            assert all(e - s >= 3 for s, e in inner), (p.name, f, [(s, e) for s, e in inner if e - s < 3])
        floor = pos[..., 1].min() if "Elephant" in rel else pos[:, 1:, 1].min()   # Bandai: not the floor root
        scale = 1.0 if "Elephant" in rel else 0.01
        above = (pos[:, feet, 1] - floor) * scale
        assert above[lab].max() < 0.14, (p.name, above[lab].max())   # metres: a foot in contact is on the floor
