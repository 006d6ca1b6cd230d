"""jaxems: multi-level predictive energy management for parallel hybrid trucks, in JAX.

After van Reeven & Hofman, "Multi-Level Energy Management for Hybrid Electric Vehicles -
Part I" (Vehicles 2019). Level 3 predicts velocity, Level 2 finds the battery costate,
Level 1 splits power and picks modes and gears with switching costs.
"""

from .params import VehicleError, VehicleParams, load_vehicle, stack_vehicles

__all__ = ["VehicleError", "VehicleParams", "load_vehicle", "stack_vehicles"]
