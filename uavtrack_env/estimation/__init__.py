"""Target state estimation: the UKF of section II-E and the dropout motion fit of Remark 2."""

from uavtrack_env.estimation.motion_prediction import MotionFit, MotionHistory, fit_polynomial
from uavtrack_env.estimation.ukf import (
    Estimate,
    Measurement,
    TargetEstimator,
    UKFConfig,
    VectorizedUKF,
    make_filter,
    measurement_model,
    process_model,
)

__all__ = [
    "Estimate",
    "Measurement",
    "MotionFit",
    "MotionHistory",
    "TargetEstimator",
    "UKFConfig",
    "VectorizedUKF",
    "fit_polynomial",
    "make_filter",
    "measurement_model",
    "process_model",
]
