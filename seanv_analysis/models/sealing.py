"""Sealing equilibrium model of the SEANV needle (paper Sec. II-C, eq. 1-4).

Units: mm, MPa (= N/mm^2), N, deg.

The sealing threshold angle theta_d is where the cam-driven needle-head
height z_c(theta) (eq. 4) equals the spring displacement at which the spring
force balances the fluid force (eq. 3). Eq. (4) has no closed-form inverse,
so, as in the paper, it is inverted by interpolation over a monotonic table.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from functools import cached_property, lru_cache
from typing import Any

import numpy as np

__all__ = [
    "NeedleGeometry",
    "fluid_force_n",
    "spring_force_n",
    "threshold_displacement_mm",
    "needle_height_mm",
    "fluid_force_core",
    "threshold_displacement_core",
    "needle_height_core",
    "angle_for_height_core",
]

# Cam angles over which eq. (4) is tabulated for the inversion [deg]. Wider
# than the valid cam range so thresholds just outside it are still found.
_TABLE_RANGE_DEG = (-60.0, 35.0)
_TABLE_POINTS = 1901


# Scalar/array cores ---------------------------------------------------------
# Plain arithmetic on floats or numpy arrays, so the same source serves the
# numpy API below and, compiled with ``numba.njit``, the simulator's kernel
# and the controllers (one home per equation).

def fluid_force_core(p1_mpa, dp_mpa, needle_diameter_mm, seat_diameter_mm):
    """Eq. (1) on plain numbers: F_w = pi/4 (d_n^2 p1 - d_o^2 dp) [N]."""
    return math.pi / 4 * (needle_diameter_mm ** 2 * p1_mpa - seat_diameter_mm ** 2 * dp_mpa)


def threshold_displacement_core(z0_mm, fluid_force, spring_constant_n_per_mm):
    """Eq. (3) on plain numbers: z_c = z0 - F_w / k [mm] (F_w from eq. 1, N)."""
    return z0_mm - fluid_force / spring_constant_n_per_mm


def needle_height_core(theta_deg, needle_x_c_mm, needle_y_c_mm, needle_head_radius_mm,
                       cam_slope_deg, z_p_mm, z_c0_mm):
    """Eq. (4) on plain numbers (sign of the constant term corrected, see
    :func:`needle_height_mm`) [mm]."""
    t = np.radians(theta_deg)
    return _needle_height_trig(np.cos(t), np.sin(t), needle_x_c_mm, needle_y_c_mm,
                               needle_head_radius_mm, cam_slope_deg, z_p_mm, z_c0_mm)


def _needle_height_trig(cos_t, sin_t, needle_x_c_mm, needle_y_c_mm, needle_head_radius_mm,
                        cam_slope_deg, z_p_mm, z_c0_mm):
    """Eq. (4) from cos and sin of the cam angle (:func:`needle_height_core`) [mm]."""
    phi = math.radians(cam_slope_deg)
    r = needle_head_radius_mm
    tp = math.tan(phi)
    return ((needle_x_c_mm - r * math.sin(phi) * cos_t) * tp * cos_t
            - (needle_y_c_mm - r * tp * sin_t) * tp * sin_t
            + (z_p_mm - r * math.cos(phi)) - z_c0_mm)


def angle_for_height_core(z_mm, z_table_mm, theta_table_deg):
    """Inverse of eq. (4) by linear interpolation in an increasing height
    table (:attr:`NeedleGeometry.height_table`) [deg]; clipped at its ends."""
    return np.interp(z_mm, z_table_mm, theta_table_deg)


@dataclass(frozen=True)
class NeedleGeometry:
    """Geometry of one needle (paper Table II) plus its centre (x_c, y_c).

    Attributes
    ----------
    needle_diameter_mm : d_n [mm]
    seat_diameter_mm : d_o [mm]
    needle_head_radius_mm : r [mm]
    cam_slope_deg : phi [deg]
    spring_constant_n_per_mm : k [N/mm]
    z_p_mm, z_c0_mm : cam-slope intercept and head-centre height at theta=0 [mm]
    needle_x_c_mm, needle_y_c_mm : needle-head centre in the cam frame [mm]
    """

    needle_diameter_mm: float
    seat_diameter_mm: float
    needle_head_radius_mm: float
    cam_slope_deg: float
    spring_constant_n_per_mm: float
    z_p_mm: float
    z_c0_mm: float
    needle_x_c_mm: float
    needle_y_c_mm: float

    @classmethod
    def from_rig(cls, rig: Any, side: str) -> "NeedleGeometry":
        """Geometry of ``side`` ('supply' or 'drain') from ``rig['valve']`` (a
        :class:`~seanv_analysis.config.RigConfig` or any mapping-like rig) [mm, deg, N/mm]."""
        v = rig["valve"]
        s = v[side]
        return cls(
            needle_diameter_mm=float(v["needle_diameter_mm"]),
            seat_diameter_mm=float(v["seat_diameter_mm"]),
            needle_head_radius_mm=float(v["needle_head_radius_mm"]),
            cam_slope_deg=float(v["cam_slope_deg"]),
            spring_constant_n_per_mm=float(v["spring_constant_n_per_mm"]),
            z_p_mm=float(v["z_p_mm"]),
            z_c0_mm=float(v["z_c0_mm"]),
            needle_x_c_mm=float(s["needle_x_c_mm"]),
            needle_y_c_mm=float(s["needle_y_c_mm"]),
        )

    def to_dict(self) -> dict[str, float]:
        return asdict(self)

    @cached_property
    def _table(self) -> tuple[np.ndarray, np.ndarray]:
        """(z_sorted, theta_sorted) for inverting eq. (4) with np.interp."""
        return _height_table(self)

    @property
    def height_table(self) -> tuple[np.ndarray, np.ndarray]:
        """(z [mm] increasing, theta [deg]): the table that inverts eq. (4)."""
        return self._table

    @property
    def opens_upward(self) -> bool:
        """True when the valve opens as theta increases (supply-like)."""
        z, theta = self._table
        return bool(theta[-1] > theta[0])

    def angle_for_height(self, z_mm: np.ndarray | float) -> np.ndarray:
        """Invert eq. (4): cam angle [deg] at which the head height is ``z_mm``.

        Linear interpolation on a 0.05 deg table (the paper's ``interp1d``);
        heights outside the table are clipped to its ends.
        """
        z, theta = self._table
        return angle_for_height_core(z_mm, z, theta)


@lru_cache(maxsize=1)
def _table_grid() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cam angles [deg] eq. (4) is tabulated at, and their cosines and
    sines: the same for every geometry (a fit of the needle centre tabulates
    thousands), made once; read-only."""
    theta = np.linspace(*_TABLE_RANGE_DEG, _TABLE_POINTS)
    t = np.radians(theta)
    grid = (theta, np.cos(t), np.sin(t))
    for a in grid:
        a.flags.writeable = False
    return grid


@lru_cache(maxsize=256)
def _height_table(geometry: NeedleGeometry) -> tuple[np.ndarray, np.ndarray]:
    """(z [mm] increasing, theta [deg]) tabulating eq. (4) of ``geometry``,
    made once per distinct geometry (the value is the key: a fit that
    rebuilds its models at every step, e.g. discover's with z0 and C free,
    makes equal geometries many times). Shared: callers must not write to it.

    Raises
    ------
    ValueError
        eq. (4) is not monotonic over the table's range (not cached).
    """
    theta, cos_t, sin_t = _table_grid()
    g = geometry
    z = _needle_height_trig(cos_t, sin_t, g.needle_x_c_mm, g.needle_y_c_mm,
                            g.needle_head_radius_mm, g.cam_slope_deg, g.z_p_mm, g.z_c0_mm)
    dz = np.diff(z)
    if not (np.all(dz > 0) or np.all(dz < 0)):
        raise ValueError(
            "needle geometry: eq. (4) is not monotonic over "
            f"{_TABLE_RANGE_DEG} deg; check needle_x_c_mm/needle_y_c_mm")
    if dz[0] < 0:
        return z[::-1].copy(), theta[::-1].copy()
    return z, theta


def fluid_force_n(p1_mpa, dp_mpa, geometry: NeedleGeometry):
    """Fluid force lifting the needle, eq. (1): F_w = pi/4 (d_n^2 p1 - d_o^2 dp) [N]."""
    return fluid_force_core(np.asarray(p1_mpa), np.asarray(dp_mpa),
                            geometry.needle_diameter_mm, geometry.seat_diameter_mm)


def spring_force_n(z0_mm, z_c_mm, geometry: NeedleGeometry):
    """Disc-spring contact force, eq. (2): F_s = k (z0 - z_c) [N]."""
    return geometry.spring_constant_n_per_mm * (np.asarray(z0_mm) - np.asarray(z_c_mm))


def threshold_displacement_mm(z0_mm, p1_mpa, dp_mpa, geometry: NeedleGeometry):
    """Sealing-threshold spring displacement, eq. (3) [mm].

    z_c = z0 - pi/(4k) (d_n^2 p1 - d_o^2 dp): the needle seals while the
    cam-set head height stays below this value.
    """
    return threshold_displacement_core(np.asarray(z0_mm), fluid_force_n(p1_mpa, dp_mpa, geometry),
                                       geometry.spring_constant_n_per_mm)


def needle_height_mm(theta_deg, geometry: NeedleGeometry):
    """Needle-head height set by the cam, eq. (4) [mm].

    z_c = (x_c - r sin(phi) cos(theta)) tan(phi) cos(theta)
          - (y_c - r tan(phi) sin(theta)) tan(phi) sin(theta)
          + (z_p - r cos(phi)) - z_c0

    Notes
    -----
    The paper prints ``- (z_p - r cos phi)``; with Table II values that gives
    z_c of about -63.7 mm, far from the sub-millimetre spring deflections of
    eq. (3). The sign is a typo: with ``+`` the constant term is
    z_p - r cos(phi) - z_c0 = 0.003 mm, consistent with z_c0 being the head
    height at theta = 0. We use ``+``.
    """
    g = geometry
    return needle_height_core(np.asarray(theta_deg, dtype=float), g.needle_x_c_mm,
                              g.needle_y_c_mm, g.needle_head_radius_mm, g.cam_slope_deg,
                              g.z_p_mm, g.z_c0_mm)
