"""Run the authors' released MoDi (``../shared/peers/MoDi``, MIT) on the CPU, patched at run time from here.

Nothing in the peer folder is modified or copied. What this harness changes while their code runs:

* their ``op`` package JIT-compiles CUDA kernels on import; a stand-in ``op`` module (our own torch forms of
  bias + leaky ReLU and of ``upfirdn2d``) is installed in ``sys.modules`` instead;
* ``Tensor.cuda()`` / ``torch.cuda.synchronize`` are identities and ``Tensor.to('cuda')`` goes to the CPU while their code runs (``--device cpu``);
* numpy aliases removed in numpy >= 1.24 (``np.int`` ...) and ``numpy.core.umath_tests.matrix_multiply`` are
  restored; ``cv2`` and ``pandas`` (imported, never
  used on these paths) are stubbed if absent;
* ``SkeletonTraits.n_channels_max`` is set from ``args.n_channels_max`` so tests can use narrow models;
* their figure drawing during training is skipped (it is not part of the training step).

Their top-level packages (``models``, ``utils``, ``Motion``, ``op``, ...) live in ``sys.modules`` only inside
:func:`peer_runtime`, so another peer with the same package names (GANimator) can run in the same process.

Data: Bandai-Namco BVH from ``../shared/data`` has a static floor root (``joint_Root``) above ``Hips``; the released
preprocessing assumes the root is the hips, so :func:`prepare_dataset` folds ``joint_Root`` into ``Hips`` first,
then runs their own ``expand_topology_edges``, ``joint_rot_2_edge_rot`` and ``split_to_fixed_length_clips``.
"""
from __future__ import annotations

import argparse
import contextlib
import copy
import os
import random
import sys
import types
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from benchmarks.peers import unavailable_reason

REPO = Path(__file__).resolve().parents[2]
PEER = REPO.parent / "shared" / "peers" / "MoDi"
BANDAI = REPO.parent / "shared" / "data" / "bvh" / "bandai-namco-1" / "data"

PEER_PACKAGES = ("op", "models", "utils", "Motion", "motion_class", "train", "evaluate", "evaluation",
                 "train_encoder", "generate", "generate_encoder", "inverse_optim", "latent_space_edit")

# narrow channel widths (coarse -> fine, as their n_channels_max) and a small mapping for fast tests
SMALL_CHANNELS = (32, 16, 16, 8, 8)
SMALL_ARGS = ("--latent", "32", "--n_mlp", "2", "--batch", "4")
# the released Mixamo model's flags (docs/results.md, "The authors' code"), minus --foot (Bandai's feet are added
# by `feet=True`)
RELEASED_FLAGS = ("--skeleton", "--conv3fast", "--glob_pos", "--normalize", "--use_velocity")


class PeerUnavailable(RuntimeError):
    """The released sources or the data they need are not beside the repository."""


# what their modules import at run time (import name -> pip name; setup.py's 'peers' extra); cv2 and pandas are
# stood in for by peer_runtime (imported, never called on these paths)
THIRD_PARTY = {"yaml": "pyyaml", "networkx": "networkx", "matplotlib": "matplotlib", "scipy": "scipy",
               "sklearn": "scikit-learn", "tqdm": "tqdm", "torch.utils.tensorboard": "tensorboard"}


def require_peer() -> Path:
    if not (PEER / "models" / "gan.py").is_file():
        raise PeerUnavailable(f"the authors' MoDi sources are not at {PEER} (../shared/peers/MoDi)")
    why = unavailable_reason("MoDi", THIRD_PARTY)
    if why is not None:
        raise PeerUnavailable(why)
    return PEER


def require_data() -> Path:
    if not BANDAI.is_dir() or not any(BANDAI.glob("*.bvh")):
        raise PeerUnavailable(f"Bandai-Namco BVH data not found at {BANDAI} (../shared/data)")
    return BANDAI


# --------------------------------------------------------------------------------------------- our torch ops
def fused_leaky_relu(x: torch.Tensor, bias: torch.Tensor, negative_slope: float = 0.2,
                     scale: float = 2 ** 0.5) -> torch.Tensor:
    """Bias (broadcast on dim 1) + leaky ReLU, times ``scale``: what their fused CUDA op computes."""
    shape = (1, bias.shape[0]) + (1,) * (x.ndim - 2)
    return F.leaky_relu(x + bias.view(shape), negative_slope) * scale


class FusedLeakyReLU(nn.Module):
    """Module form with the parameter name (``bias``) their checkpoints use."""

    def __init__(self, channel: int, negative_slope: float = 0.2, scale: float = 2 ** 0.5):
        super().__init__()
        self.bias = nn.Parameter(torch.zeros(channel))
        self.negative_slope, self.scale = negative_slope, scale

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return fused_leaky_relu(x, self.bias, self.negative_slope, self.scale)


def upfirdn2d(x: torch.Tensor, kernel: torch.Tensor, up: int = 1, down: int = 1,
              pad: Sequence[int] = (0, 0, 0, 0), skeleton_traits: Any = None) -> torch.Tensor:
    """Zero-insertion upsampling, padding (negative crops), true 2D convolution with ``kernel`` per channel,
    then decimation -- the StyleGAN2 ``upfirdn2d`` contract, on (B, C, H, W) with ``pad = (x0, x1, y0, y1)``."""
    if skeleton_traits is not None:
        up_x, up_y, down_x, down_y = skeleton_traits.upfirdn_updown(up, down)
    else:
        up_x = up_y = up
        down_x = down_y = down
    px0, px1, py0, py1 = (int(p) for p in pad)
    b, c, h, w = x.shape
    y = x.reshape(b * c, 1, h, w)
    if up_x > 1 or up_y > 1:
        z = y.new_zeros(b * c, 1, h * up_y, w * up_x)
        z[:, :, ::up_y, ::up_x] = y
        y = z
    y = F.pad(y, (px0, px1, py0, py1))
    k = torch.flip(kernel, [0, 1]).to(y.dtype).view(1, 1, *kernel.shape)
    y = F.conv2d(y, k)[:, :, ::down_y, ::down_x]
    return y.reshape(b, c, y.shape[-2], y.shape[-1])


def _op_module() -> types.ModuleType:
    op = types.ModuleType("op")
    op.__doc__ = "modi harness stand-in for the released code's JIT-compiled CUDA ops"
    op.FusedLeakyReLU, op.fused_leaky_relu, op.upfirdn2d = FusedLeakyReLU, fused_leaky_relu, upfirdn2d
    op.__path__ = []  # a package, so `op.fused_act` style imports resolve to the same functions
    for sub in ("fused_act", "upfirdn2d"):
        m = types.ModuleType(f"op.{sub}")
        m.FusedLeakyReLU, m.fused_leaky_relu, m.upfirdn2d = FusedLeakyReLU, fused_leaky_relu, upfirdn2d
        setattr(op, sub + "_module", m)
    return op


# --------------------------------------------------------------------------------------------- loading the peer
_PEER_MODULES: dict[str, types.ModuleType] = {}
_ACTIVE: list[types.SimpleNamespace] = []  # the namespace of the peer_runtime block in force, if any
_NUMPY_ALIASES = {"int": int, "float": float, "bool": bool, "object": object, "complex": complex, "str": str}


def _is_peer_module(name: str) -> bool:
    return name.split(".")[0] in PEER_PACKAGES


def _stub(name: str) -> types.ModuleType:
    """An empty module with a spec (torch's import machinery inspects ``__spec__`` of every loaded module)."""
    import importlib.machinery

    m = types.ModuleType(name)
    m.__spec__ = importlib.machinery.ModuleSpec(name, None)
    return m


def _cpu(v: Any) -> Any:
    """A CUDA device argument (their ``.to('cuda')``) as the CPU; anything else unchanged."""
    if isinstance(v, str) and v.startswith("cuda"):
        return "cpu"
    if isinstance(v, torch.device) and v.type == "cuda":
        return torch.device("cpu")
    return v


@contextlib.contextmanager
def peer_runtime(device: str = "cpu") -> Iterator[types.SimpleNamespace]:
    """Make the released modules importable and CPU-safe for the duration of the block; yields them.
    Re-entrant: a nested block reuses the outer one's state and leaves it in place.

    ``device="cuda"`` (``python -m modi_ext.validate --out``, on a GPU) runs their code as released instead: their
    own ``op`` package (JIT-compiled CUDA ops), ``.cuda()`` / ``.to('cuda')`` / ``synchronize`` untouched."""
    if _ACTIVE:
        yield _ACTIVE[-1]
        return
    cpu = not str(device).startswith("cuda")
    root = require_peer()
    saved = {n: m for n, m in sys.modules.items() if _is_peer_module(n) and n not in _PEER_MODULES}
    for n in saved:
        del sys.modules[n]
    sys.modules.update(_PEER_MODULES)
    if cpu:
        op = _op_module()
        sys.modules.setdefault("op", op)
        sys.modules.setdefault("op.fused_act", op.fused_act_module)
        sys.modules.setdefault("op.upfirdn2d", op.upfirdn2d_module)
    stubbed = []  # removed again at the end: sklearn, for one, takes any 'pandas' in sys.modules for the real one
    for name in ("cv2", "pandas"):  # imported at module level for drawing / bone-length tables we never call
        if name not in sys.modules:
            try:
                __import__(name)
            except ImportError:
                sys.modules[name] = _stub(name)
                stubbed.append(name)
    for k, v in _NUMPY_ALIASES.items():
        if k not in np.__dict__:
            setattr(np, k, v)
    if "numpy.core.umath_tests" not in sys.modules:  # removed in numpy 2; they use its matrix_multiply
        try:
            import numpy.core.umath_tests  # noqa: F401
        except ImportError:
            ut = _stub("numpy.core.umath_tests")
            ut.matrix_multiply = np.matmul
            sys.modules["numpy.core.umath_tests"] = ut
            stubbed.append("numpy.core.umath_tests")
    sys.path.insert(0, str(root))
    had_user = "USER" in os.environ
    os.environ.setdefault("USER", "modi")  # their evaluation config formats a path with $USER at import
    old_cuda, old_sync, old_to = torch.Tensor.cuda, torch.cuda.synchronize, torch.Tensor.to
    if cpu:
        torch.Tensor.cuda = lambda self, *a, **k: self  # type: ignore[method-assign]
        torch.Tensor.to = lambda self, *a, **k: old_to(self, *map(_cpu, a), **{n: _cpu(v) for n, v in k.items()})
        torch.cuda.synchronize = lambda *a, **k: None  # type: ignore[assignment]
    try:
        import models.gan as gan
        import motion_class
        import utils.traits as traits
        import utils.pre_run as pre_run
        import utils.data as data_utils
        import utils.preprocess_edges as preprocess
        from Motion import BVH, Animation, Quaternions
        motion_class.StaticConfig.CONFIG_YAML_FILE = str(root / "utils" / "config.yaml")
        ns = types.SimpleNamespace(gan=gan, motion_class=motion_class, traits=traits, pre_run=pre_run,
                                   data=data_utils, preprocess=preprocess, BVH=BVH, Animation=Animation,
                                   Quaternions=Quaternions, root=root)
        _ACTIVE.append(ns)
        yield ns
    finally:
        _ACTIVE.clear()
        torch.Tensor.cuda, torch.cuda.synchronize = old_cuda, old_sync  # type: ignore[method-assign]
        torch.Tensor.to = old_to  # type: ignore[method-assign]
        if not had_user:
            os.environ.pop("USER", None)
        with contextlib.suppress(ValueError):
            sys.path.remove(str(root))
        for n in [n for n in sys.modules if _is_peer_module(n)]:
            _PEER_MODULES[n] = sys.modules.pop(n)
        sys.modules.update(saved)
        for n in stubbed:
            sys.modules.pop(n, None)


def train_module(peer: types.SimpleNamespace) -> types.ModuleType:
    """Their ``train.py`` (imports matplotlib, tqdm, their evaluation code); only inside :func:`peer_runtime`."""
    import matplotlib

    matplotlib.use("Agg")
    import train  # noqa: F401  (the peer's train.py, on sys.path inside peer_runtime)

    return sys.modules["train"]


# --------------------------------------------------------------------------------------------- args and models
def make_args(npy: Path | str, *flags: str, channels: Sequence[int] = SMALL_CHANNELS, feet: bool = False,
              extra: Sequence[str] = SMALL_ARGS) -> argparse.Namespace:
    """Their ``TrainOptions`` parsed from the released flags (+ ``extra``), CPU device, narrow channels."""
    with peer_runtime() as peer:
        argv = ["--path", str(npy), "--device", "cpu", *(flags or RELEASED_FLAGS), *extra]
        if feet:
            argv += ["--foot", "--v2_contact_loss", "--character", "bandai"]
        args = peer.pre_run.TrainOptions().parse_args(argv)
    args.n_channels_max = [int(c) for c in channels]
    return args


@contextlib.contextmanager
def _channels(peer: types.SimpleNamespace, args: argparse.Namespace) -> Iterator[Any]:
    st = peer.traits.SkeletonTraits
    old = st.n_channels_max
    st.n_channels_max = list(getattr(args, "n_channels_max", old))
    try:
        yield peer.pre_run.setup_env(args, get_traits=True)
    finally:
        st.n_channels_max = old


_BANDAI_CONFIG = {"feet_names": ["Foot_L", "Foot_R"]}


@contextlib.contextmanager
def _bandai_config(peer: types.SimpleNamespace) -> Iterator[None]:
    """Their per-character YAML knows Mixamo names only; give 'bandai' its ankles (Foot_L/R) while we run."""
    sc = peer.motion_class.StaticConfig
    old = sc.load_config

    def load_config(path: str) -> dict:
        cfg = old(path)
        cfg = dict(cfg)
        cfg["bandai"] = {**cfg["default"], **_BANDAI_CONFIG}
        return cfg

    sc.load_config = staticmethod(load_config)
    try:
        yield
    finally:
        sc.load_config = old


def motion_statics(peer: types.SimpleNamespace, args: argparse.Namespace) -> Any:
    """Their ``StaticData`` (skeleton, pooling lists, feet) for ``args.path``, as train.py builds it."""
    raw = np.load(args.path, allow_pickle=True)
    with _bandai_config(peer):
        return peer.motion_class.StaticData.init_from_motion(
            raw[0], character_name=args.character, n_channels=4, enable_global_position=args.glob_pos,
            enable_foot_contact=args.foot, rotation_representation=args.rotation_repr)


def build_models(peer: types.SimpleNamespace, args: argparse.Namespace, statics: Any | None = None):
    """Their (Generator, Discriminator, g_ema) from their args, as train.py constructs them."""
    statics = motion_statics(peer, args) if statics is None else statics
    with _channels(peer, args) as traits_class:
        kw = dict(traits_class=traits_class, motion_statics=statics, n_inplace_conv=args.n_inplace_conv)
        g = peer.gan.Generator(args.latent, args.n_mlp, **kw)
        d = peer.gan.Discriminator(**kw)
        g_ema = peer.gan.Generator(args.latent, args.n_mlp, **kw)
    g_ema.eval()
    return g, d, g_ema


def normalisation(peer: types.SimpleNamespace, args: argparse.Namespace, statics: Any) -> tuple[np.ndarray, dict]:
    """Their ``motion_from_raw``: (normalised data (N, E, K, T), {'mean','std'} (1, K, E, 1))."""
    raw = np.load(args.path, allow_pickle=True)
    with _bandai_config(peer):
        return peer.data.motion_from_raw(args, raw, statics)


def seed_all(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def load_released(path: Path | str) -> dict:
    """A released checkpoint as data (weights only; their args Namespace and numpy arrays are allowed)."""
    from modi.interop.released_files import load_released_file

    return load_released_file(path)


# --------------------------------------------------------------------------------------------- data
def fold_floor_root(peer: types.SimpleNamespace, anim: Any, names: Sequence[str]) -> tuple[Any, np.ndarray]:
    """Drop Bandai's static ``joint_Root`` above ``Hips``: Hips becomes the root, carrying the composed global
    rotation and position, so the released preprocessing (which assumes the root is the hips) applies."""
    Q, A = peer.Quaternions.Quaternions, peer.Animation.Animation
    if names[0] != "joint_Root" or list(anim.parents[:2]) != [-1, 0]:
        return anim, np.array(names)
    r0 = anim.rotations[:, 0]
    rot = anim.rotations.qs.copy()[:, 1:]
    rot[:, 0] = (r0 * anim.rotations[:, 1]).qs
    pos = anim.positions.copy()[:, 1:]
    pos[:, 0] = r0 * anim.positions[:, 1] + anim.positions[:, 0]
    parents = anim.parents[1:] - 1
    parents[0] = -1
    offsets = anim.offsets[1:].copy()
    offsets[0] = pos[0, 0]
    out = A(Q(rot), pos, anim.orients.qs.copy()[1:] if hasattr(anim.orients, "qs") else anim.orients[1:],
            offsets, parents)
    return out, np.array(names[1:])


def prepare_dataset(out_npy: Path | str, bvh_files: Sequence[Path | str] | None = None, clip_len: int = 64,
                    stride: int = 32) -> Path:
    """Preprocess BVH files the way their ``utils/preprocess_edges.py`` does (after :func:`fold_floor_root`):
    expand the topology (dummy joints where a joint has several children), turn joint rotations into edge
    rotations, split into ``clip_len`` windows every ``stride`` frames; saves their ``.npy`` of dicts."""
    if bvh_files is None:
        bvh_files = sorted(require_data().glob("*.bvh"))[:2]
    all_clips = []
    with peer_runtime() as peer:
        pp = peer.preprocess
        for f in bvh_files:
            anim, names, frametime = peer.BVH.load(str(f))
            anim, names = fold_floor_root(peer, anim, names)
            exp, _, names_exp, _ = peer.data.expand_topology_edges(anim, np.arange(len(names)), names, None,
                                                                   nearest_joint_ratio=1)
            edge = pp.joint_rot_2_edge_rot(exp, str(f), "", names_exp, frametime)
            clips, _ = pp.split_to_fixed_length_clips(edge, str(Path(out_npy).parent), "", clip_len, stride,
                                                      str(Path(out_npy).parent), exp, frametime)
            all_clips.extend(clips)
        arr = np.empty(len(all_clips), dtype=object)
        arr[:] = all_clips
        out_npy = Path(out_npy)
        out_npy.parent.mkdir(parents=True, exist_ok=True)
        np.save(out_npy, arr, allow_pickle=True)  # pickles their Quaternions: read it inside peer_runtime
    return out_npy


# --------------------------------------------------------------------------------------------- checkpoints
def random_init_checkpoint(args: argparse.Namespace, out: Path | str, seed: int = 0) -> Path:
    """Their models at initialisation (g_ema = g, as train.py's ``accumulate(g_ema, generator, 0)``), saved in
    the dict layout of their ``train.py`` checkpoints."""
    seed_all(seed)
    with peer_runtime() as peer:
        tm = train_module(peer)
        statics = motion_statics(peer, args)
        g, d, g_ema = build_models(peer, args, statics)
        tm.accumulate(g_ema, g, 0)
        _, norm = normalisation(peer, args, statics)
        g_ratio, d_ratio = args.g_reg_every / (args.g_reg_every + 1), args.d_reg_every / (args.d_reg_every + 1)
        g_optim = torch.optim.Adam(g.parameters(), lr=args.g_lr * g_ratio, betas=(0.0, 0.99 ** g_ratio))
        d_optim = torch.optim.Adam(d.parameters(), lr=args.d_lr * d_ratio, betas=(0.0, 0.99 ** d_ratio))
        ckpt = {"g": g.state_dict(), "d": d.state_dict(), "g_ema": g_ema.state_dict(),
                "g_optim": g_optim.state_dict(), "d_optim": d_optim.state_dict(), "args": args,
                "mean_joints": norm["mean"].transpose(0, 2, 1, 3), "std_joints": norm["std"].transpose(0, 2, 1, 3)}
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    torch.save(ckpt, out)
    return out


class _NoFigure:
    def savefig(self, *a: Any, **k: Any) -> None:
        pass


def trained_checkpoint(args: argparse.Namespace, workdir: Path | str, iters: int = 2, seed: int = 0) -> Path:
    """Run their own ``train.main`` for ``iters`` (>= 2) iterations on ``args.path`` and return the last
    checkpoint it wrote (``checkpoint/{iters-1:06d}.pt``). Iteration 0 applies R1 and path length."""
    if iters < 2:
        raise ValueError("their train() divides by the number of timed report intervals: use iters >= 2")
    workdir = Path(workdir)
    argv = _argv_from_args(args) + ["--iter", str(iters), "--report_every", str(iters),
                                    "--model_save_path", str(workdir)]
    seed_all(seed)
    with peer_runtime() as peer, _bandai_config(peer):
        tm = train_module(peer)
        old_fig = tm.motion2fig
        tm.motion2fig = lambda *a, **k: _NoFigure()
        tm.get_rank = lambda: 0
        channels = list(getattr(args, "n_channels_max", peer.traits.SkeletonTraits.n_channels_max))
        old_opts = tm.TrainOptions

        class Options(old_opts):  # their parser, plus the channel widths this harness ran with (saved in args)
            def after_parse(self, a):
                a = super().after_parse(a)
                a.n_channels_max = channels
                return a

        tm.TrainOptions = Options
        try:
            with _channels(peer, args), contextlib.redirect_stderr(open(os.devnull, "w")):
                tm.main(argv)
        finally:
            tm.motion2fig, tm.TrainOptions = old_fig, old_opts
    ckpt = workdir / "checkpoint" / f"{iters - 1:06d}.pt"
    if not ckpt.is_file():
        raise RuntimeError(f"their train.main wrote no {ckpt}")
    return ckpt


class _NoContactLoss:
    """Their ``ContactLabelLoss`` for a model without contact entities (theirs assumes ``--foot`` and fails on
    other entities' values): zero."""

    def __call__(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return pred.new_zeros(())


def trained_encoder_checkpoint(generator_ckpt: Path | str, workdir: Path | str, iters: int = 2, n_frames: int = 0,
                               seed: int = 0, batch: int = 4) -> Path:
    """Run their ``train_encoder.main`` against ``generator_ckpt`` (a file this harness wrote) for ``iters``
    iterations, predicting W+ from the first ``n_frames`` frames (0: the whole motion, inversion; their masking
    with ``n_frames > 0`` fails in their ``ConditionalMask`` unless a ``cond_length`` is passed, which their
    train_encoder does not); returns its last checkpoint.

    Their loader calls ``torch.load`` with the pre-2.6 default (pickles allowed); it reads only our own file here,
    so it is given ``weights_only=False`` for that call. Their recorder writes under ``~``: HOME is ``workdir``.
    For a generator trained without ``--foot`` their contact term is replaced by zero (see ``_NoContactLoss``)."""
    workdir = Path(workdir)
    gen_args = load_released(generator_ckpt)["args"]
    argv = ["--ckpt_existing", str(generator_ckpt), "--path", str(gen_args.path), "--device", "cpu",
            "--batch", str(batch), "--iter", str(iters), "--report_every", str(iters),
            "--model_save_path", str(workdir), "--n_latent_predict", "2", "--n_frames", str(n_frames),
            "--character", getattr(gen_args, "character", "jasper")]
    seed_all(seed)
    old_load, old_home = torch.load, os.environ.get("HOME")
    with peer_runtime() as peer, _bandai_config(peer), _channels(peer, gen_args):
        train_module(peer)
        import train_encoder as te

        te.get_rank = lambda: 0
        old_contact = te.ContactLabelLoss
        if not getattr(gen_args, "foot", False):  # their contact term reads the last two entities as labels
            te.ContactLabelLoss = _NoContactLoss
        torch.load = lambda f, *a, **k: old_load(f, *a, **{**k, "weights_only": False})  # our own file only
        os.environ["HOME"] = str(workdir)
        try:
            with contextlib.redirect_stderr(open(os.devnull, "w")):
                te.main(argv)
        finally:
            torch.load, te.ContactLabelLoss = old_load, old_contact
            if old_home is None:
                os.environ.pop("HOME", None)
            else:
                os.environ["HOME"] = old_home
    ckpt = workdir / "checkpoint" / f"{iters - 1:06d}.pt"
    if not ckpt.is_file():
        raise RuntimeError(f"their train_encoder.main wrote no {ckpt}")
    return ckpt


def _argv_from_args(args: argparse.Namespace) -> list[str]:
    """Re-express a parsed Namespace as their command line (the flags this harness sets); the device is the CPU
    unless ``args.peer_device`` says otherwise (``modi_ext.validate``'s GPU stage sets it to ``cuda``)."""
    argv = ["--path", str(args.path), "--device", str(getattr(args, "peer_device", "cpu")),
            "--latent", str(args.latent), "--n_mlp", str(args.n_mlp),
            "--batch", str(args.batch), "--n_inplace_conv", str(args.n_inplace_conv), "--character", args.character]
    for flag in ("skeleton", "conv3", "conv3fast", "joints_pool", "glob_pos", "normalize", "use_velocity", "foot",
                 "v2_contact_loss"):
        if getattr(args, flag, False):
            argv.append("--" + flag)
    return argv


def models_from_checkpoint(peer: types.SimpleNamespace, ckpt: dict, args: argparse.Namespace | None = None):
    """Their (G, D, g_ema, statics) with a checkpoint's weights loaded."""
    args = copy.copy(ckpt["args"] if args is None else args)
    statics = motion_statics(peer, args)
    g, d, g_ema = build_models(peer, args, statics)
    g.load_state_dict(ckpt["g"])
    d.load_state_dict(ckpt["d"])
    g_ema.load_state_dict(ckpt["g_ema"])
    return g, d, g_ema, statics


def write_bvh(peer: types.SimpleNamespace, motion: torch.Tensor, ckpt: dict, statics: Any, path: Path | str) -> Path:
    """Their BVH writing for a normalised sample ``(B, K, E, T)`` exactly as ``train.py`` does it (they prefix the
    file name with the sample index: returns the file of sample 0)."""
    args = ckpt["args"]
    with _bandai_config(peer):
        import utils.visualization as vis

        dyn = peer.motion_class.DynamicData(motion.detach().cpu().float(), statics,
                                            use_velocity=args.entity == "Edge" and args.use_velocity)
        dyn = dyn.un_normalise(ckpt["mean_joints"].transpose(0, 2, 1, 3), ckpt["std_joints"].transpose(0, 2, 1, 3))
        vis.motion_to_bvh(dyn[0:1], str(path), args.entity, statics.parents)
    p = Path(path)
    return p.parent / f"0_{p.name}"


def session_files(root: Path | str, n_bvh: int = 2, iters: int = 2, seed: int = 0) -> types.SimpleNamespace:
    """The small files equality tests share, made once under ``root`` (a per-session temp dir) and reused:
    ``data`` (their .npy from ``n_bvh`` Bandai clips), ``args`` (narrow model, released flags), ``init`` (random
    initialisation) and ``trained`` (after ``iters`` iterations of their train.main)."""
    require_peer()
    require_data()
    root = Path(root)
    npy = root / "data" / "edge_rot_bandai.npy"
    if not npy.is_file():
        prepare_dataset(npy, sorted(require_data().glob("*.bvh"))[:n_bvh])
    args = make_args(npy)
    init = root / "init.pt"
    if not init.is_file():
        random_init_checkpoint(args, init, seed=seed)
    trained = root / "train" / "checkpoint" / f"{iters - 1:06d}.pt"
    if not trained.is_file():
        trained_checkpoint(args, root / "train", iters=iters, seed=seed)
    return types.SimpleNamespace(root=root, data=npy, args=args, init=init, trained=trained)


def session_encoder(files: types.SimpleNamespace, iters: int = 2, seed: int = 0) -> Path:
    """Their encoder trained ``iters`` iterations against ``files.trained`` (made once under ``files.root``)."""
    ckpt = files.root / "encoder" / "checkpoint" / f"{iters - 1:06d}.pt"
    if not ckpt.is_file():
        trained_encoder_checkpoint(files.trained, files.root / "encoder", iters=iters, seed=seed)
    return ckpt


__all__ = ["session_encoder", "session_files", "PEER", "BANDAI", "PeerUnavailable", "require_peer", "require_data", "peer_runtime", "train_module",
           "make_args", "build_models", "motion_statics", "normalisation", "seed_all", "load_released",
           "prepare_dataset", "random_init_checkpoint", "trained_checkpoint", "trained_encoder_checkpoint", "models_from_checkpoint",
           "write_bvh", "fused_leaky_relu", "FusedLeakyReLU", "upfirdn2d", "SMALL_CHANNELS", "RELEASED_FLAGS"]
