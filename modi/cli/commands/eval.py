"""modi eval: train the feature extractor, and measure real data, a MoDi checkpoint or GANimator outputs.

    modi eval train-features DATA --out features.pt      # ST-GCN on labelled clips; prints held-out top-1
    modi eval real DATA --features features.pt           # held-out vs train clips: the floor for generators
    modi eval gen --ckpt CKPT --features F --data DIR    # MoDi samples vs the real clips of DIR
    modi eval single --source SRC.bvh GEN_DIR/ [--features F]  # GANimator coverage / diversity (+ SinMDM scorecard)
    modi eval plausibility CLIP.bvh ...                  # foot skating, floating/penetration, jitter
"""
from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from modi.cli import types as ct

_FMT = argparse.ArgumentDefaultsHelpFormatter
_AXES = ("x", "y", "z")  # the up-axis choices (modi.api.evaluation.UP_AXES maps them)
# a frame rate above 2 fps (a Frame Time under 0.5 s, what ``_motion`` accepts from a header) and at most MAX_FPS
_single_fps = ct.float_range(2.0, ct.MAX_FPS, lo_inclusive=False)


def register(subparsers: Any) -> None:
    p = subparsers.add_parser("eval", help="evaluation metrics (MoDi and GANimator)", formatter_class=_FMT,
                              description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="eval_command", metavar="EVAL_COMMAND")
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])

    t = sub.add_parser("train-features", formatter_class=_FMT,
                       help="train the ST-GCN feature extractor on labelled BVH clips",
                       description="Train the ST-GCN action recogniser whose penultimate features FID/KID/"
                                   "precision/recall/diversity use. Labels come from a JSON beside each BVH "
                                   "(Bandai-Namco layout); the split is by file, stratified by class.")
    t.add_argument("data", help="folder with BVH files and a JSON label file beside each")
    t.add_argument("--out", required=True, type=ct.output_file, help="where to write the extractor (one .pt file)")
    t.add_argument("--label-key", default="content", help="JSON key holding the integer class label")
    t.add_argument("--window", type=ct.int_range(8, 4096), default=64, help="window length in frames")
    t.add_argument("--fps", type=ct.fps_float, default=30.0, help="frame rate the clips are resampled to")
    t.add_argument("--stride", type=ct.int_range(1, ct.MAX_FRAMES), default=4, help="stride between training windows (frames)")
    t.add_argument("--eval-stride", type=ct.int_range(1, ct.MAX_FRAMES), default=16, help="stride between held-out windows (frames)")
    t.add_argument("--holdout", type=ct.float_range(0.0, 1.0, False, False), default=0.2, help="fraction of each class's files held out")
    t.add_argument("--epochs", type=ct.int_range(1, 100_000), default=12, help="training epochs (one pass over the windows each)")
    t.add_argument("--batch", dest="batch_size", type=ct.batch_int, default=64, help="batch size")
    ct.renamed_option(t, "--batch-size", "--batch", "batch_size", type=ct.batch_int)
    t.add_argument("--lr", type=ct.lr_float, default=2e-3, help="peak learning rate (one-cycle schedule)")
    t.add_argument("--max-minutes", type=ct.minutes_float, default=None, help="stop training after this many minutes")
    t.add_argument("--up-axis", choices=sorted(_AXES), default="y", help="vertical axis of the data")
    t.add_argument("--seed", type=ct.seed_int, default=0, help="random seed (split, init, batches)")
    t.add_argument("--threads", type=ct.threads_int, default=None, help="torch CPU threads (default: torch's choice)")
    t.add_argument("--json", default=None, type=ct.output_file, help="also write the training summary here")
    t.set_defaults(func=cmd_train_features)

    r = sub.add_parser("real", formatter_class=_FMT,
                       help="real-vs-real floor: held-out clips vs training clips",
                       description="FID, KID, precision, recall and diversity of the held-out clips against "
                                   "the training clips (the extractor's own split), plus plausibility of the "
                                   "held-out clips: the floor a generator is judged against.")
    r.add_argument("data", help="the labelled folder the extractor was trained on")
    r.add_argument("--features", required=True, help="feature extractor file from train-features")
    r.add_argument("--stride", type=ct.int_range(1, ct.MAX_FRAMES), default=32, help="stride between windows of both sets (frames)")
    _metric_args(r)
    r.set_defaults(func=cmd_real)

    g = sub.add_parser("gen", formatter_class=_FMT, help="evaluate a MoDi checkpoint against real clips",
                       description="Sample N motions from a MoDi checkpoint and compare their features with "
                                   "the windows of every clip in DATA (FID, KID, precision, recall, "
                                   "diversity), plus plausibility of the samples.")
    g.add_argument("--ckpt", required=True, help="MoDi checkpoint")
    g.add_argument("--features", required=True, help="feature extractor file from train-features")
    g.add_argument("--data", required=True, help="folder of real BVH clips (same skeleton)")
    g.add_argument("--n", type=ct.int_range(4, ct.MAX_SAMPLES), default=2000, help="number of generated motions")
    g.add_argument("--psi", type=ct.float_range(-2.0, 2.0), default=1.0, help="truncation psi in [-2, 2] (1 = none)")
    g.add_argument("--ik", action="store_true", help="apply the IK foot-contact cleanup to the samples")
    g.add_argument("--stride", type=ct.int_range(1, ct.MAX_FRAMES), default=32, help="stride between windows of real clips (frames)")
    _metric_args(g)
    g.set_defaults(func=cmd_gen)

    s = sub.add_parser("single", formatter_class=_FMT,
                       help="GANimator coverage and diversity of generated BVH against one source BVH",
                       description="Coverage (30-frame windows, threshold 2.0), global diversity (patched "
                                   "nearest neighbour, segments >= 30 frames) and local diversity (15-frame "
                                   "windows) of generated BVH files against the source they were trained on, "
                                   "as the GANimator authors measure them: at 30 fps, on the reduced joints both "
                                   "files share (matched by name, namespace prefix ignored).")
    s.add_argument("generated", nargs="+", help="generated BVH files or folders of them (the source's rig; joints "
                                                "are matched by name, namespace prefix and sibling order ignored)")
    s.add_argument("--source", required=True, help="the training sequence (BVH)")
    s.add_argument("--json", default=None, type=ct.output_file, help="write the results (means and per-file values) here")
    s.add_argument("--md", default=None, type=ct.output_file, help="also write a Markdown summary here")
    s.add_argument("--window", type=ct.int_range(1, ct.MAX_FRAMES), default=30, help="coverage window (frames)")
    s.add_argument("--threshold", type=ct.positive_finite_float, default=2.0, help="coverage distance threshold")
    s.add_argument("--min-segment", type=ct.int_range(1, ct.MAX_FRAMES), default=30, help="PNN minimum segment length (frames)")
    s.add_argument("--local-window", type=ct.int_range(1, ct.MAX_FRAMES), default=15, help="local-diversity window (frames)")
    s.add_argument("--representation", choices=["6d", "matrix"], default="6d",
                   help="pose vector: the first two rows of each local rotation matrix, as in the GANimator "
                        "authors' evaluation code (what threshold 2.0 and their tables use), or all 9 entries")
    s.add_argument("--fps", type=_single_fps, default=30.0,
                   help="resample source and generated clips to this rate (the authors score at 30 fps; their "
                        "loader halves 60 fps files)")
    s.add_argument("--gen-fps", type=_single_fps, default=None,
                   help="the generated files' true frame rate, when their header's Frame Time is wrong "
                        "(unset: the header's)")
    s.add_argument("--joints", choices=["reduced", "all"], default="reduced",
                   help="score on GANimator's reduced joint set (no fingers or head-top: 24 joints of a Mixamo "
                        "rig, as the published figures) or on every joint; either way on the joints both files have")
    s.add_argument("--features", default=None,
                   help="feature extractor (modi eval train-features) on the source's rig: adds SinMDM's scorecard, "
                        "SIFID, inter/intra diversity and their harmonic mean (docs/scorecard.md)")
    s.add_argument("--sifid-stride", type=ct.int_range(1, ct.MAX_FRAMES), default=8,
                   help="frames between the feature windows whose temporal feature vectors SIFID compares")
    s.add_argument("--hm-norms", nargs=3, type=ct.positive_finite_float, metavar=("SIFID", "INTER", "INTRA_DIFF"),
                   default=None, help="the harmonic mean's normalisers (unset: the SinMDM authors', from their "
                                      "issue #26; docs/scorecard.md)")
    s.set_defaults(func=cmd_single)

    q = sub.add_parser("plausibility", formatter_class=_FMT, help="foot skating, floating, jitter of BVH clips",
                       description="Foot skating (horizontal foot speed in contact), floating/penetration "
                                   "relative to the ground and jitter (mean jerk), in the file's units.")
    q.add_argument("clips", nargs="+", help="BVH files")
    q.add_argument("--up-axis", choices=sorted(_AXES), default="y", help="vertical axis")
    q.add_argument("--feet", nargs="+", metavar="JOINT", default=None,
                   help="foot joints by name (default: joints named foot/toe/ankle/heel)")
    q.add_argument("--ground", type=ct.finite_float, default=0.0, help="ground height along the up axis")
    q.add_argument("--json", default=None, type=ct.output_file, help="write per-file and mean values here")
    q.set_defaults(func=cmd_plausibility)


def _metric_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--k", type=ct.int_range(1, 1000), default=3, help="k of the k-NN manifolds for precision/recall")
    p.add_argument("--kid-blocks", type=ct.int_range(1, 1000), default=10, help="disjoint blocks for KID's standard error")
    p.add_argument("--diversity-pairs", type=ct.int_range(1, 10_000_000), default=200, help="random pairs for diversity")
    p.add_argument("--seed", type=ct.seed_int, default=0, help="random seed (sampling, blocks, pairs)")
    p.add_argument("--json", default=None, type=ct.output_file, help="write the full report (JSON) here")
    p.add_argument("--md", default=None, type=ct.output_file, help="write a Markdown summary here")


# ----------------------------------------------------------------------------------------------------------------


def _dump(results: dict[str, Any], args: argparse.Namespace, title: str) -> None:
    from modi.api.evaluation import write_report  # lazy: torch

    text = write_report(results, title, json_path=getattr(args, "json", None), md_path=getattr(args, "md", None))
    if getattr(args, "md", None) is None:
        print(text)


def cmd_train_features(args: argparse.Namespace) -> int:
    from modi.api.evaluation import train_features  # lazy: torch

    hist = train_features(args.data, args.out, label_key=args.label_key, window=args.window, fps=args.fps,
                          stride=args.stride, eval_stride=args.eval_stride, holdout=args.holdout, epochs=args.epochs,
                          batch_size=args.batch_size, lr=args.lr, max_minutes=args.max_minutes, up_axis=args.up_axis,
                          seed=args.seed, threads=args.threads, json_path=args.json,
                          log=lambda line: print(line), warn=lambda line: print(line, file=sys.stderr))
    if "val_top1" in hist:
        print(f"held-out top-1: {hist['val_top1']:.3f} (class-balanced {hist['val_balanced_top1']:.3f}) "
              f"on {hist['val_windows']} windows of {hist['heldout_clips']} clips; trained {hist['seconds']:.0f} s "
              f"({hist['cpu_seconds']:.0f} CPU s)")
    else:
        print(f"no held-out clips; trained {hist['seconds']:.0f} s")
    print(f"wrote {args.out}")
    return 0


def cmd_real(args: argparse.Namespace) -> int:
    from modi.api.evaluation import evaluate_real  # lazy: torch

    for opt in ("json", "md"):
        if getattr(args, opt):
            ct.refuse_overwrite(getattr(args, opt), [args.features], f"--{opt}")
    results = evaluate_real(args.data, features=args.features, stride=args.stride, k=args.k,
                            kid_blocks=args.kid_blocks, diversity_pairs=args.diversity_pairs, seed=args.seed)
    _dump(results, args, "Real-vs-real floor")
    return 0


def cmd_gen(args: argparse.Namespace) -> int:
    from modi.api.evaluation import evaluate  # lazy: torch

    for opt in ("json", "md"):
        if getattr(args, opt):
            ct.refuse_overwrite(getattr(args, opt), [args.ckpt, args.features], f"--{opt}")
    results = evaluate(args.ckpt, features=args.features, data=args.data, n=args.n, seed=args.seed, psi=args.psi,
                       ik=args.ik, stride=args.stride, k=args.k, kid_blocks=args.kid_blocks,
                       diversity_pairs=args.diversity_pairs)
    _dump(results, args, "MoDi evaluation")
    return 0


# ----------------------------------------------------------------------------------------------------------------


def cmd_single(args: argparse.Namespace) -> int:
    from modi.api.evaluation import evaluate_single, write_report  # lazy: torch

    for opt in ("json", "md"):
        if getattr(args, opt):
            ct.refuse_overwrite(getattr(args, opt), [args.source, *args.generated, *filter(None, [args.features])],
                                f"--{opt}")
    out = evaluate_single(args.generated, args.source, fps=args.fps, gen_fps=args.gen_fps, joints=args.joints,
                          representation=args.representation, window=args.window, threshold=args.threshold,
                          min_segment=args.min_segment, local_window=args.local_window, features=args.features,
                          sifid_stride=args.sifid_stride,
                          **({} if args.hm_norms is None else {"normalisers": args.hm_norms}))
    joints, n_source, left_out = out["protocol"]["joint_names"], out.pop("source_joints"), out.pop("left_out")
    print(f"scoring {len(joints)} joints ({args.joints}; of the source's {n_source}) at {args.fps:g} fps: "
          + " ".join(joints))
    if left_out:
        print(f"  not in every generated file, so not scored: {' '.join(left_out)}")
    write_report(out, "Single-sequence metrics", json_path=args.json, md_path=args.md)
    print(f"coverage {out['coverage']:.4f}  global diversity {out['global_diversity']:.4f}  "
          f"local diversity {out['local_diversity']:.4f}  ({out['protocol']['n_samples']} file(s), "
          f"{out['seconds']:.1f} s)")
    card = out.get("scorecard")
    if card is not None:
        inter, hm = card["inter_diversity"], card["harmonic_mean"]
        print(f"SIFID {card['sifid']:.4f}  inter-diversity " + ("n/a (one file)" if inter is None else f"{inter:.4f}")
              + f"  intra-diversity {card['intra_diversity']:.4f} (source {card['intra_diversity_source']:.4f}, "
              f"diff {card['intra_diversity_diff']:.4f})  harmonic mean " + ("n/a" if hm is None else f"{hm:.4f}"))
    if args.json is None and args.md is None:
        print(write_report({k: v for k, v in out.items() if k != "per_file"}, "Single-sequence metrics"))
    return 0


def cmd_plausibility(args: argparse.Namespace) -> int:
    from modi.api.evaluation import evaluate_plausibility  # lazy: torch

    if args.json:
        ct.refuse_overwrite(args.json, args.clips, "--json")
    out = evaluate_plausibility(args.clips, up_axis=args.up_axis, feet=args.feet, ground=args.ground,
                                json_path=args.json, each=lambda m: print(f"{m['file']}: " + "  ".join(
                                    f"{k} {v:.4g}" for k, v in m.items() if k != "file")))
    per = out["per_file"]
    print(json.dumps(out["mean"], indent=1) if len(per) > 1 else "", end="\n" if len(per) > 1 else "")
    return 0
