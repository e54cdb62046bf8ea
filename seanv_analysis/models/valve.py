"""Flow model of the SEANV (paper Sec. II-D, eq. 5-6), per side, and the
needles' seat leakage.

Units: cam angle deg, pressure MPa (gauge), flow mm^3/s.

Supply side: p1 = p_supply, p2 = p_head, opens for theta > theta_d, C > 0.
Drain side:  p1 = p_head,   p2 = p_tank, opens for theta < theta_d, C < 0
(flow out of the actuator is negative, as in the paper).

Seat leakage (not in the paper's eq. 5; the paper saw +-50 mm^3/s of it):
each needle leaks past its seat, open or sealed, laminar, g dp: into the
head through the supply needle, out of it through the drain needle, so the
head gets Q_leak = g (dp_supply - dp_drain) beside eq. (5)
(:func:`seat_leakage_mm3_s`). The simulator's plant and the flow fit call
the same law.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from .sealing import NeedleGeometry, threshold_displacement_mm

__all__ = ["SIDES", "ValveSide", "ValveModel", "side_pressures", "signed_power",
           "signed_power_core", "opening_core", "flow_core", "cam_for_flow_core", "MIN_DP_MPA",
           "seat_leakage_core", "seat_leakage_mm3_s", "SEAT_LEAK_KEY"]

#: a fitted :class:`ValveModel`'s seat-leakage conductance [mm^3/(s MPa)] in
#: its ``extras`` (flowfit and discover write it; eq. 5 itself does not use it)
SEAT_LEAK_KEY = "seat_leak_mm3_s_per_mpa"

SIDES = ("supply", "drain")

#: eq. (6) floors dp at this value [MPa] so a vanishing dp does not ask for infinity
MIN_DP_MPA = 0.05


# Scalar/array cores ---------------------------------------------------------
# Plain arithmetic on floats or numpy arrays: the numpy API below and the
# numba-compiled simulator/controllers (``sim.jit``) share this source.

def signed_power_core(x, exponent, smooth_mpa):
    """sign(x) |x|^n, linear (slope smooth^(n-1)) for |x| < ``smooth_mpa`` (> 0),
    exact when ``smooth_mpa`` is 0."""
    # x max(|x|, s)^(n-1): = sign(x)|x|^n for |x| >= s, x s^(n-1) below.
    # Branch-free, so it costs no allocation on scalars in compiled code; the
    # tiny floor keeps x = 0 at 0 when s = 0.
    return x * np.maximum(np.abs(x), max(smooth_mpa, 1e-300)) ** (exponent - 1.0)


def opening_core(theta_deg, theta_d_deg, opens_upward):
    """Opening past the sealing threshold [deg]: max(+-(theta - theta_d), 0)."""
    d = theta_deg - theta_d_deg
    return np.maximum(d if opens_upward else -d, 0.0)


def flow_core(opening_deg, dp_power, c_flow):
    """Eq. (5) on plain numbers: Q = C opening^2 dp^n [mm^3/s] (dp^n given)."""
    return c_flow * opening_deg * opening_deg * dp_power


def cam_for_flow_core(q_mm3_s, theta_d_deg, dp_power, c_flow, opens_upward):
    """Eq. (6) on plain numbers: theta = theta_d +- sqrt(Q / (C dp^n)) [deg];
    flows of the wrong sign give theta_d."""
    opening = np.sqrt(np.maximum(q_mm3_s / (c_flow * dp_power), 0.0))
    return theta_d_deg + opening if opens_upward else theta_d_deg - opening


def seat_leakage_core(conductance, dp_supply_mpa, dp_drain_mpa):
    """Seat leakage into the head on plain numbers [mm^3/s]:
    Q_leak = g (dp_supply - dp_drain), g [mm^3/(s MPa)] per needle."""
    return conductance * (dp_supply_mpa - dp_drain_mpa)


def seat_leakage_mm3_s(dp_supply_mpa, dp_drain_mpa, *, conductance_mm3_s_per_mpa: float):
    """Flow into the actuator head past both needles' seats [mm^3/s].

    Q_leak = g (dp_s - dp_d), dp_s = p_supply - p_head, dp_d = p_head - p_tank
    [MPa]: each needle, open or sealed, leaks g dp (laminar), the supply one
    into the head, the drain one out of it. It adds to eq. (5) of the open
    side; g is the rig's ``valve.plant.leakage_conductance_mm3_s_per_mpa``
    (``identify`` measures it).

    Examples
    --------
    >>> float(seat_leakage_mm3_s(1.7, 1.6, conductance_mm3_s_per_mpa=3.0))  # doctest: +ELLIPSIS
    0.29...
    """
    return seat_leakage_core(float(conductance_mm3_s_per_mpa), np.asarray(dp_supply_mpa, float),
                             np.asarray(dp_drain_mpa, float))


def side_pressures(side: str, p_supply_mpag, p_head_mpag, p_tank_mpag=0.0):
    """(p1, dp) of one side [MPa]: supply (p_s, p_s - p_h); drain (p_h, p_h - p_t)."""
    if side == "supply":
        return p_supply_mpag, np.subtract(p_supply_mpag, p_head_mpag)
    if side == "drain":
        return p_head_mpag, np.subtract(p_head_mpag, p_tank_mpag)
    raise ValueError(f"side: expected 'supply' or 'drain', got {side!r}")


def signed_power(x, exponent: float, *, smooth_mpa: float = 0.0):
    """sign(x) |x|^n, optionally smoothed near 0 (linear below ``smooth_mpa``).

    The smoothing keeps the slope finite at dp = 0 so a stiff integrator
    stays stable; at |x| >= smooth_mpa it equals the exact law.
    """
    x = np.asarray(x, dtype=float)
    return signed_power_core(x, float(exponent), float(smooth_mpa))


@dataclass(frozen=True)
class ValveSide:
    """One needle of the SEANV: sealing threshold (eq. 3-4) and flow law (eq. 5).

    Q = C (theta - theta_d)^2 dp^n with n = 0.5 in the paper.

    Attributes
    ----------
    side : 'supply' or 'drain'
    z0_mm : initial disc-spring deflection z_0 [mm] (fitted)
    c_flow : C [mm^3/(s deg^2 MPa^n)], negative on the drain side
    geometry : needle geometry (Table II + centre)
    dp_exponent : n, 0.5 for the orifice law
    """

    side: str
    z0_mm: float
    c_flow: float
    geometry: NeedleGeometry
    dp_exponent: float = 0.5

    def __post_init__(self):
        if self.side not in SIDES:
            raise ValueError(f"side: expected 'supply' or 'drain', got {self.side!r}")

    @property
    def opens_upward(self) -> bool:
        """True when theta > theta_d opens the valve (the supply side)."""
        return self.geometry.opens_upward

    def threshold_deg(self, p1_mpa, dp_mpa, *, z0_mm=None):
        """Sealing threshold angle theta_d [deg] from eq. (3) + (4) by interpolation."""
        z0 = self.z0_mm if z0_mm is None else z0_mm
        z_thr = threshold_displacement_mm(z0, p1_mpa, dp_mpa, self.geometry)
        return self.geometry.angle_for_height(z_thr)

    def opening_deg(self, theta_deg, p1_mpa, dp_mpa):
        """Opening past the threshold [deg]: max(theta - theta_d, 0) (supply),
        max(theta_d - theta, 0) (drain)."""
        return opening_core(np.asarray(theta_deg, dtype=float),
                            self.threshold_deg(p1_mpa, dp_mpa), self.opens_upward)

    def flow(self, theta_deg, p1_mpa, dp_mpa, *, smooth_mpa: float = 0.0):
        """Flow through this side, eq. (5): Q = C (theta - theta_d)^2 dp^n [mm^3/s].

        Zero when sealed. ``dp`` below 0 gives reverse flow (sign follows dp).
        """
        opening = self.opening_deg(theta_deg, p1_mpa, dp_mpa)
        return flow_core(opening, signed_power(dp_mpa, self.dp_exponent, smooth_mpa=smooth_mpa),
                         self.c_flow)

    def cam_for_flow(self, q_mm3_s, p1_mpa, dp_mpa, *, min_dp_mpa: float = MIN_DP_MPA):
        """Cam angle for a target flow, eq. (6): theta = theta_d +- sqrt(Q / (C dp^n)) [deg].

        '+' on the supply side, '-' on the drain side. Flows of the wrong sign
        for this side give theta_d (closed at the threshold). ``dp`` is
        floored at ``min_dp_mpa`` so a vanishing dp does not ask for infinity.
        """
        dp = np.maximum(np.asarray(dp_mpa, dtype=float), min_dp_mpa)
        return cam_for_flow_core(np.asarray(q_mm3_s, dtype=float), self.threshold_deg(p1_mpa, dp),
                                 dp ** self.dp_exponent, self.c_flow, self.opens_upward)

    def to_dict(self) -> dict[str, Any]:
        return {"z0_mm": float(self.z0_mm), "c_flow": float(self.c_flow),
                "dp_exponent": float(self.dp_exponent), "geometry": self.geometry.to_dict()}


@dataclass(frozen=True)
class ValveModel:
    """Both needles of the SEANV (eq. 3-6 per side) and the valid cam range [deg].

    What ``flowfit`` identifies and ``tracking``, ``validate`` and the
    controller use; :meth:`to_dict` / :meth:`from_dict` are the content of
    the model file (:mod:`seanv_analysis.io.model_file` reads and writes it).
    """

    supply: ValveSide
    drain: ValveSide
    cam_min_deg: float = -40.0
    cam_max_deg: float = 10.0
    extras: dict = field(default_factory=dict)

    @classmethod
    def from_rig(cls, rig: Any) -> "ValveModel":
        """The rig config's valve (the paper's fitted z0 and C by default).

        ``rig``: a :class:`~seanv_analysis.config.RigConfig`, or any object
        with ``rig["valve"]`` (Table II entries and, per side, ``z0_mm``,
        ``c_flow``, ``needle_x_c_mm``, ``needle_y_c_mm``) and
        ``rig.cam_range_deg`` (min, max) [deg].
        """
        sides = {}
        for side in SIDES:
            s = rig["valve"][side]
            sides[side] = ValveSide(side, float(s["z0_mm"]), float(s["c_flow"]),
                                    NeedleGeometry.from_rig(rig, side))
        lo, hi = rig.cam_range_deg
        return cls(sides["supply"], sides["drain"], lo, hi)

    def side(self, name: str) -> ValveSide:
        if name not in SIDES:
            raise ValueError(f"side: expected 'supply' or 'drain', got {name!r}")
        return getattr(self, name)

    def with_side(self, name: str, **changes) -> "ValveModel":
        """A copy with one side's parameters replaced (``z0_mm``, ``c_flow``, ...)."""
        return replace(self, **{name: replace(self.side(name), **changes)})

    def net_flow(self, theta_deg, p_supply_mpag, p_head_mpag, p_tank_mpag=0.0,
                 *, smooth_mpa: float = 0.0):
        """Flow into the actuator head [mm^3/s]: supply flow + drain flow (eq. 5 each)."""
        total = 0.0
        for side in SIDES:
            p1, dp = side_pressures(side, p_supply_mpag, p_head_mpag, p_tank_mpag)
            total = total + self.side(side).flow(theta_deg, p1, dp, smooth_mpa=smooth_mpa)
        return total

    def cam_for_flow(self, q_mm3_s, p_supply_mpag, p_head_mpag, p_tank_mpag=0.0):
        """Cam command for a target net flow, eq. (6), clipped to the cam range [deg].

        Q > 0 uses the supply side, Q < 0 the drain side, Q = 0 the supply
        threshold (closed).
        """
        q = np.asarray(q_mm3_s, dtype=float)
        p1s, dps = side_pressures("supply", p_supply_mpag, p_head_mpag, p_tank_mpag)
        p1d, dpd = side_pressures("drain", p_supply_mpag, p_head_mpag, p_tank_mpag)
        theta_s = self.supply.cam_for_flow(np.maximum(q, 0.0), p1s, dps)
        theta_d = self.drain.cam_for_flow(np.minimum(q, 0.0), p1d, dpd)
        theta = np.where(q >= 0, theta_s, theta_d)
        return np.clip(theta, self.cam_min_deg, self.cam_max_deg)

    # Serialisation ------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (schema ``seanv-valve-model/1``): cam range [deg],
        per side z0 [mm], C, n and the needle geometry; ``extras`` if any."""
        out = {"schema": "seanv-valve-model/1",
               "cam_range_deg": [float(self.cam_min_deg), float(self.cam_max_deg)],
               "supply": self.supply.to_dict(), "drain": self.drain.to_dict()}
        if self.extras:
            out["extras"] = self.extras
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any], *, rig: Any = None) -> "ValveModel":
        """Build from :meth:`to_dict` output (``C`` is accepted for ``c_flow``).
        A side without ``geometry`` (and a dict without ``cam_range_deg``)
        takes it from ``rig`` (as :meth:`from_rig` reads it).

        Raises
        ------
        KeyError, TypeError, ValueError
            a missing or malformed entry; ``ValueError`` also when something
            only ``rig`` could give is missing and no rig was given.
        """
        if rig is None and (any("geometry" not in d[s] for s in SIDES) or "cam_range_deg" not in d):
            raise ValueError("rig: the model lacks the needle geometry or cam range; pass the "
                             "rig config it belongs to")
        sides = {}
        for side in SIDES:
            s = d[side]
            geom = (NeedleGeometry(**s["geometry"]) if "geometry" in s
                    else NeedleGeometry.from_rig(rig, side))
            c = s.get("c_flow", s.get("C"))
            sides[side] = ValveSide(side, float(s["z0_mm"]), float(c), geom,
                                    float(s.get("dp_exponent", 0.5)))
        lo, hi = d["cam_range_deg"] if "cam_range_deg" in d else rig.cam_range_deg
        return cls(sides["supply"], sides["drain"], float(lo), float(hi),
                   dict(d.get("extras", {})))

