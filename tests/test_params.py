"""Vehicle parameters: loading, unit conversion, validation (errors name field and file)."""

import math
import re
import tomllib
import warnings

import numpy as np
import pytest

import jaxems
from jaxems.params import (
    KMH,
    RPM,
    VEHICLE_DIR,
    VehicleError,
    VehicleParams,
    check_vehicle,
    load_vehicle,
    params_from_dict,
    stack_vehicles,
    with_overrides,
)

REF = VEHICLE_DIR / "reference_truck.toml"


def _doc():
    with open(REF, "rb") as fh:
        return tomllib.load(fh)


def _write(tmp_path, doc, name="truck.toml"):
    """Serialise a (flat, two-level) TOML document of numbers and lists."""
    lines = []
    for key, val in doc.items():
        if not isinstance(val, dict):
            lines.append(f"{key} = {_toml(val)}")
    for section, body in doc.items():
        if isinstance(body, dict):
            lines.append(f"[{section}]")
            lines += [f"{k} = {_toml(v)}" for k, v in body.items()]
    p = tmp_path / name
    p.write_text("\n".join(lines) + "\n")
    return p


def _toml(v):
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, list):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    if isinstance(v, float) and math.isnan(v):
        return "nan"
    if isinstance(v, float) and math.isinf(v):
        return "inf" if v > 0 else "-inf"
    return repr(v)


def test_reference_truck_values_in_si():
    vp = load_vehicle()
    assert isinstance(vp, VehicleParams)
    assert float(vp.mass) == 20000.0
    assert float(vp.we_min) == pytest.approx(600 * 2 * math.pi / 60)
    assert float(vp.r_d) == pytest.approx(52.2 * RPM)
    assert float(vp.v_cruise) == pytest.approx(85 / 3.6)
    assert float(vp.w_pred) == pytest.approx(1100 * RPM)
    # r_G(G) = 1.29^(12 - G), G = 1..12 (eq. 10)
    np.testing.assert_allclose(vp.gear_ratio, 1.29 ** (12 - np.arange(1, 13)))
    assert vp.n_gears == 12
    np.testing.assert_allclose(vp.te_max_w, np.array([600, 1000, 1400, 1600, 1800, 2300]) * RPM)
    assert float(vp.E_b0) == pytest.approx(0.5 * 4e6)
    assert float(vp.has_motor) == 1.0
    assert float(vp.conventional().has_motor) == 0.0
    assert all(np.all(np.isfinite(np.asarray(x))) for x in vp)


def test_load_by_path_equals_load_by_name(tmp_path):
    p = _write(tmp_path, _doc())
    a, b = load_vehicle(p), load_vehicle("reference_truck")
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(x, y)


@pytest.mark.parametrize(
    "section,key",
    [
        ("vehicle", "mass_kg"),
        ("engine", "max_torque_Nm"),
        ("battery", "capacity_J"),
        ("driving", "prediction_engine_speed_rpm"),
        ("gearbox", "gears"),
    ],
)
def test_missing_value_names_field_and_file(tmp_path, section, key):
    doc = _doc()
    del doc[section][key]
    p = _write(tmp_path, doc)
    with pytest.raises(VehicleError, match=re.escape(f"{p}: {section}.{key}: missing")):
        load_vehicle(p)


@pytest.mark.parametrize(
    "section,key,value,why",
    [
        ("vehicle", "mass_kg", -1.0, "must be from 1000 to 200000 kg"),
        ("vehicle", "mass_kg", 0.0, "must be from 1000 to 200000 kg"),
        ("vehicle", "mass_kg", 25.0, "must be from 1000 to 200000 kg"),  # tonnes typed as kg
        ("vehicle", "mass_kg", 1e9, "must be from 1000 to 200000 kg"),
        ("vehicle", "mass_kg", "heavy", "expected a number"),
        ("vehicle", "mass_kg", True, "expected a number"),
        ("vehicle", "mass_kg", float("nan"), "finite"),
        ("vehicle", "rolling_resistance", -0.001, "must be from 0 to 1"),
        ("engine", "efficiency", 1.2, r"must be in \(0, 1\]"),
        ("battery", "initial_fraction", 1.5, r"must be in \[0, 1\]"),
        ("gearbox", "gears", 2.5, "whole number"),
        ("engine", "max_torque_Nm", [1200.0], "at least 2"),
        ("engine", "max_torque_Nm", [1200.0, -5.0, 2500, 2200, 1950, 800], "positive"),
        ("engine", "min_torque_Nm", [-300.0, 100.0, -1500.0], "<= 0"),
        ("engine", "max_torque_rpm", [600.0, 500.0, 1400, 1600, 1800, 2300], "increasing"),
        ("engine", "max_torque_rpm", [600.0, "x", 1400, 1600, 1800, 2300], "numbers only"),
        ("driving", "cruise_speed_km_h", -85.0, "must be >= 1.8 km/h"),
        ("driving", "cruise_speed_km_h", 1.0, "must be >= 1.8 km/h"),
        ("battery", "loss_coefficient_per_W", 0.0, "must be >= 1e-12"),
        ("motor", "power_max_W", 0.0, "must be > 0 .the truck without its motor"),
        ("motor", "torque_max_Nm", 0.0, "must be > 0"),
        ("battery", "loss_coefficient_per_W", 1e-320, "must be >= 1e-12"),
        # units mixed up: a battery in kWh, a heating value in MJ/kg, a density in kg/m^3
        ("battery", "capacity_J", 100.0, "must be from 1e4 to 1e11 J"),
        ("battery", "capacity_J", 1e30, "must be from 1e4 to 1e11 J"),
        ("fuel", "lower_heating_value_J_per_kg", 42.8, "must be from 1e6 to 1e9 J/kg"),
        ("fuel", "density_kg_per_l", 832.0, "must be from 0.01 to 10 kg/l"),
        # the fields together: curves over the engine's whole speed range, Level 3's engine
        # speed within it (5000 rpm predicted a 419 kW engine), gear 1 the shortest
        ("engine", "max_torque_rpm", [700.0, 1000, 1400, 1600, 1800, 2300],
         "must span the engine's speed range, 600 to 2300 rpm"),
        ("engine", "min_torque_rpm", [600.0, 1200.0, 2000.0], "must span"),
        ("driving", "prediction_engine_speed_rpm", 5000.0,
         "must be within the engine's speed range, 600 to 2300 rpm"),
        ("driving", "prediction_engine_speed_rpm", 100.0, "must be within"),
        ("gearbox", "base", 1.0, "must be > 1 with more than one gear"),
        ("gearbox", "base", 0.8, "must be > 1"),
        # absurd values ran on: 1e300 m^2 to a 300-digit energy, 1e300 of gravity or rolling
        # resistance to a trip of 0.0 s, a base of 1e30 to an overflow warning and
        # "gear_ratio: ratios must be finite"
        ("gearbox", "base", 1e30, "must be > 0 and at most 10"),
        ("vehicle", "frontal_area_m2", 1e300, r"must be > 0 and at most 100 m\^2"),
        ("vehicle", "gravity_m_s2", 1e300, "must be from 1 to 100 m/s"),
        ("vehicle", "gravity_m_s2", 0.5, "must be from 1 to 100 m/s"),
        ("vehicle", "rolling_resistance", 1e300, "must be from 0 to 1 "),
        ("vehicle", "drag_coefficient", 11.0, "must be from 0 to 10 "),
        ("vehicle", "air_density_kg_m3", 1e3, "must be > 0 and at most 10 kg/m"),
        ("driving", "max_acceleration_m_s2", 1e300, "must be > 0 and at most 20 m/s"),
        ("driving", "max_deceleration_m_s2", 21.0, "must be > 0 and at most 20 m/s"),
        # no air at all, or less: the lower bound of the air density
        ("vehicle", "air_density_kg_m3", 0.0, "must be > 0 and at most 10 kg/m"),
        ("vehicle", "air_density_kg_m3", -1.2, "must be > 0 and at most 10 kg/m"),
        # a friction of 1e30 ran to 5e33 J of fuel with status ok (a motor's, to the hybrid as
        # the conventional truck); an open time of 1e30 s to an unfinished run, exit 0
        ("engine", "friction_lin_W_per_rad_s", 1e300, r"must be from 0 to 1e4 W/\(rad/s\)"),
        ("engine", "friction_quad_W_per_rad2_s2", 1e30, r"must be from 0 to 100 W/\(rad/s\)\^2"),
        ("engine", "friction_quad_W_per_rad2_s2", -0.1, "must be from 0 to 100"),
        ("motor", "friction_lin_W_per_rad_s", 1e30, "must be from 0 to 1e4"),
        ("motor", "friction_quad_W_per_rad2_s2", 1e300, "must be from 0 to 100"),
        ("switching", "mode_open_s", 1e30, "must be from 0 to 60 s"),
        ("switching", "gear_open_s", 1000.0, "must be from 0 to 60 s"),  # ms typed as s
        ("switching", "gear_open_s", -1.0, "must be from 0 to 60 s"),
    ],
)
def test_wrong_value_names_field_and_file(tmp_path, section, key, value, why):
    doc = _doc()
    doc[section][key] = value
    p = _write(tmp_path, doc)
    with pytest.raises(VehicleError) as e, warnings.catch_warnings():
        warnings.simplefilter("error")  # one error, no NumPy warning before it
        load_vehicle(p)
    msg = str(e.value)
    assert str(p) in msg and f"{section}.{key}" in msg
    assert re.search(why, msg), msg


def test_the_plausible_ranges_take_their_ends(tmp_path):
    """The upper bounds are far from any truck's values and take their own ends: friction
    (1e4 W/(rad/s), 100 W/(rad/s)^2) and open times (60 s)."""
    doc = _doc()
    for section in ("engine", "motor"):
        doc[section]["friction_lin_W_per_rad_s"] = 1e4
        doc[section]["friction_quad_W_per_rad2_s2"] = 100.0
    doc["switching"]["mode_open_s"] = doc["switching"]["gear_open_s"] = 60.0
    vp = load_vehicle(_write(tmp_path, doc))
    assert (float(vp.e0_lin), float(vp.m0_quad), float(vp.dt_G)) == (1e4, 100.0, 60.0)


def test_curve_length_mismatch(tmp_path):
    doc = _doc()
    doc["engine"]["max_torque_Nm"] = doc["engine"]["max_torque_Nm"][:-1]
    p = _write(tmp_path, doc)
    with pytest.raises(VehicleError, match="same length"):
        load_vehicle(p)


def test_speed_range_order(tmp_path):
    doc = _doc()
    doc["engine"]["speed_max_rpm"] = 500.0
    p = _write(tmp_path, doc)
    with pytest.raises(VehicleError, match="speed_max_rpm must exceed"):
        load_vehicle(p)


def test_unknown_section_and_field(tmp_path):
    doc = _doc()
    doc["turbo"] = {"boost": 1.0}
    p = _write(tmp_path, doc)
    with pytest.raises(VehicleError, match=r"unknown section \[turbo\]"):
        load_vehicle(p)
    doc = _doc()
    doc["vehicle"]["mass_t"] = 20.0
    p = _write(tmp_path, doc, "b.toml")
    with pytest.raises(VehicleError, match=re.escape(f"{p}: unknown field vehicle.mass_t")):
        load_vehicle(p)


def test_not_toml_and_no_such_vehicle(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text("[vehicle\nmass_kg = 1\n")
    with pytest.raises(VehicleError, match="not valid TOML"):
        load_vehicle(p)
    with pytest.raises(VehicleError, match="no such vehicle file.*reference_truck"):
        load_vehicle("no_such_truck")


def test_a_directory_or_an_unreadable_vehicle_file_is_named(tmp_path, monkeypatch):
    """A directory was "no such vehicle file"; a file the system cannot read was "[Errno 5]
    Input/output error", no file named."""
    with pytest.raises(VehicleError, match=f"^{VEHICLE_DIR}: is a directory, not a vehicle "
                                           f"file$"):
        load_vehicle(VEHICLE_DIR)

    def broken(self):
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(type(REF), "read_bytes", broken)
    with pytest.raises(VehicleError, match=rf"^{REF}: cannot read \(Input/output error\)$"):
        load_vehicle(REF)


def test_vehicle_file_encoding(tmp_path):
    """A vehicle file may start with a UTF-8 byte-order mark, as route and sweep files may;
    bytes that are not UTF-8 are an error naming the file."""
    text = REF.read_bytes()
    p = tmp_path / "bom.toml"
    p.write_bytes(b"\xef\xbb\xbf" + text)
    assert float(load_vehicle(p).mass) == float(load_vehicle(REF).mass)
    p = tmp_path / "latin1.toml"
    p.write_bytes(text.replace(b"[vehicle]", b"# caf\xe9\n[vehicle]", 1))
    with pytest.raises(VehicleError, match=re.escape(f"{p}: not UTF-8 text")):
        load_vehicle(p)


def test_params_from_dict_source_in_message():
    doc = _doc()
    doc["motor"]["efficiency"] = 0.0
    with pytest.raises(VehicleError, match=r"mine: motor.efficiency: must be in \(0, 1\]"):
        params_from_dict(doc, "mine")


def test_overrides_and_replace():
    vp = load_vehicle()
    v2 = with_overrides(vp, mass_kg=25000.0, battery_MJ=8.0)
    assert float(v2.mass) == 25000.0 and float(v2.E_b_max) == 8e6
    assert float(vp.mass) == 20000.0  # unchanged
    for bad in (-1.0, 0.0, float("nan"), float("inf")):
        with pytest.raises(VehicleError, match="mass_kg"):
            with_overrides(vp, mass_kg=bad)
        with pytest.raises(VehicleError, match="battery_MJ"):
            with_overrides(vp, battery_MJ=bad)
    for bad in (1e-3, 1e6):  # 1 kJ, 1 TJ: the battery's plausible range, in J
        with pytest.raises(VehicleError, match=r"^battery_MJ \(.* MJ\): must be from 1e4"):
            with_overrides(vp, battery_MJ=bad)
    with pytest.raises(VehicleError, match="unknown vehicle field"):
        vp.replace(weight=1.0)
    assert float(vp.replace(v_cruise=25 * KMH).v_cruise) == pytest.approx(25 / 3.6)


def test_stack_vehicles():
    vp = load_vehicle()
    batch = stack_vehicles([vp, vp.replace(mass=30000.0), vp.replace(mass=40000.0)])
    assert batch.mass.shape == (3,)
    assert batch.gear_ratio.shape == (3, 12)
    np.testing.assert_allclose(batch.mass, [20000, 30000, 40000])
    with pytest.raises(VehicleError, match="empty"):
        stack_vehicles([])
    six = vp.replace(gear_ratio=np.asarray(vp.gear_ratio)[6:])
    with pytest.raises(VehicleError, match=r"gear_ratio of vehicles\[1\] has shape \(6,\)"):
        stack_vehicles([vp, six])
    with pytest.raises(VehicleError, match=r"vehicles\[1\] is not a VehicleParams"):
        stack_vehicles([vp, None])


def _nan_at(x, i):
    x = np.array(x, dtype=float)
    x[i] = np.nan
    return x


@pytest.mark.parametrize(
    "field, change, why",
    [
        ("gear_ratio", lambda v: _nan_at(v.gear_ratio, 3), "ratios must be finite"),
        ("gear_ratio", lambda v: np.asarray(v.gear_ratio)[::-1].copy(), "falling from gear 1"),
        ("te_max", lambda v: _nan_at(v.te_max, 2), "full-load torques must be finite and > 0"),
        ("te_max_w", lambda v: np.asarray(v.te_max_w)[::-1].copy(), "strictly increasing"),
        ("te_max_w", lambda v: 0.5 * np.asarray(v.te_max_w), "must span the engine's speed"),
        ("te_min", lambda v: np.abs(np.asarray(v.te_min)) + 1.0, "engine-brake torques"),
        ("has_motor", lambda v: 0.5, "must be 0 or 1"),
        ("has_motor", lambda v: np.nan, "must be 0 or 1"),
    ],
)
def test_check_vehicle_holds_curves_gears_and_the_motor_flag(field, change, why):
    """The fields a vehicle file sets from lists (the torque curves, the gear ratios) and
    has_motor are held to the file's rules too, by field and in a batch by vehicle: a NaN gear
    ratio or torque stopped a run inside Level 3 naming no field, a falling speed axis or
    has_motor 0.5 ran to results marked ok."""
    vp = load_vehicle()
    bad = vp._replace(**{field: np.asarray(change(vp), dtype=np.float64)})
    with pytest.raises(VehicleError, match=rf"^{field}: .*{why}"):
        check_vehicle(bad)
    with pytest.raises(VehicleError, match=rf"^{field}\[1\]: .*{why}"):
        check_vehicle(stack_vehicles([vp, bad, vp]))
    with pytest.raises(VehicleError, match=rf"^{field}"):  # at the API, before anything runs
        jaxems.simulate("short_track", bad, strategy="conventional")
    with pytest.raises(VehicleError, match=r"^te_max: must have te_max_w's shape"):
        check_vehicle(vp._replace(te_max=np.asarray(vp.te_max)[:3]))
    with pytest.raises(VehicleError, match=r"^mass: expected a number \(got 'abc'\)"):
        check_vehicle(vp._replace(mass="abc"))


@pytest.mark.parametrize(
    "field,value,why",
    [
        ("mass", -1.0, "must be from 1000 to 200000 kg"),
        ("soc0", 1.5, r"must be in \[0, 1\]"),
        ("eta_e", 1.2, r"must be in \(0, 1\]"),
        ("c_r", -0.001, "must be from 0 to 1"),
        ("area", 1e300, "must be > 0 and at most 100"),
        ("g", 1e300, "must be from 1 to 100"),
        ("E_b_max", float("nan"), "expected a finite number"),
        ("w_pred", 500.0, r"must be within \[we_min, we_max\]"),
        ("beta", 1e-15, "must be >= 1e-12"),
        ("pm_max", 0.0, "must be > 0 .the truck without its motor: the conventional"),
        ("m0_quad", 1e300, "must be from 0 to 100 W"),
        ("dt_M", 1e30, "must be from 0 to 60 s"),
        # the rules read a value in the file's unit: 1 km/h as m/s, the message in km/h
        ("v_cruise", 1.0 * KMH, r"must be >= 1.8 km/h.*\(got 1\.0"),
    ],
)
def test_check_vehicle_names_the_field_and_the_vehicle(field, value, why):
    """Vehicles built in Python are held to the file's rules at the API: the field, and in a
    batch the index of the first vehicle that breaks it."""
    vp = load_vehicle()
    assert check_vehicle(vp) is vp and check_vehicle(vp.conventional()).has_motor == 0
    with pytest.raises(VehicleError, match=rf"^{field}: {why}"):
        check_vehicle(vp.replace(**{field: value}))
    batch = stack_vehicles([vp, vp.replace(mass=30000.0), vp.replace(**{field: value}), vp])
    with pytest.raises(VehicleError, match=rf"^{field}\[2\]: {why}"):
        check_vehicle(batch)


def test_an_empty_engine_speed_range_names_both_ends():
    """we_max <= we_min names both fields: a sweep's grid setting we_min = [1000] (rad/s) was
    "we_max[0]: must exceed we_min", naming the field it did not set."""
    vp = load_vehicle()
    why = r"the engine's speed range is empty \(we_max must exceed we_min\)"
    with pytest.raises(VehicleError, match=rf"^we_min, we_max: {why}"):
        check_vehicle(vp.replace(we_max=10.0))
    batch = stack_vehicles([vp, vp.replace(we_min=1000.0)])
    with pytest.raises(VehicleError, match=rf"^we_min\[1\], we_max\[1\]: {why}"):
        check_vehicle(batch)


def test_a_vehicle_name_is_text(tmp_path):
    doc = _doc()
    doc["name"] = 5
    p = _write(tmp_path, doc)
    with pytest.raises(VehicleError, match=re.escape(f"{p}: name: expected a text in quotes "
                                                     f"(got 5)")):
        load_vehicle(p)


def test_host_apis_check_the_vehicle_before_compiling():
    """Every host entry point that takes a vehicle names its bad field (here before any
    compilation: the check comes first)."""
    import jaxems
    from jaxems.levels import battery, level1
    from jaxems.levels.velocity import predict_batch

    route = jaxems.load_route("short_track")
    vp = load_vehicle()
    bad = vp.replace(mass=-1.0)
    z, v = np.zeros(8), np.full(8, 5.0)
    calls = {
        "simulate": lambda: jaxems.simulate(route, bad, "baseline"),
        "simulate_batch": lambda: jaxems.simulate_batch(route, stack_vehicles([vp, bad]),
                                                        "baseline"),
        "predict_velocity": lambda: jaxems.predict_velocity(route, bad),
        "predict_batch": lambda: predict_batch([route, route], [vp, bad]),
        "solve_costate": lambda: battery.solve_costate(bad, z, v, np.full(8, 100.0)),
        "costate_batch": lambda: battery.costate_batch(
            stack_vehicles([vp, bad]), np.zeros((2, 8)), np.full((2, 8), 5.0),
            np.full((2, 8), 100.0)),
        "level1_full": lambda: level1.level1_full(bad, z, v, z, -2.0, 1.0),
    }
    for call in calls.values():
        with pytest.raises(VehicleError, match=r"^mass(\[1\])?: must be from 1000 to 200000 kg"):
            call()
