"""The agreement half of `romannet bench inference`: how often each precision's decision is the fp32 reference's,
on the benchmark's random-init nets and on the trained nets shipped in models/ (a trained net amplifies int8's
error 15-40x over a random one, relative to its Q maps: docs/benchmarks.md, "int8 decisions").
"""

from __future__ import annotations

import logging
import statistics
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from romannet.common.config import ExplorationConfig, ModelConfig
from romannet.common.errors import RomannetError
from romannet.common.int8net import int8_ops_available
from romannet.common.model import RoManNet, load_tensors
from romannet.common.policy import INFERENCE_PRECISIONS, InferenceEngine, decide

logger = logging.getLogger(__name__)

# The packages `romannet models pack` wrote beside the code (absent from an installed wheel: then left out).
MODELS_DIR = Path(__file__).resolve().parents[1] / "models"
SHIPPED_MODELS = ("clutter", "stacking")


def first_line(err: Exception) -> str:
    """An error's first line, at most 200 characters (its type's name when it has no text)."""
    return str(err).splitlines()[0][:200] if str(err) else type(err).__name__


def precision_engines(model: RoManNet, cfg: ModelConfig, precisions: tuple[str, ...] = INFERENCE_PRECISIONS
                      ) -> tuple[dict[str, InferenceEngine], dict[str, str]]:
    """An engine per precision of these this machine can run ({precision: engine}), and why the others are
    left out."""
    engines, left_out = {}, {}
    for precision in precisions:
        if precision == "int8" and not int8_ops_available():
            left_out[precision] = "no oneDNN int8 convolutions in this PyTorch build or CPU"
            continue
        try:
            engine = InferenceEngine(model, replace(cfg, precision=precision))
            engine.forward(torch.zeros(1, 4, 32, 32), ("push",))  # oneDNN's bf16 kernels raise on AVX2-only CPUs
        except (RuntimeError, ValueError) as err:
            left_out[precision] = first_line(err)
        else:
            engines[precision] = engine
    return engines, left_out


def agreement(engines: dict[str, InferenceEngine], model: RoManNet, scenes: list, rng: np.random.Generator,
               primitives: tuple[str, ...], exploration: ExplorationConfig) -> dict[str, dict]:
    """Per precision: share of the fp32 reference's (primitive, row, col) choices made, mean decision ms over
    these inputs, and for an engine that reruns near ties the share rerun and the agreement without reruns."""
    hits = {p: 0 for p in engines}
    alone = {p: 0 for p in engines if engines[p].tie_share > 0}
    times: dict[str, list[float]] = {p: [] for p in engines}
    reruns = {p: e.exact_reruns for p, e in engines.items()}

    def choice(a: object) -> tuple:
        return a.primitive, a.row, a.col  # type: ignore[attr-defined]

    for color, depth in scenes:
        ref = choice(decide(model, color, depth, False, 0.0, rng, primitives, exploration))
        for precision, engine in engines.items():
            t0 = time.perf_counter()
            hits[precision] += choice(decide(engine, color, depth, False, 0.0, rng, primitives, exploration)) == ref
            times[precision].append((time.perf_counter() - t0) * 1e3)
            if precision in alone:
                share, engine.tie_share = engine.tie_share, 0.0
                try:
                    alone[precision] += choice(decide(engine, color, depth, False, 0.0, rng, primitives,
                                                      exploration)) == ref
                finally:
                    engine.tie_share = share
    n = len(scenes)
    result = {p: {"agreement": round(hits[p] / n, 4), "decision_mean_ms": round(statistics.fmean(times[p]), 2)}
              for p in engines}
    for p in alone:
        result[p].update(agreement_without_reruns=round(alone[p] / n, 4),
                         near_tie_reruns=round((engines[p].exact_reruns - reruns[p]) / n, 4))
    return result


def load_shipped(name: str, models_dir: Path = MODELS_DIR) -> RoManNet:
    """models/<name> as an eval-mode RoManNet in fp32 (RomannetError where absent or damaged)."""
    from romannet.learner.checkpoint import read_package  # the learner's reader of packages, checked

    tensors, _, cfg = read_package(models_dir / name)
    model = RoManNet(cfg.model)
    load_tensors(model, tensors)
    return model.eval()


def shipped_models_agreement(precisions: tuple[str, ...], scenes: list, seed: int,
                             exploration: ExplorationConfig, primitives: tuple[str, ...],
                             models_dir: Path = MODELS_DIR) -> dict[str, dict]:
    """{"models/<name>": agreement per precision} for each shipped model, its own head and channels, on the
    same scenes; a model that cannot be read is reported with why."""
    out: dict[str, dict] = {}
    for name in SHIPPED_MODELS:
        try:
            model = load_shipped(name, models_dir)
        except (RomannetError, OSError) as err:
            out[f"models/{name}"] = {"left_out": first_line(err)}
            continue
        engines, _ = precision_engines(model, model.cfg, precisions)
        try:
            out[f"models/{name}"] = agreement(engines, model, scenes, np.random.default_rng(seed), primitives,
                                              exploration)
        finally:
            for engine in engines.values():
                engine.close()
    return out
