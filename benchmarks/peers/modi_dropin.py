"""Run the authors' MoDi ``train.py`` on ``modi_ext`` layers: a run-time patch of their layer classes.

Inside :func:`dropin` (itself inside ``released_modi.peer_runtime``) their ``models.gan.ModulatedConv`` (the
generator's modulated skeletal convolutions: in place, upsampling, and the to-motion projection),
``models.gan.EqualConv`` (the discriminator's skeletal convolutions and its convolutional scalers, 3-tap and 1x1)
and ``models.gan.Blur`` (the anti-alias filter before the scalers, as modi's discriminator computes it;
``blur=False`` keeps theirs) are subclasses that build exactly as theirs do (same random draws, same masks and
fan-in factors); the convolutions then keep only the entries their mask connects: ``weight`` becomes the compact
per-pair ``(C, nnz, C', U)`` parameter that ``modi_ext.skeletal.ops`` reads, under the same name, so their optimiser
(built from ``parameters()`` after construction), ``accumulate`` (EMA by parameter name) and checkpoints keep
working:

* ``state_dict()`` writes ``weight`` back in their dense masked shape (zeros off the mask: those entries are
  multiplied by zero in their forward), so a checkpoint of the patched script is one of theirs;
* ``load_state_dict()`` takes their dense ``weight`` (or the compact one) and converts it, refusing -- with the
  entries named -- a weight that is non-zero outside its skeletal mask, or a mask of another skeleton.

Optimiser state follows the parameter, so an Adam state saved by the patched script is compact (resume it with
the patch). Only their ``--skeleton --conv3fast`` traits (the released model's) are patched; other traits are
refused at construction. Their ``out / out.std`` activation demodulation is the same statistic computed as
modi's generator does (``std_entities_frames``); their lazy intervals are untouched.
"""
from __future__ import annotations

import contextlib
import types
from typing import Any, Iterator

import torch
import torch.nn.functional as F

from modi.interop.modi_released import MaskViolation, check_masks
from modi.models.modi.fastpaths import std_entities_frames
from modi_ext.fir import blur_time as fir_blur_time
from modi_ext.skeletal import ops
from modi_ext.skeletal.reference import from_dense, to_dense
from modi_ext.csr import csr_from_lists

SUPPORTED_TRAITS = ("SkeletonAwareFastConvTraits",)


def _check_traits(st: Any, where: str) -> None:
    name = type(st).__name__
    if name not in SUPPORTED_TRAITS:
        raise ValueError(f"modi_dropin: {where} uses {name}; only the released --skeleton --conv3fast traits "
                         f"({', '.join(SUPPORTED_TRAITS)}) are patched")


def _pattern(mask: torch.Tensor) -> torch.Tensor:
    """(E_out, E_in) entity pairs a dense ``(C0, C1, E_out, E_in, U)`` mask connects for every channel and tap."""
    return (mask != 0).all(0).all(0).all(-1)


def _rows(pattern: torch.Tensor) -> list[list[int]]:
    return [torch.nonzero(pattern[j]).flatten().tolist() for j in range(pattern.shape[0])]


class _Compact:
    """Mixin: the dense-masked <-> compact conversion shared by both patched classes.

    ``_to_ext(t)`` / ``_from_ext(t)`` map their dense weight layout to the ``(C0, C1, E_out, E_in, U)`` layout
    ``modi_ext.skeletal.reference.to_dense`` uses for the op (a leading 1 for modulated weights; C0/C1 swapped for the
    upsampler, whose op weight is the adjoint downsampler's)."""

    _dense_shape: torch.Size

    def _compact_init(self, where: str) -> None:
        w, mask, scale = self.weight.detach(), self.mask.detach(), self.scale.detach()
        self._where = where
        self._dense_shape = w.shape
        dense_mask = self._to_ext(mask)
        self._check_entries(w, mask, f"{where} weight")
        topo = csr_from_lists(_rows(_pattern(dense_mask)), n_in=dense_mask.shape[3], name=f"{where} mask")
        self.register_buffer("pair_index", topo.index, persistent=False)
        self.register_buffer("pair_offsets", topo.offsets, persistent=False)
        self.n_in_entities = int(dense_mask.shape[3])
        # their equalised-lr factor (per output entity) at each stored entry, applied at run time as theirs is
        factor = self._to_ext(scale.expand_as(mask)).contiguous()
        self.register_buffer("pair_scale", from_dense(factor, topo.index, topo.offsets), persistent=False)
        self.weight = torch.nn.Parameter(from_dense(self._to_ext(w * mask), topo.index, topo.offsets))
        self._register_state_dict_hook(_dense_weight_hook)

    def _check_entries(self, w: torch.Tensor, mask: torch.Tensor, where: str) -> None:
        """Refuse weights the compact form cannot hold, naming the entries (the importer's check, on this layer;
        indices are in their ``(Cout, Cin, E_out, E_in, U)`` order)."""
        five = (lambda t: t[0]) if w.dim() == 6 else (lambda t: t)
        try:
            check_masks({"layer.mask": five(mask), "layer.weight": five(w)}, "")
        except MaskViolation as exc:
            raise MaskViolation(str(exc).replace(".layer.weight", where)) from None

    def compact_effective(self) -> torch.Tensor:
        return self.weight * self.pair_scale

    def dense_weight(self) -> torch.Tensor:
        """Their dense masked ``weight`` (zeros off the mask) for the compact one."""
        d = to_dense(self.weight.detach(), self.pair_index, self.pair_offsets, self.n_in_entities)
        return self._from_ext(d).reshape(self._dense_shape).contiguous()

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                              error_msgs):
        key, mkey = prefix + "weight", prefix + "mask"
        w = state_dict.get(key)
        if w is not None and tuple(w.shape) == tuple(self._dense_shape):
            mask = state_dict.get(mkey, self.mask).to(w.dtype)
            where = f"{prefix}weight" if prefix else f"{self._where} weight"
            if not torch.equal(_pattern(self._to_ext(mask)), _pattern(self._to_ext(self.mask.detach()))):
                raise MaskViolation(f"{where}: its mask connects other entity pairs than this model's skeleton "
                                    "(a checkpoint of another skeleton or pooling)")
            self._check_entries(w, mask, where)
            state_dict = {**state_dict, key: from_dense(self._to_ext(w * mask).to(self.weight.dtype),
                                                        self.pair_index, self.pair_offsets)}
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                                      error_msgs)


def _dense_weight_hook(module: Any, state_dict: dict, prefix: str, local_metadata: Any) -> None:
    state_dict[prefix + "weight"] = module.dense_weight()


def _classes(gan: types.ModuleType) -> tuple[type, type, type]:
    """Subclasses of their ``ModulatedConv``, ``EqualConv`` and ``Blur`` (built per loaded copy of their
    ``models.gan``)."""
    cached = getattr(gan, "_modi_dropin_classes", None)
    if cached is not None:
        return cached

    class DropInModulatedConv(_Compact, gan.ModulatedConv):
        """Their ModulatedConv with its convolution on ``modi_ext.skeletal.ops`` (keep-dims, upsampling, 1x1)."""

        def __init__(self, *a: Any, **k: Any) -> None:
            super().__init__(*a, **k)
            _check_traits(self.skeleton_traits, "ModulatedConv")
            if self.demod_obj not in ("data", None):
                raise ValueError(f"modi_dropin: demodulation {self.demod_obj!r} is not patched")
            self._compact_init("ModulatedConv" + (" (upsample)" if self.upsample else ""))

        def _to_ext(self, t: torch.Tensor) -> torch.Tensor:
            t = t[0] if t.dim() == 6 else t
            return t.transpose(0, 1) if self.upsample else t

        def _from_ext(self, t: torch.Tensor) -> torch.Tensor:
            return (t.transpose(0, 1) if self.upsample else t).unsqueeze(0)

        def forward(self, input: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
            s = self.modulation(style)
            w = self.compact_effective()
            if self.upsample:  # their transposed conv + blur frames are ours shifted by one input frame
                out = ops.skeletal_up(F.pad(input, (1, 0)).contiguous(), w, None, self.pair_index, self.pair_offsets,
                                      self.n_in_entities, style=s)[..., 2:]
            else:
                out = ops.skeletal_conv(input.contiguous(), w, None, self.pair_index, self.pair_offsets, style=s)
            if self.demod_obj == "data":  # their out / out.std((2, 3), keepdim=True), as modi's generator computes it
                out = out / std_entities_frames(out)
            return out

    class DropInEqualConv(_Compact, gan.EqualConv):
        """Their EqualConv (after their Blur, where they have one) on ``modi_ext.skeletal.ops``: in place or
        stride 2."""

        def __init__(self, *a: Any, **k: Any) -> None:
            super().__init__(*a, **k)
            _check_traits(self.skeleton_traits, "EqualConv")
            self.down = self.stride not in (1, (1, 1))
            self.kernel_size = int(self.weight.shape[-1])
            self._compact_init("EqualConv" + (" (downsample)" if self.down else ""))

        def _to_ext(self, t: torch.Tensor) -> torch.Tensor:
            return t

        def _from_ext(self, t: torch.Tensor) -> torch.Tensor:
            return t

        def forward(self, input: torch.Tensor) -> torch.Tensor:
            w = self.compact_effective()
            if not self.down:
                return ops.skeletal_conv(input.contiguous(), w, self.bias, self.pair_index, self.pair_offsets)
            # theirs: coarse frame t reads their (blurred) frames 2t+u, t < n; ours reads 2t+u-U//2: pad, crop
            u, t_in = self.kernel_size, input.shape[-1]
            half = u // 2
            crop = (half + 1) // 2
            left = 2 * crop - half
            n = (t_in - u) // 2 + 1
            right = max(0, 2 * (n + crop) - t_in - left)
            out = ops.skeletal_down(F.pad(input, (left, right)).contiguous(), w, self.bias, self.pair_index,
                                    self.pair_offsets)
            return out[..., crop:crop + n]

    class DropInBlur(gan.Blur):
        """Their ``Blur`` (the [1,3,3,1]/8 anti-alias filter before every stride-2 discriminator conv) as modi's own
        discriminator computes it: ``modi_ext.fir.blur_time``, a sum of shifted frames.

        On the CPU theirs is ``upfirdn2d_native``: a one-channel ``conv2d`` over a batch of every (sample, channel)
        row, which oneDNN runs slowly, the backward most (a third of a drop-in iteration in ``torch.profiler``:
        ``convolution_backward`` 26%, ``mkldnn_convolution`` 6%). Same filter on the frame axis, same padding: the
        outputs differ by float rounding."""

        def __init__(self, kernel: Any, pad: Any, upsample_factor: int = 1, skeleton_traits: Any = None) -> None:
            super().__init__(kernel, pad, upsample_factor=upsample_factor, skeleton_traits=skeleton_traits)
            _check_traits(skeleton_traits, "Blur")
            k = self.kernel
            # fir_blur_time pads 1 frame before and 2 after: theirs (pad0 >= 1, pad1 <= 2) is that after pad0 - 1
            # more zeros before, cropped to their length.  Any other blur (their ModulatedConv builds an upsampling
            # one that the drop-in's forward never calls) runs as theirs.
            self.as_modi = (k.shape == (1, 4) and bool(torch.allclose(k, k.new_tensor([[1.0, 3.0, 3.0, 1.0]]) / 8))
                            and len(self.pad) == 4 and not any(self.pad[2:]) and self.pad[0] >= 1
                            and self.pad[1] <= 2)

        def forward(self, input: torch.Tensor) -> torch.Tensor:
            if not self.as_modi:
                return super().forward(input)
            pad0, pad1 = self.pad[0], self.pad[1]
            n = input.shape[-1] + pad0 + pad1 - 3
            return fir_blur_time(F.pad(input, (pad0 - 1, 0)))[..., :n]

    gan._modi_dropin_classes = (DropInModulatedConv, DropInEqualConv, DropInBlur)
    return gan._modi_dropin_classes


@contextlib.contextmanager
def dropin(peer: types.SimpleNamespace, blur: bool = True) -> Iterator[tuple[type, ...]]:
    """While the block runs, models built from their ``models.gan`` (their ``Generator``, ``Discriminator``, their
    ``train.main``) use the ``modi_ext`` layers, and (``blur``) modi's blur before the stride-2 convs. ``peer``:
    what ``released_modi.peer_runtime()`` yields."""
    gan = peer.gan
    mod_cls, eq_cls, blur_cls = _classes(gan)
    old = gan.ModulatedConv, gan.EqualConv, gan.Blur
    gan.ModulatedConv, gan.EqualConv = mod_cls, eq_cls
    if blur:
        gan.Blur = blur_cls
    try:
        yield (mod_cls, eq_cls, blur_cls) if blur else (mod_cls, eq_cls)
    finally:
        gan.ModulatedConv, gan.EqualConv, gan.Blur = old


__all__ = ["dropin", "MaskViolation", "SUPPORTED_TRAITS"]
