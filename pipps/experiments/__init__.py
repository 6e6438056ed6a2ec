"""Episodic learning experiments: configuration, the learning loop, HDF5 results, sweeps,
the thesis' success-rate tables and rerun plots (experiments.md). See docs/experiments.md."""

from pipps.experiments.config import PRESET_NAMES, ConfigError, ExperimentConfig, resolve_config
from pipps.experiments.loop import ExperimentResult, TrialResult, judge_success, run_experiment
from pipps.experiments.methods import METHODS, Method
from pipps.experiments.state import restore

__all__ = [
    "ConfigError", "ExperimentConfig", "ExperimentResult", "METHODS", "Method", "PRESET_NAMES", "TrialResult",
    "judge_success", "resolve_config", "restore", "run_experiment",
]
