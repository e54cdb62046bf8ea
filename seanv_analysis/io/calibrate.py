"""Raw sensor units -> engineering units, from the rig config's [calibration].

The data contract lets a table carry a raw column (``encoder_counts``,
``p_*_v``, ``p_*_kpag``, ``cam_cmd_pulse``, ``cam_pulse``) instead of the
engineering column; the reader converts it here. Nothing is guessed: the
conversion is chosen by the raw column's name and every constant comes from
the rig config.

Conversions (constants from ``[calibration]`` unless noted)::

    encoder_counts -> position_mm = counts * encoder_mm_per_count + encoder_offset_mm
    p_*_v          -> p_*_mpag    = (V - pressure_offset_v) * pressure_mpa_per_v
    p_*_kpag       -> p_*_mpag    = kPa / kpa_per_mpa
    *_pulse        -> *_deg       = (pulses - servo_centre_pulse) * servo.resolution_deg
"""
from __future__ import annotations

import numpy as np

from ..config import RigConfig
from ..errors import ConfigError

__all__ = ["calibrate", "raw_unit"]


def raw_unit(raw_name: str) -> str:
    """Unit of a raw column from its name ('counts', 'V', 'kPa gauge', 'pulses')."""
    if raw_name == "encoder_counts":
        return "counts"
    if raw_name.endswith("_v"):
        return "V"
    if raw_name.endswith("_kpag"):
        return "kPa gauge"
    if raw_name.endswith("_pulse"):
        return "pulses"
    raise ConfigError(f"raw column '{raw_name}': no calibration rule for this name "
                      "(expected encoder_counts, *_v, *_kpag or *_pulse)")


def _const(rig: RigConfig, section: str, key: str, raw_name: str) -> float:
    try:
        return float(rig[section][key])
    except (KeyError, TypeError, ValueError):
        raise ConfigError(f"rig config: [{section}] {key} is missing or not a number; "
                          f"it is needed to convert raw column '{raw_name}'") from None


def calibrate(raw_name: str, values: np.ndarray, rig: RigConfig) -> np.ndarray:
    """Convert a raw column to its engineering unit.

    Parameters
    ----------
    raw_name : name of the raw column (decides the conversion, see module doc)
    values : raw values (float64 array; NaN stays NaN)
    rig : rig config whose ``[calibration]`` (and ``[servo] resolution_deg``)
        hold the constants

    Returns
    -------
    New float64 array in mm, MPa gauge or deg.
    """
    v = np.asarray(values, dtype=np.float64)
    unit = raw_unit(raw_name)
    if unit == "counts":
        k = _const(rig, "calibration", "encoder_mm_per_count", raw_name)
        off = _const(rig, "calibration", "encoder_offset_mm", raw_name)
        return v * k + off
    if unit == "V":
        off = _const(rig, "calibration", "pressure_offset_v", raw_name)
        k = _const(rig, "calibration", "pressure_mpa_per_v", raw_name)
        return (v - off) * k
    if unit == "kPa gauge":
        k = _const(rig, "calibration", "kpa_per_mpa", raw_name)
        return v / k
    centre = _const(rig, "calibration", "servo_centre_pulse", raw_name)
    res = _const(rig, "servo", "resolution_deg", raw_name)
    return (v - centre) * res
