"""The ROS-free registration engine: numpy clouds in metres in, a RegistrationResult out.

    registrar = Registrar.from_checkpoint()            # the weights shipped in the package
    result = registrar.register(source_xyz, target_xyz)
    result.T_target_source                              # (4, 4): p_target = T @ [p_source; 1]

One pass through six stages, each a module of its own, each with bounded work:

    bound     cegc_ros/bounding.py   finite filter, adaptive voxel grid, cap (one linear pass)
    features  cegc_ros/geometry.py   normalise, normals + FPFH on a support subsample, network points
    match     cegc_ros/matching.py   CEGC: HOCE overlap, candidates, CAMS/CFM pair confidence
    estimate  cegc_ros/estimator.py  confidence-seeded spatial compatibility (or the paper's SVD)
    refine    cegc_ros/refine.py     point-to-plane ICP on capped clouds
    verify    cegc_ros/refine.py     fitness and covariance

A pair the estimate stage leaves in doubt is drawn a second time from the bounded clouds
(features onwards, cegc_ros/second_draw.py, ``engine.redraw_ambiguity``); the stage ``redraw``
times it.

Variants (ablations) are settings, not code paths: ``engine.candidates``, ``engine.confidence``,
``engine.estimator``, ``engine.refine`` (cegc_ros/config.py). Nothing here runs a second
network (the second draw runs the same one again) or races a classical method: the classical
peers live in cegc_ros/baselines.py, which reuses these stages; the engine never imports it.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import pickle
import threading
import time
import warnings
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .allocator import apply_thread_environment

# Before torch or Open3D load OpenMP: threads that sleep instead of spinning, as every console
# script has them (cegc_ros/allocator.py; a user's own OMP_* settings win). Beside two busy
# processes this is the difference between 3.4 and 2.0 s a pair (shared/notes/CPU_FACTS.md).
_THREAD_ENV_TOO_LATE = apply_thread_environment()

from . import bounding, estimator, matching, refine, second_draw  # noqa: E402
from .matching import NetworkOutputError  # noqa: E402,F401  (re-exported: the engine's error)
from .config import EngineConfig, PreprocessConfig  # noqa: E402
from .geometry import LEGACY_FEATURES, box_corner, frame_viewpoints, point_budget, prepare_pair  # noqa: E402
from .onnx_network import RUNTIMES, OnnxNetwork  # noqa: E402
from .verification import VerificationModel, VerificationModelError  # noqa: E402
from .visibility import FreeSpace  # noqa: E402

CHECKPOINT_FORMAT = 1


def default_weights() -> Path:
    """The weights shipped with the package (one copy: share/cegc_ros/weights when installed,
    cegc_ros/weights in a checkout; cegc_ros.paths); ShippedFileError when absent."""
    from .paths import ENGINE_WEIGHTS, shipped_weights
    return shipped_weights(ENGINE_WEIGHTS)


class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable or does not match this code."""


@dataclass
class RegistrationResult:
    """Result of one registration. Points are in metres, each in its own frame."""

    T_target_source: np.ndarray          # (4, 4) float64, maps source points into the target frame
    source_points: np.ndarray            # (Ns, 3) float32, the network's source points
    target_points: np.ndarray            # (Nt, 3) float32
    source_overlap: np.ndarray           # (Ns,) float32 in [0, 1] (HOCE)
    target_overlap: np.ndarray           # (Nt,) float32 in [0, 1]
    correspondences: np.ndarray          # (K, 2) int64: (index into source_points, into target_points)
    weights: np.ndarray                  # (K,) float32 in [0, 1], the confidences the estimator used
    inliers: np.ndarray                  # (K,) bool: correspondences the estimated pose explains
    covariance: np.ndarray               # (6, 6) float64, ROS order x y z roll pitch yaw, from the inliers
    fitness: float                       # fraction of source points within inlier_distance after alignment
    inlier_distance: float               # metres
    valid: bool
    reason: str = ""                     # why not valid; "" when valid
    refined: str = "none"                # "none" | "icp"
    runtime: str = "torch"               # what ran the network: "torch" | "onnxruntime" | "torch.compile"
    voxel_size: float = 0.0              # metres of the grid that bounded the input (0: none)
    dropped: tuple[Any, Any] = ()        # bounding.Dropped of source and target: input hygiene
    timings: dict[str, float] = field(default_factory=dict)   # seconds per stage, and "total"
    #: (H, 4, 4) the poses the estimator's verification ranked (estimator.Estimate.hypotheses)
    hypotheses: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    #: in [0, 1]: how close the best distinct alignment came to the answer in the estimator's
    #: verification (estimator.ambiguity; 0: no rival, 1: a tie). High values flag answers the
    #: geometry does not settle: most wrong low-overlap answers (docs/pipeline.md).
    ambiguity: float = 0.0
    #: the estimator needed more than its first seeds (estimator.Estimate.explored)
    explored: bool = False
    #: draws of the network points the pair took (2: engine.redraw_ambiguity) and the sampling
    #: seed of the one whose answer this is
    draws: int = 1
    seed: int = 0


@dataclass
class Matched:
    """The bound, features and match stages' output (:meth:`Registrar.match_pair`): what the
    estimate stage starts from. Metres, float64."""

    bounded: bounding.BoundedPair        # the bounded clouds, each in its own frame
    source_points: np.ndarray            # (Ns, 3) the network's source points
    target_points: np.ndarray            # (Nt, 3)
    matches: matching.Matches            # correspondences into them, with confidences
    spacing: float                       # metres: median spacing of the target points (x
                                         # engine.inlier_factor = the inlier distance)
    scale: float                         # metres per unit of the network's normalised frame
    runtime: str                         # what ran the network
    timings: dict[str, float]            # seconds of the bound, features and match stages
    seed: int                            # preprocess.seed it was sampled with (ICP's draw too)


def save_checkpoint(path: str | Path, model: Any, metadata: dict[str, Any] | None = None) -> None:
    """Write format version, model config, state dict and training metadata."""
    import torch
    payload = {
        "format": CHECKPOINT_FORMAT,
        "model_config": model.cfg.to_dict(),
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        # JSON round trip: only plain types, so that weights_only=True loading accepts it.
        "metadata": json.loads(json.dumps(dict(metadata or {}), default=str)),
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(payload, tmp)
    tmp.replace(path)


def load_checkpoint(path: str | Path, device: str = "cpu") -> tuple[Any, dict[str, Any]]:
    """Build the model a checkpoint describes and load its weights; CheckpointError on any problem."""
    import torch

    from .model import CEGC, ModelConfig
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path}: file not found")
    try:
        payload = torch.load(path, map_location=device, weights_only=True)
    except (RuntimeError, EOFError, OSError, ValueError, zipfile.BadZipFile, AttributeError,
            pickle.UnpicklingError) as err:
        raise CheckpointError(f"checkpoint {path}: unreadable ({type(err).__name__}: {err})".splitlines()[0]) from err
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        got = payload.get("format") if isinstance(payload, dict) else type(payload).__name__
        raise CheckpointError(f"checkpoint {path}: format {got!r}, expected {CHECKPOINT_FORMAT}")
    try:
        raw = dict(payload["model_config"])
        for key, value in LEGACY_FEATURES.items():   # written before the radii were stored
            raw.setdefault(key, value)
        cfg = ModelConfig.from_dict(raw)
        model = CEGC(cfg)
        model.load_state_dict(payload["state_dict"])
    except (KeyError, TypeError, ValueError, RuntimeError) as err:
        raise CheckpointError(f"checkpoint {path}: does not match the CEGC model ({err})".splitlines()[0]) from err
    model.to(device).eval()
    return model, dict(payload.get("metadata", {}))


def resolve_device(device: str) -> str:
    """'auto' -> 'cuda' when available else 'cpu'; other values are checked."""
    import torch
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {device!r} requested but CUDA is not available")
    if device != "cpu" and not device.startswith("cuda"):
        raise ValueError(f"device must be 'auto', 'cpu' or 'cuda[:N]', got {device!r}")
    return device


class Registrar:
    """Registers two clouds with a CEGC checkpoint. Thread-safe: one registration at a time."""

    MIN_POINTS = 16

    def __init__(self, model: Any, device: str, checkpoint_path: str, metadata: dict[str, Any],
                 preprocess: PreprocessConfig | None = None, engine: EngineConfig | None = None) -> None:
        self.model = model
        self.device = device
        self.checkpoint_path = checkpoint_path
        self.metadata = metadata
        self.preprocess = copy.deepcopy(preprocess) if preprocess else PreprocessConfig()
        self.engine = copy.deepcopy(engine) if engine else EngineConfig()
        self.compat = estimator.CompatibilityConfig()
        self._lock = threading.Lock()
        # engine.compile: a compiled graph for clouds of the start-up num_points (a new size would
        # recompile for ~45 s in the middle of a stream, so other sizes run eagerly).
        self._compiled: Any = None
        self._compile_points = self.preprocess.num_points
        self._compile_key: tuple[int, str] = (0, "")
        self.compiled_runs = 0                # forward passes that used the compiled graph
        self._onnx: OnnxNetwork | None = None  # engine.runtime: the ONNX export, when it is used
        self.runtime_note = ""                # why ONNX Runtime is not used ("" when it is)
        #: engine.verify_score 'learned': the verification model (the shipped one, loaded on first use)
        self.verifier: VerificationModel | None = None

    @classmethod
    def from_checkpoint(cls, path: str | Path | None = None, device: str = "auto",
                        preprocess: PreprocessConfig | None = None,
                        engine: EngineConfig | None = None, warm: bool = True) -> Registrar:
        """Load a checkpoint (None or "" = the weights shipped in the package) onto a device.

        ``warm``: register one tiny synthetic pair before returning (:meth:`warm_start`), so
        that the first real pair does not pay for imports and first-touch set-up."""
        if _THREAD_ENV_TOO_LATE:
            warnings.warn(f"torch or open3d was imported before cegc_ros.engine, so "
                          f"{', '.join(_THREAD_ENV_TOO_LATE)} could not take effect: beside busy "
                          f"processes the engine runs slower; import cegc_ros.engine first or set "
                          f"OMP_WAIT_POLICY=PASSIVE in the environment", RuntimeWarning, stacklevel=2)
        import torch
        engine = copy.deepcopy(engine) if engine else EngineConfig()
        if path in (None, ""):
            path = engine.checkpoint or default_weights()
        dev = resolve_device(device if device != "auto" else engine.device)
        if engine.threads > 0:
            torch.set_num_threads(engine.threads)
        model, meta = load_checkpoint(path, dev)
        engine.checkpoint = str(path)
        engine.device = dev
        registrar = cls(model, dev, str(path), meta, preprocess, engine)
        if engine.runtime not in RUNTIMES:
            raise ValueError(f"engine.runtime must be one of {RUNTIMES}, got {engine.runtime!r}")
        if engine.runtime != "torch":
            if dev != "cpu":
                registrar.runtime_note = f"ONNX Runtime runs on the CPU only; {dev} runs torch"
            else:
                registrar._onnx, registrar.runtime_note = OnnxNetwork.for_checkpoint(
                    path, model.cfg, engine.threads)
            if engine.runtime == "onnxruntime" and registrar._onnx is None:
                raise CheckpointError(f"engine.runtime onnxruntime: {registrar.runtime_note}")
        if engine.verify_score == "learned":
            registrar._verification_model()      # a missing or bad file fails here, not mid-stream
        if warm:
            registrar.warm_start()
        return registrar

    def update(self, preprocess: PreprocessConfig | None = None, engine: EngineConfig | None = None) -> None:
        """Change settings; they apply from the next register() call."""
        with self._lock:
            if preprocess is not None:
                self.preprocess = copy.deepcopy(preprocess)
            if engine is not None:
                keep = (self.engine.checkpoint, self.engine.device, self.engine.compile, self.engine.runtime,
                        self.engine.verification)
                self.engine = copy.deepcopy(engine)
                (self.engine.checkpoint, self.engine.device, self.engine.compile,
                 self.engine.runtime, self.engine.verification) = keep

    def warm_start(self) -> float:
        """Register a tiny synthetic pair (two views of a box corner, 64 network points, eager):
        Open3D and SciPy get imported, the BLAS / OpenMP thread pools and torch's kernels start.
        A fresh Registrar's first real pair then costs about a warm one instead of ~3x
        (docs/performance.md). Returns the seconds spent."""
        t0 = time.perf_counter()
        corner = box_corner(400)
        pre = dataclasses.replace(self.preprocess, num_points=64, support_points=128, voxel_size=0.0)
        eng = dataclasses.replace(self.engine, compile=False)
        with self._lock:
            self._register(corner, corner[::-1] + 0.01, pre, eng)
        return time.perf_counter() - t0

    def warm_up(self) -> float:
        """With ``engine.compile``, compile the network now (seconds spent; 0 without it), so
        that the first real pair does not pay for it."""
        if not self.engine.compile:
            return 0.0
        t0 = time.perf_counter()
        rng = np.random.default_rng(0)
        n = self._compile_points
        with self._lock:
            # enough points that the voxel grid and the small-cloud budget leave n network points
            m = 2 * max(4, self.preprocess.points_per_network_point) * n
            clouds = [rng.uniform(-1, 1, (m, 3)) * [1.0, 1.0, 0.3] for _ in range(2)]
            try:
                self._register(clouds[0], clouds[1], self.preprocess, self.engine)
            except Exception as err:   # e.g. no C++ compiler for inductor: stay usable
                self.engine.compile = False
                self._compiled = None
                raise RuntimeError(f"engine.compile failed, the network runs eagerly: {err}") from err
        return time.perf_counter() - t0

    def _network(self, n_source: int, n_target: int, eng: EngineConfig) -> tuple[Any, str]:
        """(what runs the network, its name): under engine.compile a compiled graph for
        start-up-sized clouds; else the ONNX export where it serves these settings; else the
        torch model."""
        if not eng.compile or eng.candidates == "all" or not n_source == n_target == self._compile_points:
            onnx = self._onnx
            if (onnx is not None and eng.runtime != "torch" and eng.candidates == "both"
                    and eng.learned_candidates == onnx.learned_candidates):
                return onnx, "onnxruntime"
            return self.model, "torch"
        key = (eng.learned_candidates + eng.fpfh_candidates, eng.candidates)
        if self._compiled is None or key != self._compile_key:
            import torch
            self._compiled = _Compiled(self.model, torch.compile(self.model.score_candidates, dynamic=False))
            self._compile_key = key
        self.compiled_runs += 1
        return self._compiled, "torch.compile"

    def register(self, source_xyz: np.ndarray, target_xyz: np.ndarray) -> RegistrationResult:
        """Register source onto target (both (N, 3), metres). ValueError on unusable input;
        NetworkOutputError when the network returns non-finite values."""
        with self._lock:
            return self._register(source_xyz, target_xyz, self.preprocess, self.engine)

    def match_pair(self, source_xyz: np.ndarray, target_xyz: np.ndarray) -> Matched:
        """The first three stages of :meth:`register` (bound, features, match): what the
        estimate stage starts from. With :meth:`finish` it is :meth:`register`, split for
        studies of the later stages under other ``engine`` settings on the same correspondences
        (cegc_ros/tools/estimator_study.py). ValueError on unusable input."""
        with self._lock:
            return self._match(source_xyz, target_xyz, self.preprocess, self.engine)

    #: The ``engine`` settings :meth:`finish` reads (the estimate, refine and verify stages);
    #: the others act in :meth:`match_pair` or when the registrar is built.
    FINISH_SETTINGS = ("estimator", "inlier_factor", "verify_hypotheses", "verify_score", "explore_seeds",
                       "free_space", "sure_fitness", "sure_seeds", "sure_ambiguity", "redraw_ambiguity", "refine",
                       "icp_max_distance", "icp_max_iterations", "icp_points", "min_valid_fitness")

    def finish(self, matched: Matched) -> RegistrationResult:
        """The last three stages of :meth:`register` (estimate, refine, verify) on
        :meth:`match_pair`'s output, under this registrar's current ``engine`` settings (those of
        :data:`FINISH_SETTINGS` matter here) and the sampling seed it was matched with, with the
        second draw where it is wanted (from ``matched.bounded``, under the current
        ``preprocess`` settings); ``matched`` is not changed, so it can be finished again under
        other settings."""
        with self._lock:
            return self._finish(matched, self.engine, self.preprocess)

    def _register(self, source_xyz: np.ndarray, target_xyz: np.ndarray,
                  pre: PreprocessConfig, eng: EngineConfig) -> RegistrationResult:
        """bound -> features -> match -> estimate -> refine -> verify, one timer per stage."""
        return self._finish(self._match(source_xyz, target_xyz, pre, eng), eng, pre)

    def _match(self, source_xyz: np.ndarray, target_xyz: np.ndarray, pre: PreprocessConfig,
               eng: EngineConfig) -> Matched:
        timings: dict[str, float] = {}
        with _StageClock(timings)("bound"):
            bounded = bounding.bound_pair(source_xyz, target_xyz, pre, self.MIN_POINTS)
        return self._draw(bounded, pre, eng, timings)

    def _draw(self, bounded: bounding.BoundedPair, pre: PreprocessConfig, eng: EngineConfig,
              timings: dict[str, float]) -> Matched:
        """The features and match stages on bounded clouds, sampled with ``pre.seed``; their
        timers are added to ``timings``."""
        clock = _StageClock(timings)
        src, tgt = bounded.source, bounded.target
        with clock("features"):
            n_net, n_support = point_budget(min(len(src), len(tgt)), pre.num_points, pre.support_points,
                                            pre.points_per_network_point)
            ps, pt, norm = prepare_pair(src, tgt, n_net, n_support,
                                        np.random.default_rng(pre.seed), self.model.cfg.features(),
                                        pre.sampling, frame_viewpoints(pre.normals))
            src_m = ps.points.astype(np.float64) * norm.scale + norm.c_source      # network points, metres
            tgt_m = pt.points.astype(np.float64) * norm.scale + norm.c_target
            spacing = refine.median_spacing(tgt_m)
        with clock("match"):
            network, runtime = self._network(len(ps.points), len(pt.points), eng)
            try:
                m = matching.match(network, ps, pt, eng, self.device)
            except NetworkOutputError as err:
                raise NetworkOutputError(f"the network ({runtime}) {err}; the pair is not "
                                         f"registered (checkpoint {self.checkpoint_path})") from None
        return Matched(bounded, src_m, tgt_m, m, spacing, norm.scale, runtime, timings, pre.seed)

    def _verification_model(self) -> VerificationModel:
        """The learned verification's model: :attr:`verifier`, else the file of
        ``engine.verification`` or the shipped one (loaded once); CheckpointError when it cannot
        be read."""
        if self.verifier is None:
            from .paths import VERIFICATION_WEIGHTS, ShippedFileError, shipped_weights
            try:
                path = self.engine.verification or shipped_weights(VERIFICATION_WEIGHTS)
                self.verifier = VerificationModel.load(path)
            except (ShippedFileError, VerificationModelError) as err:
                raise CheckpointError(f"engine.verify_score learned: {err}".splitlines()[0]) from err
        return self.verifier

    def _finish(self, matched: Matched, eng: EngineConfig, pre: PreprocessConfig) -> RegistrationResult:
        """estimate -> refine -> verify on one draw; then, where the answer is in doubt, the
        second draw (cegc_ros/second_draw.py) and the better of the two answers."""
        first = self._finish_draw(matched, eng)
        if eng.verify_score != "learned" or not second_draw.wanted(first.explored, first.ambiguity,
                                                                   eng.redraw_ambiguity):
            return first
        start = time.perf_counter()
        again = self._draw(matched.bounded, dataclasses.replace(pre, seed=matched.seed + second_draw.SEED_OFFSET),
                           eng, {})
        second = self._finish_draw(again, eng)
        draws = [self.draw_evidence(m, r.inlier_distance) for m, r in ((matched, first), (again, second))]
        space = FreeSpace(matched.bounded.source, matched.bounded.target) if eng.free_space > 0 else None
        pick = second_draw.choose(self._verification_model(), np.stack([first.T_target_source,
                                                                        second.T_target_source]),
                                  np.array([first.valid, second.valid]), draws, space)
        timings = dict(first.timings)
        timings["redraw"] = time.perf_counter() - start
        timings["total"] = first.timings["total"] + timings["redraw"]
        return dataclasses.replace((first, second)[pick], timings=timings, draws=2)

    @staticmethod
    def draw_evidence(matched: Matched, inlier_distance: float) -> second_draw.Draw:
        """What the learned verification reads of one draw (:func:`second_draw.pose_features`),
        at the inlier distance its result was finished with."""
        m, c = matched.matches, matched.matches.correspondences
        return second_draw.Draw(matched.source_points, matched.target_points, matched.source_points[c[:, 0]],
                                matched.target_points[c[:, 1]], m.weights, m.similarity, m.source_overlap,
                                inlier_distance)

    def _finish_draw(self, matched: Matched, eng: EngineConfig) -> RegistrationResult:
        timings = dict(matched.timings)
        clock = _StageClock(timings)
        src, tgt = matched.bounded.source, matched.bounded.target
        src_m, tgt_m, m = matched.source_points, matched.target_points, matched.matches
        inlier = eng.inlier_factor * matched.spacing
        with clock("estimate"):
            c = m.correspondences
            compat = dataclasses.replace(self.compat, verify=eng.verify_hypotheses,
                                         explore_seeds=eng.explore_seeds, free_space=eng.free_space,
                                         sure_fitness=eng.sure_fitness, sure_seeds=eng.sure_seeds,
                                         sure_ambiguity=eng.sure_ambiguity)
            sim = m.similarity if eng.verify_score in ("features", "learned") else None
            model = self._verification_model() if eng.verify_score == "learned" else None
            est = estimator.estimate(eng.estimator, src_m[c[:, 0]], tgt_m[c[:, 1]], m.weights, inlier, compat,
                                     (src_m, tgt_m), (src, tgt), sim, m.source_overlap, model)
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = est.R, est.t
            valid, reason = est.valid, est.reason
            if valid and not np.isfinite(T).all():
                valid, reason = False, "non-finite transform"
        refined = "none"
        if valid and eng.refine == "icp":
            with clock("refine"):
                T = refine.icp(src, tgt, T, eng.icp_max_distance * matched.scale, eng.icp_max_iterations,
                               eng.icp_points, matched.seed)
                refined = "icp"
        with clock("verify"):
            fit = refine.fitness(src_m, tgt_m, T, inlier)
            inl = est.inliers
            cov = refine.covariance(src_m[c[inl, 0]], tgt_m[c[inl, 1]], m.weights[inl], T)
            if valid and fit < eng.min_valid_fitness:
                valid, reason = False, (f"fitness {fit:.3f} < engine.min_valid_fitness "
                                        f"{eng.min_valid_fitness:g}: the pose explains almost "
                                        f"none of the source")
        timings["total"] = sum(timings.values())
        bounded = matched.bounded
        return RegistrationResult(
            T_target_source=T, source_points=src_m.astype(np.float32), target_points=tgt_m.astype(np.float32),
            source_overlap=m.source_overlap, target_overlap=m.target_overlap, correspondences=c,
            weights=m.weights, inliers=inl, covariance=cov, fitness=fit, inlier_distance=inlier, valid=valid,
            reason=reason, refined=refined, runtime=matched.runtime, voxel_size=bounded.voxel,
            dropped=bounded.dropped, timings=timings, hypotheses=est.hypotheses, ambiguity=est.ambiguity,
            explored=est.explored, seed=matched.seed)


class _StageClock:
    """``with clock("name"):`` adds the block's wall time to timings["name"]."""

    def __init__(self, timings: dict[str, float]) -> None:
        self.timings = timings

    def __call__(self, name: str) -> _StageClock:
        self._name = name
        return self

    def __enter__(self) -> None:
        self._t0 = time.perf_counter()

    def __exit__(self, *exc: object) -> None:
        self.timings[self._name] = self.timings.get(self._name, 0.0) + time.perf_counter() - self._t0


class _Compiled:
    """The model with score_candidates replaced by its compiled graph (engine.compile)."""

    def __init__(self, model: Any, compiled: Any) -> None:
        self.cfg = model.cfg
        self._model = model
        self.score_candidates = compiled

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self._model(*args, **kwargs)
