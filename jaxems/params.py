"""Vehicle parameters: the reference truck of the paper (Table 3) plus capability curves.

`VehicleParams` is a `NamedTuple` of arrays, hence a JAX pytree: every value a sweep may vary
(mass, battery size, efficiencies, curves) is an array leaf, so new values never recompile.
Only shapes are structure: the number of gears (`gear_ratio.shape == (n_gears,)`) and the number
of points of each capability curve.

All leaves are SI: kg, m, s, W, J, rad/s, N m. rpm, km/h and MJ only appear in the TOML files and
at the command line. `load_vehicle` reads and validates a TOML file (see
`data/vehicles/reference_truck.toml`); every wrong or missing value is a `VehicleError` naming
the field and the file.
"""

from __future__ import annotations

import math
import numbers
import os
import tomllib
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from .route import SPEED_MIN_KMH

RPM = 2.0 * math.pi / 60.0  # rad/s per rpm
KMH = 1.0 / 3.6  # m/s per km/h

DATA_DIR = Path(__file__).resolve().parent.parent / "data"
VEHICLE_DIR = DATA_DIR / "vehicles"


class VehicleError(ValueError):
    """A vehicle file or parameter value is wrong; the message names the field and the file."""


class VehicleParams(NamedTuple):
    """One vehicle; every field is an array leaf (scalars have shape ``()``).

    Shapes: curves ``te_max_w, te_max: (Nmax,)``, ``te_min_w, te_min: (Nmin,)``,
    ``gear_ratio: (n_gears,)``; everything else ``()``. A batch of vehicles is the same
    structure with a leading batch axis on the leaves that vary (see `stack_vehicles`).
    """

    # vehicle (eqs. 14-18)
    mass: Any  # kg
    rho: Any  # kg/m^3 air density
    c_w: Any  # - drag coefficient
    area: Any  # m^2 frontal area
    c_r: Any  # - rolling resistance coefficient
    g: Any  # m/s^2
    # engine (eqs. 1-3)
    eta_e: Any  # - indicated efficiency
    e0_lin: Any  # W/(rad/s):   P_e0(w) = -(e0_lin w + e0_quad w^2)
    e0_quad: Any  # W/(rad/s)^2
    we_min: Any  # rad/s lowest connected engine speed (idle)
    we_max: Any  # rad/s highest engine speed
    te_max_w: Any  # rad/s  (Nmax,) speed points of the full-load torque curve
    te_max: Any  # N m    (Nmax,)
    te_min_w: Any  # rad/s (Nmin,) speed points of the engine-brake torque curve
    te_min: Any  # N m    (Nmin,) negative
    I_e: Any  # kg m^2
    # motor/generator (eqs. 4-5)
    eta_m: Any  # -
    m0_lin: Any  # W/(rad/s):  P_m0(w) = -(m0_lin w + m0_quad w^2)
    m0_quad: Any  # W/(rad/s)^2
    wm_max: Any  # rad/s
    tm_max: Any  # N m   |P_m| <= min(tm_max w, pm_max)
    pm_max: Any  # W
    I_m: Any  # kg m^2
    has_motor: Any  # 1.0 hybrid, 0.0 conventional (motor disconnected for good)
    # battery (eqs. 6-8)
    beta: Any  # 1/W   P_bi = P_b + beta P_b^2
    E_b_max: Any  # J usable size; E_b in [0, E_b_max]
    soc0: Any  # - initial fraction: E_b(t0) = soc0 * E_b_max
    # gearbox (eqs. 10-11)
    gear_ratio: Any  # - (n_gears,) r_G(G) for G = 1..n_gears
    r_d: Any  # rad/s of gearbox output per m/s of vehicle speed
    # switching (eq. 12, Appendix C)
    dt_M: Any  # s open driveline during a mode switch
    dt_G: Any  # s open driveline during a gear switch
    # fuel
    lhv: Any  # J/kg
    fuel_density: Any  # kg/l
    # driving (Level 3)
    a_max: Any  # m/s^2 largest acceleration
    a_min: Any  # m/s^2 largest deceleration (positive number)
    v_cruise: Any  # m/s reference cruise speed v0
    w_pred: Any  # rad/s engine speed Level 3 assumes (CVT at fixed speed, section 6)

    @property
    def n_gears(self) -> int:
        return int(np.shape(self.gear_ratio)[-1])

    @property
    def E_b0(self):
        """Initial battery energy (J)."""
        return self.soc0 * self.E_b_max

    def replace(self, **changes) -> VehicleParams:
        """A copy with some fields changed (array values; shapes of curves may not change)."""
        bad = set(changes) - set(self._fields)
        if bad:
            raise VehicleError(f"unknown vehicle field(s): {', '.join(sorted(bad))}")
        out = {}
        for k, v in changes.items():
            try:
                out[k] = np.asarray(v, dtype=np.float64)
            except (TypeError, ValueError):
                raise VehicleError(f"{k}: must be a number or an array of numbers (got "
                                   f"{v!r})") from None
        return self._replace(**out)

    def conventional(self) -> VehicleParams:
        """The same truck with the motor disconnected for good (the non-hybrid reference)."""
        return self._replace(has_motor=np.float64(0.0))


# --------------------------------------------------------------------------------------------
# TOML schema: (section, key) -> (field, scale, check). `check` is one of
# "pos" (> 0), "nonneg" (>= 0), "frac" (0 < x <= 1), "unit" (0 <= x <= 1), "any", "curve+",
# "curve-" (a list of numbers, positive / negative), "speeds" (strictly increasing, >= 0), or
# another rule of `_NUMBER_RULES` (a plausible range: "mass", "area", "gear_base", ...).
_SCHEMA: dict[tuple[str, str], tuple[str, float, str]] = {
    ("vehicle", "mass_kg"): ("mass", 1.0, "mass"),
    ("vehicle", "air_density_kg_m3"): ("rho", 1.0, "rho"),
    ("vehicle", "drag_coefficient"): ("c_w", 1.0, "drag"),
    ("vehicle", "frontal_area_m2"): ("area", 1.0, "area"),
    ("vehicle", "rolling_resistance"): ("c_r", 1.0, "rolling"),
    ("vehicle", "gravity_m_s2"): ("g", 1.0, "gravity"),
    ("engine", "efficiency"): ("eta_e", 1.0, "frac"),
    ("engine", "speed_min_rpm"): ("we_min", RPM, "pos"),
    ("engine", "speed_max_rpm"): ("we_max", RPM, "pos"),
    ("engine", "friction_lin_W_per_rad_s"): ("e0_lin", 1.0, "friction_lin"),
    ("engine", "friction_quad_W_per_rad2_s2"): ("e0_quad", 1.0, "friction_quad"),
    ("engine", "max_torque_rpm"): ("te_max_w", RPM, "speeds"),
    ("engine", "max_torque_Nm"): ("te_max", 1.0, "curve+"),
    ("engine", "min_torque_rpm"): ("te_min_w", RPM, "speeds"),
    ("engine", "min_torque_Nm"): ("te_min", 1.0, "curve-"),
    ("engine", "inertia_kg_m2"): ("I_e", 1.0, "nonneg"),
    ("motor", "efficiency"): ("eta_m", 1.0, "frac"),
    ("motor", "speed_max_rpm"): ("wm_max", RPM, "pos"),
    ("motor", "torque_max_Nm"): ("tm_max", 1.0, "motor"),
    ("motor", "power_max_W"): ("pm_max", 1.0, "motor"),
    ("motor", "friction_lin_W_per_rad_s"): ("m0_lin", 1.0, "friction_lin"),
    ("motor", "friction_quad_W_per_rad2_s2"): ("m0_quad", 1.0, "friction_quad"),
    ("motor", "inertia_kg_m2"): ("I_m", 1.0, "nonneg"),
    ("battery", "loss_coefficient_per_W"): ("beta", 1.0, "beta"),
    ("battery", "capacity_J"): ("E_b_max", 1.0, "capacity"),
    ("battery", "initial_fraction"): ("soc0", 1.0, "unit"),
    ("gearbox", "base"): ("_gear_base", 1.0, "gear_base"),
    ("gearbox", "gears"): ("_gears", 1.0, "int"),
    ("gearbox", "final_drive_rpm_per_m_s"): ("r_d", RPM, "pos"),
    ("switching", "mode_open_s"): ("dt_M", 1.0, "open_time"),
    ("switching", "gear_open_s"): ("dt_G", 1.0, "open_time"),
    ("fuel", "lower_heating_value_J_per_kg"): ("lhv", 1.0, "lhv"),
    ("fuel", "density_kg_per_l"): ("fuel_density", 1.0, "density"),
    ("driving", "max_acceleration_m_s2"): ("a_max", 1.0, "accel"),
    ("driving", "max_deceleration_m_s2"): ("a_min", 1.0, "accel"),
    ("driving", "cruise_speed_km_h"): ("v_cruise", KMH, "cruise"),
    ("driving", "prediction_engine_speed_rpm"): ("w_pred", RPM, "pos"),
}
_SECTIONS = sorted({s for s, _ in _SCHEMA})


BETA_MIN = 1e-12  # 1/W: the least battery loss coefficient (see "beta" below)

_NUMBER_RULES = {
    "finite": (lambda x: True, ""),
    "pos": (lambda x: x > 0, "must be > 0"),
    "nonneg": (lambda x: x >= 0, "must be >= 0"),
    "frac": (lambda x: 0 < x <= 1, "must be in (0, 1]"),
    "unit": (lambda x: 0 <= x <= 1, "must be in [0, 1]"),
    "int": (lambda x: x == int(x) and 1 <= x <= 32, "must be a whole number from 1 to 32"),
    "zero_one": (lambda x: x in (0.0, 1.0), "must be 0 or 1"),
    # the battery's loss coefficient: Level 1's split divides by it (at 1e-320 a run's fuel
    # was NaN); below this a battery loses less than 1 W at 1 MW, lossless for any purpose
    "beta": (lambda x: x >= BETA_MIN, f"must be >= {BETA_MIN:g} (1/W)"),
    # a hybrid's motor: at 0 it still turned (its friction drained the battery) and Level 2's
    # costate ran to its bracket's end; the truck without it is the conventional strategy's
    "motor": (lambda x: x > 0, "must be > 0 (the truck without its motor: the conventional "
                               "strategy, or has_motor = 0)"),
    # plausible ranges where a unit mixed up runs on, silently wrong: a battery of 100 "J"
    # meant as kWh or MJ (whose dE_b vanishes in float64 at 1e30 J), a heating value in MJ/kg
    # (42.8 for diesel's 42.8e6 J/kg: a million times the fuel), a density in kg/m^3
    "capacity": (lambda x: 1e4 <= x <= 1e11, "must be from 1e4 to 1e11 J (10 kJ to 28 MWh)"),
    # a vehicle's mass: 25 (tonnes typed as kg) ran a 25 kg truck at 8 l/100 km, 1e9 a route
    # no gear could climb
    "mass": (lambda x: 1e3 <= x <= 2e5, "must be from 1000 to 200000 kg (1 to 200 t)"),
    "lhv": (lambda x: 1e6 <= x <= 1e9, "must be from 1e6 to 1e9 J/kg (diesel: 42.8e6)"),
    "density": (lambda x: 0.01 <= x <= 10, "must be from 0.01 to 10 kg/l (diesel: 0.83)"),
    # the road load's and the driving's: 1e300 m^2 of frontal area, g or rolling resistance
    # ran to a 300-digit traction energy, or to a trip of 0.0 s (infeasible-route), exit 0
    "rho": (lambda x: 0 < x <= 10, "must be > 0 and at most 10 kg/m^3 (air: 1.2)"),
    "drag": (lambda x: 0 <= x <= 10, "must be from 0 to 10 (trucks: 0.5 to 0.8)"),
    "area": (lambda x: 0 < x <= 100, "must be > 0 and at most 100 m^2 (trucks: about 10)"),
    "rolling": (lambda x: 0 <= x <= 1, "must be from 0 to 1 (truck tyres: about 0.005)"),
    "gravity": (lambda x: 1 <= x <= 100, "must be from 1 to 100 m/s^2 (the Earth's: 9.8)"),
    "accel": (lambda x: 0 < x <= 20, "must be > 0 and at most 20 m/s^2 (2 g; trucks: about 1)"),
    # the ratio of a gear to the next: at 1e30 the ratios base^(gears - G) overflowed (a NumPy
    # warning, then "gear_ratio: ratios must be finite"); 10^31 (32 gears) is finite
    "gear_base": (lambda x: 0 < x <= 10, "must be > 0 and at most 10 (one gear's ratio to the "
                                         "next; trucks: 1.2 to 1.5)"),
    # the friction of the engine and the motor, P_0(w) = -(lin w + quad w^2): at 1e30 (or
    # 1e300) a run's fuel was 5e33 J (5e303) with status ok, and a motor's made the hybrid the
    # conventional truck without a word; at the bounds the friction at 2300 rpm is 2.4 MW and
    # 5.8 MW, beyond what any truck's engine delivers (the reference truck's: about 370 kW)
    "friction_lin": (lambda x: 0 <= x <= 1e4, "must be from 0 to 1e4 W/(rad/s) (the reference "
                                              "truck's: 38.2 engine, 5 motor)"),
    "friction_quad": (lambda x: 0 <= x <= 100, "must be from 0 to 100 W/(rad/s)^2 (the "
                                               "reference truck's: 0.73 engine, 0.02 motor)"),
    # the driveline's open time of a switch: at 1e30 s a switch held it open for the rest of
    # the trip (an unfinished run of 0 to 0.1 MJ of fuel, exit 0); at 60 s the short track
    # still runs to its end, in two to three times Level 3's trip time
    "open_time": (lambda x: 0 <= x <= 60, "must be from 0 to 60 s (trucks: about 1 s)"),
    # the cruise speed (in the file's km/h): not below the slowest speed Level 3 predicts
    "cruise": (lambda x: x >= SPEED_MIN_KMH,
               f"must be >= {SPEED_MIN_KMH:g} km/h, the slowest the prediction drives"),
}


def check_number(value: Any, kind: str, where: str, error: type = ValueError) -> float:
    """`value` as a float where it is a finite number (not a bool) that meets `kind`'s rule
    (finite, pos, nonneg, frac (0, 1], unit [0, 1], int 1-32, zero_one 0 or 1, beta >=
    BETA_MIN, motor > 0, cruise >= SPEED_MIN_KMH, and the plausible ranges of mass, capacity,
    lhv, density, rho, drag, area, rolling, gravity, accel, gear_base, friction_lin,
    friction_quad and open_time); else raises `error` naming `where`. The one scalar check of
    vehicle files, sweep files and the API's overrides."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise error(f"{where}: expected a number (got {value!r})")
    x = float(value)
    if not math.isfinite(x):
        raise error(f"{where}: expected a finite number (got {value!r})")
    ok, words = _NUMBER_RULES[kind]
    if not ok(x):
        raise error(f"{where}: {words} (got {value!r})")
    return x


def _check(value: Any, kind: str, where: str) -> np.ndarray:
    def fail(why: str) -> VehicleError:
        return VehicleError(f"{where}: {why} (got {value!r})")

    if kind in ("speeds", "curve+", "curve-"):
        if not isinstance(value, list) or len(value) < 2:
            raise fail("expected a list of at least 2 numbers")
        if not all(isinstance(x, int | float) and not isinstance(x, bool) for x in value):
            raise fail("expected numbers only")
        arr = np.asarray(value, dtype=np.float64)
        if not np.all(np.isfinite(arr)):
            raise fail("expected finite numbers")
        if kind == "speeds" and (np.any(arr < 0) or np.any(np.diff(arr) <= 0)):
            raise fail("speeds must be >= 0 and strictly increasing")
        if kind == "curve+" and np.any(arr <= 0):
            raise fail("torques must be positive")
        if kind == "curve-" and np.any(arr > 0):
            raise fail("engine-brake torques must be <= 0")
        return arr
    return np.float64(check_number(value, kind, where, VehicleError))


def params_from_dict(doc: dict, source: str = "<dict>") -> VehicleParams:
    """Build and validate `VehicleParams` from a parsed TOML document (sections as in the file)."""
    for section, body in doc.items():
        if section == "name":
            if not isinstance(body, str):  # name = 5 was taken
                raise VehicleError(f"{source}: name: expected a text in quotes (got {body!r})")
            continue
        if section not in _SECTIONS:
            raise VehicleError(f"{source}: unknown section [{section}]")
        if not isinstance(body, dict):
            raise VehicleError(f"{source}: [{section}] must be a table")
        for key in body:
            if (section, key) not in _SCHEMA:
                raise VehicleError(f"{source}: unknown field {section}.{key}")
    vals: dict[str, Any] = {}
    for (section, key), (field, scale, kind) in _SCHEMA.items():
        where = f"{source}: {section}.{key}"
        if section not in doc or key not in doc[section]:
            raise VehicleError(f"{where}: missing")
        vals[field] = _check(doc[section][key], kind, where) * scale
    for a, b in (("te_max_w", "te_max"), ("te_min_w", "te_min")):
        if vals[a].shape != vals[b].shape:
            raise VehicleError(
                f"{source}: engine.{a.replace('te_', '').replace('_w', '')}_torque_rpm and "
                f"_Nm must have the same length"
            )
    if vals["we_max"] <= vals["we_min"]:
        raise VehicleError(f"{source}: engine.speed_max_rpm must exceed engine.speed_min_rpm")
    # the fields together: the torque curves span the engine's speed range (beyond their ends
    # they are held flat: a curve that stops short ran on made-up torque); Level 3 predicts at
    # a speed the engine runs at (5000 rpm made a 419 kW engine of it); gear 1 is the shortest
    speeds = f"the engine's speed range, {doc['engine']['speed_min_rpm']:g} to " \
             f"{doc['engine']['speed_max_rpm']:g} rpm"
    for field, key in (("te_max_w", "max_torque_rpm"), ("te_min_w", "min_torque_rpm")):
        if vals[field][0] > vals["we_min"] or vals[field][-1] < vals["we_max"]:
            raise VehicleError(f"{source}: engine.{key}: must span {speeds} "
                               f"(got {doc['engine'][key]!r})")
    if not vals["we_min"] <= vals["w_pred"] <= vals["we_max"]:
        raise VehicleError(f"{source}: driving.prediction_engine_speed_rpm: must be within "
                           f"{speeds} (got {doc['driving']['prediction_engine_speed_rpm']!r})")
    n = int(vals.pop("_gears"))
    base = vals.pop("_gear_base")
    if n > 1 and base <= 1:
        raise VehicleError(f"{source}: gearbox.base: must be > 1 with more than one gear (the "
                           f"ratios base^(gears - G) fall from gear 1) (got {base:g})")
    vals["gear_ratio"] = base ** (n - np.arange(1, n + 1, dtype=np.float64))
    vals["has_motor"] = np.float64(1.0)
    return VehicleParams(**vals)


def load_vehicle(name_or_path: str | Path = "reference_truck") -> VehicleParams:
    """Load a vehicle by name (a file in `data/vehicles/`) or by path to a TOML file.

    Raises `VehicleError` (a `ValueError`) naming the file and the field on any bad value.
    """
    p = vehicle_file(name_or_path)
    if p.is_dir():  # was "no such vehicle file"
        raise VehicleError(f"{name_or_path}: is a directory, not a vehicle file")
    if not p.is_file():
        known = ", ".join(sorted(f.stem for f in VEHICLE_DIR.glob("*.toml")))
        raise VehicleError(f"{name_or_path}: no such vehicle file (bundled vehicles: {known})")
    return params_from_dict(read_toml(p, VehicleError)[1], str(p))


def vehicle_file(name_or_path: str | os.PathLike) -> Path:
    """The file `load_vehicle` reads for a path or a bundled vehicle's name (which need not
    exist): a path as it is, a bare name (no suffix, no such file) in `data/vehicles/`."""
    if not isinstance(name_or_path, str | os.PathLike):
        raise VehicleError(f"vehicle: expected a VehicleParams, a vehicle file's path or a "
                           f"bundled vehicle's name (got {type(name_or_path).__name__})")
    p = Path(name_or_path)
    if not p.suffix and not p.exists():
        p = VEHICLE_DIR / f"{name_or_path}.toml"
    return p


def read_toml(path: Path, error: type = ValueError) -> tuple[str, dict]:
    """(text, TOML document) of the file `path` (UTF-8, a byte-order mark allowed); else
    `error` naming the file: not readable (the system's reason), not UTF-8 (the byte), not
    valid TOML (the line and column). The reading of vehicle and sweep files."""
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise error(f"{path}: not UTF-8 text (byte {e.start})") from None
    except OSError as e:  # "[Errno 5] Input/output error" named no file
        raise error(f"{path}: cannot read ({e.strerror or e})") from None
    try:
        return text, tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise error(f"{path}: not valid TOML: {e}") from None


def check_vehicle(vp: VehicleParams) -> VehicleParams:
    """`vp` where every scalar field, of each vehicle of a batch, meets its rule of the vehicle
    file (`check_number`: mass from 1 to 200 t, soc0 in [0, 1], ...), the engine's speed range
    is not empty and the curves, gear ratios and has_motor are what a file gives
    (`_array_rules`); else a `VehicleError` naming the field (and the vehicle's index in a
    batch). Files are checked as they load; this checks vehicles built or changed in Python at
    the API. Traced leaves (a host API called under `jit`) are left to the caller's concrete
    call."""
    for field, scale, kind in _SCHEMA.values():
        if field.startswith("_") or kind not in _NUMBER_RULES:
            continue
        try:  # in the file's unit, which the rules are written in (km/h, rpm)
            x = np.asarray(getattr(vp, field), dtype=np.float64) / scale
        except TypeError:  # a tracer
            continue
        except ValueError:
            raise VehicleError(f"{field}: expected a number (got "
                               f"{getattr(vp, field)!r})") from None
        flat = x.reshape(-1)
        for v in np.unique(flat):  # a sweep's batch holds few distinct values
            try:
                check_number(float(v), kind, field, VehicleError)
            except VehicleError:
                if x.ndim == 0:
                    raise
                i = int(np.flatnonzero((flat == v) | (np.isnan(flat) & np.isnan(v)))[0])
                check_number(float(v), kind, f"{field}[{i}]", VehicleError)
    try:
        we_min, we_max, w_pred = (np.asarray(x) for x in (vp.we_min, vp.we_max, vp.w_pred))
        rules = ((("we_min", "we_max"), we_max <= we_min,
                  "the engine's speed range is empty (we_max must exceed we_min)"),
                 ("w_pred", (w_pred < we_min) | (w_pred > we_max),
                  "must be within [we_min, we_max] (the engine's speed range)"))
        rules += _array_rules(vp)
    except TypeError:  # a tracer
        return vp
    for field, broken, words in rules:
        bad = np.flatnonzero(np.reshape(broken, -1))
        if bad.size:  # a rule across fields names each (a grid sets one of them)
            at = '' if np.ndim(broken) == 0 else f'[{bad[0]}]'
            names = ", ".join(f"{f}{at}" for f in ((field,) if isinstance(field, str) else field))
            raise VehicleError(f"{names}: {words}")
    return vp


def _array_rules(vp: VehicleParams) -> tuple:
    """(field, broken (batch shape) bool, words) of the fields that are not scalars, as the
    vehicle file's rules hold them (`_check`, `params_from_dict`): the torque curves (speeds
    increasing from >= 0, torques > 0 at full load and <= 0 braking, of their speeds' length,
    spanning the engine's speed range), the gear ratios (> 0, falling from gear 1, at least
    one) and has_motor (0 or 1). A NaN in a curve stopped a run inside Level 3 with no field
    named, a falling full-load curve or has_motor 0.5 ran to results marked ok."""
    a = {}
    for k in ("te_max_w", "te_max", "te_min_w", "te_min", "gear_ratio", "has_motor", "we_min",
              "we_max"):
        try:
            a[k] = np.asarray(getattr(vp, k), dtype=np.float64)
        except ValueError:
            raise VehicleError(f"{k}: expected numbers (got {getattr(vp, k)!r})") from None
    out = []
    for w, t, sign, name in (("te_max_w", "te_max", 1, "full-load"),
                             ("te_min_w", "te_min", -1, "engine-brake")):
        sp, tq = a[w], a[t]
        if sp.ndim < 1 or sp.shape[-1] < 2:
            raise VehicleError(f"{w}: expected at least 2 speeds (got shape {sp.shape})")
        if tq.shape != sp.shape:
            raise VehicleError(f"{t}: must have {w}'s shape {sp.shape} (got {tq.shape})")
        with np.errstate(invalid="ignore"):
            out += [(w, ~np.all(np.isfinite(sp) & (sp >= 0), -1) | ~np.all(np.diff(sp) > 0, -1),
                     "speeds must be finite, >= 0 and strictly increasing"),
                    (t, ~np.all(np.isfinite(tq) & ((tq > 0) if sign > 0 else (tq <= 0)), -1),
                     f"{name} torques must be finite and " + ("> 0" if sign > 0 else "<= 0")),
                    (w, ~((sp[..., 0] <= a["we_min"]) & (sp[..., -1] >= a["we_max"])),
                     "must span the engine's speed range [we_min, we_max]")]
    g = a["gear_ratio"]
    if g.ndim < 1 or g.shape[-1] < 1:
        raise VehicleError(f"gear_ratio: expected at least one gear (got shape {g.shape})")
    with np.errstate(invalid="ignore"):
        out += [("gear_ratio", ~np.all(np.isfinite(g) & (g > 0), -1) | ~np.all(np.diff(g) < 0, -1),
                 "ratios must be finite, > 0 and falling from gear 1 (the shortest)"),
                ("has_motor", ~np.isin(a["has_motor"], (0.0, 1.0)), "must be 0 or 1")]
    return tuple(out)


def with_overrides(
    vp: VehicleParams, *, mass_kg: float | None = None, battery_MJ: float | None = None,
    initial_soc: float | None = None,
) -> VehicleParams:
    """The user-facing overrides of the CLI and sweeps, validated (mass > 0, battery > 0, the
    starting charge in [0, 1] of the battery)."""
    if mass_kg is not None:
        vp = vp.replace(mass=check_number(mass_kg, "mass", "mass_kg", VehicleError))
    if battery_MJ is not None:
        mj = check_number(battery_MJ, "pos", "battery_MJ", VehicleError)
        vp = vp.replace(E_b_max=check_number(mj * 1e6, "capacity", f"battery_MJ ({mj:g} MJ)",
                                             VehicleError))
    if initial_soc is not None:
        vp = vp.replace(soc0=check_number(initial_soc, "unit", "initial_soc", VehicleError))
    return vp


def stack_vehicles(vehicles: list[VehicleParams]) -> VehicleParams:
    """Stack vehicles of the same structure into one batch (leading axis on every leaf); a
    field whose shapes differ (curves of other lengths, another number of gears) is a
    `VehicleError` naming it."""
    if not vehicles:
        raise VehicleError("stack_vehicles: empty list")
    for i, v in enumerate(vehicles):
        if not isinstance(v, VehicleParams):
            raise VehicleError(f"stack_vehicles: vehicles[{i}] is not a VehicleParams (got "
                               f"{type(v).__name__})")
    for k in VehicleParams._fields:
        shapes = [np.shape(getattr(v, k)) for v in vehicles]
        if any(sh != shapes[0] for sh in shapes):
            i = next(i for i, sh in enumerate(shapes) if sh != shapes[0])
            raise VehicleError(f"stack_vehicles: {k} of vehicles[{i}] has shape {shapes[i]}, "
                               f"vehicles[0]'s {shapes[0]} (a batch's vehicles share their "
                               "shapes: as many gears and curve points)")
    return VehicleParams(*(np.stack(leaves) for leaves in zip(*vehicles, strict=True)))


def vehicle_axes(vp: VehicleParams, batched: list[str] | tuple[str, ...]) -> VehicleParams:
    """`in_axes` for `jax.vmap` over a vehicle whose `batched` fields carry a leading axis."""
    bad = set(batched) - set(VehicleParams._fields)
    if bad:
        raise VehicleError(f"unknown vehicle field(s): {', '.join(sorted(bad))}")
    return VehicleParams(*(0 if f in batched else None for f in VehicleParams._fields))
