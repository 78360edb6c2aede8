"""training layer: teacher-forced training, batched closed-loop evaluation, metrics, reports."""
from gscan_ros.training.evaluate import EvalResult, Prediction, evaluate_episodes, token_accuracy

__all__ = ["EvalResult", "Prediction", "evaluate_episodes", "token_accuracy"]
