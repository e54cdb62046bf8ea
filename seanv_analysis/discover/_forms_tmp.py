"""TEMPORARY: effect functional forms until models/effects.py lands (to be merged)."""
import numpy as np


def drift_multiplier(run_index, *, step, every, offset=0):
    """C multiplier (1 - step)^floor((i + offset) / every)."""
    k = np.floor((np.asarray(run_index, float) + offset) / every)
    return (1.0 - step) ** k


def threshold_shift_mm(run_index, *, rate_mm_per_run):
    return rate_mm_per_run * np.asarray(run_index, float)


def backlash_cam_deg(theta_deg, approach, *, width_deg):
    return np.asarray(theta_deg, float) - 0.5 * width_deg * np.asarray(approach, float)


def saturate_flow(q, q_max, sharpness=8.0):
    q = np.asarray(q, float)
    q_max = np.broadcast_to(np.asarray(q_max, float), q.shape)
    out = q.copy()
    m = np.isfinite(q_max)
    out[m] = q[m] / (1.0 + (np.abs(q[m]) / q_max[m]) ** sharpness) ** (1.0 / sharpness)
    return out


def true_from_measured(measured, *, gain, sensor="pressure"):
    return np.asarray(measured, float) / gain
