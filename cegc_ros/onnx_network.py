"""The engine's network under ONNX Runtime: the same weights, the same outputs, less time.

Torch stays the reference implementation and the training path. For inference on a CPU, the
candidate path of the network (:meth:`CEGC.score_candidates` with ``engine.candidates: both``)
is exported once to ONNX and run by ONNX Runtime, which fuses the attention and the linear
layers' epilogues that torch runs as separate kernels (docs/performance.md has the measured
gain and the command).

    export_onnx(model, checkpoint, out)  # python -m cegc_ros.tools.export_onnx CKPT [OUT]
    net = OnnxNetwork.for_checkpoint(checkpoint, cfg)   # None when no matching export exists
    net.score_candidates(...)            # the torch method's signature and outputs

The export sits beside its checkpoint (``cegc_views.pt`` -> ``cegc_views.onnx``) and records
the SHA-256 of the checkpoint it came from and the learned-candidate count it baked in; a file
whose record does not match is not used (the engine runs torch and says why in
``Registrar.runtime_note``). Shapes: the point count is a dynamic axis (any
``preprocess.num_points`` >= 64; the engine always feeds exactly that many), the number of extra
(FPFH) candidates too; ``learned_candidates`` is a constant of the graph.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .denormals import flush_denormals

RUNTIMES = ("auto", "torch", "onnxruntime")
#: ONNX opset of the export (TorchScript exporter; supported by ONNX Runtime >= 1.14).
OPSET = 17
#: Export sizes (the graph is traced at these; the point axes stay dynamic).
EXPORT_POINTS = 256
_INPUTS = ("src", "tgt", "src_normals", "tgt_normals", "src_desc", "tgt_desc", "extra")
OUTPUTS = ("src_overlap_logits", "tgt_overlap_logits", "candidates", "scores", "similarity")


class OnnxExportError(RuntimeError):
    """The network could not be exported (no ``onnx`` package, an unsupported operator)."""


def sha256_of(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def onnx_path_for(checkpoint: str | Path) -> Path:
    """Where the export of ``checkpoint`` lives: beside it, with the suffix ``.onnx``."""
    return Path(checkpoint).with_suffix(".onnx")


def export_onnx(model: Any, checkpoint: str | Path, out: str | Path | None = None,
                learned_candidates: int = 3) -> Path:
    """Export the candidate path of ``model`` (the CEGC loaded from ``checkpoint``, on the CPU;
    ``learned_candidates`` baked in) to ``out`` (default :func:`onnx_path_for`), recording the
    checkpoint's SHA-256. Needs the ``onnx`` package (export time only)."""
    import torch
    try:
        import onnx
    except ModuleNotFoundError as err:
        raise OnnxExportError("exporting needs the onnx package (pip install onnx)") from err
    out = Path(out) if out is not None else onnx_path_for(checkpoint)

    class CandidatePath(torch.nn.Module):
        """score_candidates with the learned-candidate count fixed, for the exporter."""

        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(self, src, tgt, sn, tn, sd, td, extra):  # noqa: ANN001, ANN202
            o = self.model.score_candidates(src, tgt, sn, tn, sd, td, k_learned=learned_candidates,
                                            extra=extra, stack=False)   # any two point counts
            return o.src_overlap_logits, o.tgt_overlap_logits, o.candidates, o.scores, o.similarity
    wrapper = CandidatePath().eval()
    g = torch.Generator().manual_seed(0)
    n = EXPORT_POINTS

    def cloud() -> list[torch.Tensor]:
        pts = torch.rand(1, n, 3, generator=g) - 0.5
        normals = torch.nn.functional.normalize(torch.randn(1, n, 3, generator=g), dim=-1)
        desc = torch.rand(1, n, model.cfg.desc_dim, generator=g)
        return [pts, normals, desc]
    (s, sn, sd), (t, tn, td) = cloud(), cloud()
    extra = torch.randint(0, n, (1, n, 2), generator=g)
    dynamic = {"src": {1: "n"}, "src_normals": {1: "n"}, "src_desc": {1: "n"}, "extra": {1: "n", 2: "ke"},
               "tgt": {1: "m"}, "tgt_normals": {1: "m"}, "tgt_desc": {1: "m"},
               "candidates": {1: "n", 2: "k"}, "scores": {1: "n", 2: "k"},
               "src_overlap_logits": {1: "n"}, "tgt_overlap_logits": {1: "m"},
               "similarity": {1: "n", 2: "m"}}
    tmp = out.with_suffix(".onnx.tmp")
    try:
        with torch.inference_mode(False), torch.no_grad():
            torch.onnx.export(wrapper, (s, t, sn, tn, sd, td, extra), str(tmp), opset_version=OPSET,
                              dynamo=False, input_names=list(_INPUTS), output_names=list(OUTPUTS),
                              dynamic_axes=dynamic)
        proto = onnx.load(str(tmp))
        for key, value in {"cegc_checkpoint_sha256": sha256_of(checkpoint),
                           "cegc_learned_candidates": str(learned_candidates),
                           "cegc_torch": torch.__version__}.items():
            entry = proto.metadata_props.add()
            entry.key, entry.value = key, value
        onnx.save(proto, str(tmp))
        tmp.replace(out)
    except Exception as err:
        tmp.unlink(missing_ok=True)
        if isinstance(err, OnnxExportError):
            raise
        raise OnnxExportError(f"ONNX export of {checkpoint} failed: {type(err).__name__}: {err}"
                              .splitlines()[0]) from err
    return out


def feeds_of(src: Any, tgt: Any, src_normals: Any, tgt_normals: Any, src_desc: Any, tgt_desc: Any,
             extra: Any) -> dict[str, np.ndarray]:
    """score_candidates' tensors (CPU, (1, N, .)) -> the export's inputs by name (numpy,
    contiguous; ``extra`` int64)."""
    feeds = {name: np.ascontiguousarray(t.detach().cpu().numpy()) for name, t in
             zip(_INPUTS, (src, tgt, src_normals, tgt_normals, src_desc, tgt_desc, extra))}
    feeds["extra"] = feeds["extra"].astype(np.int64, copy=False)
    return feeds


@dataclass
class OnnxCandidates:
    """What :meth:`OnnxNetwork.score_candidates` returns: the fields of ``CandidateOutput`` that
    the engine reads, as torch tensors (zero-copy views of ONNX Runtime's arrays)."""

    src_overlap_logits: Any   # (1, N)
    tgt_overlap_logits: Any   # (1, M)
    candidates: Any           # (1, N, k) int64
    scores: Any               # (1, N, k)
    similarity: Any           # (1, N, M) cosines of the attention features (HOCE's M_S)


def session_options(threads: int = 0) -> Any:
    """The engine's ONNX Runtime session options: ``threads`` intra-op threads (0: one per
    physical core), one inter-op thread, no spinning under OMP_WAIT_POLICY=PASSIVE, subnormals
    flushed in the pool."""
    import onnxruntime as ort
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = int(threads)
    opts.inter_op_num_threads = 1
    # Pool threads that spin between kernels cost a busy robot's CPU as OpenMP's do: they
    # sleep when the process runs with OMP_WAIT_POLICY=PASSIVE (the engine's default).
    if os.environ.get("OMP_WAIT_POLICY", "").upper() == "PASSIVE":
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    # Subnormals flushed in the pool threads (cegc_ros/denormals.py).
    opts.add_session_config_entry("session.set_denormal_as_zero", "1")
    return opts


def open_session(path: str | Path, opts: Any) -> Any:
    """An ONNX Runtime CPU session; creating one with ``set_denormal_as_zero`` also flushes the
    creating thread, which is given its own state back."""
    import onnxruntime as ort
    with flush_denormals(on=False):
        return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


class OnnxNetwork:
    """An ONNX Runtime session over the export of one checkpoint; ``cfg`` is the network's
    ModelConfig (the engine reads its feature settings)."""

    def __init__(self, path: str | Path, cfg: Any, threads: int = 0) -> None:
        self.session = open_session(path, session_options(threads))
        meta = self.session.get_modelmeta().custom_metadata_map
        self.path = Path(path)
        self.cfg = cfg
        self.checkpoint_sha256 = meta.get("cegc_checkpoint_sha256", "")
        self.learned_candidates = int(meta.get("cegc_learned_candidates", "0"))

    @classmethod
    def for_checkpoint(cls, checkpoint: str | Path, cfg: Any, threads: int = 0
                       ) -> tuple[OnnxNetwork | None, str]:
        """The export beside ``checkpoint`` when it is there, loads and was made from this very
        file; else (None, why not)."""
        path = onnx_path_for(checkpoint)
        if not path.is_file():
            return None, f"no ONNX export beside the checkpoint ({path.name}; python -m cegc_ros.tools.export_onnx)"
        try:
            import onnxruntime  # noqa: F401
        except ModuleNotFoundError:
            return None, "onnxruntime is not installed"
        try:
            net = cls(path, cfg, threads)
        except Exception as err:   # a corrupt file: onnxruntime raises its own exception types
            return None, f"{path.name} does not load: {type(err).__name__}: {err}".splitlines()[0]
        if net.checkpoint_sha256 != sha256_of(checkpoint):
            return None, f"{path.name} was exported from another checkpoint (re-export it)"
        have = {x.name for x in net.session.get_outputs()}
        missing = [o for o in OUTPUTS if o not in have]
        if missing:
            return None, f"{path.name} lacks the output {missing[0]} of this version (re-export it)"
        return net, ""

    def score_candidates(self, src: Any, tgt: Any, src_normals: Any, tgt_normals: Any, src_desc: Any,
                         tgt_desc: Any, k_learned: int, extra: Any) -> OnnxCandidates:
        """The torch method's arguments (CPU tensors (1, N, .)); ``k_learned`` must be the
        export's and ``extra`` (1, N, ke) given (``engine.candidates: both``)."""
        import torch
        if k_learned != self.learned_candidates or extra is None:
            raise ValueError(f"the ONNX export scores {self.learned_candidates} learned + extra "
                             f"candidates, asked for {k_learned} learned and "
                             f"{'no' if extra is None else 'some'} extra")
        feeds = feeds_of(src, tgt, src_normals, tgt_normals, src_desc, tgt_desc, extra=extra)
        outs = self.session.run(list(OUTPUTS), feeds)   # the caller flushes (matching.match)
        return OnnxCandidates(*(torch.from_numpy(o) for o in outs))
