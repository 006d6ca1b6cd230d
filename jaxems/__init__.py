"""jaxems: multi-level predictive energy management for parallel hybrid trucks, in JAX.

After van Reeven & Hofman, "Multi-Level Energy Management for Hybrid Electric Vehicles -
Part I" (Vehicles 2019). Level 3 predicts velocity, Level 2 finds the battery costate,
Level 1 splits power and picks modes and gears with switching costs; the plant runs the
decisions in closed loop, and strategies compare the EMS with a conventional truck, a hybrid
without preview and the dynamic-programming optimum.
"""

from .dp import Transition, ViterbiResult, dense_transition, viterbi, viterbi_first
from .io import list_routes, load_route, route_name
from .levels.battery import (
    CostateResult,
    HorizonResult,
    Switching,
    bisect_costate,
    costate_batch,
    costate_product,
    level2_horizon,
    minimal_switching,
    solve_costate,
    status_names,
)
from .levels.level1 import Level1Result, level1_batch, level1_full, level1_mpc
from .levels.powersplit import (
    Guards,
    Split,
    closed_form_mode,
    guards,
    hamiltonian_table,
    interior_region,
    mode_gear_split,
    optimal_mode_gear,
)
from .levels.velocity import (
    EcoResult,
    Prediction,
    Profile,
    eco_cost,
    eco_cost_exact,
    match_trip_time,
    optimize_velocity,
    optimize_velocity_batch,
    predict_batch,
    predict_velocity,
    profile_from_speed,
)
from .params import VehicleError, VehicleParams, load_vehicle, stack_vehicles, vehicle_axes
from .route import Route, RouteError, pad_routes
from .shard import map_batch, use_host_devices
from .strategies import STRATEGIES, Options, Result, simulate, simulate_batch
from .switching import SwitchCostParams, eps_G, eps_M, switch_cost_matrix

__all__ = [
    "STRATEGIES", "CostateResult", "EcoResult", "Guards", "HorizonResult", "Level1Result",
    "Options", "eco_cost", "eco_cost_exact", "match_trip_time", "optimize_velocity",
    "optimize_velocity_batch", "profile_from_speed",
    "Prediction", "Profile", "Result", "Route", "RouteError", "Split", "SwitchCostParams",
    "SweepError", "Switching", "Transition", "VehicleError", "VehicleParams", "ViterbiResult",
    "bisect_costate", "closed_form_mode", "compare_strategies", "costate_batch",
    "costate_product", "dense_transition",
    "eps_G", "eps_M", "guards", "hamiltonian_table", "interior_region", "level1_batch",
    "level1_full", "level1_mpc", "level2_horizon", "list_routes", "load_route", "load_sweep",
    "load_vehicle", "map_batch",
    "minimal_switching", "mode_gear_split", "optimal_mode_gear", "pad_routes", "predict_batch",
    "predict_velocity", "route_name", "run_sweep", "simulate", "simulate_batch", "solve_costate",
    "stack_vehicles", "status_names", "switch_cost_matrix", "use_host_devices", "vehicle_axes",
    "viterbi", "viterbi_first",
]


_LAZY = {"SweepError": "sweep", "load_sweep": "sweep", "run_sweep": "sweep",
         "compare_strategies": "sweep"}


def __getattr__(name):  # the sweep machinery (pandas, pyarrow) loads on first use
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module 'jaxems' has no attribute {name!r}")
