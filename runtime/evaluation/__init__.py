"""Measuring: calibration (K*, K_c), self-calibration, test conditions, the paper's metrics,
model predictors, the uncertainty fit and the rectifier over a points file."""
