"""A "foreign rig": an independent generator of data-contract data sets.

This module does NOT use ``seanv_analysis.sim`` (nor the package's writer):
it has its own, deliberately different, plant and writes the run folders
itself, exactly as ``data-contract.md`` (``seanv-run/1``) describes. The only
package code it calls is the paper's sealing model (eq. 3-4, through
``seanv_analysis.models``) to place the sealing threshold theta_d, and the
flow-model inversion (eq. 6) used by the foreign controller; the paper's
Table II valve dimensions are read from the package's rig file (the needle
centres too, unless this rig brings its own: see below).

How the foreign rig differs from the built-in simulator
-------------------------------------------------------
- plant: no tube model, no actuator mass; the flow into the actuator follows
  the valve's steady flow (eq. 5 with this rig's z0 and C) through a
  first-order lag (``tau_flow_s``); the head pressure is quasi-static:
  (load force + Coulomb + viscous friction) / actuator area; at an end stop
  the flow stops and the head pressure relaxes to the supply (or tank)
  pressure;
- supply at 3.0 MPaG with a flow-dependent droop and a 33 Hz ripple;
  optional tank back pressure logged in ``p_tank_mpag``;
- sample rates: encoder 500 Hz or 2 kHz, pressure 200 Hz, servo 50 Hz,
  controller 50 Hz; every stream starts at its own instant (0..25 ms) and
  carries timestamp jitter; encoder quantised to 0.01 mm; pressure noise
  0.01 MPa; servo feedback quantised to the servo step, sometimes absent
  (empty ``cam_deg``);
- files: some tables are Parquet; extra columns (numbers and text) and
  unknown run.json fields; ``started_at`` with a +09:00 offset and
  fractional seconds; a few runs with ``load_mpag`` null;
- position control: P controller Q_ref = kp (x_ref - x) at 50 Hz, cam from
  eq. (6); the actual flow is the valve's flow at the cam command of
  ``delay_s`` earlier (a pure delay, no other dynamics in the flow path).

The defaults above are this rig as it always was (same seed, same files).

Opt-in: a rig that owns every constant the paper does not publish
-----------------------------------------------------------------
``ForeignTruth`` fields, all defaulting to the behaviour above, and
:func:`own_rig`, which sets every one of them away from the package's
``data_schema/rig/default.toml``:

- needle centres ``supply_x_c_mm``, ``supply_y_c_mm``, ``drain_x_c_mm``,
  ``drain_y_c_mm`` [mm] (None: the package default). Given, the valve uses a
  :class:`~seanv_analysis.models.NeedleGeometry` with the paper's Table II
  values (read from the rig file) and this centre, in eq. (3)-(4); the
  position controller's eq. (6) uses the same geometry (the lab knows its
  own valve). :meth:`ForeignTruth.geometry` gives the geometry in use.
- servo ``servo_dead_s``, ``servo_tau_s``, ``servo_rate_deg_s``: the goal is
  quantised to the servo step (360/4096 deg), delayed by the dead time T_d,
  then followed by a rate-limited first-order lag::

      theta(t + h) = theta + clip((g(t - T_d) - theta) h / tau, -r h, +r h)

  Used in flow steps always, and in position control when
  ``servo_in_position``: then the servo's goal is the controller's command
  ``delay_s`` ago (``delay_s`` is an extra pure delay, e.g. bus latency, and
  may be 0), the valve sees the servo's angle, and the logged ``cam_deg`` is
  that angle quantised (so it lags ``cam_cmd_deg`` by about
  ``delay_s + servo_dead_s + servo_tau_s``).
- between the servo and the needle, in position control only, what the cam
  feedback does not see: ``needle_delay_s`` (a pure delay) and
  ``cam_backlash_deg`` (total play; the needle lags half of it behind the
  servo in the direction it last moved). Both 0 by default.
- flow path ``flow_path``: ``"first_order"`` (above) or ``"tube"``, a lumped
  hydraulic line, in flow steps and position control alike. Its one state is
  the pressure p_l of the line volume at the valve port (compliance
  C_l = ``line_compliance_mm3_per_mpa``), joined to the actuator head through
  a resistance R_l = ``line_resistance_mpa_s_per_mm3``; the head pressure
  stays quasi-static (no actuator mass)::

      C_l dp_l/dt = Q_v(theta, p_s, p_l, p_t) + Q_leak - Q_a
      Q_a = (p_l - (F_load + s F_c) / A) / (R_l + b / A^2)   (moving, s = sign of motion)
      Q_a = 0                                                 (stuck, at an end stop)
      p_h = p_l - R_l Q_a,   dx/dt = Q_a / A

  Q_v is eq. (5) at the valve-port pressure, Q_leak = g_l (p_s - p_l)
  - g_l (p_l - p_t) (seat leakage, g_l = 1.5 mm^3/s/MPa per needle), F_c the Coulomb
  force, b the viscous coefficient, A the actuator area. The logged
  ``p_head_mpag`` is p_l (the sensor sits on the valve block), so eq. (5)
  holds at the logged pressures at every instant while the actuator's flow
  Q_a lags the valve's flow Q_v with the time constant
  ``C_l (R_l + b / A^2)`` (:meth:`ForeignTruth.flow_lag_s`, the valve taken
  as a flow source; its own pressure sensitivity g = dQ_v/dp_l ~ Q_v / (2 dp)
  shortens it by the factor 1 / (1 + g (R_l + b / A^2)): 5-20 % at large
  openings).
  This is not the package's model (a 3-segment R-I tube with compliance at
  the nodes, an actuator mass and Stribeck friction).
- friction ``static_n`` (breakaway force, None: no stiction). The actuator
  is stuck while |p A - F_load| <= F_s (F_s = ``static_n``; on the tube path
  with ``static_n`` None, F_s = F_c: a Coulomb dead band, no stick-slip);
  while stuck Q_a = 0 and the head pressure follows the valve through the
  line compliance (C_l dp/dt = Q_v + Q_leak: it climbs towards the supply or
  falls towards the tank pressure); it breaks away when the net force exceeds
  F_s and sticks again when its flow reaches zero (tube: when Q_a above
  changes sign; first-order path: when both the valve's and the lagged flow
  fall below A x 0.05 mm/s in the direction of motion; while it moves the
  head pressure is quasi-static as above, so it drops from the breakaway
  level to the quasi-static one at the instant of release). F_s > F_c
  gives stick-slip: a slow flow charges the line by (F_s - F_c)/A, the
  actuator jumps, stops, and waits again. End stops hold the actuator the
  same way (it only leaves them in the free direction).

Opt-in: effects outside discover's vocabulary
---------------------------------------------
Four more ``ForeignTruth`` fields, each None (off) by default, put into the
valve an effect that none of discover's named effects describes (for
testing a search for the missing term). Each is a dict naming its valve
side (``"side": "supply" | "drain"``) and acts in this generator's own
valve code (:class:`_Needle`, not the package's ``term`` effect), in flow
steps and position control alike. Q5 = C (theta - theta_d)^2 sqrt(dp) is
this rig's eq. (5) for the side (dp > 0), theta_d its eq. (3)-(4)
threshold, p_load the true (regulated) load pressure:

- ``dp_choke`` {"side", "dp_c_mpa", "n"}: the flow chokes above dp_c::

      Q = Q5 / (1 + (dp / dp_c)^n)^(1/n)

  (~Q5 for dp << dp_c; ~C (theta - theta_d)^2 sqrt(dp) dp_c / dp, falling
  with dp, for dp >> dp_c);
- ``load_c`` {"side", "k_per_mpa", "load_ref_mpag"}: a flow coefficient that
  depends on the load::

      C_eff = C (1 + k (p_load - load_ref))

- ``pressure_leak`` {"side", "k_mm3_s", "m"}: a leak past the needle that
  grows with the pressure difference, open or sealed::

      Q = Q5 + s k dp^m     (dp > 0; s = +1 supply, -1 drain; k [mm^3/s/MPa^m])

- ``approach_threshold`` {"side", "shift_deg"}: a sealing threshold that
  depends on the direction the cam reached its angle::

      theta_d -> theta_d + shift a

  a = +1 when the needle last moved up, -1 down (flow steps: before the log
  starts the cam came from the closed angle -12 deg; position control: 0
  until the needle first moves). In this rig's flow steps the supply cam
  always arrives moving up and the drain cam moving down unless
  ``approach_overshoot_deg`` > 0: then every odd repeat (``Step.repeat``)
  commands ``approach_overshoot_deg`` beyond its angle (away from the
  closed angle) for 0.3 s first, so it reaches the angle from the far side
  (the servo log shows it: the analysis's ``cam_approach`` is -1 on the
  supply side, +1 on the drain side for those runs).

Everything is seeded: the same arguments give the same files.
"""
from __future__ import annotations

import bisect
import json
import math
from dataclasses import asdict, dataclass, field
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

__all__ = ["ForeignTruth", "own_rig", "write_flowsteps", "write_position", "flowstep_plan",
           "ACTUATOR_AREA_MM2"]

ACTUATOR_AREA_MM2 = 201.06          # 16 mm bore
LOAD_AREA_MM2 = math.pi / 4 * 32.0 ** 2   # pneumatic load piston (full bore)
SERVO_STEP_DEG = 0.087890625        # 360/4096
FLOW_PATHS = ("first_order", "tube")
LEAK_MM3_S_PER_MPA = 1.5            # seat leakage of each needle, open or sealed
STICK_V_MM_S = 0.05                 # first-order path: sticks again below this speed
SUPPLY_DROOP_MPA_S_PER_MM3 = 2.0e-5  # the supply falls 0.1 MPa at 5000 mm^3/s drawn
CAM_NEUTRAL_DEG = -15.0             # controller without flow model: the paper's neutral ...
CAM_KP_DEG_PER_MM = 8.0             # ... and a gain this rig's loop is stable with
JST = timezone(timedelta(hours=9))
CAM_CLOSED_DEG = -12.0              # flow steps: both needles sealed here on this rig
OVERSHOOT_S = 0.3                   # flow steps: time at the far-side angle (opt-in)
#: the out-of-vocabulary valve effects: field, its keys besides "side", the
#: keys that must be > 0
_VALVE_EFFECTS = (("dp_choke", ("dp_c_mpa", "n"), ("dp_c_mpa", "n")),
                  ("load_c", ("k_per_mpa", "load_ref_mpag"), ()),
                  ("pressure_leak", ("k_mm3_s", "m"), ("m",)),
                  ("approach_threshold", ("shift_deg",), ()))


@dataclass
class ForeignTruth:
    """The foreign rig's true valve and plant parameters."""

    supply_z0_mm: float = -0.12
    supply_c: float = 15.0
    drain_z0_mm: float = -0.05
    drain_c: float = -20.0
    tau_flow_s: float = 0.15
    delay_s: float = 0.30
    supply_mpag: float = 3.0
    coulomb_n: float = 30.0
    viscous_n_s_per_mm: float = 0.4
    stroke_mm: float = (2.0, 72.0)  # type: ignore[assignment]
    drift: dict | None = None       # {"side": "drain", "step": 0.02, "every": 3}
    # both sides' C x (1 + a sin(2 pi i / period)): a wear/temperature pattern
    # that comes and goes, which no candidate effect describes
    c_modulation: dict | None = None  # {"amplitude": 0.08, "period_runs": 30}
    # --- opt-in: constants the paper does not publish (module docstring) ---
    # needle-head centres [mm]; None = the package's default.toml value
    supply_x_c_mm: float | None = None
    supply_y_c_mm: float | None = None
    drain_x_c_mm: float | None = None
    drain_y_c_mm: float | None = None
    # servo: dead time, first-order lag, rate limit (flow steps; position
    # control too when servo_in_position)
    servo_dead_s: float = 0.02
    servo_tau_s: float = 0.04
    servo_rate_deg_s: float = 300.0
    servo_in_position: bool = False
    # "first_order" (tau_flow_s in flow steps, instantaneous in position
    # control) or "tube" (lumped line C_l, R_l in both)
    flow_path: str = "first_order"
    line_compliance_mm3_per_mpa: float = 2000.0
    line_resistance_mpa_s_per_mm3: float = 4.5e-5
    # breakaway force [N]; None = no stiction
    static_n: float | None = None
    # position control only, effects the cam feedback does not see: a pure
    # delay between the servo's (logged) angle and the needle, and a play of
    # this total width between them (the needle lags width/2 behind the servo
    # in the direction it last moved)
    needle_delay_s: float = 0.0
    cam_backlash_deg: float = 0.0
    # --- opt-in: effects outside discover's vocabulary (module docstring);
    # None = off; each names its valve side ("side": "supply" | "drain")
    dp_choke: dict | None = None            # {"side": "supply", "dp_c_mpa": 1.5, "n": 4.0}
    load_c: dict | None = None              # {"side": "drain", "k_per_mpa": 1.0,
    #                                          "load_ref_mpag": 0.3}
    pressure_leak: dict | None = None       # {"side": "supply", "k_mm3_s": 60.0, "m": 2.0}
    approach_threshold: dict | None = None  # {"side": "supply", "shift_deg": 0.6}
    # flow steps: odd repeats overshoot their angle by this much first (0: never)
    approach_overshoot_deg: float = 0.0
    runs: list = field(default_factory=list)

    def __post_init__(self):
        if self.flow_path not in FLOW_PATHS:
            raise ValueError(f"flow_path: expected one of {FLOW_PATHS}, got {self.flow_path!r}")
        if self.static_n is not None and self.static_n < self.coulomb_n:
            raise ValueError(f"static_n ({self.static_n} N) must be >= coulomb_n "
                             f"({self.coulomb_n} N)")
        if min(self.servo_tau_s, self.servo_rate_deg_s, self.line_compliance_mm3_per_mpa,
               self.line_resistance_mpa_s_per_mm3) <= 0 or self.servo_dead_s < 0 \
                or min(self.delay_s, self.needle_delay_s, self.cam_backlash_deg) < 0:
            raise ValueError("servo/line constants must be > 0 (dead times, delays and play "
                             ">= 0)")
        for name, keys, positive in _VALVE_EFFECTS:
            d = getattr(self, name)
            if d is None:
                continue
            if not isinstance(d, dict) or d.get("side") not in ("supply", "drain") \
                    or set(d) != {"side", *keys}:
                raise ValueError(f"{name}: expected {{'side': 'supply' | 'drain', "
                                 f"{', '.join(repr(k) + ': number' for k in keys)}}}, got {d!r}")
            for k in positive:
                if not float(d[k]) > 0:
                    raise ValueError(f"{name}: {k}: expected > 0, got {d[k]!r}")
        if self.approach_overshoot_deg < 0:
            raise ValueError(f"approach_overshoot_deg: expected >= 0, got "
                             f"{self.approach_overshoot_deg!r}")

    @property
    def _simple_plant(self) -> bool:
        """True for the original plant loops (first-order path, no stiction)."""
        return self.flow_path == "first_order" and self.static_n is None

    def geometry(self, side: str):
        """The :class:`~seanv_analysis.models.NeedleGeometry` this rig's
        ``side`` valve uses: the rig file's Table II values and centre, the
        centre replaced by this truth's ``<side>_x_c_mm`` / ``_y_c_mm`` when
        given."""
        from seanv_analysis.config import load_rig
        from seanv_analysis.models import NeedleGeometry

        g = NeedleGeometry.from_rig(load_rig(), side)
        xc, yc = getattr(self, f"{side}_x_c_mm"), getattr(self, f"{side}_y_c_mm")
        if xc is None and yc is None:
            return g
        d = g.to_dict()
        d["needle_x_c_mm"] = float(d["needle_x_c_mm"] if xc is None else xc)
        d["needle_y_c_mm"] = float(d["needle_y_c_mm"] if yc is None else yc)
        return NeedleGeometry(**d)

    def servo_lag_s(self) -> float:
        """Servo dead time + time constant [s] (small steps, below the rate limit)."""
        return self.servo_dead_s + self.servo_tau_s

    def flow_lag_s(self, kind: str = "position_control") -> float:
        """Equivalent first-order time constant [s] of the flow path from the
        valve's flow to the actuator's flow in ``kind`` runs ('flow_step' or
        'position_control'): ``tau_flow_s`` in first-order flow steps, 0 in
        first-order position control (instantaneous), C_l (R_l + b / A^2)
        on the tube path (the valve taken as a flow source)."""
        if kind not in ("flow_step", "position_control"):
            raise ValueError(f"kind: expected 'flow_step' or 'position_control', got {kind!r}")
        if self.flow_path == "tube":
            return self.line_compliance_mm3_per_mpa * (
                self.line_resistance_mpa_s_per_mm3
                + self.viscous_n_s_per_mm / ACTUATOR_AREA_MM2 ** 2)
        return self.tau_flow_s if kind == "flow_step" else 0.0

    def position_lag_s(self) -> float:
        """Expected lag [s] of the actual flow behind the controller's command
        in position control: pure delay + servo (when in the loop) + flow path."""
        servo = self.servo_lag_s() if self.servo_in_position else 0.0
        return self.delay_s + servo + self.flow_lag_s("position_control")

    def to_json_dict(self) -> dict:
        d = asdict(self)
        d["stroke_mm"] = list(self.stroke_mm)
        d["needle_geometry"] = {s: self.geometry(s).to_dict() for s in ("supply", "drain")}
        d["flow_lag_s"] = {k: self.flow_lag_s(k) for k in ("flow_step", "position_control")}
        d["servo_lag_s"] = self.servo_lag_s()
        d["position_lag_s"] = self.position_lag_s()
        return d


def own_rig(**over) -> ForeignTruth:
    """A foreign rig whose every unpublished constant differs from the
    package's ``default.toml`` (``over``: field overrides).

    ====================  ======================  ======================
    constant              default.toml            this rig
    ====================  ======================  ======================
    supply centre x, y    -7.10, -20 mm           -4.0, -28.0 mm
    drain centre x, y     -9.30, +20 mm           -8.0, +13.0 mm
    servo dead, tau, rate 0.03 s, 0.07 s, 240/s   0.05 s, 0.03 s, 180/s
    flow path             3-segment tube, B 150   lumped line, lag 0.12 s
    friction C, S, visc.  155 N, 160 N, 2 N s/mm  40 N, 55 N, 0.6 N s/mm
    ====================  ======================  ======================

    Servo in the position loop, no extra pure delay. The centres put the
    sealing thresholds at this rig's pressures (supply 3.0 MPaG, loads
    0.1-0.5 MPaG) at about -10 .. -8 deg (supply) and -21 .. -18 deg (drain),
    so the default flow-step angles open the valves; and their slope over the
    pressure range differs from the default geometry's enough that no z0 makes
    the default geometry fit (max residual ~0.4 deg per side).
    """
    kw = dict(supply_x_c_mm=-4.0, supply_y_c_mm=-28.0, drain_x_c_mm=-8.0, drain_y_c_mm=13.0,
              servo_dead_s=0.05, servo_tau_s=0.03, servo_rate_deg_s=180.0,
              servo_in_position=True, delay_s=0.0, flow_path="tube",
              line_compliance_mm3_per_mpa=2000.0, line_resistance_mpa_s_per_mm3=4.5e-5,
              coulomb_n=40.0, static_n=55.0, viscous_n_s_per_mm=0.6)
    kw.update(over)
    return ForeignTruth(**kw)


# ---------------------------------------------------------------------------
# valve: eq. (5) with theta_d from the paper's sealing model (eq. 3-4)
# ---------------------------------------------------------------------------

class _Needle:
    """One needle with scalar (fast) threshold and flow functions."""

    def __init__(self, side: str, z0_mm: float, c: float, geometry=None):
        if geometry is None:
            from seanv_analysis.config import load_rig
            from seanv_analysis.models import NeedleGeometry

            geometry = NeedleGeometry.from_rig(load_rig(), side)
        g = self.geometry = geometry
        self.side, self.z0, self.c = side, float(z0_mm), float(c)
        self.dn2, self.do2, self.k = g.needle_diameter_mm ** 2, g.seat_diameter_mm ** 2, \
            g.spring_constant_n_per_mm
        z, th = g.height_table
        self.z_tab, self.th_tab = np.asarray(z), np.asarray(th)
        self._zl, self._tl = self.z_tab.tolist(), self.th_tab.tolist()   # for _theta_d1
        self.up = g.opens_upward
        self.choke = self.load_c = self.leak = self.shift = None
        self.plain = True

    def set_effects(self, tr: "ForeignTruth") -> "_Needle":
        """Take this side's out-of-vocabulary effects from ``tr`` (module
        docstring); none: :meth:`flow1` is the plain eq. (5)."""
        def mine(d):
            return d if d is not None and d["side"] == self.side else None

        self.choke, self.load_c = mine(tr.dp_choke), mine(tr.load_c)
        self.leak, self.shift = mine(tr.pressure_leak), mine(tr.approach_threshold)
        self.plain = all(e is None for e in (self.choke, self.load_c, self.leak, self.shift))
        return self

    def theta_d(self, p1, dp, z0=None):
        """Sealing threshold [deg], eq. (1)+(3) then eq. (4) inverted (table)."""
        z0 = self.z0 if z0 is None else z0
        fw = math.pi / 4 * (self.dn2 * np.asarray(p1) - self.do2 * np.asarray(dp))
        return np.interp(z0 - fw / self.k, self.z_tab, self.th_tab)

    def flow(self, theta, p1, dp, c=None):
        """Eq. (5): C (theta - theta_d)^2 sqrt(dp), zero when sealed or dp <= 0."""
        c = self.c if c is None else c
        d = np.asarray(theta, float) - self.theta_d(p1, dp)
        opening = np.maximum(d if self.up else -d, 0.0)
        return c * opening ** 2 * np.sqrt(np.maximum(np.asarray(dp, float), 0.0))

    def flow1(self, theta: float, p1: float, dp: float, c: float, load: float = 0.0,
              approach: float = 0.0) -> float:
        """Scalar :meth:`flow` (pure Python, for the time-stepping loops);
        with this side's out-of-vocabulary effects (:meth:`set_effects`),
        which read the true load pressure ``load`` [MPaG] and the cam's
        ``approach`` direction (+1 up, -1 down, 0 unknown)."""
        if not self.plain:
            return self._flow1_effects(theta, p1, dp, c, load, approach)
        if dp <= 0.0:
            return 0.0
        th = self._theta_d1(p1, dp)
        d = theta - th if self.up else th - theta
        return c * d * d * math.sqrt(dp) if d > 0.0 else 0.0

    def _theta_d1(self, p1: float, dp: float) -> float:
        """Scalar :meth:`theta_d` [deg]."""
        z = self.z0 - math.pi / 4 * (self.dn2 * p1 - self.do2 * dp) / self.k
        zt, tt = self._zl, self._tl
        j = bisect.bisect_right(zt, z)
        if j <= 0:
            return tt[0]
        if j >= len(zt):
            return tt[-1]
        z0, z1 = zt[j - 1], zt[j]
        return tt[j - 1] + (tt[j] - tt[j - 1]) * (z - z0) / (z1 - z0)

    def _flow1_effects(self, theta, p1, dp, c, load, approach) -> float:
        """:meth:`flow1` with the effects of the module docstring."""
        q = 0.0
        if dp <= 0.0:
            return q
        if self.leak is not None:   # past the needle, open or sealed
            q += (1.0 if self.side == "supply" else -1.0) * self.leak["k_mm3_s"] * \
                dp ** self.leak["m"]
        th = self._theta_d1(p1, dp)
        if self.shift is not None:
            th += self.shift["shift_deg"] * approach
        d = theta - th if self.up else th - theta
        if d <= 0.0:
            return q
        if self.load_c is not None:
            c = c * (1.0 + self.load_c["k_per_mpa"] * (load - self.load_c["load_ref_mpag"]))
        q5 = c * d * d * math.sqrt(dp)
        if self.choke is not None:
            n = self.choke["n"]
            q5 /= (1.0 + (dp / self.choke["dp_c_mpa"]) ** n) ** (1.0 / n)
        return q + q5


# ---------------------------------------------------------------------------
# sampling and writing
# ---------------------------------------------------------------------------

def _stamps(rng, t_end: float, rate_hz: float, *, jitter: float, start_max_s: float = 0.025,
            end_trim_s: float = 0.0) -> np.ndarray:
    """Sample instants of one stream: own start offset, +-jitter (fraction of dt)."""
    dt = 1.0 / rate_hz
    t0 = rng.uniform(0.0, start_max_s)
    n = int(math.floor((t_end - end_trim_s - t0) / dt)) + 1
    t = t0 + dt * np.arange(n) + rng.uniform(-jitter, jitter, n) * dt
    t[0] = max(t[0], 0.0)
    return np.round(t, 6)


def _write_table(path_stem: Path, df: pd.DataFrame, fmt: str) -> None:
    if fmt == "parquet":
        pq.write_table(pa.Table.from_pandas(df, preserve_index=False),
                       path_stem.with_suffix(".parquet"))
    else:
        path_stem.with_suffix(".csv").write_text(_csv_text(df))


def _csv_text(df: pd.DataFrame) -> str:
    """The CSV text of ``df`` as ``to_csv(index=False, float_format="%.6g",
    na_rep="")`` writes it, with the timestamps to the microsecond (%.6g
    would cut them), built column by column (to_csv formats value by value
    through pandas' string arrays, several times slower). Text columns are
    written as they are: this rig's never hold a comma, quote or newline."""
    cols = []
    for name in df.columns:
        values = df[name].tolist()
        kind = df[name].dtype.kind
        if name == "t_s":
            cols.append([f"{v:.6f}" for v in values])
        elif kind == "f":
            cols.append(["%.6g" % v if v == v else "" for v in values])
        elif kind in "iub":
            cols.append([str(v) for v in values])
        else:
            text = [str(v) for v in values]
            if any(c in v for v in text for c in ',"\n\r'):
                raise ValueError(f"column {name!r}: text to quote; use to_csv")
            cols.append(text)
    lines = [",".join(df.columns)] + [",".join(row) for row in zip(*cols)]
    return "\n".join(lines) + "\n"


def _write_run(run_dir: Path, meta: dict, tables: dict[str, pd.DataFrame],
               formats: dict[str, str]) -> None:
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "run.json").write_text(json.dumps(meta, indent=2))
    for name, df in tables.items():
        fmt = formats.get(name, "csv")
        _write_table(run_dir / name, df, fmt)


def _iso(t: datetime) -> str:
    return t.astimezone(JST).isoformat(timespec="milliseconds")


# ---------------------------------------------------------------------------
# flow-step runs
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Step:
    side: str
    cam_deg: float
    load_mpag: float
    repeat: int


def flowstep_plan(*, supply_cams: Sequence[float] = (-5.0, 0.0, 5.0, 10.0),
                  drain_cams: Sequence[float] = (-40.0, -35.0, -30.0, -25.0, -20.0),
                  loads: Sequence[float] = (0.1, 0.2, 0.3, 0.4, 0.5), repeats: int = 3
                  ) -> list[Step]:
    """The foreign protocol in time order: per load, per repeat, the drain
    sweep (high to low opening) then the supply sweep (low to high)."""
    out = []
    for load in loads:
        for rep in range(repeats):
            out += [Step("drain", float(c), float(load), rep) for c in sorted(drain_cams)]
            out += [Step("supply", float(c), float(load), rep) for c in sorted(supply_cams)]
    return out


def _head_pressure(load_mpag: float, v_mm_s: float, tr: ForeignTruth) -> float:
    """Quasi-static head pressure: (load + Coulomb + viscous) / area [MPaG]."""
    f = (load_mpag * LOAD_AREA_MM2 + tr.coulomb_n * math.tanh(v_mm_s / 0.3)
         + tr.viscous_n_s_per_mm * v_mm_s)
    return f / ACTUATOR_AREA_MM2


def _servo_track(t: np.ndarray, cmd: np.ndarray, *, dead_s=0.02, tau_s=0.04,
                 rate_deg_s=300.0) -> np.ndarray:
    """Servo angle on the fine grid t: goal quantised to the servo step (as a
    position-controlled servo does), dead time, rate limit, first-order lag."""
    cmd = np.round(np.asarray(cmd, float) / SERVO_STEP_DEG) * SERVO_STEP_DEG
    h = float(t[1] - t[0])
    nd = int(round(dead_s / h))
    c = np.concatenate((np.full(nd, cmd[0]), cmd[:cmd.size - nd])) if nd else cmd
    out = np.empty_like(cmd)
    y = cmd[0]
    a = h / tau_s
    for i in range(cmd.size):
        dy = a * (c[i] - y)
        lim = rate_deg_s * h
        y += min(max(dy, -lim), lim)
        out[i] = y
    return out


class _Servo:
    """:func:`_servo_track` one step at a time (for the position loop)."""

    def __init__(self, tr: ForeignTruth, h: float, theta0: float):
        self.nd = int(round(tr.servo_dead_s / h))
        self.a, self.lim = h / tr.servo_tau_s, tr.servo_rate_deg_s * h
        self.y = round(theta0 / SERVO_STEP_DEG) * SERVO_STEP_DEG
        self.goals = [self.y] * self.nd     # goals in flight (dead time)
        self.k = 0

    def step(self, goal: float) -> float:
        """The servo angle after one step towards ``goal`` [deg]."""
        g = round(goal / SERVO_STEP_DEG) * SERVO_STEP_DEG
        if self.nd:
            c, self.goals[self.k] = self.goals[self.k], g
            self.k = (self.k + 1) % self.nd
        else:
            c = g
        self.y += min(max(self.a * (c - self.y), -self.lim), self.lim)
        return self.y


class _Plant:
    """Actuator + flow path of the opt-in modes (``flow_path='tube'`` or
    ``static_n`` given), one step at a time; the equations are in the module
    docstring. ``tau_s``: the first-order lag (first-order path; 0 =
    instantaneous). ``p`` is the logged head pressure (the line pressure on
    the tube path), ``q`` the actuator's flow, ``qv`` the valve's (leakage
    included)."""

    def __init__(self, tr: ForeignTruth, needles: dict, *, x: float, load_mpag: float,
                 tau_s: float, approach: float = 0.0):
        self.tr, self.tube, self.tau = tr, tr.flow_path == "tube", float(tau_s)
        self.sup, self.drn = needles["supply"], needles["drain"]
        self.fs = tr.static_n if tr.static_n is not None else tr.coulomb_n
        self.stiction = self.tube or tr.static_n is not None
        self.cl = tr.line_compliance_mm3_per_mpa
        self.rl = tr.line_resistance_mpa_s_per_mm3
        self.r_eff = self.rl + tr.viscous_n_s_per_mm / ACTUATOR_AREA_MM2 ** 2
        self.lo, self.hi = tr.stroke_mm
        self.x, self.q, self.qv, self.s = float(x), 0.0, 0.0, 0
        self.p = load_mpag * LOAD_AREA_MM2 / ACTUATOR_AREA_MM2
        self.stuck = True
        # direction the needle last moved (the approach_threshold effect)
        self.cam, self.approach = None, float(approach)

    def _valve(self, cam, ps, p, p_tank, cs, cd, load=0.0):
        a = self.approach
        return (self.sup.flow1(cam, ps, ps - p, cs, load, a)
                + self.drn.flow1(cam, p, p - p_tank, cd, load, a)
                + LEAK_MM3_S_PER_MPA * (ps - p) - LEAK_MM3_S_PER_MPA * (p - p_tank))

    def _breakaway(self, f_load: float) -> None:
        """Stuck: leave when the net force exceeds F_s, in a free direction."""
        f = self.p * ACTUATOR_AREA_MM2 - f_load
        if f > self.fs and self.x < self.hi:
            self.stuck, self.s = False, 1
        elif f < -self.fs and self.x > self.lo:
            self.stuck, self.s = False, -1

    def step(self, cam: float, ps: float, p_tank: float, load_mpag: float, h: float,
             cs: float, cd: float) -> None:
        tr, area = self.tr, ACTUATOR_AREA_MM2
        f_load = load_mpag * LOAD_AREA_MM2
        if self.cam is not None and cam != self.cam:
            self.approach = 1.0 if cam > self.cam else -1.0
        self.cam = cam
        if self.tube:
            if self.stuck:
                self._breakaway(f_load)
            qa = 0.0
            if not self.stuck:
                qa = (self.p - (f_load + self.s * tr.coulomb_n) / area) / self.r_eff
                if qa * self.s <= 0.0:
                    self.stuck, qa = True, 0.0
            self.qv = self._valve(cam, ps, self.p, p_tank, cs, cd, load_mpag)
            self.p += (self.qv - qa) * h / self.cl   # actuator side: p - R_l qa
        else:
            if self.stuck and self.stiction:
                self._breakaway(f_load)
                if not self.stuck:   # released: quasi-static again, flow from rest
                    self.q = 0.0
            if self.stuck and self.stiction:
                qa = 0.0
                self.qv = self._valve(cam, ps, self.p, p_tank, cs, cd, load_mpag)
                self.p += self.qv * h / self.cl
            else:
                self.p = _head_pressure(load_mpag, self.q / area, tr)
                self.qv = self._valve(cam, ps, self.p, p_tank, cs, cd, load_mpag)
                if self.tau > 0.0:
                    self.q += (self.qv - self.q) * h / self.tau
                else:
                    self.q = self.qv
                qa = self.q
                # sticks again once both the valve's and the lagged flow died out
                if self.stiction and max(qa * self.s, self.qv * self.s) < STICK_V_MM_S * area:
                    self.stuck, qa = True, 0.0
        self.p = min(max(self.p, min(p_tank, 0.0) - 0.05), ps + 0.05)
        self.q = qa
        x = self.x + qa / area * h
        if x >= self.hi or x <= self.lo:   # end stop: held there like a stuck actuator
            x = min(max(x, self.lo), self.hi)
            self.q, self.stuck = 0.0, True
        self.x = x


def _simulate_step(step: Step, tr: ForeignTruth, needles: dict[str, _Needle], c_now: dict,
                   rng, *, h: float = 1e-3, p_tank: float = 0.0):
    """Fine-grid (1 kHz) true signals of one flow step."""
    closed = CAM_CLOSED_DEG  # both needles sealed here on this rig
    direct = rng.random() < 0.25           # log starts already at the angle
    pre = 0.0 if direct else rng.uniform(0.3, 0.6)
    hold = rng.uniform(2.2, 2.8)
    post = 0.3
    t = np.arange(0.0, pre + hold + post + 0.05, h)
    cmd = np.where(t < pre, closed, step.cam_deg)
    cmd = np.where(t >= pre + hold, closed, cmd)
    # the direction the cam comes from (before the log: the closed angle)
    approach0 = 1.0 if step.cam_deg >= closed else -1.0
    if tr.approach_overshoot_deg > 0 and step.repeat % 2 == 1 and not direct:
        # reach the angle from the far side: overshoot first (opt-in)
        far = step.cam_deg + approach0 * tr.approach_overshoot_deg
        cmd = np.where((t >= pre) & (t < pre + OVERSHOOT_S), far, cmd)
    cam = _servo_track(t, cmd.astype(float), dead_s=tr.servo_dead_s, tau_s=tr.servo_tau_s,
                       rate_deg_s=tr.servo_rate_deg_s)
    lo, hi = tr.stroke_mm
    x = lo + 1.0 if step.side == "supply" else hi - 1.0
    q = 0.0
    at_stop = False
    ph_stop = None
    n = t.size
    X, Q, PS, PH = (np.empty(n) for _ in range(4))
    sup, drn = needles["supply"], needles["drain"]
    ripple_phase = rng.uniform(0, 2 * math.pi)
    cs, cd = c_now["supply"], c_now["drain"]
    cam = cam.tolist()
    t_l = t.tolist()
    if not tr._simple_plant:
        plant = _Plant(tr, needles, x=x, load_mpag=step.load_mpag,
                       tau_s=tr.tau_flow_s, approach=approach0)
        for i in range(n):
            ps = tr.supply_mpag - SUPPLY_DROOP_MPA_S_PER_MM3 * max(plant.qv, 0.0) \
                + 0.02 * math.sin(2 * math.pi * 33.0 * t_l[i] + ripple_phase)
            plant.step(cam[i], ps, p_tank, step.load_mpag, h, cs, cd)
            X[i], Q[i], PS[i], PH[i] = plant.x, plant.q, ps, plant.p
        return t, cmd, np.asarray(cam), X, Q, PS, PH
    v = 0.0
    track = tr.approach_threshold is not None
    approach, cam_prev = approach0, cam[0]
    load = step.load_mpag
    for i in range(n):
        v = q / ACTUATOR_AREA_MM2
        ps = tr.supply_mpag - SUPPLY_DROOP_MPA_S_PER_MM3 * max(q, 0.0) \
            + 0.02 * math.sin(2 * math.pi * 33.0 * t_l[i] + ripple_phase)
        if at_stop:
            target = ps if step.side == "supply" else p_tank
            ph_stop += (target - ph_stop) * h / 0.05
            ph = ph_stop
        else:
            ph = _head_pressure(step.load_mpag, v, tr)
        ci = cam[i]
        if track and ci != cam_prev:
            approach, cam_prev = (1.0 if ci > cam_prev else -1.0), ci
        qs = sup.flow1(ci, ps, ps - ph, cs, load, approach) + \
            drn.flow1(ci, ph, ph - p_tank, cd, load, approach)
        # seat leakage of both needles (open or sealed): a few mm^3/s, not in eq. (5)
        qs += 1.5 * (ps - ph) - 1.5 * (ph - p_tank)
        if not at_stop:
            q += (qs - q) * h / tr.tau_flow_s
            x += q / ACTUATOR_AREA_MM2 * h
            if x >= hi or x <= lo:
                x = min(max(x, lo), hi)
                at_stop, ph_stop, q = True, ph, 0.0
        X[i], Q[i], PS[i], PH[i] = x, q, ps, ph
    return t, cmd, np.asarray(cam), X, Q, PS, PH


def _flowstep_tables(step, t, cmd, cam, X, PS, PH, load_true, p_tank, rng, *,
                     enc_rate, feedback: bool, tank_column: bool):
    t_end = float(t[-1])
    te = _stamps(rng, t_end, enc_rate, jitter=0.04)
    tp = _stamps(rng, t_end, 200.0, jitter=0.02, end_trim_s=rng.uniform(0, 0.02))
    tsv = _stamps(rng, t_end, 50.0, jitter=0.01, end_trim_s=rng.uniform(0, 0.03))
    pos = np.interp(te, t, X)
    pos = np.round(pos / 0.01) * 0.01
    enc = pd.DataFrame({"t_s": te, "position_mm": pos,
                        "sample_no": np.arange(te.size, dtype=np.int64)})
    noise = 0.01
    pres = pd.DataFrame({
        "t_s": tp,
        "p_supply_mpag": np.interp(tp, t, PS) + rng.normal(0, noise, tp.size),
        "p_head_mpag": np.interp(tp, t, PH) + rng.normal(0, noise, tp.size),
        "p_load_mpag": load_true + rng.normal(0, noise / 2, tp.size),
    })
    if tank_column:
        pres["p_tank_mpag"] = p_tank + rng.normal(0, noise / 2, tp.size)
    pres["oil_temp_c"] = 21.5 + rng.normal(0, 0.05, tp.size)
    # the servo logs the command in force at its sample instant
    cmd_s = cmd[np.clip(np.searchsorted(t, tsv, side="right") - 1, 0, t.size - 1)]
    fb = np.round(np.interp(tsv, t, cam) / SERVO_STEP_DEG) * SERVO_STEP_DEG
    fb = fb + SERVO_STEP_DEG * rng.choice([-1, 0, 0, 0, 0, 0, 1], tsv.size)
    servo = pd.DataFrame({"t_s": tsv, "cam_cmd_deg": cmd_s,
                          "cam_deg": fb if feedback else np.full(tsv.size, np.nan),
                          "status": np.where(feedback, "ok", "nofb").repeat(tsv.size)})
    return {"encoder": enc, "pressure": pres, "servo": servo}


def _start(out, truth, seed_key):
    """(truth, output folder created, seeded rng, the two needles) of a writer."""
    tr = truth or ForeignTruth()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    needles = {"supply": _Needle("supply", tr.supply_z0_mm, tr.supply_c,
                                 tr.geometry("supply")).set_effects(tr),
               "drain": _Needle("drain", tr.drain_z0_mm, tr.drain_c,
                                tr.geometry("drain")).set_effects(tr)}
    return tr, out, np.random.default_rng(seed_key), needles


def write_flowsteps(out: str | Path, *, plan: Iterable[Step] | None = None, seed: int = 0,
                    truth: ForeignTruth | None = None, start: datetime | None = None,
                    name_prefix: str = "B", trace: bool = False) -> ForeignTruth:
    """Write flow-step runs of the foreign rig under ``out``; return the truth.

    ``truth.drift`` = {"side": ..., "step": s, "every": k} multiplies that
    side's C by (1 - s)^floor(i / k), i = the run's 0-based position in time
    order among all runs written here.
    """
    tr, out, rng, needles = _start(out, truth, [seed, 0xF0E1])
    steps = list(plan) if plan is not None else flowstep_plan()
    t_wall = start or datetime(2026, 5, 11, 1, 14, 5, 250000, tzinfo=timezone.utc)
    for i, step in enumerate(steps):
        c_now = {"supply": tr.supply_c, "drain": tr.drain_c}
        if tr.drift:
            s = tr.drift["side"]
            c_now[s] *= (1.0 - tr.drift["step"]) ** math.floor(i / tr.drift["every"])
        if tr.c_modulation:
            f = 1.0 + tr.c_modulation["amplitude"] * math.sin(
                2.0 * math.pi * i / tr.c_modulation["period_runs"])
            c_now = {k: v * f for k, v in c_now.items()}
        p_tank = float(rng.choice([0.0, 0.0, 0.03, 0.05]))
        tank_column = p_tank > 0 or rng.random() < 0.3
        load_true = step.load_mpag + rng.normal(0, 0.003)
        t, cmd, cam, X, Q, PS, PH = _simulate_step(step, tr, needles, c_now, rng, p_tank=p_tank)
        enc_rate = float(rng.choice([500.0, 2000.0]))
        feedback = rng.random() > 0.2
        tables = _flowstep_tables(step, t, cmd, cam, X, PS, PH, load_true, p_tank, rng,
                                  enc_rate=enc_rate, feedback=feedback,
                                  tank_column=tank_column)
        rid = (f"{name_prefix}{i:03d}_{step.side[:3]}_L{step.load_mpag:.2f}_"
               f"c{step.cam_deg:+.1f}_r{step.repeat + 1}")
        load_field = None if rng.random() < 0.1 else round(step.load_mpag, 3)
        meta = {"schema": "seanv-run/1", "run_id": rid, "kind": "flow_step",
                "started_at": _iso(t_wall), "load_mpag": load_field, "side": step.side,
                "cam_deg": step.cam_deg, "rig": {}, "operator": "foreign-lab",
                "bench": {"name": "B-2", "firmware": "3.1"}}
        formats = {k: ("parquet" if rng.random() < 0.3 else "csv") for k in tables}
        _write_run(out / rid, meta, tables, formats)
        if trace:  # true plant signals, for debugging only (not a contract table)
            pd.DataFrame({"t_s": t, "x_mm": X, "q_mm3_s": Q, "p_supply_mpag": PS,
                          "p_head_mpag": PH, "cam_deg": cam}).to_parquet(
                out / rid / "_trace.parquet")
        tr.runs.append({"run_id": rid, "side": step.side, "cam_deg": step.cam_deg,
                        "load_mpag": step.load_mpag, "c_true": c_now[step.side],
                        "p_tank_mpag": p_tank, "encoder_rate_hz": enc_rate,
                        "feedback": bool(feedback)})
        t_wall += timedelta(seconds=float(t[-1]) + rng.uniform(6.0, 12.0))
    return tr


# ---------------------------------------------------------------------------
# position control
# ---------------------------------------------------------------------------

class _Transmission:
    """Servo angle -> needle angle in position control: ``needle_delay_s`` of
    pure delay, then ``cam_backlash_deg`` of play (identity when both are 0)."""

    def __init__(self, tr: ForeignTruth, h: float, theta0: float):
        self.hist = [theta0] * (int(round(tr.needle_delay_s / h)) + 1)
        self.half = 0.5 * tr.cam_backlash_deg
        self.needle = theta0
        self.i = 0

    def step(self, servo_deg: float) -> float:
        n = len(self.hist)
        self.hist[self.i % n] = servo_deg
        self.i += 1
        delayed = self.hist[self.i % n]  # written n - 1 steps ago (theta0 before)
        if delayed > self.needle + self.half:
            self.needle = delayed - self.half
        elif delayed < self.needle - self.half:
            self.needle = delayed + self.half
        return self.needle


def _controller_model(tr: ForeignTruth):
    """The foreign controller's eq. (6) model: this rig's z0, C and needle
    geometry (the same the valve has)."""
    from seanv_analysis.config import load_rig
    from seanv_analysis.models import ValveModel

    return ValveModel.from_rig(load_rig()).with_side("supply", z0_mm=tr.supply_z0_mm,
                                                    c_flow=tr.supply_c,
                                                    geometry=tr.geometry("supply")) \
        .with_side("drain", z0_mm=tr.drain_z0_mm, c_flow=tr.drain_c,
                   geometry=tr.geometry("drain"))


def _simulate_position(tr: ForeignTruth, needles, rng, *, refs, t_ref, loads, t_load,
                       duration_s, kp=480.0, rate_hz=50.0, h=1e-3, p_tank=0.0, cam_law=None):
    model = _controller_model(tr)
    if not tr._simple_plant:
        return _simulate_position_plant(tr, needles, model, refs=refs, t_ref=t_ref, loads=loads,
                                        t_load=t_load, duration_s=duration_s, kp=kp,
                                        rate_hz=rate_hz, h=h, p_tank=p_tank, cam_law=cam_law)
    if cam_law is not None:
        raise ValueError("the cam controller needs the opt-in plant (own_rig())")
    t = np.arange(0.0, duration_s, h)
    n = t.size
    nd = int(round(tr.delay_s / h))
    ctrl_every = int(round(1.0 / (rate_hz * h)))
    x = 5.0
    q = 0.0
    load_reg = loads[0]
    X, Q, PS, PH, PL, CAM = (np.empty(n) for _ in range(6))
    ctrl_t, ctrl_x, ctrl_q = [], [], []
    cam_hist = np.full(n, -12.0)
    cam_cmd = -12.0
    sup, drn = needles["supply"], needles["drain"]
    lo, hi = tr.stroke_mm
    servo = _Servo(tr, h, -12.0) if tr.servo_in_position else None
    to_needle = _Transmission(tr, h, -12.0)
    approach, needle_prev = 0.0, -12.0
    for i in range(n):
        ti = t[i]
        load_sp = loads[np.searchsorted(t_load, ti, side="right") - 1]
        load_reg += (load_sp - load_reg) * h / 0.1
        v = q / ACTUATOR_AREA_MM2
        ps = (tr.supply_mpag - SUPPLY_DROOP_MPA_S_PER_MM3 * max(q, 0.0)
              + 0.02 * math.sin(2 * math.pi * 33.0 * ti))
        ph = _head_pressure(load_reg, v, tr)
        if i % ctrl_every == 0:
            x_ref = refs[np.searchsorted(t_ref, ti, side="right") - 1]
            x_meas = round(x / 0.01) * 0.01
            q_ref = kp * (x_ref - x_meas)
            cam_cmd = float(model.cam_for_flow(q_ref, ps, ph, p_tank))
            ctrl_t.append(ti)
            ctrl_x.append(x_ref)
            ctrl_q.append(q_ref)
        cam_hist[i] = cam_cmd
        cam_valve = cam_hist[i - nd] if i >= nd else -12.0
        if servo is not None:  # the servo follows the (delayed) command
            cam_valve = servo.step(cam_valve)
        # pure delay: the valve sees the command of delay_s ago, flow is instantaneous
        needle = to_needle.step(cam_valve)
        if needle != needle_prev:
            approach, needle_prev = (1.0 if needle > needle_prev else -1.0), needle
        q = sup.flow1(needle, ps, ps - ph, sup.c, load_reg, approach) + \
            drn.flow1(needle, ph, ph - p_tank, drn.c, load_reg, approach)
        x = min(max(x + q / ACTUATOR_AREA_MM2 * h, lo), hi)
        X[i], Q[i], PS[i], PH[i], PL[i], CAM[i] = x, q, ps, ph, load_reg, cam_valve
    return t, X, Q, PS, PH, PL, cam_hist, CAM, (np.array(ctrl_t), np.array(ctrl_x),
                                                np.array(ctrl_q))


def _simulate_position_plant(tr: ForeignTruth, needles, model, *, refs, t_ref, loads, t_load,
                             duration_s, kp, rate_hz, h, p_tank, cam_law=None):
    """:func:`_simulate_position` with the opt-in plant (:class:`_Plant`);
    ``cam_law(e_mm) -> cam [deg]``: a controller without flow model instead
    of eq. (6) (Q_ref logged as NaN)."""
    t = np.arange(0.0, duration_s, h)
    n = t.size
    t_l = t.tolist()
    nd = int(round(tr.delay_s / h))
    ctrl_every = int(round(1.0 / (rate_hz * h)))
    i_ref = (np.searchsorted(t_ref, t, side="right") - 1).tolist()
    i_load = (np.searchsorted(t_load, t, side="right") - 1).tolist()
    refs, loads = [float(r) for r in refs], [float(v) for v in loads]
    load_reg = loads[0]
    plant = _Plant(tr, needles, x=5.0, load_mpag=load_reg, tau_s=0.0)
    servo = _Servo(tr, h, -12.0) if tr.servo_in_position else None
    to_needle = _Transmission(tr, h, -12.0)
    X, Q, PS, PH, PL, CAM = ([0.0] * n for _ in range(6))
    ctrl_t, ctrl_x, ctrl_q = [], [], []
    cam_hist = [-12.0] * n
    cam_cmd = -12.0
    cs, cd = needles["supply"].c, needles["drain"].c
    two_pi_33 = 2 * math.pi * 33.0
    for i in range(n):
        ti = t_l[i]
        load_reg += (loads[i_load[i]] - load_reg) * h / 0.1
        ps = (tr.supply_mpag - SUPPLY_DROOP_MPA_S_PER_MM3 * max(plant.qv, 0.0)
              + 0.02 * math.sin(two_pi_33 * ti))
        if i % ctrl_every == 0:
            x_ref = refs[i_ref[i]]
            x_meas = round(plant.x / 0.01) * 0.01
            if cam_law is None:
                q_ref = kp * (x_ref - x_meas)
                cam_cmd = float(model.cam_for_flow(q_ref, ps, plant.p, p_tank))
            else:
                q_ref = math.nan
                cam_cmd = float(cam_law(x_ref - x_meas))
            ctrl_t.append(ti)
            ctrl_x.append(x_ref)
            ctrl_q.append(q_ref)
        cam_hist[i] = cam_cmd
        cam_valve = cam_hist[i - nd] if i >= nd else -12.0
        if servo is not None:
            cam_valve = servo.step(cam_valve)
        plant.step(to_needle.step(cam_valve), ps, p_tank, load_reg, h, cs, cd)
        X[i], Q[i], PS[i], PH[i], PL[i], CAM[i] = plant.x, plant.q, ps, plant.p, load_reg, \
            cam_valve
    arr = np.asarray
    return t, arr(X), arr(Q), arr(PS), arr(PH), arr(PL), arr(cam_hist), arr(CAM), (
        arr(ctrl_t), arr(ctrl_x), arr(ctrl_q))


def write_position(out: str | Path, *, seed: int = 0, truth: ForeignTruth | None = None,
                   n_runs: int = 2, duration_s: float = 64.0,
                   start: datetime | None = None, empty_qref_run: bool = True,
                   trace: bool = False, controllers: Sequence[str] | None = None
                   ) -> ForeignTruth:
    """Write ``n_runs`` position-control runs (flow model, kp 480, 50 Hz) of
    the foreign rig under ``out``. The last one logs an empty q_ref column
    when ``empty_qref_run`` (the analysis must rebuild Q_ref from kp).
    ``controllers``: per run ``"flow_model"`` (eq. 6, the default) or
    ``"cam"`` (no flow model: cam = -15 deg + 8 deg/mm x e, the paper's
    law with a gain this rig's faster loop does not limit-cycle with, no
    hold; opt-in plant only). ``trace``: also write the true 1 kHz
    signals (``_trace.parquet``, not a contract table)."""
    tr, out, rng, needles = _start(out, truth, [seed, 0xB0B])
    t_wall = start or datetime(2026, 5, 12, 0, 30, 0, tzinfo=timezone.utc)
    for k in range(n_runs):
        refs = np.array([0.0, 25.0, 10.0, 35.0, 20.0, 40.0, 5.0]) + rng.uniform(-2, 2)
        refs[0] = 5.0
        t_ref = np.array([0.0] + [4.0 + 10.0 * j for j in range(6)])
        loads = np.array([0.3, 0.4, 0.3, 0.4, 0.3, 0.4, 0.3])
        t_load = np.array([0.0] + [4.0 + 10.0 * j + 5.0 for j in range(6)])
        kind = "flow_model" if controllers is None else controllers[k]
        if kind not in ("flow_model", "cam"):
            raise ValueError(f"controllers: expected 'flow_model' or 'cam', got {kind!r}")
        law = None if kind == "flow_model" else (
            lambda e: min(max(CAM_NEUTRAL_DEG + CAM_KP_DEG_PER_MM * e, -40.0), 10.0))
        t, X, Q, PS, PH, PL, cam_cmd, cam_valve, ctrl = _simulate_position(
            tr, needles, rng, refs=refs, t_ref=t_ref, loads=loads, t_load=t_load,
            duration_s=duration_s, cam_law=law)
        enc_rate = 2000.0 if k % 2 == 0 else 500.0
        te = _stamps(rng, t[-1], enc_rate, jitter=0.04)
        tp = _stamps(rng, t[-1], 200.0, jitter=0.02)
        tsv = _stamps(rng, t[-1], 50.0, jitter=0.01)
        enc = pd.DataFrame({"t_s": te, "position_mm": np.round(np.interp(te, t, X) / 0.01) * 0.01})
        pres = pd.DataFrame({
            "t_s": tp,
            "p_supply_mpag": np.interp(tp, t, PS) + rng.normal(0, 0.01, tp.size),
            "p_head_mpag": np.interp(tp, t, PH) + rng.normal(0, 0.01, tp.size),
            "p_load_mpag": np.interp(tp, t, PL) + rng.normal(0, 0.005, tp.size),
            "p_tank_mpag": rng.normal(0, 0.003, tp.size)})
        idx = np.clip(np.searchsorted(t, tsv, side="right") - 1, 0, t.size - 1)
        servo = pd.DataFrame({"t_s": tsv, "cam_cmd_deg": cam_cmd[idx],
                              "cam_deg": np.round(np.interp(tsv, t, cam_valve) / SERVO_STEP_DEG)
                              * SERVO_STEP_DEG})
        ct, cx, cq = ctrl
        # the controller's log: its own instants (the control ticks), slight jitter
        ct_log = np.round(ct + 0.004 + rng.uniform(-1e-4, 1e-4, ct.size), 6)
        q_log = np.full(cq.size, np.nan) if (empty_qref_run and k == n_runs - 1) else cq
        controller = pd.DataFrame({"t_s": ct_log, "x_ref_mm": cx, "q_ref_mm3_s": q_log,
                                   "mode": "P"})
        rid = f"B-pos-{k + 1:02d}"
        meta = {"schema": "seanv-run/1", "run_id": rid, "kind": "position_control",
                "started_at": _iso(t_wall), "load_mpag": None,
                "controller": ({"kp": 480.0, "flow_model": True, "rate_hz": 50} if law is None
                               else {"kp": CAM_KP_DEG_PER_MM, "flow_model": False,
                                     "rate_hz": 50}),
                "rig": {}, "operator": "foreign-lab"}
        formats = {"encoder": "parquet" if k % 2 else "csv", "pressure": "csv",
                   "servo": "csv", "controller": "parquet" if k % 2 == 0 else "csv"}
        _write_run(out / rid, meta, {"encoder": enc, "pressure": pres, "servo": servo,
                                     "controller": controller}, formats)
        if trace:  # true plant signals, for debugging only (not a contract table)
            pd.DataFrame({"t_s": t, "x_mm": X, "q_mm3_s": Q, "p_supply_mpag": PS,
                          "p_head_mpag": PH, "p_load_mpag": PL, "cam_cmd_deg": cam_cmd,
                          "cam_deg": cam_valve}).to_parquet(out / rid / "_trace.parquet")
        tr.runs.append({"run_id": rid, "kind": "position_control", "encoder_rate_hz": enc_rate})
        t_wall += timedelta(seconds=duration_s + 60.0)
    return tr


if __name__ == "__main__":  # pragma: no cover - manual use
    import argparse

    ap = argparse.ArgumentParser(description="write a foreign-rig data set")
    ap.add_argument("out")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--drift", action="store_true", help="drain C -2 %% every 3 runs")
    ap.add_argument("--no-position", action="store_true")
    ap.add_argument("--full", action="store_true", help="cam every 2.5 deg (else 5 deg)")
    ap.add_argument("--own", action="store_true",
                    help="own_rig(): own needle centres, servo, line and stiction")
    a = ap.parse_args()
    drift = {"side": "drain", "step": 0.02, "every": 3} if a.drift else None
    truth = own_rig(drift=drift) if a.own else ForeignTruth(drift=drift)
    plan = flowstep_plan(
        supply_cams=np.arange(-10.0, 10.0 + 1e-9, 2.5 if a.full else 5.0),
        drain_cams=np.arange(-40.0, -15.0 + 1e-9, 2.5 if a.full else 5.0))
    write_flowsteps(Path(a.out) / "flow", plan=plan, seed=a.seed, truth=truth)
    if not a.no_position:
        write_position(Path(a.out) / "position", seed=a.seed, truth=truth)
    (Path(a.out) / "_foreign_truth.json").write_text(json.dumps(truth.to_json_dict(), indent=1))
