"""The 3D HTML viewer: the page's content and size, the CLI, notebooks, and the page in a real headless Chromium."""
from __future__ import annotations

import base64
import html
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from modi.cli import main
from modi.io import bvh as bvh_io
from modi.core.kinematics import bvh_positions
from modi.data.procedural import builtin_skeleton, generate_clip
from modi.viz.viewer import Viewer, from_positions, load_motion, page_html, show

CHROMIUM = shutil.which("chromium")
needs_chromium = pytest.mark.skipif(CHROMIUM is None, reason="headless browser test needs the Debian package "
                                                             "'chromium' (binary 'chromium' on PATH)")


@pytest.fixture(scope="module")
def clips(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("clips")
    out = {}
    for kind, seed in (("walk", 1), ("wave", 2)):
        out[kind] = d / f"{kind}.bvh"
        generate_clip(kind, 64, 30.0, rng=seed).save(out[kind])
    return out


def page_data(text: str) -> dict:
    m = re.search(r'<script type="application/json" id="modi-data">(.*?)</script>', text, re.S)
    assert m, "the page carries its motions as JSON"
    return json.loads(m.group(1))


def decoded_positions(m: dict) -> np.ndarray:
    q = np.frombuffer(base64.b64decode(m["pos"]), dtype="<i2").astype(np.float64)
    return (np.asarray(m["origin"]) + (q.reshape(m["frames"], len(m["names"]), 3) + 32768) * m["step"])


def test_cli_page_for_bvh_is_self_contained_and_exact(clips, tmp_path, capsys):
    out = tmp_path / "view.html"
    assert main(["view", str(clips["walk"]), str(clips["wave"]), "--out", str(out)]) == 0
    assert str(out) in capsys.readouterr().out
    text = out.read_text(encoding="utf-8")
    assert not re.search(r"https?://", text), "the page must not reference the network"
    assert not re.search(r"<(script|link|img|iframe)[^>]*\s(src|href)=", text), "no external resources"
    data = page_data(text)
    assert [m["title"] for m in data["motions"]] == ["walk", "wave"]
    for m, path in zip(data["motions"], (clips["walk"], clips["wave"])):
        b = bvh_io.load(path)
        ref = bvh_positions(b) * 0.01  # the procedural rig is in centimetres
        ref[..., 1] -= ref[..., 1].min()
        assert m["names"] == b.names and m["parents"] == list(b.parents) and m["fps"] == pytest.approx(b.fps)
        assert np.abs(decoded_positions(m) - ref).max() < 1e-4  # int16 quantisation: < 0.1 mm
        assert m["contacts"] is not None  # walking and standing feet touch the ground


def test_page_for_16_motions_of_64_frames_is_small():
    sk = builtin_skeleton()
    rng = np.random.default_rng(0)
    motions = [from_positions(rng.normal(size=(64, sk.n_joints, 3)) * 0.5, sk.parents, sk.names, 30.0,
                              contacts=rng.random((64, sk.n_joints)) < 0.2, title=f"{i}") for i in range(16)]
    size = len(page_html(motions).encode("utf-8"))
    assert size < 2_000_000, f"{size} bytes"
    # the bound is meant to hold with room: 16 x 64 frames x 22 joints fit in well under a third of it
    assert size < 600_000, f"{size} bytes"


def test_a_translating_root_link_is_not_drawn_as_a_bone():
    t = np.linspace(0, 2, 30)
    pos = np.zeros((30, 3, 3))  # a floor root fixed at the origin, hips walking away from it, a head above them
    pos[:, 1] = np.stack([t, np.full_like(t, 0.9), 0 * t], -1)
    pos[:, 2] = pos[:, 1] + [0, 0.8, 0]
    m = page_data(page_html([from_positions(pos, [-1, 0, 1], ["Root", "Hips", "Head"])]))["motions"][0]
    assert m["hide"] == [0, 1, 0]
    pos[:, 1] = [0, 0.9, 0]  # a still clip: the floor root under the hips is still not a bone (Bandai's bows)
    pos[:, 2] = pos[:, 1] + [0, 0.8, 0]
    assert page_data(page_html([from_positions(pos, [-1, 0, 1])]))["motions"][0]["hide"] == [0, 1, 0]
    pos[:, 0] = [0, 0.9, 0]  # a hips root above a foot, rigid links to its children: bones
    pos[:, 1] = [0.1, 0.0, 0]
    pos[:, 2] = [0, 1.6, 0]
    assert page_data(page_html([from_positions(pos, [-1, 0, 0])]))["motions"][0]["hide"] == [0, 0, 0]


def test_cli_refuses_bad_input_and_writes_nothing(clips, tmp_path, capsys):
    garbage = tmp_path / "garbage.bvh"
    garbage.write_bytes(b"\x89PNG\r\n\x1a\n\x00\xff" * 50)
    text_file = tmp_path / "motion.txt"
    text_file.write_text("HIERARCHY\n")
    broken = tmp_path / "broken.bvh"
    broken.write_text("HIERARCHY\nROOT Hips\n{\n")
    junk_glb = tmp_path / "junk.glb"
    junk_glb.write_bytes(bytes(range(256)) * 2)
    out = tmp_path / "sub" / "view.html"
    for bad in ([str(tmp_path / "missing.bvh")], [str(tmp_path)], [str(text_file)], [str(garbage)],
                [str(broken)], [str(junk_glb)], [str(clips["walk"]), str(tmp_path / "missing.glb")]):
        capsys.readouterr()
        assert main(["view", *bad, "--out", str(out)]) == 2, bad
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and Path(bad[-1]).name in err, err
        assert not out.exists() and not out.parent.exists(), bad
    assert main(["view", str(clips["walk"]), "--out", str(tmp_path / "v.png")]) == 2
    assert main(["view", str(clips["walk"]), "--out", str(clips["walk"])]) == 2
    assert clips["walk"].read_text().startswith("HIERARCHY")


def test_glb_input_matches_the_bvh(clips, tmp_path):
    gltf = pytest.importorskip("modi.io.gltf", reason="modi.io.gltf (the glTF reader) is not in this checkout")
    glb = tmp_path / "walk.glb"
    gltf.save(bvh_io.load(clips["walk"]), glb)
    out = tmp_path / "view.html"
    assert main(["view", str(clips["walk"]), str(glb), "--out", str(out)]) == 0
    a, b = page_data(out.read_text(encoding="utf-8"))["motions"]
    assert b["title"] == "walk" and b["names"] == a["names"] and b["frames"] == a["frames"]
    # the same unit guess for the BVH as the export made: both in metres, equal to float32 + int16 precision
    assert np.abs(decoded_positions(a) - decoded_positions(b)).max() < 2e-4


def test_show_for_notebooks_without_jupyter(clips, tmp_path):
    v = show(str(clips["walk"]))
    assert isinstance(v, Viewer)
    frag = v._repr_html_()
    assert frag.startswith("<iframe ") and "<script" not in frag  # the page is escaped into srcdoc
    srcdoc = html.unescape(re.search(r'srcdoc="([^"]*)"', frag).group(1))
    assert srcdoc == v.html and page_data(srcdoc)["motions"][0]["names"] == bvh_io.load(clips["walk"]).names
    m = generate_clip("jump", 20, 30.0, rng=3)
    from_motion = show(m, layout="scene")
    got = decoded_positions(page_data(from_motion.html)["motions"][0])
    ref = m.positions().numpy() * 0.01
    ref[..., 1] -= ref[..., 1].min()
    assert np.abs(got - ref).max() < 1e-4
    assert v.save(tmp_path / "nb.html").read_text(encoding="utf-8") == v.html
    with pytest.raises(TypeError):
        show(42)


# ------------------------------------------------------------------------------------------------ Chromium
def chromium(url: str, *extra: str) -> subprocess.CompletedProcess:
    cmd = [CHROMIUM, "--headless=new", "--disable-gpu", "--no-sandbox", "--hide-scrollbars", "--mute-audio",
           "--no-first-run", "--disable-extensions", "--enable-logging=stderr", "--v=0", *extra, url]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=60)


def console_errors(stderr: str) -> list[str]:
    return [ln for ln in stderr.splitlines() if "CONSOLE" in ln and ("rror" in ln or "Uncaught" in ln)]


def body_attrs(dom: str) -> dict[str, str]:
    m = re.search(r"<body([^>]*)>", dom)
    assert m, dom[:500]
    return dict(re.findall(r'([\w-]+)="([^"]*)"', m.group(1)))


@needs_chromium
def test_page_runs_in_chromium_without_errors(clips, tmp_path):
    out = tmp_path / "view.html"
    walk = load_motion(clips["walk"])
    out.write_text(page_html([walk, load_motion(clips["wave"])]), encoding="utf-8")
    head = walk.names.index("Head")
    r = chromium(f"{out.as_uri()}?frame=20&paused=1&probe=0,{head}", "--dump-dom")
    attrs = body_attrs(r.stdout)
    assert attrs.get("data-status") == "ready", (attrs, r.stderr[-2000:])
    assert "data-errors" not in attrs and not console_errors(r.stderr), (attrs, console_errors(r.stderr))
    assert attrs.get("data-probe") == "Head"  # hovering a joint names it
    assert re.search(r'id="frame"[^>]*>frame 20 / 63 ', r.stdout)  # ?frame=N is honoured
    # the harness can fail: the same page with a script error is caught by it
    bad = tmp_path / "bad.html"
    bad.write_text(out.read_text(encoding="utf-8").replace("'use strict';", "'use strict'; noSuchFunction();", 1),
                   encoding="utf-8")
    r = chromium(bad.as_uri(), "--dump-dom")
    attrs = body_attrs(r.stdout)
    assert "noSuchFunction" in attrs.get("data-errors", "") and "data-status" not in attrs


def _box(mask: np.ndarray, margin: int) -> np.ndarray:
    """The bounding box of a mask's pixels, grown by ``margin``."""
    ys, xs = np.nonzero(mask)
    out = np.zeros_like(mask)
    out[max(0, ys.min() - margin):ys.max() + margin + 1, max(0, xs.min() - margin):xs.max() + margin + 1] = True
    return out


@needs_chromium
def test_stills_differ_where_the_figure_is(clips, tmp_path):
    from PIL import Image

    out = tmp_path / "view.html"
    walk = load_motion(clips["walk"])
    out.write_text(page_html([walk]), encoding="utf-8")
    shots = []
    for frame in (0, 30):
        png = tmp_path / f"still_{frame}.png"
        r = chromium(f"{out.as_uri()}?frame={frame}&paused=1&follow=0", f"--screenshot={png}",
                     "--window-size=800,600")  # a still camera: the background must not change
        assert png.is_file(), r.stderr[-2000:]
        assert not console_errors(r.stderr), console_errors(r.stderr)
        shots.append(np.asarray(Image.open(png).convert("RGB")).astype(np.int16))
    a, b = (s[:-40] for s in shots)  # the canvas; the control bar below it shows the frame number
    assert a.shape == b.shape and a.shape[0] > 400

    def figure(img):  # the figure is drawn in saturated colours, the background and the grid in greys
        m = (img.max(-1) - img.min(-1)) > 60
        m[:30, :200] = False  # the legend
        return m

    fa, fb = figure(a), figure(b)
    assert fa.sum() > 300 and fb.sum() > 300, "the figure is visible in both stills"
    assert (fa & fb).sum() < 0.8 * min(fa.sum(), fb.sum()), "the figure moved between the stills"
    diff = (a != b).any(-1)
    near = _box(fa, 20) | _box(fb, 20)  # the figure with its floor shadow
    assert diff[near].sum() > 300, "the stills differ where the figure is"
    assert not diff[~near].any(), "the background (grid, floor) is the same in both stills"
    assert (~near).mean() > 0.7, "the comparison covers most of the background"
    # contacts are highlighted: frame 0 has a foot on the ground, drawn in the contact red
    assert walk.contacts[0].any()
    red = (np.abs(a - np.array([225, 40, 40])).max(-1) < 12)
    assert red.sum() > 10


# ------------------------------------------------------------------------------------------------ beside GIFs
@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory):
    import torch

    from modi.models.modi.encoder.training import generator_bundle
    from test_latent import build_tiny

    torch.set_num_threads(1)
    g, codec = build_tiny()
    path = tmp_path_factory.mktemp("ckpt") / "tiny.pt"
    torch.save(generator_bundle(g, codec), path)
    return path, g, codec


def test_gif_writing_commands_write_the_viewer_beside(tiny_ckpt, tmp_path):
    from modi.models.modi.sampling import generate_tensors, write_outputs
    from modi.viz import view_pages

    ckpt, g, codec = tiny_ckpt
    assert main(["latent", "mean", str(ckpt), "--out", str(tmp_path / "m")]) == 0
    data = page_data((tmp_path / "m" / "view.html").read_text(encoding="utf-8"))
    assert (tmp_path / "m" / "mean.gif").is_file() and data["motions"][0]["names"] == list(codec.skeleton.names)
    assert main(["latent", "truncate", str(ckpt), "--out", str(tmp_path / "t"), "--steps", "2", "--no-view"]) == 0
    assert (tmp_path / "t" / "truncation.gif").is_file() and not list((tmp_path / "t").glob("*.html"))
    assert main(["latent", "cluster", str(ckpt), "--out", str(tmp_path / "c"), "--n", "12", "--k", "2",
                 "--per-cluster", "2", "--tsne-max", "0"]) == 0  # several GIFs in one folder: NAME.html each
    assert sorted(p.name for p in (tmp_path / "c").glob("*.html")) == ["cluster_0.html", "cluster_1.html"]
    x, _ = generate_tensors(None, 3, model=(g, codec, None))  # what 'modi generate' writes
    write_outputs(codec, x, tmp_path / "gen", bvh=False)
    assert len(page_data((tmp_path / "gen" / "view.html").read_text(encoding="utf-8"))["motions"]) == 3
    with view_pages(False):
        write_outputs(codec, x, tmp_path / "gen2", bvh=False)
    assert (tmp_path / "gen2" / "samples.gif").is_file() and not (tmp_path / "gen2" / "view.html").exists()


@needs_chromium
def test_notebook_iframe_renders_in_chromium(clips, tmp_path):
    from PIL import Image

    nb = tmp_path / "notebook.html"  # what Jupyter does with _repr_html_: put the fragment into its page
    nb.write_text("<!DOCTYPE html><html><body><h3>cell output</h3>" + show(str(clips["walk"]))._repr_html_()
                  + "</body></html>", encoding="utf-8")
    png = tmp_path / "nb.png"
    # the iframe loads after the page's own load event: give the page (virtual) time to draw before the shot, or a
    # loaded machine photographs an empty frame; a busy machine gets a second, longer try
    for budget in (5000, 20000):
        r = chromium(nb.as_uri(), f"--screenshot={png}", "--window-size=800,600", f"--virtual-time-budget={budget}")
        assert png.is_file() and not console_errors(r.stderr), r.stderr[-2000:]
        img = np.asarray(Image.open(png).convert("RGB")).astype(np.int16)
        figure = (img.max(-1) - img.min(-1)) > 60
        figure[:80, :250] = False  # the heading and the legend
        if figure.sum() > 300:
            break
    assert figure.sum() > 300, "the viewer draws the figure inside the notebook's iframe"


class _DevTools:
    """A minimal Chrome DevTools Protocol client over ``--remote-debugging-pipe`` (fd 3 in, fd 4 out, NUL-framed
    JSON): real mouse and key events, and every console error and uncaught exception of the page."""

    def __init__(self, width: int = 800, height: int = 600):
        import select  # noqa: F401 - checked here so a platform without it fails at once

        cmd = ["sh", "-c", 'exec "$0" "$@" 3<&0 4>&1 0</dev/null 1>/dev/null', CHROMIUM, "--headless=new",
               "--disable-gpu", "--no-sandbox", "--hide-scrollbars", "--mute-audio", "--no-first-run",
               "--remote-debugging-pipe", f"--window-size={width},{height}", "about:blank"]
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        self.buf, self.next_id, self.errors, self.session = b"", 0, [], None
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        self.session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        for domain in ("Runtime", "Log", "Page"):
            self.call(f"{domain}.enable")

    def _events(self, msg: dict) -> None:
        method, params = msg.get("method"), msg.get("params", {})
        if method == "Runtime.exceptionThrown":
            d = params["exceptionDetails"]
            self.errors.append(d.get("exception", {}).get("description") or d.get("text"))
        elif method == "Runtime.consoleAPICalled" and params.get("type") in ("error", "assert"):
            self.errors.append(" ".join(str(a.get("value", a.get("description"))) for a in params.get("args", [])))
        elif method == "Log.entryAdded" and params["entry"].get("level") == "error":
            self.errors.append(params["entry"].get("text"))

    def call(self, method: str, timeout: float = 30.0, **params) -> dict:
        import select
        import time

        self.next_id += 1
        msg = {"id": self.next_id, "method": method, "params": params}
        if self.session:
            msg["sessionId"] = self.session
        self.proc.stdin.write(json.dumps(msg).encode() + b"\0")
        self.proc.stdin.flush()
        end = time.monotonic() + timeout
        while True:
            while b"\0" in self.buf:
                raw, self.buf = self.buf.split(b"\0", 1)
                reply = json.loads(raw)
                if reply.get("id") == self.next_id:
                    if "error" in reply:
                        raise RuntimeError(f"{method}: {reply['error']}")
                    return reply.get("result", {})
                self._events(reply)
            left = end - time.monotonic()
            if left <= 0 or not select.select([self.proc.stdout], [], [], left)[0]:
                raise TimeoutError(f"no reply to {method} from chromium")
            chunk = os.read(self.proc.stdout.fileno(), 1 << 16)
            if not chunk:
                raise RuntimeError("chromium closed the DevTools pipe")
            self.buf += chunk

    def js(self, expression: str):
        r = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in r:
            raise RuntimeError(r["exceptionDetails"])
        return r["result"].get("value")

    def mouse(self, kind: str, x: float, y: float, **kw) -> None:
        self.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, **kw)

    def close(self) -> None:
        self.proc.kill()
        self.proc.wait(timeout=30)


@needs_chromium
def test_orbit_zoom_hover_keys_and_scrub_with_real_input_events(clips, tmp_path):
    import time

    out = tmp_path / "view.html"
    walk = load_motion(clips["walk"])
    out.write_text(page_html([walk]), encoding="utf-8")
    head = walk.names.index("Head")
    dt = _DevTools()
    try:
        dt.call("Page.navigate", url=f"{out.as_uri()}?frame=10&paused=1&follow=0")
        for _ in range(100):
            if dt.js("document.body && document.body.getAttribute('data-status')") == "ready":
                break
            time.sleep(0.05)
        state = lambda: dt.js("modiViewer.state()")  # noqa: E731
        s0 = state()
        assert s0["frame"] == 10 and not s0["playing"]
        x, y = dt.js(f"modiViewer.screenOf(0, {head})")
        dt.mouse("mouseMoved", x, y)  # hover: the joint's name
        tip = "document.getElementById('tip')"
        assert dt.js(f"getComputedStyle({tip}).display") == "block" and dt.js(f"{tip}.textContent") == "Head"
        before = dt.js("document.getElementById('view').toDataURL()")
        dt.mouse("mousePressed", 400, 300, button="left", buttons=1, clickCount=1)
        dt.mouse("mouseMoved", 500, 280, button="left", buttons=1)
        dt.mouse("mouseReleased", 500, 280, button="left", buttons=0, clickCount=1)
        s1 = state()  # dragging right turns the camera, dragging up raises it, and the picture changes
        assert s1["az"] == pytest.approx(s0["az"] - 100 * 0.008) and s1["el"] == pytest.approx(s0["el"] - 20 * 0.008)
        assert dt.js("document.getElementById('view').toDataURL()") != before
        dt.mouse("mouseWheel", 400, 300, deltaX=0, deltaY=500)  # the wheel zooms out
        assert state()["dist"] == pytest.approx(s1["dist"] * np.exp(0.5), rel=1e-6)
        dt.js("var s = document.getElementById('scrub'); s.value = 33; s.dispatchEvent(new Event('input'))")  # the scrub bar seeks and pauses
        assert state()["frame"] == 33 and not state()["playing"]
        dt.call("Input.dispatchKeyEvent", type="keyDown", key="ArrowRight", code="ArrowRight",
                windowsVirtualKeyCode=39)
        assert state()["frame"] == 34
        dt.call("Input.dispatchKeyEvent", type="keyDown", key=" ", code="Space", windowsVirtualKeyCode=32)
        time.sleep(0.4)  # space plays: the frame moves on
        s2 = state()
        assert s2["playing"] and s2["frame"] != 34
        assert not dt.errors, dt.errors
    finally:
        dt.close()
