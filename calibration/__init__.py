"""calibration: sphere-indentation calibration (contact detection, ground truth, light models, LUT)."""
