"""The encoder's Table 5 metrics (paper 001 App. D.4): how well G(I(m)) reproduces unseen motions m.

* ``l2`` / ``l1`` -- mean squared / absolute error over every element of the normalised representation (the
  quantity the reconstruction loss trains; comparable across rigs only in spirit, since it depends on the data's
  normalisation).
* ``root_mm`` -- global root position error: the root trajectory rebuilt from the velocities, compared frame by
  frame.
* ``local_mm`` -- joint positions relative to the root (root placed at the origin, its rotation kept).
* ``global_mm`` -- global joint positions.

Two definitions of the position columns are reported side by side:

* ours (``root_mm``, ``local_mm``, ``global_mm``): the mean Euclidean distance per joint and frame, in
  millimetres; the data's unit is read from the body size (``space.mm_per_unit``; override with ``units``);
* the released code's (``root_mse``, ``local_mse``, ``global_mse``; ``generate_encoder.py`` ``test_encoder`` with
  ``models/encoder_mask.py`` ``PositionLoss``/``PositionLossRoot``): the *mean squared coordinate error* in the
  data's own units (an ``MSELoss`` over every joint, frame and x/y/z), local = FK with the root translation zeroed,
  root = the root trajectory. These are the numbers the paper's Table 5 labels "mm" (``PAPER_TABLE5``).

L2/L1 are the same in both: ``MSELoss``/``L1Loss`` over the whole normalised tensor (every channel and entity,
root motion and contacts included). ``*_mse_cm2`` are the squared errors converted to cm².
"""
from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from modi.models.modi.encoder.model import encode
from modi.models.modi.latent.space import mean_motion, mm_per_unit, synthesize

PAPER_TABLE5 = {"l2": 0.293, "l1": 0.316, "root_mm": 59.0, "local_mm": 20.4, "global_mm": 78.2}
METRIC_NAMES = {"l2": "Reconst. (L2)", "l1": "Reconst. (L1)", "root_mm": "Global root position (mm)",
                "local_mm": "Local position (mm)", "global_mm": "Global position (mm)"}
RELEASED_NAMES = {"l2": "Reconst. (L2)", "l1": "Reconst. (L1)", "root_mse": "Global root position (MSE)",
                  "local_mse": "Local position (MSE)", "global_mse": "Global position (MSE)"}
# the paper's Table 5 under the released definitions (its "mm" columns are the script's MSEs in data units)
PAPER_TABLE5_RELEASED = {"l2": 0.293, "l1": 0.316, "root_mse": 59.0, "local_mse": 20.4, "global_mse": 78.2}


def _sums(codec: Any, real: Tensor, rec: Tensor, mm: float) -> dict[str, float]:
    """Sums of per-element/per-joint errors for one batch (so batches of any size average exactly)."""
    d_real, d_rec = codec.decode(real.float()), codec.decode(rec.float())
    p_real, p_rec = d_real["positions"] * mm, d_rec["positions"] * mm  # (B, T, J, 3) in mm
    root_real, root_rec = p_real[..., :1, :], p_rec[..., :1, :]
    loc_real, loc_rec = p_real - root_real, p_rec - root_rec
    diff = rec.float() - real.float()

    def dist(a: Tensor, b: Tensor) -> Tensor:
        return torch.linalg.vector_norm(a - b, dim=-1)

    return {
        "l2": float(diff.pow(2).sum()), "l1": float(diff.abs().sum()), "n_elem": float(diff.numel()),
        "root_mm": float(dist(root_real, root_rec).sum()), "n_root": float(root_real[..., 0].numel()),
        "local_mm": float(dist(loc_real, loc_rec).sum()), "global_mm": float(dist(p_real, p_rec).sum()),
        "n_joint": float(p_real[..., 0].numel()),
        "root_mse": float(((root_real - root_rec) / mm).pow(2).sum()),
        "local_mse": float(((loc_real - loc_rec) / mm).pow(2).sum()),
        "global_mse": float(((p_real - p_rec) / mm).pow(2).sum()),
        "root_mse_cm2": float(((root_real - root_rec) / 10).pow(2).sum()),
        "local_mse_cm2": float(((loc_real - loc_rec) / 10).pow(2).sum()),
        "global_mse_cm2": float(((p_real - p_rec) / 10).pow(2).sum()),
    }


def _finish(acc: dict[str, float]) -> dict[str, float]:
    n_el, n_root, n_j = acc["n_elem"], acc["n_root"], acc["n_joint"]
    return {
        "l2": acc["l2"] / n_el, "l1": acc["l1"] / n_el,
        "root_mm": acc["root_mm"] / n_root, "local_mm": acc["local_mm"] / n_j, "global_mm": acc["global_mm"] / n_j,
        "root_mse": acc["root_mse"] / (3 * n_root), "local_mse": acc["local_mse"] / (3 * n_j),
        "global_mse": acc["global_mse"] / (3 * n_j),
        "root_mse_cm2": acc["root_mse_cm2"] / (3 * n_root), "local_mse_cm2": acc["local_mse_cm2"] / (3 * n_j),
        "global_mse_cm2": acc["global_mse_cm2"] / (3 * n_j),
    }


def reconstruction_metrics(codec: Any, real: Tensor, rec: Tensor, units: str = "auto") -> dict[str, float]:
    """Table 5 metrics of reconstructions ``rec`` of ``real`` (both normalised (B, K, E, T))."""
    if real.shape != rec.shape:
        raise ValueError(f"real {tuple(real.shape)} and reconstruction {tuple(rec.shape)} differ in shape")
    with torch.no_grad():
        return _finish(_sums(codec, real.cpu(), rec.cpu(), mm_per_unit(codec.height, units)))


@torch.no_grad()
def evaluate_encoder(encoder: Any, g: Any, codec: Any, windows: Tensor, batch: int = 64, units: str = "auto",
                     baselines: bool = True) -> dict[str, Any]:
    """Metrics of G(I(m)) over ``windows`` (normalised), plus two trivial baselines: the mean motion G(w̄) for every
    input, and the data mean (an all-zero normalised tensor, i.e. the average pose and velocity per frame)."""
    if windows.shape[0] == 0:
        raise ValueError("no windows to evaluate")
    mm = mm_per_unit(codec.height, units)
    dev = next(g.parameters()).device
    was_training = encoder.training
    encoder.eval()
    acc: dict[str, dict[str, float]] = {"encoder": {}}
    if baselines:
        acc.update(mean_motion={}, data_mean={})
        mean_x = mean_motion(g).cpu()
    for i in range(0, windows.shape[0], batch):
        real = windows[i:i + batch].to(dev).float()
        rec = synthesize(g, encode(encoder, real)).cpu()
        real = real.cpu()
        outs = {"encoder": rec}
        if baselines:
            outs["mean_motion"] = mean_x.expand_as(real)
            zeros = torch.zeros_like(real)
            zeros[:, :, codec.rep.contacts] = (real[:, :, codec.rep.contacts] > 0.5).float().mean()  # base rate
            outs["data_mean"] = zeros
        for k, x in outs.items():
            for name, v in _sums(codec, real, x, mm).items():
                acc[k][name] = acc[k].get(name, 0.0) + v
    encoder.train(was_training)
    result: dict[str, Any] = {k: _finish(v) for k, v in acc.items()}
    result["n_windows"] = int(windows.shape[0])
    result["mm_per_unit"] = mm
    return result


def format_table5(result: dict[str, Any], paper: bool = True,
                  definitions: tuple[str, ...] = ("ours", "released")) -> str:
    """Markdown tables of the encoder and the baselines, one per definition: ``ours`` (mean distances in mm) and
    ``released`` (the authors' script: mean squared coordinate errors in data units, beside the paper's Mixamo
    row, which uses that definition)."""
    labels = {"encoder": "encoder G(I(m))", "mean_motion": "baseline: mean motion G(w̄)",
              "data_mean": "baseline: data mean (zero tensor)"}
    tables = []
    for definition in definitions:
        if definition not in ("ours", "released"):
            raise ValueError(f"unknown Table 5 definition {definition!r}")
        names = METRIC_NAMES if definition == "ours" else RELEASED_NAMES
        cols = list(names)
        if not any(k in result and all(c in result[k] for c in cols) for k in labels):
            continue  # e.g. results saved before the released columns existed
        title = ("ours: position errors as mean Euclidean distance (mm)" if definition == "ours" else
                 "released definitions: position errors as mean squared coordinate error (data units²)")
        lines = [f"*{title}*", "", "| | " + " | ".join(names[c] for c in cols) + " |", "|---" * (len(cols) + 1) + "|"]

        def row(name: str, vals: dict[str, float]) -> str:
            return f"| {name} | " + " | ".join(f"{vals[c]:.3f}" if c in ("l2", "l1") else f"{vals[c]:.1f}"
                                              for c in cols) + " |"

        for key in ("encoder", "mean_motion", "data_mean"):
            if key in result and all(c in result[key] for c in cols):
                lines.append(row(labels[key], result[key]))
        if paper and definition == "released":
            lines.append(row("paper, Mixamo (Table 5, all losses)", PAPER_TABLE5_RELEASED))
        tables.append("\n".join(lines))
    return "\n\n".join(tables)


__all__ = ["PAPER_TABLE5", "PAPER_TABLE5_RELEASED", "METRIC_NAMES", "RELEASED_NAMES", "reconstruction_metrics", "evaluate_encoder", "format_table5"]
