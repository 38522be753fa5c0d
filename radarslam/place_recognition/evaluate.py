"""The evaluation harness: one split, one ground truth (9 m), one metric code for every method.

A method produces a :class:`Ranking` (per query, database frames best first with a lower-is-better
score): descriptors through :class:`~.retrieval.DescriptorIndex`, ScanContext
through its own two-stage search. RCSHR re-orders a ranking's top-M. :func:`evaluate_ranking`
turns a ranking into recall@N, the PR curve, max F1 and AP (reference definitions, see
:mod:`.metrics`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from radarslam.errors import DataError
from radarslam.io.atomic import write_json_atomic, write_text_atomic
from radarslam.place_recognition.config import (
    EvalConfig,
    M2DPConfig,
    RerankConfig,
    RetrievalConfig,
    ScanContextConfig,
)
from radarslam.place_recognition.dataset import PreparedData
from radarslam.place_recognition.metrics import PRCurve, pr_curve, recall_at_n
from radarslam.place_recognition.rcshr import rcs_histograms, rerank
from radarslam.place_recognition.retrieval import DescriptorIndex


@dataclass(frozen=True)
class Ranking:
    """Retrieval output for a set of query frames."""

    query_frames: np.ndarray  # (Q,) frame indices
    db_frames: np.ndarray  # (Q, K) frame indices of database frames, best first
    scores: np.ndarray  # (Q, K) ascending (descriptor distance or re-ranked score)
    distances: np.ndarray | None = None  # (Q, K) descriptor distance when scores are re-ranked


@dataclass
class EvalResult:
    name: str
    split: str
    num_queries: int
    recall: dict[int, float]
    max_f1: float
    average_precision: float
    curve: PRCurve = field(repr=False)
    extra: dict = field(default_factory=dict)

    def row(self) -> dict:
        out = {"method": self.name, "split": self.split, "queries": self.num_queries}
        out.update({f"R@{n}": round(100 * r, 2) for n, r in self.recall.items()})
        out.update(maxF1=round(self.max_f1, 4), AP=round(self.average_precision, 4))
        out.update(self.extra)
        return out


def _split(data: PreparedData, split: str) -> np.ndarray:
    if split not in data.splits:
        raise DataError(f"{data.root}: unknown split {split!r} (have {sorted(data.splits)})")
    idx = np.asarray(data.splits[split], dtype=np.int64)
    if len(idx) == 0:
        raise DataError(f"{data.root}: split {split!r} is empty")
    return idx


def _query_split(data: PreparedData, split: str) -> np.ndarray:
    """The frames of a split that may be queried: not the database, not what was trained on."""
    if split in ("database", "train"):
        from radarslam.errors import ConfigError

        raise ConfigError(
            f"split {split!r} cannot be evaluated (its frames are the database or were trained "
            "on); use 'val' or 'test'"
        )
    return _split(data, split)


def descriptor_ranking(
    data: PreparedData,
    db_descriptors: np.ndarray,
    query_descriptors: np.ndarray,
    query_frames: np.ndarray,
    k: int,
    cfg: RetrievalConfig | None = None,
) -> Ranking:
    """Rank the database (rows = ``data.splits['database']``) by Euclidean descriptor distance."""
    db = data.splits["database"]
    if len(db_descriptors) != len(db):
        raise DataError(f"{len(db_descriptors)} database descriptors for {len(db)} DB frames")
    if len(query_descriptors) != len(query_frames):
        raise DataError(
            f"{len(query_descriptors)} query descriptors for {len(query_frames)} frames"
        )
    res = DescriptorIndex.from_descriptors(db_descriptors, cfg).search(query_descriptors, k)
    return Ranking(np.asarray(query_frames), db[res.indices], res.distances, res.distances)


def _ranking_hists(data: PreparedData, ranking: Ranking, cfg: RerankConfig):
    m = min(cfg.top_m, ranking.db_frames.shape[1])
    cand = ranking.db_frames[:, :m]
    frames = np.unique(np.concatenate([ranking.query_frames, cand.ravel()]))
    if len(data.rcs) != len(data):
        raise DataError(f"{data.root}: RCSHR needs the per-frame RCS values (points.npz)")
    hists = rcs_histograms([data.rcs[i] for i in frames], cfg)
    row_of = np.full(len(data), -1, np.int64)
    row_of[frames] = np.arange(len(frames))
    return frames, hists, row_of


def apply_rcshr(data: PreparedData, ranking: Ranking, cfg: RerankConfig, _hists=None) -> Ranking:
    """Re-order each query's top-M (by the ranking's score) with the RCS histogram KL."""
    m = min(cfg.top_m, ranking.db_frames.shape[1])
    cand = ranking.db_frames[:, :m]
    dist = (ranking.distances if ranking.distances is not None else ranking.scores)[:, :m]
    frames, hists, row_of = _hists if _hists is not None else _ranking_hists(data, ranking, cfg)
    out = rerank(row_of[cand], dist, hists[row_of[ranking.query_frames]], hists, cfg.alpha)
    return Ranking(ranking.query_frames, frames[out.indices], out.scores, out.distances)


def evaluate_ranking(
    data: PreparedData,
    ranking: Ranking,
    cfg: EvalConfig,
    name: str,
    split: str = "test",
    positives: Callable[[int], np.ndarray] | None = None,
) -> EvalResult:
    """Recall@N, PR curve, max F1 and AP of a ranking; a retrieved frame is correct when it is a
    positive of its query (``positives(query)``; by default any DB frame within the radius)."""
    if positives is None:
        correct = data.is_positive(ranking.query_frames, ranking.db_frames)
    else:
        correct = np.stack(
            [np.isin(row, positives(int(q))) for q, row in
             zip(ranking.query_frames, ranking.db_frames, strict=True)]
        ) if len(ranking.query_frames) else np.zeros(ranking.db_frames.shape, bool)  # fmt: skip
    if correct.shape[1] == 0:
        raise DataError("the ranking retrieved no database frame")
    rec = recall_at_n(correct, cfg.recall_at)
    curve = pr_curve(ranking.scores[:, 0], correct[:, 0], cfg.pr_decimals)
    return EvalResult(
        name=name,
        split=split,
        num_queries=len(ranking.query_frames),
        recall=rec,
        max_f1=curve.max_f1,
        average_precision=curve.average_precision,
        curve=curve,
    )


def rcshr_grid() -> list[RerankConfig]:
    """The small grid tuned on validation: b_m x b_w x alpha around the paper's values."""
    out = []
    for b_m in (0.0, 0.02, 0.04, 0.06):
        for b_w in (0.02, 0.04, 0.06, 0.08):
            for alpha in (0.02, 0.05, 0.1, 0.2, 0.3, 0.41, 0.5, 0.7):
                out.append(RerankConfig(bin_min=b_m, bin_width=b_w, alpha=alpha))
    return out


@dataclass(frozen=True)
class TuneResult:
    best: RerankConfig
    best_recall_at_1: float
    baseline_recall_at_1: float
    trials: list[dict]


def tune_rcshr(
    data: PreparedData,
    val_ranking: Ranking,
    grid: Sequence[RerankConfig] | None = None,
) -> TuneResult:
    """Grid search of (b_m, b_w, alpha) on the VALIDATION ranking only (max R@1, then mean R@5)."""
    grid = list(grid) if grid is not None else rcshr_grid()
    if not grid:
        raise DataError("empty RCSHR grid")
    base = data.is_positive(val_ranking.query_frames, val_ranking.db_frames[:, :1]).mean()
    best, best_key, trials = None, None, []
    hist_cache: dict[tuple, tuple] = {}
    for cfg in grid:
        key = (cfg.bin_min, cfg.bin_width, cfg.epsilon, cfg.top_m)
        if key not in hist_cache:
            hist_cache[key] = _ranking_hists(data, val_ranking, cfg)
        r = apply_rcshr(data, val_ranking, cfg, hist_cache[key])
        correct = data.is_positive(r.query_frames, r.db_frames[:, :5])
        r1 = float(correct[:, 0].mean())
        r5 = float(np.logical_or.accumulate(correct, axis=1)[:, -1].mean())
        trials.append({"bin_min": cfg.bin_min, "bin_width": cfg.bin_width, "alpha": cfg.alpha,
                       "R@1": r1, "R@5": r5})  # fmt: skip
        score = (r1, r5)
        if best_key is None or score > best_key:
            best, best_key = cfg, score
    assert best is not None and best_key is not None
    return TuneResult(best=best, best_recall_at_1=best_key[0], baseline_recall_at_1=float(base),
                      trials=trials)  # fmt: skip


# ---- handcrafted baselines ------------------------------------------------------------------
def m2dp_descriptors(data: PreparedData, frames: np.ndarray, cfg: M2DPConfig) -> np.ndarray:
    from radarslam.place_recognition.baselines.m2dp import m2dp

    return np.stack([m2dp(data.points_xy[i], cfg) for i in np.asarray(frames)])


def scancontext_ranking(
    data: PreparedData, query_frames: np.ndarray, k: int, cfg: ScanContextConfig
) -> Ranking:
    from radarslam.place_recognition.baselines.scancontext import ScanContextIndex

    db = data.splits["database"]
    index = ScanContextIndex(cfg)
    index.add(np.stack([index.describe(data.points_xy[i], data.rcs[i]) for i in db]))
    queries = np.stack([index.describe(data.points_xy[i], data.rcs[i]) for i in query_frames])
    res = index.search(queries, k)
    return Ranking(np.asarray(query_frames), db[res.indices], res.distances, res.distances)


def evaluate_method(
    data: PreparedData,
    name: str,
    ranking_fn: Callable[[np.ndarray, int], Ranking],
    cfg: EvalConfig,
    split: str = "test",
    rerank_cfg: RerankConfig | None = None,
    tune_on_val: bool = False,
) -> list[EvalResult]:
    """Evaluate ``ranking_fn(query_frames, k)`` on ``split``; with RCSHR also a "+RCSHR" row.

    ``tune_on_val``: the RCSHR parameters are grid-searched on the val split's ranking first.
    """
    queries = _query_split(data, split)
    k = max(max(cfg.recall_at), cfg.rerank.top_m if rerank_cfg is not None else 0)
    ranking = ranking_fn(queries, k)
    results = [evaluate_ranking(data, ranking, cfg, name, split)]
    if rerank_cfg is not None:
        extra = {}
        if tune_on_val:
            tuned = tune_rcshr(data, ranking_fn(_split(data, "val"), k))
            rerank_cfg = tuned.best.model_copy(update={"top_m": rerank_cfg.top_m})
            extra = {"val_R@1": round(100 * tuned.best_recall_at_1, 2)}
        rr = evaluate_ranking(data, apply_rcshr(data, ranking, rerank_cfg), cfg,
                              f"{name}+RCSHR", split)  # fmt: skip
        rr.extra.update(extra, b_m=rerank_cfg.bin_min, b_w=rerank_cfg.bin_width,
                        alpha=rerank_cfg.alpha)  # fmt: skip
        results.append(rr)
    return results


def evaluate_turned(
    data: PreparedData,
    name: str,
    turned_ranking_fn: Callable[[np.ndarray, int], Ranking],
    cfg: EvalConfig,
    split: str = "test",
    max_heading_error_deg: float = 45.0,
) -> EvalResult | None:
    """The turned search of SLAM (``loops.reversed_search``) on its own: every query of ``split``
    that has positives driven the other way round, ranked from its images turned by 180 deg
    (``turned_ranking_fn``); a hit is such a positive. None when no query has one."""
    queries = _query_split(data, split)
    queries = np.array(
        [q for q in queries if len(data.reversed_positives(int(q), max_heading_error_deg))],
        dtype=np.int64,
    )
    if not len(queries):
        return None
    ranking = turned_ranking_fn(queries, max(cfg.recall_at))
    return evaluate_ranking(
        data, ranking, cfg, f"{name} turned", split,
        positives=lambda q: data.reversed_positives(q, max_heading_error_deg),
    )  # fmt: skip


def descriptor_ranking_fn(
    data: PreparedData,
    describe: Callable[[np.ndarray], np.ndarray],
    cfg: EvalConfig,
    describe_queries: Callable[[np.ndarray], np.ndarray] | None = None,
    db_cache: dict[str, np.ndarray] | None = None,
) -> Callable[[np.ndarray, int], Ranking]:
    """A ranking function from ``describe(frames) -> (M, D)`` (queries through
    ``describe_queries`` if given); the DB is described once (into ``db_cache`` if given, which
    ranking functions of the same ``describe`` may share)."""
    cache: dict[str, np.ndarray] = {} if db_cache is None else db_cache

    def fn(query_frames: np.ndarray, k: int) -> Ranking:
        if "db" not in cache:
            cache["db"] = describe(data.splits["database"])
        q = (describe_queries or describe)(query_frames)
        return descriptor_ranking(data, cache["db"], q, query_frames, k, cfg.retrieval)

    return fn


# ---- tables ---------------------------------------------------------------------------------
def markdown_table(rows: Sequence[dict], columns: Sequence[str] | None = None) -> str:
    if not rows:
        return "(no results)\n"
    cols = list(columns) if columns else list(dict.fromkeys(k for r in rows for k in r))
    lines = ["| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    for r in rows:
        cells = []
        for c in cols:
            v = r.get(c, "")
            cells.append(f"{v:.4g}" if isinstance(v, float) else str(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_results(
    results: Sequence[EvalResult], out_dir: str | Path, stem: str = "results", plot: bool = True
) -> dict[str, Path]:
    """``<stem>.json``, ``<stem>.md`` and (optionally) ``<stem>_pr.png``, all atomic."""
    from radarslam.place_recognition.metrics import save_pr_plot

    out = Path(out_dir)
    rows = [r.row() for r in results]
    paths = {"json": out / f"{stem}.json", "md": out / f"{stem}.md"}
    payload = {
        "rows": rows,
        "curves": {
            r.name: {
                "thresholds": r.curve.thresholds.tolist(),
                "precision": r.curve.precision.tolist(),
                "recall": r.curve.recall.tolist(),
            }
            for r in results
        },
    }
    write_json_atomic(paths["json"], payload)
    write_text_atomic(paths["md"], markdown_table(rows))
    if plot:
        paths["png"] = save_pr_plot({r.name: r.curve for r in results}, out / f"{stem}_pr.png")
    return paths


# ---- method factories (CLI, ablation, bench) ------------------------------------------------
BASELINES = ("scancontext", "m2dp")


def baseline_ranking_fn(
    data: PreparedData,
    name: str,
    cfg: EvalConfig,
    scancontext: ScanContextConfig | None = None,
    m2dp_cfg: M2DPConfig | None = None,
) -> tuple[str, Callable[[np.ndarray, int], Ranking]]:
    """("ScanContext" | "M2DP", ranking function) on the prepared (DPR'd, cropped) points."""
    from radarslam.errors import ConfigError

    if name not in BASELINES:
        raise ConfigError(f"unknown baseline {name!r} (choose from {', '.join(BASELINES)})")
    if not data.points_xy:
        raise DataError(f"{data.root}: the prepared data holds no points for the baselines")
    if name == "scancontext":
        sc = scancontext or ScanContextConfig()
        return "ScanContext", lambda q, k: scancontext_ranking(data, q, k, sc)
    mc = m2dp_cfg or M2DPConfig()
    return "M2DP", descriptor_ranking_fn(data, lambda f: m2dp_descriptors(data, f, mc), cfg)


def model_describe_fn(
    model, data: PreparedData, batch_size: int = 32, device: str = "cpu", turned: bool = False
):
    """``frames -> (M, D)`` descriptors of the sequences ending at ``frames`` (``turned``: of
    their images turned by 180 deg)."""
    from radarslam.place_recognition.train import compute_descriptors

    return lambda frames: compute_descriptors(
        model, data, frames, batch_size, device, turned=turned
    )


def checkpoint_ranking_fn(
    data: PreparedData, checkpoint: str | Path, cfg: EvalConfig, device: str = "cpu"
) -> tuple[str, Callable[[np.ndarray, int], Ranking], Callable[[np.ndarray, int], Ranking]]:
    """(name, ranking function, turned ranking function) of a checkpoint: the second describes
    the queries from their images turned by 180 deg (:func:`evaluate_turned`); both share the
    model and the database's descriptors."""
    from radarslam.place_recognition.checkpoint import load_model

    model, model_cfg, _ = load_model(checkpoint, device=device)
    name = str(getattr(model_cfg, "preset", "") or Path(checkpoint).stem)
    describe = model_describe_fn(model, data, cfg.batch_size, device)
    turned = model_describe_fn(model, data, cfg.batch_size, device, turned=True)
    db: dict[str, np.ndarray] = {}
    return (
        name,
        descriptor_ranking_fn(data, describe, cfg, db_cache=db),
        descriptor_ranking_fn(data, describe, cfg, turned, db_cache=db),
    )
