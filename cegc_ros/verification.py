"""Learned verification: which of the estimator's verified hypotheses to choose, by a
log-linear model of evidence the engine already has, fitted on generated training pairs.

The estimator (cegc_ros/estimator.py, step 5) verifies its ~100 best-counted distinct poses.
Under ``engine.verify_score: learned`` its last pass (the one with the free-space check) ranks
them by

    score_h = exp(p x (w . x_h - max_g w . x_g)) x exp(-p x w_free x v_h)

with x_h the hypothesis' :data:`FEATURES` (:func:`features`), v_h its free-space violations
(cegc_ros/visibility.py) and ``p = 2 / (w_count + w_agreement)``, so that a score reads like
count x agreement, the score it replaces (and :func:`cegc_ros.estimator.ambiguity`, a ratio of
scores, keeps its scale). The free-space term stays a factor <= 1, so the estimator's lazy
check (:func:`cegc_ros.estimator._free_space_scores`) still checks only the poses that can
matter.

Why: count x agreement x exp(-10 v) chose a right pose, before ICP, on 257 of the 674
low-overlap validation evaluations that had one on 347; the fitted weights (the agreement
weighs ~13x the count, and HOCE's overlap confidence of the points a pose lands tells where
the network sees overlap) chose one on 266-272; end to end 43 won / 17 lost at fresh seeds
(docs/accuracy.md, "Learned verification"). The model is a conditional logit (McFadden 1973): for each evaluation, the
softmax of w . x over its verified hypotheses, fitted to put its mass on the right ones
(:func:`fit`; ``python -m cegc_ros.tools.fit_verification`` writes the shipped file).

Shapes: H hypotheses, Ns source points. Nothing here imports torch, Open3D or the engine.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

#: The evidence of one hypothesis (all from one nearest-neighbour search of the network's
#: points, :func:`cegc_ros.refine.landing_evidence`, and the count the estimator has):
#: log of the count, of the feature agreement and of the fitness; log of the share of the
#: source's HOCE overlap confidence on the points the pose lands within the inlier distance of
#: a target point; and the mean confidence of those points (0 when none lands).
FEATURES = ("log_count", "log_agreement", "log_fitness", "log_overlap_landed", "overlap_precision")
#: Added inside every logarithm (counts, agreements and shares of 0 stay finite).
EPS = 1e-3
FORMAT = 1


class VerificationModelError(ValueError):
    """A verification model file that is missing, unreadable or does not match this code."""


@dataclass(frozen=True)
class VerificationModel:
    """Weights of :data:`FEATURES` and of the free-space violations (``free_space`` >= 0: the
    log-score falls by this much per unit of violations), with how they were fitted."""

    weights: dict[str, float]
    free_space: float
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if set(self.weights) != set(FEATURES):
            raise VerificationModelError(f"weights must name {', '.join(FEATURES)}, got {sorted(self.weights)}")
        values = [*self.weights.values(), self.free_space]
        if not all(np.isfinite(v) for v in values):
            raise VerificationModelError("weights must be finite")
        if self.free_space < 0:
            raise VerificationModelError(f"free_space weight must be >= 0, got {self.free_space}")
        if not self.weights["log_count"] + self.weights["log_agreement"] > 0:
            raise VerificationModelError("log_count + log_agreement weights must be > 0")

    @property
    def scale(self) -> float:
        """p: the power that makes a score read like count x agreement."""
        return 2.0 / (self.weights["log_count"] + self.weights["log_agreement"])

    def linear(self, x: np.ndarray) -> np.ndarray:
        """(H, len(FEATURES)) -> (H,) the weighted sum of the evidence (before the scale and the
        free-space term): what :meth:`ranks` normalises, comparable across calls."""
        return np.asarray(x, np.float64) @ np.array([self.weights[f] for f in FEATURES])

    def ranks(self, x: np.ndarray) -> np.ndarray:
        """(H, len(FEATURES)) -> (H,) scores in (0, 1] before the free-space factor (the best 1)."""
        s = self.linear(x)
        return np.exp(self.scale * (s - s.max()))

    def log_scores(self, x: np.ndarray, violations: np.ndarray) -> np.ndarray:
        """(H, len(FEATURES)) and (H,) free-space violations -> (H,) the logarithm of what the
        estimator ranks by (:meth:`ranks` x exp(-:attr:`free_space_strength` x violations)),
        every hypothesis scored in full."""
        return np.log(self.ranks(x)) - self.free_space_strength * np.asarray(violations, np.float64)

    @property
    def free_space_strength(self) -> float:
        """The factor's strength on the scale of :meth:`ranks`: exp(-strength x violations)."""
        return self.scale * self.free_space

    @classmethod
    def load(cls, path: str | Path) -> VerificationModel:
        path = Path(path)
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError) as err:
            raise VerificationModelError(f"verification model {path}: unreadable ({err})".splitlines()[0]) from err
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            got = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
            raise VerificationModelError(f"verification model {path}: format {got!r}, expected {FORMAT}")
        try:
            return cls({k: float(v) for k, v in doc["weights"].items()}, float(doc["free_space"]),
                       dict(doc.get("meta", {})))
        except (KeyError, TypeError, AttributeError, ValueError) as err:
            raise VerificationModelError(f"verification model {path}: {err}".splitlines()[0]) from err

    def save(self, path: str | Path) -> None:
        doc = {"format": FORMAT, "weights": {f: self.weights[f] for f in FEATURES},
               "free_space": self.free_space, "meta": self.meta}
        Path(path).write_text(json.dumps(doc, indent=1, default=str) + "\n")


def features(count: np.ndarray, agreement: np.ndarray, fitness: np.ndarray, overlap_landed: np.ndarray,
             overlap_precision: np.ndarray) -> np.ndarray:
    """The evidence of H hypotheses, each (H,) -> (H, len(FEATURES)) in :data:`FEATURES`' order."""
    return np.stack([np.log(np.asarray(count, np.float64) + EPS), np.log(np.asarray(agreement, np.float64) + EPS),
                     np.log(np.asarray(fitness, np.float64) + EPS),
                     np.log(np.asarray(overlap_landed, np.float64) + EPS),
                     np.asarray(overlap_precision, np.float64)], axis=1)


def fit(x: np.ndarray, violations: np.ndarray, group: np.ndarray, right: np.ndarray, l2: float = 1e-3
        ) -> tuple[dict[str, float], float]:
    """Conditional-logit weights: x (n, len(FEATURES)) and violations (n,) of n hypotheses,
    group (n,) int of the evaluation each belongs to, right (n,) bool -> (weights, free-space
    weight). Maximises the mean over the evaluations that hold a right hypothesis of
    log sum_{right h} softmax_g(w . x - w_free v)_h, with an L2 penalty ``l2`` on the weights of
    the standardised features. ValueError when no evaluation holds both a right and a wrong one."""
    from scipy.optimize import minimize
    X = np.column_stack([np.asarray(x, np.float64), -np.asarray(violations, np.float64)])
    g = np.unique(np.asarray(group), return_inverse=True)[1]
    y = np.asarray(right, bool).astype(np.float64)
    ng = int(g.max()) + 1 if len(g) else 0
    n_right = np.bincount(g, y, ng)
    useful = (n_right > 0) & (n_right < np.bincount(g, None, ng))
    if not useful.any():
        raise ValueError("no evaluation holds both a right and a wrong hypothesis: nothing to fit")
    keep = useful[g]
    X, g, y = X[keep], np.unique(g[keep], return_inverse=True)[1], y[keep]
    ng = int(g.max()) + 1
    mu, sd = X.mean(0), X.std(0) + 1e-12
    Z = (X - mu) / sd

    def loss(theta: np.ndarray) -> tuple[float, np.ndarray]:
        s = Z @ theta
        top = np.full(ng, -np.inf)
        np.maximum.at(top, g, s)
        e = np.exp(s - top[g])
        total, on_right = np.bincount(g, e, ng), np.bincount(g, e * y, ng)
        value = -np.mean(np.log(on_right) - np.log(total)) + 0.5 * l2 * theta @ theta
        grad = -((y * e / on_right[g] - e / total[g])[:, None] * Z).sum(0) / ng + l2 * theta
        return float(value), grad

    theta = minimize(loss, np.zeros(Z.shape[1]), jac=True, method="L-BFGS-B").x / sd
    weights = {f: float(w) for f, w in zip(FEATURES, theta[:-1])}
    return weights, max(0.0, float(theta[-1]))
