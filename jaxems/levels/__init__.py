"""The three levels of the multi-level EMS: velocity (3), battery (2), power split (1)."""
