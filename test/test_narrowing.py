"""model/narrowing.py: a narrower CEGC's tensors cut from a wider one's, channel for channel."""

from __future__ import annotations

import pytest
import torch

from cegc_ros.model import CEGC, ModelConfig
from cegc_ros.model.narrowing import NarrowingError, narrowed_state

TEACHER = dict(agnn_dims=(16, 16, 32), feat_dim=64, attn_layers=2, attn_heads=4, cams_dim=16, hoce_topk=4)
STUDENT = dict(agnn_dims=(8, 12, 16), feat_dim=48, attn_layers=1, attn_heads=4, cams_dim=8, hoce_topk=4)


def models(**student: object) -> tuple[CEGC, CEGC]:
    torch.manual_seed(0)
    teacher = CEGC(ModelConfig(**TEACHER))
    return teacher, CEGC(ModelConfig(**{**STUDENT, **student}))


def test_each_part_of_a_concatenation_and_each_head_keeps_its_first_channels():
    teacher, student = models()
    t = teacher.state_dict()
    cut = narrowed_state(t, teacher.cfg, student.state_dict(), student.cfg)
    student.load_state_dict(cut, strict=True)             # every student tensor comes from the teacher
    assert not any(k.startswith("context.self_blocks.1.") for k in cut)   # the block it lacks
    r = lambda a, b: list(range(a, b))                    # noqa: E731
    # AGNN layer 3's edges [f_i, f_j - f_i] of layer 2's 16 (teacher) / 12 (student) channels
    assert torch.equal(cut["agnn.layers.2.embed.0.weight"],
                       t["agnn.layers.2.embed.0.weight"][:16][:, r(0, 12) + r(16, 28)])
    # layer 1's edges [ppf, fpfh]: its inputs are the teacher's, its outputs the first 8
    assert torch.equal(cut["agnn.layers.0.embed.0.weight"], t["agnn.layers.0.embed.0.weight"][:8])
    # the head on the three layers' outputs 16 + 16 + 32 -> 8 + 12 + 16
    assert torch.equal(cut["agnn.head.0.weight"], t["agnn.head.0.weight"][:48][:, r(0, 8) + r(16, 28) + r(32, 48)])
    # four heads of 16 -> four heads of 12: the first 12 of each head
    heads = r(0, 12) + r(16, 28) + r(32, 44) + r(48, 60)
    for name in ("qkv_q", "qkv_k", "qkv_v"):
        w = f"context.cross_blocks.0.{name}.weight"
        assert torch.equal(cut[w], t[w][heads][:, :48])
        assert torch.equal(cut[f"context.cross_blocks.0.{name}.bias"], t[f"context.cross_blocks.0.{name}.bias"][heads])
    assert torch.equal(cut["context.self_blocks.0.merge.weight"],
                       t["context.self_blocks.0.merge.weight"][:48][:, heads])
    # an attention block's update on [x, message]
    assert torch.equal(cut["context.self_blocks.0.update.0.weight"],
                       t["context.self_blocks.0.update.0.weight"][:48][:, r(0, 48) + r(64, 112)])
    # plain widths: HOCE on 48 -> 24 -> 12 channels, CAMS at 8, LayerNorms
    assert torch.equal(cut["hoce.semantic.0.0.weight"], t["hoce.semantic.0.0.weight"][:24, :48])
    assert torch.equal(cut["cams.ft1.a.weight"], t["cams.ft1.a.weight"][:8, :48])
    assert torch.equal(cut["agnn.head.1.weight"], t["agnn.head.1.weight"][:48])


def test_the_teachers_own_shape_is_copied_whole_and_a_wider_or_other_student_is_refused():
    teacher, _ = models()
    same = CEGC(ModelConfig(**{**TEACHER, "k": 8}))       # k changes no tensor
    cut = narrowed_state(teacher.state_dict(), teacher.cfg, same.state_dict(), same.cfg)
    assert cut.keys() == same.state_dict().keys()
    assert all(torch.equal(v, teacher.state_dict()[k]) for k, v in cut.items())
    for other, match in ((dict(feat_dim=80), "wider than the teacher: feat_dim 80 > 64"),
                         (dict(agnn_dims=(8, 24, 16)), r"agnn_dims\[1\] 24 > 16"),
                         (dict(attn_heads=2), "attn_heads differs"),
                         (dict(feat_dim=50), "not a multiple of attn_heads")):
        with pytest.raises(NarrowingError, match=match):     # the designs are compared first
            narrowed_state(teacher.state_dict(), teacher.cfg, {}, ModelConfig(**{**STUDENT, **other}))
