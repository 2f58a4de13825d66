"""A narrower CEGC cut from a wider one: the starting point of a distilled student.

A student of the same design with fewer channels (``feat_dim``, ``agnn_dims``, ``cams_dim``, the
attention's head width, fewer attention blocks) starts from its teacher's tensors instead of
random ones: each student tensor is the teacher's tensor of the same name restricted to the
channels the student keeps. The kept channels are the first ones of each width, taken
consistently along the network, so a kept channel reads what it read in the teacher:

- a plain width (a linear map's outputs, the residual stream, a LayerNorm): its first channels;
- a concatenation (the AGNN layers' ``[f_i, f_j - f_i]`` edges, the AGNN head's three layer
  outputs, an attention block's ``[x, message]``): the first channels of each part;
- the attention's heads (``qkv_*`` outputs, ``merge`` inputs): the first channels of each head,
  so that every head keeps its own (the student has as many heads as the teacher).

What the cut drops (the dropped channels' share of each sum, LayerNorm statistics over fewer
channels) distillation then learns back (cegc_ros/training.py, ``distill.init_from_teacher``).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from .config import ModelConfig


class NarrowingError(ValueError):
    """The student is not a narrowing of the teacher (another design, a wider width)."""


def _check(teacher: ModelConfig, student: ModelConfig) -> None:
    same = ("variant", "attn_heads", "desc_dim", "hoce_topk")
    for name in same:
        if getattr(teacher, name) != getattr(student, name):
            raise NarrowingError(f"model.{name} differs from the teacher's ({getattr(student, name)!r} "
                                 f"against {getattr(teacher, name)!r})")
    wider = [f"{n} {getattr(student, n)} > {getattr(teacher, n)}" for n in ("feat_dim", "cams_dim", "attn_layers")
             if getattr(student, n) > getattr(teacher, n)]
    wider += [f"agnn_dims[{i}] {s} > {t}" for i, (s, t) in enumerate(zip(student.agnn_dims, teacher.agnn_dims))
              if s > t]
    if wider:
        raise NarrowingError(f"the student is wider than the teacher: {', '.join(wider)}")
    if student.feat_dim % student.attn_heads:
        raise NarrowingError(f"model.feat_dim {student.feat_dim} is not a multiple of attn_heads {student.attn_heads}")


def _parts(widths_t: list[int], widths_s: list[int]) -> np.ndarray:
    """The kept indices of a concatenation of parts of widths_t, keeping widths_s of each."""
    starts = np.cumsum([0] + list(widths_t[:-1]))
    return np.concatenate([start + np.arange(s) for start, s in zip(starts, widths_s)])


def _axis_maps(name: str, teacher: ModelConfig, student: ModelConfig) -> dict[int, np.ndarray]:
    """The kept teacher indices along the axes of tensor ``name`` that are not a plain prefix
    (a concatenation or heads); the other axes keep their first channels."""
    maps: dict[int, np.ndarray] = {}
    ta, sa = teacher.agnn_dims, student.agnn_dims
    if name.startswith("agnn.layers.") and name.endswith("embed.0.weight"):
        i = int(name.split(".")[2])
        if i > 0:                                                     # [f_i, f_j - f_i]
            maps[1] = _parts([ta[i - 1]] * 2, [sa[i - 1]] * 2)
    elif name == "agnn.head.0.weight":                                # the three layers' outputs
        maps[1] = _parts(list(ta), list(sa))
    elif name.startswith("context."):
        h, dt, ds = teacher.attn_heads, teacher.feat_dim // teacher.attn_heads, student.feat_dim // student.attn_heads
        heads = _parts([dt] * h, [ds] * h)
        leaf = name.split(".", 3)[3]                                  # e.g. "qkv_q.weight"
        if leaf.startswith("qkv_"):
            maps[0] = heads
        elif leaf == "merge.weight":
            maps[1] = heads
        elif leaf == "update.0.weight":                               # [x, message]
            maps[1] = _parts([teacher.feat_dim] * 2, [student.feat_dim] * 2)
    return maps


def narrowed_state(teacher_state: dict[str, Tensor], teacher: ModelConfig,
                   student_state: dict[str, Tensor], student: ModelConfig) -> dict[str, Tensor]:
    """The student's state dict cut from the teacher's (see the module docstring): every
    student tensor whose name the teacher has (a block the student lacks is left out; a tensor
    only the student has is not returned). NarrowingError when ``student`` is not a narrowing of
    ``teacher`` or a tensor does not fit."""
    _check(teacher, student)
    out: dict[str, Tensor] = {}
    for name, own in student_state.items():
        if name not in teacher_state:
            continue
        src = teacher_state[name]
        if src.dim() != own.dim():
            raise NarrowingError(f"{name}: {src.dim()} axes in the teacher, {own.dim()} in the student")
        maps = _axis_maps(name, teacher, student)
        cut = src
        for axis, size in enumerate(own.shape):
            keep = maps.get(axis)
            if keep is None:
                if size > src.shape[axis]:
                    raise NarrowingError(f"{name}: axis {axis} has {size} channels, the teacher's {src.shape[axis]}")
                cut = cut.narrow(axis, 0, size)
            else:
                if len(keep) != size or keep.max() >= src.shape[axis]:
                    raise NarrowingError(f"{name}: axis {axis} does not cut to {size} channels")
                cut = cut.index_select(axis, torch.as_tensor(keep, dtype=torch.long, device=src.device))
        out[name] = cut.detach().clone().to(own.dtype)
    return out
