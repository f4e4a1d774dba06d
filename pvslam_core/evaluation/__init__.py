"""Evaluation: trajectory accuracy (ATE/RPE through evo), panoptic quality (PQ, VPQ), loop precision/recall,
and :func:`pvslam_core.evaluation.run_eval.evaluate_run` that recomputes a run directory's metrics."""
