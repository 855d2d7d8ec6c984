"""Evaluation: the paper's statistics (in fusion metrics) and ground-truth scores (synthetic data)."""

from pavemap.evaluate.gt import MATCH_DIST_M, RULE, evaluate, load_truth, match, score_instances

__all__ = ["MATCH_DIST_M", "RULE", "evaluate", "load_truth", "match", "score_instances"]
