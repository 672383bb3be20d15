"""``modi info FILE``: what a modi file is (kind, format, step, skeleton, config, precision, the modi that wrote it).

The description is ``modi.inspect`` (``modi.api.info``); this command parses and prints it.
"""
from __future__ import annotations


def register(subparsers) -> None:
    p = subparsers.add_parser("info", help="what a modi checkpoint, encoder or feature-extractor file is",
                              description="Print the kind, format version, training step, skeleton, config and "
                                          "modi version of a MoDi or GANimator checkpoint (or run folder) with the "
                                          "precision it was trained in (fp32 or bf16), an "
                                          "encoder or a feature-extractor file. The file is read as data only: "
                                          "nothing in it runs, and a file that names code is refused.")
    p.add_argument("file", help="checkpoint file, or a run folder (ganimator.ckpt / checkpoint.pt inside)")
    p.add_argument("--json", action="store_true", help="print the description as JSON")
    p.set_defaults(func=_info)


def _info(args) -> int:
    from modi.api.info import inspect  # lazy: torch; `modi --help` imports every command module

    info = inspect(args.file)
    print(info.to_json() if args.json else str(info))
    return 0
