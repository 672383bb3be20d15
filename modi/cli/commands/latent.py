"""``modi latent ...``: MoDi's latent-space applications on a trained checkpoint (BVH + GIF, PNG plots, JSON).

Latents on the command line: an integer (or ``seed:N``) is the latent of motion 0 of ``modi generate --seed N``;
``mean`` is the mean latent w̄; a path to ``.npy`` is a saved W (D,) or W+ (L, D) latent (``latent invert`` and
``apply invert`` write them). Motions are synthesised with the model's fixed noise, so a latent fixes its motion.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from modi.cli import types as ct
from modi.errors import UserError
from modi.io.formats import add_format_options
from modi.viz import add_view_option

_LATENT_HELP = "a seed (integer or seed:N), 'mean', or a .npy W/W+ latent file"


def _common(p: argparse.ArgumentParser, out: bool = True) -> None:
    p.add_argument("ckpt", metavar="CKPT", help="MoDi checkpoint written by 'modi train'")
    if out:
        p.add_argument("--out", required=True, metavar="DIR", type=ct.output_dir, help="output folder (created if missing)")
    p.add_argument("--device", default="cpu", type=ct.device, help="cpu, cuda or cuda:N")
    p.add_argument("--threads", type=ct.threads_int, default=None, help="torch CPU threads (default: torch's choice)")
    p.add_argument("--raw-weights", action="store_true", help="use the raw generator instead of its EMA")
    add_format_options(p)


def register(subparsers) -> None:
    fmt = argparse.ArgumentDefaultsHelpFormatter
    p = subparsers.add_parser("latent", help="latent-space applications: mean, truncation, interpolation, "
                                             "clustering, editing, crowds, inversion",
                              description=__doc__, formatter_class=fmt)
    sub = p.add_subparsers(dest="latent_command", metavar="ACTION")
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])

    q = sub.add_parser("mean", help="the mean motion G(w̄)", formatter_class=fmt,
                       description="Write the mean motion G(w̄) as mean.bvh + mean.gif and w̄ as mean_w.npy.")
    _common(q)
    q.set_defaults(func=run_mean)

    q = sub.add_parser("truncate", help="truncation sequence from a latent to the mean", formatter_class=fmt,
                       description="w_i = w + i/C (w̄ - w), i = 0..C: step_00.bvh is the motion itself, step_C the "
                                   "mean motion; all side by side in truncation.gif. W+ latents move every layer.")
    _common(q)
    q.add_argument("--latent", default="0", help=_LATENT_HELP)
    q.add_argument("--steps", type=ct.int_range(1, 1000), default=4, help="C: number of interpolation steps")
    q.set_defaults(func=run_truncate)

    q = sub.add_parser("interpolate", help="interpolation sequence between two latents", formatter_class=fmt,
                       description="w_i = a + i/C (b - a), i = 0..C, in W (two W latents) or W+ (any W+ "
                                   "endpoint; a W endpoint is lifted to W+). step_00 is A, step_C is B.")
    _common(q)
    q.add_argument("--from", dest="a", default="0", help="start latent: " + _LATENT_HELP)
    q.add_argument("--to", dest="b", default="1", help="end latent: " + _LATENT_HELP)
    q.add_argument("--steps", type=ct.int_range(1, 1000), default=4, help="C: number of interpolation steps")
    q.set_defaults(func=run_interpolate)

    q = sub.add_parser("cluster", help="K-means on W, t-SNE plot, members of each cluster", formatter_class=fmt,
                       description="Sample N latents, cluster their W codes with K-means, plot a t-SNE map "
                                   "coloured by cluster (tsne.png) and render members of every cluster side by side "
                                   "(cluster_C.gif + BVH in cluster_C/); clusters.json has sizes and members.")
    _common(q)
    q.add_argument("--n", type=ct.int_range(2, ct.MAX_SAMPLES), default=10_000, help="sampled motions")
    q.add_argument("--k", type=ct.int_range(1, 1000), default=8, help="clusters")
    q.add_argument("--per-cluster", type=ct.int_range(0, 100), default=4, help="members rendered per cluster")
    q.add_argument("--pick", choices=("random", "nearest"), default="random",
                   help="which members to render: random ones, or those nearest the cluster centre")
    q.add_argument("--tsne-max", type=ct.int_range(0, ct.MAX_SAMPLES), default=2000, help="samples in the t-SNE plot (0: no plot)")
    q.add_argument("--seed", type=ct.seed_int, default=0, help="sampling / clustering seed")
    q.set_defaults(func=run_cluster)

    q = sub.add_parser("edit", help="semantic editing along an SVM boundary in W", formatter_class=fmt,
                       description="Score N sampled motions for an attribute, fit a linear SVM between the top and "
                                   "bottom --ratio, and edit held-out seeds by w + α n for each α (in units of the "
                                   "std of w·n). Writes boundary.json, report.json (scores, monotonicity), "
                                   "score_vs_alpha.png and, for the first --render seeds, edit_SEED.gif + BVH.")
    _common(q)
    q.add_argument("--attribute", default="gral", choices=("gral", "gral_released", "verticality", "speed"),
                   help="gral = gradual right-arm lifting (App. C.2); gral_released = the authors' code's score "
                        "(rotation angles of the right arm and clavicle)")
    q.add_argument("--svm", choices=("ours", "released"), default="ours",
                   help="boundary fit: 'ours' = LinearSVC refitted on all extremes; 'released' = SVC with a linear "
                        "kernel on 70%% of them (the authors' InterFaceGAN code; they sample --n 10000)")
    q.add_argument("--n", type=ct.int_range(10, ct.MAX_SAMPLES), default=2000, help="sampled motions for the boundary")
    q.add_argument("--ratio", type=ct.float_range(0.0, 0.5, lo_inclusive=False), default=0.2, help="fraction at each extreme used as SVM classes")
    q.add_argument("--boundary", default=None, metavar="JSON", help="reuse a saved boundary instead of fitting")
    q.add_argument("--held-out", type=ct.int_range(1, 10_000), default=16, help="held-out seeds scored along the edit")
    q.add_argument("--first-seed", type=ct.int_range(0, ct.MAX_SEED - 10_000), default=100_000, help="held-out seeds are FIRST..FIRST+held-out-1")
    q.add_argument("--alphas", type=ct.float_range(-100.0, 100.0), nargs="+", default=[-3, -2, -1, 0, 1, 2, 3],
                   help="edit strengths in units of the std of w·n (increasing)")
    q.add_argument("--render", type=ct.int_range(0, 1000), default=2, help="held-out seeds rendered as α sequences")
    q.add_argument("--seed", type=ct.seed_int, default=0, help="sampling seed for the boundary")
    q.set_defaults(func=run_edit)

    q = sub.add_parser("crowd", help="crowd: variations around one latent in one scene", formatter_class=fmt,
                       description="Sample K latents w + σ ε around a motion's latent; write crowd_NN.bvh placed "
                                   "on a grid (crowd_00_source is the motion itself) and crowd.gif with every "
                                   "character in one scene. The paper uses σ between 0.1 and 0.8.")
    _common(q)
    q.add_argument("--latent", default="0", help=_LATENT_HELP)
    q.add_argument("--k", type=ct.int_range(1, 1000), default=8, help="variations")
    q.add_argument("--sigma", type=ct.float_range(0.0, 100.0), default=0.4, help="std of the Gaussian around w")
    q.add_argument("--seed", type=ct.seed_int, default=0, help="seed of the perturbations")
    q.add_argument("--spacing", type=ct.positive_finite_float, default=None,
                   help="distance between characters in skeleton units (default 0.9 body heights)")
    q.add_argument("--no-source", action="store_true", help="leave the original motion out of the crowd")
    q.set_defaults(func=run_crowd)

    q = sub.add_parser("invert", help="invert a BVH clip into W+ by optimisation", formatter_class=fmt,
                       description="Optimise a W+ latent so G(W+) matches a window of a BVH clip (L2 on the "
                                   "representation + λ_FK × position MSE in tenths of the body size). Writes "
                                   "input/result BVH side by side in inversion.gif, the latent (wplus.npy, usable by the other actions), "
                                   "the loss curve (loss.png) and history.json.")
    _common(q)
    q.add_argument("bvh", metavar="BVH", help="clip on the model's skeleton (joints matched by name)")
    q.add_argument("--start", type=ct.int_range(0, ct.MAX_FRAMES), default=0, help="first frame of the window (after resampling)")
    q.add_argument("--steps", type=ct.int_range(0, 1_000_000), default=300, help="optimisation steps")
    q.add_argument("--lr", type=ct.lr_float, default=0.02, help="Adam learning rate")
    q.add_argument("--lambda-fk", type=ct.float_range(0.0, 1e6), default=1.0,
                   help="weight of the FK-position term (positions in tenths of the body size)")
    q.add_argument("--init", choices=("mean", "random"), default="mean", help="starting latent")
    q.set_defaults(func=run_invert)
    for action in sub.choices.values():  # every action writes GIF previews, and the 3D viewer beside them
        add_view_option(action)


# --------------------------------------------------------------------------------------------- helpers
def _setup(args: argparse.Namespace):
    """The :class:`modi.ModiGenerator` of CKPT, opened as every action opens it."""
    from modi.api.latent import open_generator  # lazy: torch

    return open_generator(args.ckpt, device=args.device, threads=args.threads, ema=not args.raw_weights)


def _latent(gen, spec: str, option: str):
    """A latent word (seed, ``seed:N``, ``mean``, ``.npy``) of a :class:`modi.ModiGenerator` as ``(tensor,
    label)``; errors name ``option``."""
    s = str(spec).strip()
    s = s[5:] if s.startswith("seed:") else s
    try:
        seed = int(s)
    except ValueError:
        seed = None
    if seed is not None and not 0 <= seed <= ct.MAX_SEED:
        raise UserError(f"{option}: a seed must be between 0 and {ct.MAX_SEED}, got {seed}")
    try:
        w = gen.latent(seed if seed is not None else spec)
    except UserError as exc:
        raise UserError(f"{option}: {exc}") from None
    label = f"seed {seed}" if seed is not None else ("mean" if s == "mean" else Path(s).stem)
    return w, label


# --------------------------------------------------------------------------------------------- actions
def run_mean(args: argparse.Namespace) -> int:
    from modi.api.latent import write_mean  # lazy: torch

    files = write_mean(_setup(args), args.out)
    print(f"modi latent mean: {files['bvh']}, {files['gif']}, {files['latent']}")
    return 0


def run_truncate(args: argparse.Namespace) -> int:
    from modi.api.latent import write_truncation  # lazy: torch

    gen = _setup(args)
    w, label = _latent(gen, args.latent, "--latent")
    paths = write_truncation(gen, w, args.out, args.steps)
    print(f"modi latent truncate: {len(paths)} motions from {label} to the mean in {args.out} (truncation.gif)")
    return 0


def run_interpolate(args: argparse.Namespace) -> int:
    from modi.api.latent import write_interpolation  # lazy: torch

    gen = _setup(args)
    a, la = _latent(gen, args.a, "--from")
    b, lb = _latent(gen, args.b, "--to")
    paths, space = write_interpolation(gen, a, b, args.out, args.steps)
    print(f"modi latent interpolate: {len(paths)} motions from {la} to {lb} in {space}, {args.out} "
          f"(interpolation.gif)")
    return 0


def run_cluster(args: argparse.Namespace) -> int:
    from modi.api.latent import write_clusters  # lazy: torch

    res = write_clusters(_setup(args), args.out, n=args.n, k=args.k, per_cluster=args.per_cluster, pick=args.pick,
                         tsne_max=args.tsne_max, seed=args.seed)
    print(f"modi latent cluster: {args.n} samples, k={args.k}, sizes {res.sizes}; "
          f"{res.files.get('tsne', 'no t-SNE')}, {len(res.files.get('gifs', []))} cluster GIFs in {args.out}")
    return 0


def run_edit(args: argparse.Namespace) -> int:
    from modi.api.latent import write_edit  # lazy: torch

    boundary, report = write_edit(_setup(args), args.out, attribute=args.attribute, svm=args.svm, n=args.n,
                                  ratio=args.ratio, boundary=args.boundary, held_out=args.held_out,
                                  first_seed=args.first_seed, alphas=args.alphas, render=args.render, seed=args.seed)
    out = Path(args.out)
    print(f"modi latent edit: boundary accuracy {boundary.accuracy:.2f} (held-out extremes); {report.summary()}")
    print(f"modi latent edit: {out / 'report.json'}, {out / 'score_vs_alpha.png'}")
    return 0


def run_crowd(args: argparse.Namespace) -> int:
    from modi.api.latent import SIGMA_RANGE, write_crowd  # lazy: torch

    gen = _setup(args)
    if not SIGMA_RANGE[0] <= args.sigma <= SIGMA_RANGE[1]:
        print(f"modi latent crowd: note: σ={args.sigma:g} is outside the paper's range "
              f"{SIGMA_RANGE[0]}-{SIGMA_RANGE[1]}")
    w, label = _latent(gen, args.latent, "--latent")
    crowd = write_crowd(gen, w, args.out, k=args.k, sigma=args.sigma, seed=args.seed,
                        include_source=not args.no_source, spacing=args.spacing)
    print(f"modi latent crowd: {len(crowd.files['bvh'])} characters around {label} (σ={args.sigma:g}) in "
          f"{args.out}; scene preview {crowd.files.get('gif')}")
    return 0


def run_invert(args: argparse.Namespace) -> int:
    from modi.api.latent import write_inversion  # lazy: torch

    res = write_inversion(_setup(args), args.bvh, args.out, start=args.start, steps=args.steps, lr=args.lr,
                          lambda_fk=args.lambda_fk, init=args.init)
    out = Path(args.out)
    print(f"modi latent invert: loss {res.history[0]:.4f} -> {res.history[-1]:.4f} (rec {res.rec[-1]:.4f}, "
          f"fk {res.fk[-1]:.4f}); {out / 'inversion.gif'}, {out / 'wplus.npy'}")
    return 0
