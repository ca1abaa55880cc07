"""The runner: the steps of a registration (:mod:`scanreg.runner.steps`), one run from its config
(:mod:`scanreg.runner.pipeline`), and what a run writes and prints (:mod:`scanreg.runner.outputs`)."""

from scanreg.runner.build import Stages, build_stages
from scanreg.runner.outputs import repair_table, summary_lines, write_keypoints, write_outputs
from scanreg.runner.pipeline import REPAIR_PREFIX, run_pipeline, run_stages
from scanreg.runner.steps import MIN_POINTS, Evaluation, evaluate_pair, load_problem, prepare_scan, register_pair

__all__ = ["MIN_POINTS", "REPAIR_PREFIX", "Evaluation", "Stages", "build_stages", "evaluate_pair", "load_problem", "prepare_scan",
           "register_pair", "repair_table", "run_pipeline", "run_stages", "summary_lines", "write_keypoints",
           "write_outputs"]
